"""The main job, end to end on the simulated cell, with real processes:

sim_cell_node -> recorder_node (MCAP bag with aligned pairs) -> hybrid-kinematics train -> evaluate ->
kinematics_node serving the model -> a client calls FK and IK -> a summary table and an HTML report.

Every process started here is stopped when the demo ends or is interrupted.
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
LIB = ROOT / "install" / "hybrid_kinematics_ros" / "lib" / "hybrid_kinematics_ros"
PROCS: list[subprocess.Popen] = []


def say(text: str) -> None:
    print(f"\n=== {text}", flush=True)


def launch(name: str, *args: str, log: Path) -> subprocess.Popen:
    proc = subprocess.Popen(
        [str(LIB / name), "--ros-args", *args],
        stdout=log.open("w"),
        stderr=subprocess.STDOUT,
        cwd=ROOT,
        start_new_session=True,
    )
    PROCS.append(proc)
    return proc


def stop(proc: subprocess.Popen, timeout: float = 60.0) -> None:
    if proc.poll() is None:
        os.killpg(proc.pid, signal.SIGINT)
        try:
            proc.wait(timeout)
        except subprocess.TimeoutExpired:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()


def cli(*args: str) -> str:
    result = subprocess.run(["hybrid-kinematics", *args], cwd=ROOT, stdout=subprocess.PIPE, text=True, check=False)
    if result.returncode != 0:
        raise SystemExit(f"hybrid-kinematics {args[0]} failed (exit {result.returncode})")
    return result.stdout


def wait_for(path: Path, text: str, timeout: float = 90.0) -> None:
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if path.exists() and text in path.read_text():
            return
        time.sleep(0.5)
    raise SystemExit(f"timed out waiting for '{text}' in {path}")


def client_round_trip(model_dir: Path, out: Path, radius: float | None) -> dict:
    """FK and IK through the running kinematics node, checked against the model served as the node serves it."""
    import numpy as np
    import rclpy

    from hybrid_kinematics_interfaces.srv import ComputeFK, ComputeIK
    from hybrid_kinematics_ros.kinematics import se3
    from hybrid_kinematics_ros.model.hybrid import HybridModel
    from hybrid_kinematics_ros.nodes.convert import joint_state_msg, pose_msg

    model = HybridModel.load(model_dir)
    if radius is not None:
        model = model.with_coverage_radius(radius).with_range_policy("parametric")
    rclpy.init()
    node = rclpy.create_node("demo_client")
    try:
        fk = node.create_client(ComputeFK, "/kinematics_node/compute_fk")
        ik = node.create_client(ComputeIK, "/kinematics_node/compute_ik")
        if not (fk.wait_for_service(timeout_sec=60) and ik.wait_for_service(timeout_sec=60)):
            raise SystemExit("the kinematics node did not come up; see " + str(out / "kinematics_node.log"))

        def call(client, request):
            future = client.call_async(request)
            while not future.done():
                rclpy.spin_once(node, timeout_sec=0.05)
            return future.result()

        rng = np.random.default_rng(7)
        q = rng.uniform(model.trained_lower, model.trained_upper, (20, model.chain.dof))
        stamp = node.get_clock().now().to_msg()
        req = ComputeFK.Request(joint_states=[joint_state_msg(qi, model.joint_names, stamp) for qi in q])
        fk_resp = call(fk, req)
        ik_pos, ik_rot, ik_ms, solved = [], [], [], 0
        for target in fk_resp.poses:
            start = time.perf_counter()
            resp = call(ik, ComputeIK.Request(target=target, max_solutions=1))
            ik_ms.append(1e3 * (time.perf_counter() - start))
            if resp.success:
                solved += 1
                T = model.fk_single(np.array(resp.solutions[0].position))
                p, r = se3.pose_errors(
                    T,
                    se3.matrix_from_pose(
                        [target.pose.position.x, target.pose.position.y, target.pose.position.z],
                        [
                            target.pose.orientation.x,
                            target.pose.orientation.y,
                            target.pose.orientation.z,
                            target.pose.orientation.w,
                        ],
                    )[0],
                )
                ik_pos.append(float(p))
                ik_rot.append(float(r))
        many = call(ik, ComputeIK.Request(target=pose_msg(model.fk_single(q[0]), "base_link", stamp), max_solutions=8))
        return {
            "fk_success": fk_resp.success,
            "ik_solved": solved,
            "ik_requests": len(q),
            "ik_position_error_mm_mean": float(np.mean(ik_pos)) if ik_pos else None,
            "ik_orientation_error_deg_mean": float(np.mean(ik_rot)) if ik_rot else None,
            "ik_round_trip_ms_median": float(np.median(ik_ms)),
            "ik_solutions_for_8": len(many.solutions),
        }
    finally:
        node.destroy_node()
        rclpy.shutdown()


def near_trajectory_test_set(bag: Path, out: Path, count: int = 5000) -> None:
    """Fresh virtual-cell measurements (with tracker noise) at configurations within ±0.03 rad of recorded
    ones: the region a calibration covers. A trajectory is a curve in joint space, so this is where the
    model is meant to be used; far from it the nets extrapolate (the demo prints that too)."""
    import numpy as np

    from hybrid_kinematics_ros.io.pairs import Pairs, read_pairs, write_pairs
    from hybrid_kinematics_ros.kinematics.robot_config import load_robot_config
    from hybrid_kinematics_ros.simulation.cell import VirtualCell

    cfg = load_robot_config("ur10")
    recorded = read_pairs(bag, cfg.chain.joint_names)
    rng = np.random.default_rng(123)
    q = recorded.q[rng.integers(0, len(recorded), count)] + rng.uniform(-0.03, 0.03, (count, cfg.chain.dof))
    q = np.clip(q, cfg.chain.lower, cfg.chain.upper)
    T = VirtualCell.from_config(cfg).measure(q, rng)
    write_pairs(out, Pairs(q, T, 10**18 + 10**7 * np.arange(count), cfg.chain.joint_names, cfg.base_link))


MODELS = (("URDF model", "analytic"), ("parametric stage", "parametric"), ("hybrid model", "hybrid"))
ROWS = (
    ("position mean (mm)", "position_mm_mean"),
    ("position p95 (mm)", "position_mm_p95"),
    ("position max (mm)", "position_mm_max"),
    ("orientation mean (deg)", "orientation_deg_mean"),
    ("orientation p95 (deg)", "orientation_deg_p95"),
    ("orientation max (deg)", "orientation_deg_max"),
)
# the two test sets, by what they show: where the recording calibrated the robot, and away from it
TEST_SETS = (
    ("near", "near the recorded trajectory (configurations within 0.03 rad of recorded ones)"),
    ("away", "over 60 % of the joint range, mostly away from the recording: the nets extrapolate there"),
)


def model_columns(evaluation: dict, served: dict | None, radius: float | None) -> list[tuple[str, dict]]:
    """(label, statistics) of each model the evaluation has (the parametric stage is optional), and of the
    hybrid model as served with the coverage radius (``served``: its evaluation), if one was found."""
    columns = [(label, evaluation[k]) for label, k in MODELS if k in evaluation]
    if served is not None:
        columns.append((f"nets within {radius:.2f} rad", served["hybrid"]))
    return columns


def html_report(out: Path, evaluations: dict, served: dict, radius: float | None, ros: dict, meta: dict) -> Path:
    tables = ""
    for key, title in TEST_SETS:
        evaluation = evaluations[key]
        columns = model_columns(evaluation, served.get(key), radius)
        head = "".join(f"<th>{label}</th>" for label, _ in columns)
        rows = "".join(
            f"<tr><td>{label}</td>" + "".join(f"<td>{stats[k]:.5f}</td>" for _, stats in columns) + "</tr>"
            for label, k in ROWS
        )
        tables += (
            f"<h2>Test set {title}</h2><p>{evaluation['pairs']} separate virtual-cell samples with tracker noise.</p>"
        )
        tables += f"<table><tr><th>error</th>{head}</tr>{rows}</table>"
    plots = "".join(
        f'<img src="{Path(p).relative_to(out)}" style="max-width:100%">' for p in evaluations["near"]["plots"]
    )
    page = f"""<!doctype html><html><head><meta charset="utf-8"><title>hybrid_kinematics_ros demo report</title>
