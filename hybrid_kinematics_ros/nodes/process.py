"""How a process that answers requests in time runs: no full garbage collection of the loaded model inside a
request, and BLAS on the calling thread only. The kinematics node applies both once its model is loaded; the
benches that time requests apply them as the node does. No ROS import: a bench needs none."""

from __future__ import annotations

import gc

from threadpoolctl import threadpool_limits


def freeze_heap() -> None:
    """Exempt what the process holds now from the garbage collector's full collections: call it once the model
    and its solver are loaded, and again after a reload (what was frozen before is collected first). torch and
    a model leave hundreds of thousands of objects on the heap, and a full collection walks every one, for
    longer than a request's budget, inside whichever request's allocations trigger it. Frozen, they are never
    walked again; what requests allocate is collected as usual. A reload pays one such collection (holding the
    interpreter lock, so the node's other services wait for it) instead of a request."""
    gc.unfreeze()
    gc.collect()
    gc.freeze()


def one_blas_thread() -> None:
    """Set the thread pools of the process's BLAS libraries loaded by now (numpy's, and scipy's, which the compiled
    nets' batches call) to one thread, for the rest of the process: call it where answers must come in time, as
    :func:`freeze_heap` (``make`` and the tests set OPENBLAS_NUM_THREADS=1 for the same reason; a node started by
    ``ros2 run`` or a launch file does not). Their pools of one thread per core spin after each call, and on a
    two-core machine a pool's thread waiting for the other core can stall the next small product by tens of
    milliseconds, past a request's budget. The IK's products are at most 64 x 256 x 256, where one thread costs
    a small fraction of a millisecond."""
    threadpool_limits(limits=1, user_api="blas")
