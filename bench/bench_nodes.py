"""The kinematics node under measurement: FK round trips against a server that does no work (in the same
run), batch FK, IK requests, 8 client processes under a 110 Hz joint stream, trajectory compensation, and FK
with and without error bounds.

``--only latency,compensate`` measures some parts and keeps the others' text in BENCHMARKS.md (each part
says when and how it was measured)."""

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


def call_service(node, srv, req, timeout: float):
    """One call, waited for with a spin_once loop; None when unanswered within ``timeout`` (s)."""
    import rclpy

    future = srv.call_async(req)
    deadline = time.monotonic() + timeout
    while not future.done() and time.monotonic() < deadline:
        rclpy.spin_once(node, timeout_sec=0.5)
    if not future.done():
        srv.remove_pending_request(future)
        return None
    return future.result()


def client(calls: int, batch: int = 1, kinds: str = "fk", depth: int = 10) -> dict:
    """``calls`` rounds; each round calls every kind in ``kinds`` (comma-separated) once, so that kinds
    compared with each other see the same machine state (on this VM the floor alone drifts by 30 %
    between runs a minute apart). ``depth``: the client's reply queue (rclpy's default is 10)."""
    import rclpy
    from rclpy.qos import QoSProfile, ReliabilityPolicy
    from std_srvs.srv import Trigger

    from hybrid_kinematics_interfaces.srv import ComputeFK, ComputeIK
    from hybrid_kinematics_ros.kinematics.robot_config import load_robot_config
    from hybrid_kinematics_ros.nodes.convert import joint_state_msg, pose_msg

    rclpy.init()
    node = rclpy.create_node(f"bench_client_{os.getpid()}")
    names = list(load_robot_config("ur10").chain.joint_names)
    stamp = node.get_clock().now().to_msg()
    qos = QoSProfile(depth=depth, reliability=ReliabilityPolicy.RELIABLE)

    def endpoint(kind: str):
        if kind == "trigger":
            return node.create_client(Trigger, "/bench_trivial/trigger", qos_profile=qos), Trigger.Request()
        if kind in ("fk_empty", "fk_pose"):  # the same request to a server that computes nothing
            srv = node.create_client(ComputeFK, f"/bench_trivial/{kind[3:]}", qos_profile=qos)
            return srv, ComputeFK.Request(joint_states=[joint_state_msg(np.zeros(6), names, stamp)])
        if kind.startswith("ik"):  # ik<solutions>[@/namespace]
            from hybrid_kinematics_ros.kinematics import fk
            from hybrid_kinematics_ros.kinematics.robot_config import load_robot_config

            chain = load_robot_config("ur10").chain
            target = fk.fk_single(chain, np.array([0.3, -1.2, 1.3, -0.9, 1.1, 0.2]))
            solutions, _, namespace = kind[2:].partition("@")
            srv = node.create_client(ComputeIK, f"{namespace}/kinematics_node/compute_ik", qos_profile=qos)
            request = ComputeIK.Request(target=pose_msg(target, "base_link", stamp), max_solutions=int(solutions or 1))
            return srv, request
        q = np.random.default_rng(os.getpid()).uniform(-1, 0, (batch, 6))
        namespace = kind.partition("@")[2]  # fk@/ns: the node started in namespace /ns
        srv = node.create_client(ComputeFK, f"{namespace}/kinematics_node/compute_fk", qos_profile=qos)
        return srv, ComputeFK.Request(joint_states=[joint_state_msg(qi, names, stamp) for qi in q])

    endpoints = {kind: endpoint(kind) for kind in kinds.split(",")}
    for srv, _ in endpoints.values():
        assert srv.wait_for_service(timeout_sec=60)

    def call(srv, req, timeout: float):
        return call_service(node, srv, req, timeout)

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
    services = ("fk", "ik") if any(k.startswith("ik") for k in endpoints) else ("fk",)
    handler = served_handler_ms(node, services) if any(k.startswith("fk@") or k == "fk" for k in endpoints) else {}
    node.destroy_node()
    rclpy.shutdown()
    return {"times": times, "failures": failures, "lost": lost, "handler_ms": handler}


