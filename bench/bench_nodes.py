"""The kinematics node under measurement: FK round trips against the rclpy floor (a std_srvs/Trigger round
trip in the same run), batch FK, IK requests, and 8 client processes under a 110 Hz joint stream."""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
LIB = ROOT / "install" / "hybrid_kinematics_ros" / "lib" / "hybrid_kinematics_ros"


LATENCY_KINDS = "fk,trigger,fk_empty,fk_pose"  # called in turn by one client: one machine state for all
DEEP_REPLY_QUEUE = 100  # the client QoS depth the README recommends for many concurrent clients


def rss_mb(pid: int) -> float:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS"):
            return int(line.split()[1]) / 1024
    return float("nan")


def client(calls: int, batch: int = 1, kinds: str = "fk", depth: int = 10) -> dict:
    """``calls`` rounds; each round calls every kind in ``kinds`` (comma-separated) once, so that kinds
    compared with each other see the same machine state (on this VM the floor alone drifts by 30 %
    between runs a minute apart). ``depth``: the client's reply queue (rclpy's default is 10)."""
    import rclpy
    from rclpy.qos import QoSProfile, ReliabilityPolicy
    from std_srvs.srv import Trigger

    from hybrid_kinematics_interfaces.srv import ComputeFK, ComputeIK
    from hybrid_kinematics_ros.nodes.convert import joint_state_msg, pose_msg

    rclpy.init()
    node = rclpy.create_node(f"bench_client_{os.getpid()}")
    names = [f"joint_{i}" for i in range(1, 7)]
    stamp = node.get_clock().now().to_msg()
    qos = QoSProfile(depth=depth, reliability=ReliabilityPolicy.RELIABLE)

    def endpoint(kind: str):
        if kind == "trigger":
            return node.create_client(Trigger, "/bench_trivial/trigger", qos_profile=qos), Trigger.Request()
        if kind in ("fk_empty", "fk_pose"):  # the same request to a server that computes nothing
            srv = node.create_client(ComputeFK, f"/bench_trivial/{kind[3:]}", qos_profile=qos)
            return srv, ComputeFK.Request(joint_states=[joint_state_msg(np.zeros(6), names, stamp)])
        if kind.startswith("ik"):
            from hybrid_kinematics_ros.kinematics import fk
            from hybrid_kinematics_ros.kinematics.robot_config import load_robot_config

            chain = load_robot_config("ur10").chain
            target = fk.fk_single(chain, np.array([0.3, -1.2, 1.3, -0.9, 1.1, 0.2]))
            srv = node.create_client(ComputeIK, "/kinematics_node/compute_ik", qos_profile=qos)
            return srv, ComputeIK.Request(target=pose_msg(target, "base_link", stamp), max_solutions=int(kind[2:] or 1))
        q = np.random.default_rng(os.getpid()).uniform(-1, 0, (batch, 6))
        srv = node.create_client(ComputeFK, "/kinematics_node/compute_fk", qos_profile=qos)
        return srv, ComputeFK.Request(joint_states=[joint_state_msg(qi, names, stamp) for qi in q])

    endpoints = {kind: endpoint(kind) for kind in kinds.split(",")}
    for srv, _ in endpoints.values():
        assert srv.wait_for_service(timeout_sec=60)

    def call(srv, req, timeout: float):
        future = srv.call_async(req)
        deadline = time.monotonic() + timeout
        while not future.done() and time.monotonic() < deadline:
            rclpy.spin_once(node, timeout_sec=0.5)
        if not future.done():
            srv.remove_pending_request(future)
            return None
        return future.result()

    # wait_for_service sees the server's request reader; its reply writer can match this client's reader a
    # moment later, and a reply sent before that is lost (a known rmw race). One answered call per service
    # first, resent while unanswered, as a client that starts up would do; then the measured calls.
    for srv, req in endpoints.values():
        for _ in range(30):
            if call(srv, req, 2.0) is not None:
                break
    times: dict[str, list[float]] = {kind: [] for kind in endpoints}
    failures = lost = 0
    for _ in range(calls):
        for kind, (srv, req) in endpoints.items():
            start = time.perf_counter()
            answer = call(srv, req, 10.0)
            if answer is None:  # counted, not waited for forever
                lost += 1
                continue
            times[kind].append(time.perf_counter() - start)
            failures += not getattr(answer, "success", True) and kind not in ("trigger", "fk_empty")
    node.destroy_node()
    rclpy.shutdown()
    return {"times": times, "failures": failures, "lost": lost}


def run_client(calls: int, batch: int = 1, kinds: str = "fk", depth: int = 10) -> subprocess.Popen:
    args = ["--client", str(calls), "--batch", str(batch), "--kinds", kinds, "--depth", str(depth)]
    return subprocess.Popen(
        [sys.executable, "-m", "bench.bench_nodes", *args],
        stdout=subprocess.PIPE,
        text=True,
        cwd=ROOT,
    )


def result_of(proc: subprocess.Popen) -> dict:
    out, _ = proc.communicate(timeout=900)
    return json.loads(out.strip().splitlines()[-1])


