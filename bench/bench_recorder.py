"""Recorder throughput: the simulated cell at 110 Hz + 3 kHz into the recorder for minutes on end.

Usage: python -m bench.bench_recorder [--minutes M]
       python -m bench.bench_recorder --simulated-minutes 60

``--simulated-minutes``: the recorder's path without ROS transport, faster than real time: synthetic
stamped messages of the simulated cell (3 kHz tracker, 110 Hz joints) go into the raw bag writer and the
:class:`StreamingAligner` as the node's callbacks pass them, a worker thread aligns segments as the node's
does, and their pairs are written into the bag. Resident memory is read from /proc after every simulated
minute. Nothing can be lost in transport here; "dropped" counts messages fed but missing from the bag.

Both nodes run as the executables ``ros2 run`` would start. The sim logs what it published and how late
(its publish jitter); the bag tells what the recorder kept. Dropped = published − recorded. CPU and
resident memory of both processes are sampled from /proc every few seconds. The tracker runs without noise
here, so the aligned pairs against the virtual robot's true poses measure what alignment alone costs
(interpolation, the estimated clock offset).
"""

from __future__ import annotations

import argparse
import os
import re
import signal
import subprocess
import tempfile
import time
from pathlib import Path

import numpy as np
import yaml

from bench.report import table, write_section
from hybrid_kinematics_ros.io.pairs import RAW_JOINTS_TOPIC, RAW_POSE_TOPIC, read_pairs
from hybrid_kinematics_ros.io.raw_bag import read_raw
from hybrid_kinematics_ros.kinematics import se3
from hybrid_kinematics_ros.kinematics.robot_config import load_robot_config
from hybrid_kinematics_ros.simulation.truth import TrueRobot

ROOT = Path(__file__).resolve().parents[1]
LIB = ROOT / "install" / "hybrid_kinematics_ros" / "lib" / "hybrid_kinematics_ros"
TICK = os.sysconf("SC_CLK_TCK")


def start(name: str, log: Path, *args: str) -> subprocess.Popen:
    return subprocess.Popen(
        [str(LIB / name), "--ros-args", *args],
        stdout=log.open("w"),
        stderr=subprocess.STDOUT,
        start_new_session=True,
    )


def cpu_seconds(pid: int) -> float:
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / TICK  # utime + stime


def rss_mb(pid: int) -> float:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024
    return float("nan")


def stop(proc: subprocess.Popen, timeout: float) -> int:
    os.killpg(proc.pid, signal.SIGINT)
    try:
        return proc.wait(timeout)
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGKILL)
        return proc.wait()