def served_handler_ms(node, services: tuple[str, ...] = ("fk",), timeout: float = 3.0) -> dict[str, dict]:
    """Each node's own time in its callbacks (p50/p90/p99 ms over its last 1,000 requests of each of
    ``services``), from its /diagnostics, by the model it serves ("analytic URDF model" or a directory): the
    part of the round trip that is the node's work, measured inside the served process."""
    import rclpy
    from diagnostic_msgs.msg import DiagnosticArray

    found: dict[str, dict] = {}

    def on_diagnostics(msg: DiagnosticArray) -> None:
        for status in msg.status:
            values = {kv.key: kv.value for kv in status.values}
            if all(f"{s}_latency_p50_ms" in values for s in services):
                found[values.get("model", "")] = {
                    f"{s}_{p}": float(values[f"{s}_latency_{p}_ms"]) for s in services for p in ("p50", "p90", "p99")
                }

    sub = node.create_subscription(DiagnosticArray, "/diagnostics", on_diagnostics, 10)
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:  # every node publishes once a second: wait for all of them
        rclpy.spin_once(node, timeout_sec=0.1)
    node.destroy_subscription(sub)
    return found


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


PARTS = ("latency", "fk_batch", "ik", "load", "compensate", "bounds")
TITLE = "Kinematics node: latency, batch FK, IK, load, trajectory compensation and error bounds"
FK_TARGET = 1.15  # FK round trip / a zero-work ComputeFK server returning one prebuilt pose (#18)
COMPENSATE_POINTS = 1000
PLAN_FROM = np.array([0.3, -1.5, 1.6, -1.2, 0.9, 0.4])  # a rest-to-rest move as the tests plan it
PLAN_TO = np.array([0.9, -1.0, 1.1, -0.6, 1.5, 1.0])