<style>body{{font-family:sans-serif;max-width:1000px;margin:2em auto}}
td,th{{padding:4px 10px;border-bottom:1px solid #ddd}}</style>
</head><body><h1>Hybrid kinematics: calibration report (simulated UR10 cell)</h1>
<p>Recording: {meta["pairs"]} aligned pairs, tracker clock offset {meta["offset_ms"]:.3f} ms.</p>
<p>{radius_note(radius)}</p>
{tables}
<p>The full accuracy report over the second test set (workspace, calibrated range, parametric stage):
<a href="accuracy_report/index.html">accuracy_report/index.html</a>.</p>
<h2>Kinematics node</h2><pre>{json.dumps(ros, indent=2)}</pre>
<h2>Error distributions near the recorded trajectory (paper Figs. 4 and 8)</h2>{plots}</body></html>"""
    path = out / "report.html"
    path.write_text(page)
    return path


def radius_note(radius: float | None) -> str:
    if radius is None:
        return "The nets helped at every distance from the recording: no coverage radius is needed."
    return (
        f"Coverage radius {radius:.3f} rad, chosen by hybrid-kinematics evaluate on a third test set over 60 % of "
        "the joint range: beyond it from every recorded configuration, the model served drops the nets and "
        "falls back to its parametric stage (column 'nets within')."
    )


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--record-seconds", type=float, default=150.0)
    parser.add_argument("--train-minutes", type=float, default=3.0)
    parser.add_argument("--out", type=Path, default=ROOT / "out" / "demo")
    args = parser.parse_args()
    out = args.out.resolve()
    if out.exists():
        import shutil

        shutil.rmtree(out)
    out.mkdir(parents=True)
    os.environ.setdefault("ROS_DOMAIN_ID", str(30 + os.getpid() % 60))
    os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
    bag = out / "recording"
    try:
        say(f"1/5 simulated cell (110 Hz joints, 3 kHz tracker) and recorder, {args.record_seconds:g} s")
        sim = launch(
            "sim_cell_node",
            "--params-file",
            str(ROOT / "config" / "sim_cell.yaml"),
            "-p",
            "speed:=0.6",
            "-p",
            "dwell_s:=0.1",
            log=out / "sim_cell_node.log",
        )
        rec = launch(
            "recorder_node",
            "-p",
            f"output_dir:={out}",
            "-p",
            "bag_name:=recording",
            "-p",
            "pairs_frame_id:=base_link",
            "-p",
            "max_joint_speed:=1.5",
            log=out / "recorder_node.log",
        )
        wait_for(out / "recorder_node.log", "recording into")
        for elapsed in range(int(args.record_seconds)):
            if elapsed % 15 == 0:
                print(f"  recording... {elapsed:>4d} s / {args.record_seconds:g} s", flush=True)
            time.sleep(1.0)
        stop(rec, timeout=120)
        stop(sim)
        print("  " + (out / "recorder_node.log").read_text().strip().splitlines()[-1])
        meta = __import__("yaml").safe_load((bag / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
        custom = meta["custom_data"]
        info = {"pairs": int(custom.get("pairs", 0)), "offset_ms": 1e3 * float(custom.get("clock_offset_s", "nan"))}

        say(f"2/5 training the hybrid model ({args.train_minutes:g} min budget)")
        model = out / "model"
        cli(
            "train", "--bag", str(bag), "--robot", "ur10", "--out", str(model), "--max-minutes", str(args.train_minutes)
        )

        say("3/5 evaluating on separate test sets from the virtual cell: near the recording, and away from it")
        test_bags = {"near": out / "test_near_bag", "away": out / "test_away_bag"}
        near_trajectory_test_set(bag, test_bags["near"])
        for name, seed, samples in (("away", "99", "5000"), ("radius", "98", "2000")):
            cli(
                "simulate",
                "--robot",
                "ur10",
                "--samples",
                samples,
                "--out",
                str(out / f"test_{name}_bag"),
                "--seed",
                seed,
                "--range-fraction",
                "0.6",
            )
        # the coverage radius comes from a set of its own, so that the tables below test it fairly
        radius = json.loads(cli("evaluate", "--model", str(model), "--bag", str(out / "test_radius_bag")))["coverage"][
            "suggested_radius_rad"
        ]
        served = (
            {}
            if radius is None
            else {
                key: json.loads(
                    cli("evaluate", "--model", str(model), "--bag", str(path), "--coverage-radius", str(radius))
                )
                for key, path in test_bags.items()
            }
        )
        evaluations = {
            key: json.loads(
                cli(
                    "evaluate",
                    "--model",
                    str(model),
                    "--bag",
                    str(bag_path),
                    "--json",
                    str(out / f"evaluation_{key}.json"),
                    "--plots",
                    str(out / f"plots_{key}"),
                )
            )
            for key, bag_path in test_bags.items()
        }

        cli("report", "--model", str(model), "--bag", str(test_bags["away"]), "--out", str(out / "accuracy_report"))

        say("4/5 kinematics node serving the model; a client calls FK and IK")
        coverage = ["-p", "out_of_range_policy:=parametric", "-p", f"coverage_radius_rad:={radius}"] if radius else []
        node = launch("kinematics_node", "-p", f"model_dir:={model}", *coverage, log=out / "kinematics_node.log")
        ros = client_round_trip(model, out, radius)
        stop(node)

        say("5/5 report")
        report = html_report(out, evaluations, served, radius, ros, info)
        print("\n" + radius_note(radius))
        for key, title in TEST_SETS:
            columns = model_columns(evaluations[key], served.get(key), radius)
            print(f"\nTest set {title}:")
            print(f"{'':28s}" + "".join(f"{label:>22s}" for label, _ in columns))
            for label, k in ROWS:
                print(f"{label:28s}" + "".join(f"{stats[k]:22.5f}" for _, stats in columns))
        print(
            f"\nIK via the node: {ros['ik_solved']}/{ros['ik_requests']} solved, round-trip error "
            f"{ros['ik_position_error_mm_mean']:.2e} mm / {ros['ik_orientation_error_deg_mean']:.2e} deg, "
            f"median {ros['ik_round_trip_ms_median']:.1f} ms; {ros['ik_solutions_for_8']} solutions for an "
            "8-solution request"
        )
        print(f"recording: {bag}  ({info['pairs']} pairs, clock offset {info['offset_ms']:.3f} ms)")
        print(f"report:    {report}  (accuracy report: {out / 'accuracy_report' / 'index.html'})")
        return 0
    finally:
        for proc in PROCS:
            stop(proc, timeout=20)


if __name__ == "__main__":
    signal.signal(signal.SIGTERM, lambda *_: sys.exit(143))
    sys.exit(main())
