"""Whatever a test started is stopped when it ends, even when it fails half-way; when a test fails, the
logs of the processes it started are printed with the failure (a CI run leaves nothing else behind).
Each module runs in a ROS domain of its own, so that nothing an earlier module left in discovery (a killed
participant, a full shared-memory port) reaches it."""

from __future__ import annotations

import itertools
import os
import signal

import pytest

from test.nodes.rosutil import LOGS, STARTED, stop

SESSION_DOMAIN = int(os.environ["ROS_DOMAIN_ID"])  # set per session by test/conftest.py
MODULE_DOMAINS = itertools.count(SESSION_DOMAIN + 1)


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_makereport(item, call):
    outcome = yield
    report = outcome.get_result()
    if report.when == "call":
        item.failed_call = report.failed


@pytest.fixture(scope="module", autouse=True)
def own_domain():
    """Read by ``rclpy.init`` in this process and inherited by every node a test starts."""
    os.environ["ROS_DOMAIN_ID"] = str(next(MODULE_DOMAINS) % 233)
    yield
    os.environ["ROS_DOMAIN_ID"] = str(SESSION_DOMAIN)


@pytest.fixture(autouse=True)
def no_leftover_processes(request):
    before = len(STARTED)
    yield
    for proc in STARTED[before:]:
        stop(proc, signal.SIGKILL, timeout=5.0)
    if getattr(request.node, "failed_call", False):
        running = [proc for proc in STARTED[:before] if proc.poll() is None]  # e.g. the module's simulated cell
        for proc in running + STARTED[before:]:
            log = LOGS.get(proc.pid)
            if log is not None and log.is_file():
                tail = log.read_text(errors="replace").splitlines()[-40:]
                print(f"----- {proc.args[0]} (pid {proc.pid}, exit {proc.returncode}), {log}:", *tail, sep="\n")