def load(node_pid: int, depth: int) -> tuple[list[dict], dict, float, float]:
    """8 clients x 500 FK calls while /joint_states runs at 110 Hz: their results, the corrected-pose lag, and
    the node's resident memory (MB) before and after."""
    rss_before = rss_mb(node_pid)
    pub = subprocess.Popen(
        [sys.executable, "-m", "bench.bench_nodes", "--publish", "20"], stdout=subprocess.PIPE, text=True, cwd=ROOT
    )
    time.sleep(2)
    clients = [run_client(500, depth=depth) for _ in range(8)]
    results = [result_of(c) for c in clients]
    lag = json.loads(pub.communicate(timeout=300)[0].strip().splitlines()[-1])
    return results, lag, rss_before, rss_mb(node_pid)


def main() -> None:
    from bench.report import table, write_section

    os.environ["ROS_DOMAIN_ID"] = str(40 + os.getpid() % 50)
    os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
    tmp = Path(tempfile.mkdtemp())
    node = subprocess.Popen(
        [
            str(LIB / "kinematics_node"),
            "--ros-args",
            "--params-file",
            str(ROOT / "config/kinematics.yaml"),
            "-p",
            f"urdf_path:={ROOT / 'config/ur10.urdf'}",
            *(["-p", f"model_dir:={sys.argv[1]}"] if len(sys.argv) > 1 else []),
        ],
        stdout=(tmp / "node.log").open("w"),
        stderr=subprocess.STDOUT,
    )
    trivial = [
        subprocess.Popen([sys.executable, "-m", "bench.bench_nodes", "--serve-trivial", kind], cwd=ROOT)
        for kind in ("trigger", "empty", "pose")
    ]
    try:
        time.sleep(3)
        ms = {k: np.array(v) * 1e3 for k, v in result_of(run_client(2000, kinds=LATENCY_KINDS))["times"].items()}
        fk1, trig, empty, one_pose = (ms[k] for k in LATENCY_KINDS.split(","))
        fk1000 = np.array(result_of(run_client(50, batch=1000))["times"]["fk"]) * 1e3
        ik1 = np.array(result_of(run_client(100, kinds="ik1"))["times"]["ik1"]) * 1e3
        ik8 = np.array(result_of(run_client(30, kinds="ik8"))["times"]["ik8"]) * 1e3
        loads, lag, rss_before, rss_after = load(node.pid, DEEP_REPLY_QUEUE)
        shallow, shallow_lag, _, _ = load(node.pid, 10)
    finally:
        for proc in (node, *trivial):
            proc.terminate()
            proc.wait(30)
    all_load, shallow_load = (np.concatenate([np.array(r["times"]["fk"]) for r in x]) * 1e3 for x in (loads, shallow))

    def stats(x):
        return [f"{np.median(x):.3f}", f"{np.percentile(x, 95):.3f}", f"{np.percentile(x, 99):.3f}"]

    rows = [
        ["FK, one configuration", *stats(fk1)],
        ["std_srvs/Trigger to a trivial server, the rclpy floor", *stats(trig)],
        ["ComputeFK to a trivial server, empty response", *stats(empty)],
        ["ComputeFK to a trivial server, one prebuilt pose", *stats(one_pose)],
        ["FK, 1,000 configurations per request (50 calls)", *stats(fk1000)],
        ["IK, one solution (100 calls)", *stats(ik1)],
        ["IK, up to 8 solutions (30 calls)", *stats(ik8)],
        ["FK under load: 8 clients x 500 calls, /joint_states at 110 Hz", *stats(all_load)],
        ["the same load, clients with rclpy's default reply queue (10)", *stats(shallow_load)],
    ]
    left_us = 1e3 * (1.5 * np.median(trig) - np.median(one_pose))  # for the node's work, within the target
    budget = (
        f"Within the 1.5× target, that leaves {left_us:.0f} µs for the node's work."
        if left_us > 0
        else "That alone reaches the 1.5× target, with nothing left for the node's work."
    )
    model = f"model {sys.argv[1]}" if len(sys.argv) > 1 else "the analytic UR10 (no model_dir)"
    body = (
        f"kinematics_node serving {model}; each client is a separate process waiting with a spin_once loop. "
        "The first four rows come from one client calling the four services in turn, 2,000 rounds; each trivial "
        "service runs in a plain Python process of its own with rclpy's EventsExecutor, as the node uses, so "
        "that every call wakes a server that sat idle during the other three.\n\n"
        + table(["request", "median (ms)", "p95 (ms)", "p99 (ms)"], rows)
        + f"\n\nFK round trip against the Trigger floor: **{np.median(fk1) / np.median(trig):.2f}×** median "
        f"(target ≤ 1.5×). A server that does no work costs {np.median(empty) / np.median(trig):.2f}× for the same "
        f"request (empty response) and {np.median(one_pose) / np.median(trig):.2f}× with one prebuilt pose: that "
        f"much is the message types' own cost in rclpy. {budget} The node's work on the request takes "
        f"{1e3 * (np.median(fk1) - np.median(one_pose)):.0f} µs. "
        f"FK of 1,000 configurations: {np.median(fk1000) / 1000 * 1e3:.1f} µs per configuration.\n\n"
        f"Under load, clients with a reply queue of {DEEP_REPLY_QUEUE}: {sum(r['failures'] for r in loads)} failed "
        f"and {sum(r['lost'] for r in loads)} unanswered (10 s) calls of {8 * 500}; corrected-pose lag median "
        f"{lag['lag_p50_ms']:.2f} ms, p99 {lag['lag_p99_ms']:.2f} ms ({lag['received']} of {lag['sent']} poses "
        f"received); node memory {rss_before:.0f} MB before and {rss_after:.0f} MB after. With rclpy's default "
        f"reply queue of 10: {sum(r['failures'] for r in shallow)} failed and {sum(r['lost'] for r in shallow)} "
        f"unanswered; lag median {shallow_lag['lag_p50_ms']:.2f} ms, p99 {shallow_lag['lag_p99_ms']:.2f} ms. "
        "Fast DDS delivers every reply to every client's reply queue, which keeps only its own; a client that "
        "the scheduler keeps waiting while the others' replies fill its queue loses its own reply."
    )
    write_section("nodes", "Kinematics node: latency, batch FK, IK and load", body)


