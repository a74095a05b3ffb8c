"""Whatever a test started is stopped when it ends, even when it fails half-way; when a test fails, the
logs of the processes it started are printed with the failure (a CI run leaves nothing else behind).
Each module runs in a ROS domain of its own, so that nothing an earlier module left in discovery (a killed
participant, a full shared-memory port) reaches it."""

from __future__ import annotations

import itertools
import os
import signal
import time

import pytest

from test.conftest import DOMAIN_STRIDE, DOMAIN_WRAP
from test.nodes.rosutil import LOGS, STARTED, stop

SESSION_DOMAIN = int(os.environ["ROS_DOMAIN_ID"])  # set per session by test/conftest.py
# in steps of the number of pytest-xdist workers: each worker keeps to its own residue (test/conftest.py)
MODULE_DOMAINS = itertools.count(SESSION_DOMAIN + DOMAIN_STRIDE, DOMAIN_STRIDE)


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_makereport(item, call):
    outcome = yield
    report = outcome.get_result()
    if report.when == "call":
        item.failed_call = report.failed


@pytest.fixture(scope="module", autouse=True)
def own_domain():
    """Read by ``rclpy.init`` in this process and inherited by every node a test starts."""
    os.environ["ROS_DOMAIN_ID"] = str(next(MODULE_DOMAINS) % DOMAIN_WRAP)  # a wrap keeps the residue
    yield
    os.environ["ROS_DOMAIN_ID"] = str(SESSION_DOMAIN)


def dump_stacks(proc, timeout: float = 5.0) -> None:
    """Before a failed test's process is killed: its threads' stacks into its log (SIGUSR1, nodes/runtime.py),
    so the failure shows where a node that never answered was waiting."""
    log = LOGS.get(proc.pid)
    if proc.poll() is not None or log is None:
        return
    os.kill(proc.pid, signal.SIGUSR1)
    deadline = time.monotonic() + timeout
    size = -1
    while time.monotonic() < deadline:  # until the dump has begun and stopped growing
        text = log.read_text(errors="replace")
        if "most recent call first" in text and len(text) == size:
            break
        size = len(text)
        time.sleep(0.2)


@pytest.fixture(autouse=True)
def no_leftover_processes(request):
    before = len(STARTED)
    yield
    failed = getattr(request.node, "failed_call", False)
    for proc in STARTED[before:]:
        if failed:
            dump_stacks(proc)
        stop(proc, signal.SIGKILL, timeout=5.0)
    if failed:
        running = [proc for proc in STARTED[:before] if proc.poll() is None]  # e.g. the module's simulated cell
        for proc in running + STARTED[before:]:
            log = LOGS.get(proc.pid)
            if log is not None and log.is_file():
                tail = log.read_text(errors="replace").splitlines()[-80:]
                print(f"----- {proc.args[0]} (pid {proc.pid}, exit {proc.returncode}), {log}:", *tail, sep="\n")