def simulated(minutes: int) -> None:
    import struct
    import threading

    from hybrid_kinematics_ros.calibration.windowed import StreamingAligner
    from hybrid_kinematics_ros.io.pairs import JOINT_STATE, POSE_STAMPED, TYPESTORE, joint_state_msg, pose_stamped_msg
    from hybrid_kinematics_ros.io.raw_bag import BagWriter, write_pairs_into
    from hybrid_kinematics_ros.kinematics.se3 import pose_from_matrix
    from hybrid_kinematics_ros.simulation.cell import VirtualCell
    from hybrid_kinematics_ros.simulation.trajectory import random_waypoints, through

    cfg = load_robot_config("ur10")
    cell = VirtualCell.from_config(cfg, noise=True)
    rng = np.random.default_rng(7)
    traj = through(random_waypoints(cfg.chain, 15 * minutes, rng), 0.25, 0.3)
    offset, t0 = 0.0123, 1_700_000_000_000_000_000
    template = bytearray(
        TYPESTORE.serialize_cdr(pose_stamped_msg(0, "tracker", np.zeros(3), [0, 0, 0, 1]), POSE_STAMPED)
    )
    n_frame = struct.unpack_from("<I", template, 12)[0]
    values_at = 4 + ((12 + n_frame + 7) & ~7)
    fed = {"joints": 0, "poses": 0}
    rss, wall = [], time.perf_counter()
    with tempfile.TemporaryDirectory() as tmp:
        writer = BagWriter(Path(tmp) / "simulated")
        writer.add_topic(RAW_JOINTS_TOPIC, JOINT_STATE)
        writer.add_topic(RAW_POSE_TOPIC, POSE_STAMPED)
        aligner = StreamingAligner(cfg.chain)
        ready: list = []
        worker: threading.Thread | None = None
        pid = os.getpid()
        rss.append(rss_mb(pid))
        for second in range(60 * minutes):
            tj = second + np.arange(0.0, 1.0, 1 / 110)
            tp = second + np.arange(0.0, 1.0, 1 / 3000)
            p, quat = pose_from_matrix(cell.measure(traj(tp), rng))
            stamps_p = t0 + np.round((tp + offset) * 1e9).astype(np.int64)
            values = np.hstack([p, quat])
            for stamp, q in zip(t0 + np.round(tj * 1e9).astype(np.int64), traj(tj), strict=True):
                writer.write_msg(RAW_JOINTS_TOPIC, int(stamp), joint_state_msg(int(stamp), cfg.chain.joint_names, q))
                aligner.add_joints(int(stamp), q, int(stamp))
                fed["joints"] += 1
            for stamp, v in zip(stamps_p, values, strict=True):
                stamp = int(stamp)
                struct.pack_into("<iI", template, 4, stamp // 1_000_000_000, stamp % 1_000_000_000)
                struct.pack_into("<7d", template, values_at, *v)
                writer.write(RAW_POSE_TOPIC, stamp, template)
                aligner.add_pose(stamp, v, "tracker")
                fed["poses"] += 1
            while ready:  # the node's timer: pairs of finished segments into the bag
                segment = ready.pop(0)
                write_pairs_into(writer, segment.result.pairs, segment.log_ns)
            if worker is None or not worker.is_alive():
                worker = threading.Thread(target=lambda: ready.extend(aligner.poll()), daemon=True)
                worker.start()
            if (second + 1) % 60 == 0:
                rss.append(rss_mb(pid))
        worker.join()
        writer.split()
        stop_start = time.perf_counter()
        for segment in ready + aligner.poll(final=True):
            write_pairs_into(writer, segment.result.pairs, segment.log_ns)
        finalise_s = time.perf_counter() - stop_start
        writer.close()
        rss.append(rss_mb(pid))
        counts = dict(writer.counts)
        hwm = next(
            int(x.split()[1]) / 1024
            for x in Path("/proc/self/status").read_text().splitlines()
            if x.startswith("VmHWM:")
        )
        retained_peak = aligner.peak_retained
        clock = aligner.summary_clock()
    wall = time.perf_counter() - wall
    rss = np.array(rss)
    growth = rss[-1] - rss[0]
    running = rss[1:-1]  # once a simulated minute while recording (the last sample is after the stop)
    plateau = float(running[len(running) // 4 :].max()) - rss[0]  # the highest once settled, over the start
    late = running[len(running) // 2 :]  # the second half: is there still a trend?
    slope_h = 60.0 * float(np.polyfit(np.arange(len(late)), late, 1)[0])  # MB an hour, from per-minute samples
    dropped_j = fed["joints"] - counts.get(RAW_JOINTS_TOPIC, 0)
    dropped_p = fed["poses"] - counts.get(RAW_POSE_TOPIC, 0)
    body = (
        f"**Simulated time, not wall-clock time**: {minutes} minutes of the recorder's path fed faster than real "
        f"time (`--simulated-minutes`, no ROS transport: synthetic CDR messages of the simulated UR10 cell, "
        f"tracker 3 kHz with 15 µm noise and a 12.3 ms clock offset, joints 110 Hz, into the raw bag writer and "
        f"the streaming aligner, segments aligned by a worker thread as in the node); {wall / 60:.1f} min of wall "
        f"time. Resident memory of the process (`/proc/self/status` VmRSS) once a simulated minute.\n\n"
        + table(
            ["measure", "value"],
            [
                [
                    "joint states fed / in the bag / dropped",
                    f"{fed['joints']:,} / {counts.get(RAW_JOINTS_TOPIC, 0):,} / {dropped_j}",
                ],
                [
                    "tracker poses fed / in the bag / dropped",
                    f"{fed['poses']:,} / {counts.get(RAW_POSE_TOPIC, 0):,} / {dropped_p}",
                ],
                ["pairs written", f"{aligner.pairs:,}"],
                ["pairs rejected, by reason", ", ".join(f"{k} {v}" for k, v in (+aligner.rejected).items()) or "none"],
                ["clock offset, estimated / true (ms)", f"{1e3 * clock.offset_s:.3f} / {1e3 * offset:.3f}"],
                ["samples held, peak", f"{retained_peak:,}"],
                ["RSS at start / after 1 min / at end (MB)", f"{rss[0]:.0f} / {rss[1]:.0f} / {rss[-1]:.0f}"],
                [f"RSS growth over {minutes} min, at the end after the stop (MB)", f"{growth:.0f}"],
                [
                    "RSS plateau: highest minute sample from the first quarter on, and its growth over the start (MB)",
                    f"{rss[0] + plateau:.0f} / +{plateau:.0f}",
                ],
                [
                    "RSS peak (VmHWM, transient, while a segment's clock is estimated), and over the start (MB)",
                    f"{hwm:.0f} / +{hwm - rss[0]:.0f}",
                ],
                ["RSS trend over the second half (MB/h)", f"{slope_h:.1f}"],
                [
                    "projected RSS growth for 8 h: plateau + trend (MB)",
                    f"{plateau + max(slope_h, 0.0) * (8 - minutes / 60):.0f}",
                ],
                ["aligning the last segment on stop (s)", f"{finalise_s:.1f}"],
            ],
        )
        + "\n\nRSS once a simulated minute (MB): "
        + ", ".join(f"{x:.0f}" for x in rss)
    )
    write_section("recorder_8h", "Recorder memory over long sessions (issue 17): simulated 60 minutes", body)


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--minutes", type=float, default=10.0)
    parser.add_argument("--simulated-minutes", type=int, default=0, help="the recorder's path, faster than real time")
    args = parser.parse_args()
    if args.simulated_minutes:
        simulated(args.simulated_minutes)
        return
    seconds = 60.0 * args.minutes
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp)
        recorder = start(
            "recorder_node",
            out / "recorder.log",
            *("-p", f"output_dir:={out}", "-p", "bag_name:=throughput", "-p", "pairs_frame_id:=base_link"),
        )
        time.sleep(3.0)  # discovery before the first message
        sim_config = ROOT / "config" / "sim_cell.yaml"
        sim = start("sim_cell_node", out / "sim.log", "--params-file", str(sim_config), "-p", "noise:=false")
        samples = {"sim": [], "recorder": []}
        t_start = time.perf_counter()
        cpu0 = {"sim": cpu_seconds(sim.pid), "recorder": cpu_seconds(recorder.pid)}
        while time.perf_counter() - t_start < seconds:
            time.sleep(5.0)
            for name, proc in (("sim", sim), ("recorder", recorder)):
                samples[name].append(rss_mb(proc.pid))
        elapsed = time.perf_counter() - t_start
        cpu = {
            "sim": (cpu_seconds(sim.pid) - cpu0["sim"]) / elapsed,
            "recorder": (cpu_seconds(recorder.pid) - cpu0["recorder"]) / elapsed,
        }
        stop(sim, 30)
        time.sleep(2.0)  # the last messages in flight
        stop_start = time.perf_counter()
        code = stop(recorder, 600)
        finalise_s = time.perf_counter() - stop_start
        sim_log = (out / "sim.log").read_text()
        published = re.findall(r"published (\d+) joint states, (\d+) tracker poses \((\d+) lost", sim_log)[-1]
        late = re.findall(r"lateness p50 (\d+) µs, p99 (\d+) µs", sim_log)[-1]
        rec = read_raw(out / "throughput", RAW_JOINTS_TOPIC, RAW_POSE_TOPIC)
        meta = yaml.safe_load((out / "throughput" / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
        sim_params = yaml.safe_load(sim_config.read_text())["sim_cell_node"]["ros__parameters"]
        cfg = load_robot_config(sim_params["robot"])
        pairs = read_pairs(out / "throughput", cfg.chain.joint_names)
        pos_err, rot_err = se3.pose_errors(pairs.T, TrueRobot.from_config(cfg).fk(pairs.q))
        offset_ms = 1e3 * float(meta["custom_data"]["clock_offset_s"])
        rejected = {k[len("rejected_") :]: v for k, v in meta["custom_data"].items() if k.startswith("rejected_")}
    joints_pub, poses_pub, beam = (int(x) for x in published)
    rows = [
        ["joint states (110 Hz)", joints_pub, len(rec.joint_stamps), joints_pub - len(rec.joint_stamps)],
        ["tracker poses (3 kHz)", poses_pub, len(rec.pose_stamps), poses_pub - len(rec.pose_stamps)],
    ]
    dt_j = np.diff(rec.joint_stamps) * 1e-9
    dt_p = np.diff(rec.pose_stamps) * 1e-9
    body = (
        f"The simulated cell (`config/sim_cell.yaml`: joints at 110 Hz, tracker at 3 kHz with beam breaks) "
        f"published into the recorder for {elapsed / 60:.1f} min; both nodes ran as installed executables on "
        f"this 2-core machine, the tracker without noise. Recorder exit code {code} after SIGINT; finalising (aligning "
        f"{len(rec.joint_stamps):,} joint states against {len(rec.pose_stamps):,} tracker poses and writing the "
        f"pairs) took {finalise_s:.1f} s. {beam:,} tracker samples fell into simulated beam breaks and were "
        "never published.\n\n"
        + table(["stream", "published", "recorded", "dropped"], rows)
        + "\n\n"
        + table(
            ["measure", "value"],
            [
                ["joint-state rate, from the recorded stamps (Hz)", 1.0 / dt_j.mean()],
                ["tracker rate, from the recorded stamps, beam breaks excluded (Hz)", 1.0 / np.median(dt_p)],
                ["sim publish lateness p50 (µs)", float(late[0])],
                ["sim publish lateness p99 (µs)", float(late[1])],
                ["sim CPU (cores)", cpu["sim"]],
                ["aligned pairs", len(pairs)],
                ["pairs rejected, by reason", ", ".join(f"{k} {v}" for k, v in rejected.items()) or "none"],
                [
                    "clock offset, estimated / true (ms)",
                    f"{offset_ms:.3f} / {1e3 * sim_params['tracker_clock_offset_s']:.3f}",
                ],
                [
                    "alignment position error, mean / p99 (µm)",
                    f"{1e3 * pos_err.mean():.2f} / {1e3 * np.percentile(pos_err, 99):.2f}",
                ],
                [
                    "alignment orientation error, mean / p99 (µdeg)",
                    f"{1e6 * rot_err.mean():.1f} / {1e6 * np.percentile(rot_err, 99):.1f}",
                ],
                ["recorder CPU (cores)", cpu["recorder"]],
                ["sim resident memory, start / end (MB)", f"{samples['sim'][0]:.0f} / {samples['sim'][-1]:.0f}"],
                [
                    "recorder resident memory, start / end (MB)",
                    f"{samples['recorder'][0]:.0f} / {samples['recorder'][-1]:.0f}",
                ],
            ],
        )
    )
    write_section("throughput", "Recorder throughput: 110 Hz + 3 kHz for minutes", body)


if __name__ == "__main__":
    main()