def serve_trivial(kind: str) -> None:
    """One service that answers at once, in a plain single-threaded process of its own: ``trigger`` (the
    rclpy floor), or ComputeFK with an ``empty`` response or one prebuilt ``pose`` (the cost of the message
    types alone). One process per service, so that each call of a round wakes a process that sat idle
    during the others, as the kinematics node does; a server called twice in a row answers faster."""
    import rclpy
    from geometry_msgs.msg import PoseStamped
    from rclpy.experimental import EventsExecutor
    from std_srvs.srv import Trigger

    from hybrid_kinematics_interfaces.srv import ComputeFK

    rclpy.init()
    node = rclpy.create_node(f"bench_trivial_{kind}")
    prebuilt = [PoseStamped()]

    def one_pose(request, response):
        response.poses, response.in_calibrated_range, response.success = prebuilt, [True], True
        return response

    srv_type, handler = {
        "trigger": (Trigger, lambda request, response: response),
        "empty": (ComputeFK, lambda request, response: response),
        "pose": (ComputeFK, one_pose),
    }[kind]
    node.create_service(srv_type, f"/bench_trivial/{kind}", handler)
    executor = EventsExecutor()
    executor.add_node(node)
    while rclpy.ok():
        executor.spin_once(timeout_sec=0.1)


def publish(seconds: float) -> dict:
    import rclpy
    from geometry_msgs.msg import PoseStamped
    from sensor_msgs.msg import JointState

    rclpy.init()
    node = rclpy.create_node("bench_joint_publisher")
    pub = node.create_publisher(JointState, "/joint_states", 100)
    lags, sent = [], {}
    node.create_subscription(
        PoseStamped,
        "/kinematics_node/corrected_pose",
        lambda m: lags.append(time.time() - sent.get((m.header.stamp.sec, m.header.stamp.nanosec), time.time())),
        100,
    )
    names = [f"joint_{i}" for i in range(1, 7)]
    end = time.monotonic() + seconds
    tick = time.monotonic()
    while time.monotonic() < end:
        msg = JointState(name=names, position=[0.1, -1.0, 1.0, -1.0, 1.0, 0.1])
        msg.header.stamp = node.get_clock().now().to_msg()
        sent[(msg.header.stamp.sec, msg.header.stamp.nanosec)] = time.time()
        pub.publish(msg)
        tick += 1 / 110
        while time.monotonic() < tick:
            rclpy.spin_once(node, timeout_sec=max(0.0, tick - time.monotonic()))
    deadline = time.monotonic() + 1.0
    while time.monotonic() < deadline:
        rclpy.spin_once(node, timeout_sec=0.05)
    node.destroy_node()
    rclpy.shutdown()
    return {
        "lag_p50_ms": float(np.median(np.array(lags) * 1e3)) if lags else float("nan"),
        "lag_p99_ms": float(np.percentile(np.array(lags) * 1e3, 99)) if lags else float("nan"),
        "received": len(lags),
        "sent": len(sent),
    }


if __name__ == "__main__":
    parser = argparse.ArgumentParser()
    parser.add_argument("model_dir", nargs="?")
    parser.add_argument("--client", type=int)
    parser.add_argument("--batch", type=int, default=1)
    parser.add_argument("--kinds", default="fk")
    parser.add_argument("--depth", type=int, default=10)
    parser.add_argument("--publish", type=float)
    parser.add_argument("--serve-trivial", choices=("trigger", "empty", "pose"))
    args = parser.parse_args()
    if args.serve_trivial:
        serve_trivial(args.serve_trivial)
    elif args.client:
        print(json.dumps(client(args.client, args.batch, args.kinds, args.depth)))
    elif args.publish:
        print(json.dumps(publish(args.publish)))
    else:
        sys.argv = [sys.argv[0], *([args.model_dir] if args.model_dir else [])]
        main()
