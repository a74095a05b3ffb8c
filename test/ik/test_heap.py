"""``freeze_heap``: what a process holds once its model is loaded is exempt from the collector's full
collections (a full collection of a loaded model's heap took 140 ms inside a 50 ms IK request); what the
requests allocate afterwards is still collected."""

from __future__ import annotations

import gc
import weakref

from hybrid_kinematics_ros.ik.solver import IKOptions, IKSolver
from hybrid_kinematics_ros.nodes.process import freeze_heap


class Cyclic:
    me: Cyclic | None = None


def test_the_loaded_model_is_frozen_and_later_garbage_still_collected(trained):
    _, model, _, _ = trained
    solver = IKSolver(model, IKOptions())
    try:
        freeze_heap()
        frozen = gc.get_freeze_count()
        assert frozen > 10_000  # torch and the model's objects
        # what a full collection still walks: a small part of the heap
        assert len(gc.get_objects()) < 0.2 * frozen
        # a cycle made afterwards (as a request makes them) is collected as before, by the collector's own
        # young-generation pass that a request's allocations set off
        cycle = Cyclic()
        cycle.me = cycle
        gone = weakref.ref(cycle)
        del cycle
        allocated = [[] for _ in range(5 * gc.get_threshold()[0])]
        assert gone() is None and allocated
        # a second call (a reload) freezes what is held now, once: the count does not pile up
        freeze_heap()
        assert abs(gc.get_freeze_count() - frozen) < 0.1 * frozen
        assert solver.solve(model.fk_single(model.chain.mid_limits())).success
    finally:
        gc.unfreeze()
