"""Helpers for tests that run real nodes: executables from install/, clients that wait without
``spin_until_future_complete`` (12 ms per call here), and clean process shutdown."""

from __future__ import annotations

import os
import signal
import subprocess
import time
import warnings
from collections.abc import Callable
from pathlib import Path

import rclpy
from rclpy.executors import SingleThreadedExecutor

ROOT = Path(__file__).resolve().parents[2]
LIB = ROOT / "install" / "hybrid_kinematics_ros" / "lib" / "hybrid_kinematics_ros"
STARTED: list[subprocess.Popen] = []  # every process a test started; conftest stops leftovers after each test
LOGS: dict[int, Path] = {}  # pid -> log file, shown when a test fails


def executable(name: str) -> Path:
    path = LIB / name
    if not path.is_file():
        raise RuntimeError(f"{path} is missing: run make bootstrap (the colcon build)")
    return path


def start(name: str, *ros_args: str, log: Path | None = None) -> subprocess.Popen:
    """Start an installed executable the way ``ros2 run`` would, in its own process group."""
    return start_command([str(executable(name)), "--ros-args", *ros_args], log=log)


def start_command(
    argv: list[str], log: Path | None = None, cwd: Path = ROOT, env: dict[str, str] | None = None
) -> subprocess.Popen:
    """Start any command in its own process group; it is stopped after the test like ``start``'s."""
    out = open(log, "w") if log else subprocess.DEVNULL  # noqa: SIM115 - closed with the process
    proc = subprocess.Popen(
        argv,
        stdout=out,
        stderr=subprocess.STDOUT,
        cwd=cwd,
        start_new_session=True,
        env=os.environ.copy() if env is None else env,
    )
    STARTED.append(proc)
    if log:
        LOGS[proc.pid] = log
    return proc


def stop(proc: subprocess.Popen, sig: int = signal.SIGINT, timeout: float = 15.0) -> int:
    if proc.poll() is None:
        os.killpg(proc.pid, sig)
        try:
            proc.wait(timeout)
        except subprocess.TimeoutExpired:  # its threads' stacks into its log first (nodes/runtime.py)
            os.kill(proc.pid, signal.SIGUSR1)
            try:
                proc.wait(2.0)
            except subprocess.TimeoutExpired:
                os.killpg(proc.pid, signal.SIGKILL)
                proc.wait()
    return proc.returncode


class Client:
    """A client node with its own executor; ``call`` spins until the answer or a timeout."""

    def __init__(self, name: str = "test_client") -> None:
        self.node = rclpy.create_node(name)
        self.executor = SingleThreadedExecutor()
        self.executor.add_node(self.node)

    # generous: on a healthy machine both return within a second; a loaded CI runner has taken a minute
    def service(self, srv_type, name: str, timeout: float = 120.0):
        client = self.node.create_client(srv_type, name)
        if not client.wait_for_service(timeout_sec=timeout):
            raise TimeoutError(f"service {name} did not appear within {timeout} s; {self.graph()}")
        return client

    def service_of(
        self,
        proc: subprocess.Popen,
        srv_type,
        name: str,
        restart: Callable[[], subprocess.Popen],
        timeout: float = 90.0,
    ) -> tuple[subprocess.Popen, object]:
        """Wait for a service of the node ``proc`` runs; if it never shows, stop that process and start it
        once more with ``restart``. Under load Fast DDS's shared-memory transport has left a new participant
        half-discovered for minutes (CI: its services listed, its node and its replies never arriving), and
        only a new participant recovers. The retry is reported as a warning, and a second miss fails."""
        try:
            return proc, self.service(srv_type, name, timeout)
        except TimeoutError as first:
            warnings.warn(f"restarting {proc.args[0]}: {first}", stacklevel=2)
            stop(proc, signal.SIGINT, timeout=60.0)
            proc = restart()
            return proc, self.service(srv_type, name, timeout)

    def graph(self) -> str:
        """What this participant's discovery sees: tells a node that never came up from one not discovered."""
        nodes = sorted(f"{ns.rstrip('/')}/{n}" for n, ns in self.node.get_node_names_and_namespaces())
        services = sorted(name for name, _ in self.node.get_service_names_and_types())
        return f"domain {os.environ.get('ROS_DOMAIN_ID')}, nodes seen {nodes}, services seen {services}"

    def call(self, client, request, timeout: float = 60.0, resend_after: float = 5.0):
        """Call, and resend every ``resend_after`` seconds while unanswered: with Fast DDS a reply can be
        lost while the client's response reader is still matching. A request that must not arrive twice
        passes ``resend_after=timeout``."""
        end = time.monotonic() + timeout
        while time.monotonic() < end:
            future = client.call_async(request)
            deadline = min(end, time.monotonic() + resend_after)
            while not future.done() and time.monotonic() < deadline:
                self.executor.spin_once(timeout_sec=0.05)
            if future.done():
                return future.result()
            client.remove_pending_request(future)
        raise TimeoutError(f"no answer from {client.srv_name} within {timeout} s; {self.graph()}")

    def spin_for(self, seconds: float) -> None:
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            self.executor.spin_once(timeout_sec=0.01)

    def close(self) -> None:
        self.executor.shutdown()
        self.node.destroy_node()
