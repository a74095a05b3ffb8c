"""``one_blas_thread``: a process that answers IK requests runs BLAS on its own thread only. On two cores, a BLAS
pool's second thread waiting for the other core stalled a small product by 10-65 ms, past a 50 ms budget."""

from __future__ import annotations

import json
import subprocess
import sys

PROBE = """
import json
import numpy as np
from threadpoolctl import threadpool_info
from hybrid_kinematics_ros.ik.solver import one_blas_thread
from hybrid_kinematics_ros.model import mlp_kernel  # loads scipy's BLAS, which the compiled nets call
blas = lambda: {d["filepath"]: d["num_threads"] for d in threadpool_info() if d["user_api"] == "blas"}
before = blas()
one_blas_thread()
print(json.dumps([before, blas()]))
"""


def test_every_blas_library_of_the_process_runs_on_one_thread():
    # a process of its own: the limit holds for the rest of the process that calls it
    out = subprocess.run([sys.executable, "-c", PROBE], capture_output=True, text=True, check=True).stdout
    before, after = json.loads(out.splitlines()[-1])
    # numpy's and scipy's OpenBLAS are both there (numba's products go through scipy's)
    assert len(before) >= 2 and before.keys() == after.keys()
    assert set(after.values()) == {1}