def plan(n: int, seconds: float = 6.0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A rest-to-rest joint move with a cosine profile: times (s), positions and velocities ``(n, 6)``."""
    t = np.linspace(0.0, seconds, n)
    s = 0.5 - 0.5 * np.cos(np.pi * t / seconds)
    ds = 0.5 * np.pi / seconds * np.sin(np.pi * t / seconds)
    d = PLAN_TO - PLAN_FROM
    return t, PLAN_FROM + s[:, None] * d, ds[:, None] * d


def compensate_client(model_dir: str, calls: int) -> dict:
    """``calls`` requests of a 1,000-point plan to ~/compensate_trajectory (after one answered warm-up call);
    then the corrected points' hybrid FK against the plan's URDF FK, with the served model loaded here."""
    import rclpy
    from builtin_interfaces.msg import Duration
    from trajectory_msgs.msg import JointTrajectory, JointTrajectoryPoint

    from hybrid_kinematics_interfaces.srv import CompensateTrajectory
    from hybrid_kinematics_ros.kinematics import se3
    from hybrid_kinematics_ros.model.hybrid import HybridModel

    model = HybridModel.load(model_dir)
    t, q, qd = plan(COMPENSATE_POINTS)
    msg = JointTrajectory(joint_names=list(model.joint_names))
    for tk, qk, vk in zip(t, q, qd, strict=True):
        sec = int(tk)
        msg.points.append(
            JointTrajectoryPoint(
                positions=qk.tolist(),
                velocities=vk.tolist(),
                time_from_start=Duration(sec=sec, nanosec=round((tk - sec) * 1e9)),
            )
        )
    req = CompensateTrajectory.Request(trajectory=msg)
    rclpy.init()
    node = rclpy.create_node(f"bench_compensate_{os.getpid()}")
    srv = node.create_client(CompensateTrajectory, "/kinematics_node/compensate_trajectory")
    assert srv.wait_for_service(timeout_sec=60)
    for _ in range(30):  # the reply writer may match a moment after wait_for_service (see client)
        if call_service(node, srv, req, 10.0) is not None:
            break
    times, answers = [], []
    for _ in range(calls):
        start = time.perf_counter()
        answer = call_service(node, srv, req, 30.0)
        if answer is not None:
            times.append(time.perf_counter() - start)
            answers.append(answer)
    node.destroy_node()
    rclpy.shutdown()
    last = answers[-1]
    corrected = np.array([p.positions for p in last.trajectory.points])
    ok = all(a.success for a in answers) and len(corrected) == len(q)
    mm, deg = se3.pose_errors(model.fk(corrected), model.fk(q, analytic=True)) if ok else (np.nan, np.nan)
    return {
        "times": times,
        "answered": len(answers),
        "success": ok,
        "message": last.message,
        "max_mm": float(np.max(mm)),
        "max_deg": float(np.max(deg)),
        "max_correction_rad": float(np.max(np.abs(corrected - q))) if ok else float("nan"),
    }


def small_model(out: Path) -> Path:
    """A UR10 model trained as the tests train theirs (virtual cell, 4,000 poses, `fast` preset with
    mlp:64x2, 12 s), with the parametric stage a calibration of a real cell has."""
    from dataclasses import replace

    from bench.bench_hybrid import dataset
    from hybrid_kinematics_ros.calibration import train
    from hybrid_kinematics_ros.calibration.fit import fit
    from hybrid_kinematics_ros.calibration.recipe import Recipe
    from hybrid_kinematics_ros.kinematics.robot_config import load_robot_config

    cfg = load_robot_config("ur10")
    tr, va, te = dataset("ur10", 4000, 1), dataset("ur10", 500, 2), dataset("ur10", 500, 3)
    preset = replace(train.PRESETS["fast"], arch="mlp:64x2:silu")
    fit(
        cfg.chain,
        tr,
        va,
        te,
        out,
        Recipe(preset, 0.2, payload_mass=cfg.payload_mass, payload_com=tuple(cfg.payload_com)),
    )
    return out


def start_node(model_dir: str | None, log: Path, namespace: str = "") -> subprocess.Popen:
    return subprocess.Popen(
        [
            str(LIB / "kinematics_node"),
            "--ros-args",
            "--params-file",
            str(ROOT / "config/kinematics.yaml"),
            "-p",
            f"urdf_path:={ROOT / 'config/ur10.urdf'}",
            *(["-p", f"model_dir:={model_dir}"] if model_dir else []),
            *(["-r", f"__ns:={namespace}"] if namespace else []),
        ],
        stdout=log.open("w"),
        stderr=subprocess.STDOUT,
    )


def stop(procs: list[subprocess.Popen]) -> None:
    for proc in procs:
        proc.terminate()
    for proc in procs:
        proc.wait(30)


def stats(x: np.ndarray) -> list[str]:
    return [f"{np.median(x):.3f}", f"{np.percentile(x, 95):.3f}", f"{np.percentile(x, 99):.3f}"]


HEADERS = ["request", "median (ms)", "p95 (ms)", "p99 (ms)"]


def latency_part(repeat: int, rounds: int) -> str:
    """``repeat`` clients in turn, each calling FK and the three zero-work servers in rounds."""
    from bench.report import table

    runs = [result_of(run_client(rounds, kinds=LATENCY_KINDS)) for _ in range(repeat)]
    kinds = LATENCY_KINDS.split(",")
    ms = {k: [np.array(r["times"][k]) * 1e3 for r in runs] for k in kinds}
    ratio_pose = np.array([np.median(f) / np.median(p) for f, p in zip(ms["fk"], ms["fk_pose"], strict=True)])
    ratio_trig = np.array([np.median(f) / np.median(t) for f, t in zip(ms["fk"], ms["trigger"], strict=True)])
    served = [next(iter(r["handler_ms"].values())) for r in runs if r["handler_ms"]]  # the one node's
    handler = [h["fk_p50"] * 1e3 for h in served]
    handler_p99 = [h["fk_p99"] * 1e3 for h in served]
    pooled = {k: np.concatenate(v) for k, v in ms.items()}
    rows = [
        ["FK, one configuration", *stats(pooled["fk"])],
        ["std_srvs/Trigger to a zero-work server, the rclpy floor", *stats(pooled["trigger"])],
        ["ComputeFK to a zero-work server, empty response", *stats(pooled["fk_empty"])],
        ["ComputeFK to a zero-work server, one prebuilt pose", *stats(pooled["fk_pose"])],
    ]
    met = "met" if np.median(ratio_pose) <= FK_TARGET else "not met"
    return (
        f"Each client is a separate process waiting with a spin_once loop, calling the four services in turn, "
        f"{rounds:,} rounds; {repeat} such clients one after the other (the table pools their calls). Each "
        "zero-work service runs in a plain Python process of its own with rclpy's EventsExecutor, as the node "
        "uses, so that every call wakes a server that sat idle during the other three.\n\n"
        + table(HEADERS, rows)
        + f"\n\nFK round trip against the zero-work ComputeFK server returning one prebuilt pose, in the same "
        f"run: **{np.median(ratio_pose):.2f}×**, the median of the {repeat} runs' ratios of medians (spread "
        f"{ratio_pose.min():.2f}-{ratio_pose.max():.2f}: {', '.join(f'{r:.2f}' for r in ratio_pose)}); target "
        f"≤ {FK_TARGET}×: {met}. Against the Trigger floor: {np.median(ratio_trig):.2f}× (spread "
        f"{ratio_trig.min():.2f}-{ratio_trig.max():.2f}). The node's own time in its FK callback, from its "
        f"/diagnostics (median over its last 1,000 requests, per run): "
        f"{', '.join(f'{h:.0f}' for h in handler)} µs; its p99: {', '.join(f'{h:.0f}' for h in handler_p99)} µs."
    )


def fk_batch_part(calls: int = 50) -> str:
    from bench.report import table

    fk1000 = np.array(result_of(run_client(calls, batch=1000))["times"]["fk"]) * 1e3
    return (
        table(HEADERS, [[f"FK, 1,000 configurations per request ({calls} calls)", *stats(fk1000)]])
        + f"\n\nFK of 1,000 configurations: {np.median(fk1000) / 1000 * 1e3:.1f} µs per configuration."
    )


def ik_part(model_dir: str | None, tmp: Path, rounds: int = 500) -> str:
    """IK round trips against FK round trips of the same node, called in turn by one client: a node serving the
    URDF model and one serving a hybrid model, side by side."""
    from bench.report import table

    hybrid_dir, about = served_model(model_dir, tmp)
    nodes = [
        start_node(None, tmp / "urdf_node.log"),  # the parameters file names base and tip for this name only
        start_node(hybrid_dir, tmp / "hybrid_node.log", "/hybrid"),
    ]
    try:
        one = result_of(run_client(rounds, kinds="fk,ik1,fk@/hybrid,ik1@/hybrid"))
        many = result_of(run_client(30, kinds="ik8,ik8@/hybrid"))
    finally:
        stop(nodes)
    ms = {k: np.array(v) * 1e3 for k, v in {**one["times"], **many["times"]}.items()}
    rows, ratios = [], []
    for ns, label in (("", "the URDF model"), ("@/hybrid", "the hybrid model")):
        rows += [
            [f"FK, one configuration, {label} ({rounds} calls)", *stats(ms[f"fk{ns}"])],
            [f"IK, one solution, {label} ({rounds} calls)", *stats(ms[f"ik1{ns}"])],
            [f"IK, up to 8 solutions, {label} (30 calls)", *stats(ms[f"ik8{ns}"])],
        ]
        ratios.append(f"{np.median(ms[f'ik1{ns}']) / np.median(ms[f'fk{ns}']):.2f}× with {label}")
    served = {
        "the URDF model": one["handler_ms"].get("analytic URDF model"),
        "the hybrid model": one["handler_ms"].get(hybrid_dir),
    }
    callbacks = "; ".join(
        f"{label}: FK {h['fk_p50'] * 1e3:.0f} µs, IK {h['ik_p50'] * 1e3:.0f} µs" for label, h in served.items() if h
    )
    return (
        f"Two kinematics_node processes, one serving the UR10's URDF model, one serving {about}; one client "
        "calls FK and IK (one solution) of each in turn, so each pair sees the same machine state. IK of one "
        f"solution against FK, ratio of the medians: **{'; '.join(ratios)}** (target ≤ 1.5×).\n\n"
        + table(HEADERS, rows)
        + "\n\nThe nodes' own time in their callbacks in this run, from their /diagnostics (median over the last "
        f"1,000 requests): {callbacks}. A callback served between other processes' work runs 2-3× slower than "
        "the same call repeated back to back in one process (caches refilled on every request): compare the "
        "in-process solve in the IK sections."
    )


def load_part(node_pid: int) -> str:
    from bench.report import table

    loads, lag, rss_before, rss_after = load(node_pid, DEEP_REPLY_QUEUE)
    shallow, shallow_lag, _, _ = load(node_pid, 10)
    all_load, shallow_load = (np.concatenate([np.array(r["times"]["fk"]) for r in x]) * 1e3 for x in (loads, shallow))
    rows = [
        ["FK under load: 8 clients x 500 calls, /joint_states at 110 Hz", *stats(all_load)],
        ["the same load, clients with rclpy's default reply queue (10)", *stats(shallow_load)],
    ]
    return (
        table(HEADERS, rows) + f"\n\nUnder load, clients with a reply queue of {DEEP_REPLY_QUEUE}: "
        f"{sum(r['failures'] for r in loads)} failed and {sum(r['lost'] for r in loads)} unanswered (10 s) calls "
        f"of {8 * 500}; corrected-pose lag median {lag['lag_p50_ms']:.2f} ms, p99 {lag['lag_p99_ms']:.2f} ms "
        f"({lag['received']} of {lag['sent']} poses received); node memory {rss_before:.0f} MB before and "
        f"{rss_after:.0f} MB after. With rclpy's default reply queue of 10: {sum(r['failures'] for r in shallow)} "
        f"failed and {sum(r['lost'] for r in shallow)} unanswered; lag median {shallow_lag['lag_p50_ms']:.2f} ms, "
        f"p99 {shallow_lag['lag_p99_ms']:.2f} ms. Fast DDS delivers every reply to every client's reply queue, "
        "which keeps only its own; a client that the scheduler keeps waiting while the others' replies fill its "
        "queue loses its own reply."
    )


TRAINING_SECONDS: dict[Path, float] = {}  # small_model's, per run folder


def served_model(model_dir: str | None, tmp: Path) -> tuple[str, str]:
    """The model a part serves and how to describe it: ``model_dir``, or else :func:`small_model`, trained
    once per run (the parts that need it share it)."""
    if model_dir is not None:
        return model_dir, f"model {model_dir}"
    out = tmp / "model"
    if out not in TRAINING_SECONDS:
        start = time.perf_counter()
        small_model(out)
        TRAINING_SECONDS[out] = time.perf_counter() - start
    return str(out), f"a UR10 model trained for this run ({TRAINING_SECONDS[out]:.0f} s; see `small_model`)"


def compensate_part(model_dir: str | None, tmp: Path, calls: int = 10) -> str:
    from bench.report import table

    model_dir, about = served_model(model_dir, tmp)
    node = start_node(model_dir, tmp / "compensate_node.log")
    try:
        proc = subprocess.Popen(
            [sys.executable, "-m", "bench.bench_nodes", "--compensate-client", model_dir, "--calls", str(calls)],
            stdout=subprocess.PIPE,
            text=True,
            cwd=ROOT,
        )
        r = result_of(proc)
    finally:
        stop([node])
    ms = np.array(r["times"]) * 1e3
    row = [
        f"~/compensate_trajectory, {COMPENSATE_POINTS:,} points ({len(ms)} calls)",
        *stats(ms),
        f"{r['max_mm']:.2g}",
        f"{r['max_deg']:.2g}",
    ]
    return (
        f"kinematics_node serving {about}, its default compensation tolerances (config/kinematics.yaml); one "
        f"client process sends a rest-to-rest plan of {COMPENSATE_POINTS:,} points with velocities (6 s, "
        "cosine profile) after one warm-up call. Deviation: the corrected points' hybrid FK against the plan's "
        "URDF FK, with the served model loaded in the client.\n\n"
        + table([*HEADERS, "max FK deviation (mm)", "max FK deviation (deg)"], [row])
        + f"\n\n{'Every call succeeded' if r['success'] else 'FAILED: ' + r['message']}; largest joint "
        f"correction {1e3 * r['max_correction_rad']:.1f} mrad. Targets (#18): ≤ 250 ms per 1,000 points "
        f"({'met' if np.median(ms) <= 250 else 'not met'} by the median), within 1e-6 mm and 1e-6° "
        f"({'met' if r['max_mm'] <= 1e-6 and r['max_deg'] <= 1e-6 else 'not met'})."
    )


def bounds_part(model_dir: str | None, tmp: Path, repeat: int, rounds: int) -> str:
    """FK round trips of one model served twice, with its error bounds and without them (the same
    model.json less its ``bounds`` section), called in turn by each client with the zero-work server."""
    import shutil

    from bench.report import table

    model_dir, about = served_model(model_dir, tmp)
    plain = tmp / "without_bounds"
    shutil.copytree(model_dir, plain)
    manifest = json.loads((plain / "model.json").read_text())
    if manifest.pop("bounds", None) is None:
        raise SystemExit(f"{model_dir} has no error bounds: retrain it with this version")
    (plain / "model.json").write_text(json.dumps(manifest))
    nodes = [
        start_node(model_dir, tmp / "bounded_node.log", "/bounded"),
        start_node(str(plain), tmp / "plain_node.log", "/plain"),
    ]
    trivial = subprocess.Popen([sys.executable, "-m", "bench.bench_nodes", "--serve-trivial", "pose"], cwd=ROOT)
    kinds = "fk@/bounded,fk@/plain,fk_pose"
    try:
        runs = [result_of(run_client(rounds, kinds=kinds)) for _ in range(repeat)]
    finally:
        stop([*nodes, trivial])
    ms = {k: [np.array(r["times"][k]) * 1e3 for r in runs] for k in kinds.split(",")}

    def ratios(a: str, b: str) -> np.ndarray:
        return np.array([np.median(x) / np.median(y) for x, y in zip(ms[a], ms[b], strict=True)])

    with_without, with_zero, without_zero = (
        ratios("fk@/bounded", "fk@/plain"),
        ratios("fk@/bounded", "fk_pose"),
        ratios("fk@/plain", "fk_pose"),
    )
    pooled = {k: np.concatenate(v) for k, v in ms.items()}
    rows = [
        ["FK, one configuration, with its error bounds", *stats(pooled["fk@/bounded"])],
        ["FK, one configuration, the same model without bounds", *stats(pooled["fk@/plain"])],
        ["ComputeFK to a zero-work server, one prebuilt pose", *stats(pooled["fk_pose"])],
    ]

    def spread(r: np.ndarray) -> str:
        return f"**{np.median(r):.2f}×** (spread {r.min():.2f}-{r.max():.2f})"

    return (
        f"kinematics_node serving {about} twice, in two namespaces: with the model's error bounds, and with the "
        f"same model.json less its `bounds` section. Each client process calls both and the zero-work server in "
        f"turn, {rounds:,} rounds; {repeat} clients one after the other (the table pools their calls; the "
        "ratios are the median of the clients' ratios of medians).\n\n"
        + table(HEADERS, rows)
        + f"\n\nFK round trip with bounds against without: {spread(with_without)}. Against the zero-work server: "
        f"with bounds {spread(with_zero)}, without {spread(without_zero)}; target ≤ {FK_TARGET}× with bounds: "
        f"{'met' if np.median(with_zero) <= FK_TARGET else 'not met'}."
    )


def write_parts(new: dict[str, str]) -> None:
    """Replace the measured parts of the nodes section of BENCHMARKS.md and keep the others."""
    import re

    from bench.report import BENCHMARKS, write_section

    text = BENCHMARKS.read_text() if BENCHMARKS.exists() else ""
    section = re.search(r"<!-- section:nodes -->.*?<!-- end:nodes -->", text, re.S)
    old = (
        dict(re.findall(r"<!-- part:(\w+) -->\n(.*?)\n<!-- end-part:\1 -->", section.group(0), re.S)) if section else {}
    )
    parts = {**old, **new}
    body = "\n\n".join(f"<!-- part:{k} -->\n{parts[k].strip()}\n<!-- end-part:{k} -->" for k in PARTS if k in parts)
    write_section("nodes", TITLE, body)


def main(only: list[str], model_dir: str | None, repeat: int, rounds: int) -> None:
    from datetime import UTC, datetime

    os.environ["ROS_DOMAIN_ID"] = str(40 + os.getpid() % 50)
    os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
    tmp = Path(tempfile.mkdtemp())
    command = " ".join(["python -m bench.bench_nodes", *sys.argv[1:]])
    served = f"model {model_dir}" if model_dir else "the analytic UR10 (no model_dir)"
    parts: dict[str, str] = {}

    def measured(name: str, run, what: str) -> None:
        load_before = os.getloadavg()[0]
        start = time.perf_counter()
        body = run()
        stamp = datetime.now(UTC).strftime("%Y-%m-%d %H:%M UTC")
        parts[name] = (
            f"*{name}: `{command}`, {stamp}, {time.perf_counter() - start:.0f} s, {what}; 1-minute load average "
            f"{load_before:.1f} before and {os.getloadavg()[0]:.1f} after (2 cores, shared).*\n\n{body}"
        )

    node_parts = [p for p in only if p not in ("ik", "compensate", "bounds")]
    if node_parts:
        node = start_node(model_dir, tmp / "node.log")
        trivial = [
            subprocess.Popen([sys.executable, "-m", "bench.bench_nodes", "--serve-trivial", kind], cwd=ROOT)
            for kind in ("trigger", "empty", "pose")
        ]
        what = f"kinematics_node serving {served}"
        try:
            time.sleep(3)
            if "latency" in only:
                measured("latency", lambda: latency_part(repeat, rounds), what)
            if "fk_batch" in only:
                measured("fk_batch", fk_batch_part, what)
            if "load" in only:
                measured("load", lambda: load_part(node.pid), what)
        finally:
            stop([node, *trivial])
    if "ik" in only:
        measured("ik", lambda: ik_part(model_dir, tmp), "FK and IK round trips side by side")
    if "compensate" in only:
        measured("compensate", lambda: compensate_part(model_dir, tmp), "trajectory compensation")
    if "bounds" in only:
        measured("bounds", lambda: bounds_part(model_dir, tmp, repeat, rounds), "FK with and without error bounds")
    write_parts(parts)


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

    from hybrid_kinematics_ros.kinematics.robot_config import load_robot_config

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
    names = list(load_robot_config("ur10").chain.joint_names)
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
    parser.add_argument(
        "model_dir", nargs="?", help="the model to serve (default: the analytic UR10; compensation trains a small one)"
    )
    parser.add_argument("--only", default=",".join(PARTS), help=f"comma-separated parts of {', '.join(PARTS)}")
    parser.add_argument("--repeat", type=int, default=5, help="latency: clients one after the other")
    parser.add_argument("--rounds", type=int, default=2000, help="latency: rounds per client")
    parser.add_argument("--compensate-client")
    parser.add_argument("--calls", type=int, default=10)
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
    elif args.compensate_client:
        print(json.dumps(compensate_client(args.compensate_client, args.calls)))
    else:
        only = args.only.split(",")
        unknown = sorted(set(only) - set(PARTS))
        if unknown:
            parser.error(f"--only: unknown part(s) {', '.join(unknown)}; choose from {', '.join(PARTS)}")
        main(only, args.model_dir, args.repeat, args.rounds)
