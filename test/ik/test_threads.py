"""``one_blas_thread``: a process that answers IK requests runs BLAS on its own thread only. On two cores, a BLAS
pool's second thread waiting for the other core stalled a small product by 10-65 ms, past a 50 ms budget."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import pytest

PROBE = """
import json
from threadpoolctl import threadpool_info
import hybrid_kinematics_ros.ik.solver  # numpy's and scipy's BLAS, loaded as the node loads them
from hybrid_kinematics_ros.nodes.process import one_blas_thread
blas = lambda: {d["filepath"]: d["num_threads"] for d in threadpool_info() if d["user_api"] == "blas"}
before = blas()
one_blas_thread()
print(json.dumps([before, blas()]))
"""
# what would set the pools' size before the call (make and test/conftest.py set the first, for the suite)
LIMITS = ("OPENBLAS_NUM_THREADS", "GOTO_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS")


@pytest.mark.skipif((os.cpu_count() or 1) < 2, reason="one core: BLAS pools have one thread already")
def test_every_blas_library_of_the_process_runs_on_one_thread():
    # a process of its own, as a node started by ros2 run: no limit in its environment, and the call's limit
    # holds for the rest of the process that makes it
    env = {k: v for k, v in os.environ.items() if k not in LIMITS}
    out = subprocess.run([sys.executable, "-c", PROBE], capture_output=True, text=True, check=True, env=env).stdout
    before, after = json.loads(out.splitlines()[-1])
    assert before and max(before.values()) > 1  # numpy's (and the solver's scipy's) pools: one thread per core
    assert before.keys() == after.keys() and set(after.values()) == {1}
