"""The tracker's clock from the data: offset and skew found by ``align`` (what ``hybrid-kinematics align`` and the
recorder's own alignment run) on simulated raw recordings with a known clock.

The simulated UR10 cell (``simulation/recording.py``): its truth robot, tracker noise 15 µm, the joints at
110 Hz; the tracker at the robot's base, or placed as a real cell places it (``PLACED``: 2.6 m away, turned by
126°, the target off the flange), where it measures in its own frame. The tracker's clock runs 12.3 ms ahead
of the robot's, and in the long recording it drifts by 20 ppm too (12 ms more after 10 minutes).

Usage: python -m bench.bench_clock
"""

from __future__ import annotations

import time

import numpy as np

from bench.report import table, write_section
from hybrid_kinematics_ros.calibration.alignment import align
from hybrid_kinematics_ros.simulation.recording import PLACED, RecordingSpec, simulated_recording

OFFSET_S = 0.0123
SEEDS = (1, 2, 3)


def offset_row(label: str, frames: dict | None, seconds: float = 30.0) -> list:
    """Offset errors of three recordings (seeds), each found with the skew left at zero (too short for one)."""
    errors, times = [], []
    for seed in SEEDS:
        sim = simulated_recording(RecordingSpec(offset_s=OFFSET_S, seconds=seconds, seed=seed, frames=frames))
        start = time.perf_counter()
        result = align(sim.cfg.chain, sim.recording)
        times.append(time.perf_counter() - start)
        errors.append(1e3 * (result.offset_s - OFFSET_S))
    found = " / ".join(f"{e:+.3f}" for e in errors)
    return [label, f"{1e3 * OFFSET_S:.1f} ms", found + " ms", f"{max(abs(e) for e in errors):.3f} ms", _seconds(times)]


def drift_row(drift_ppm: float = 20.0, seconds: float = 600.0) -> list:
    """Offset and skew over a long recording whose tracker clock drifts (the tracker at 500 Hz to keep it quick)."""
    spec = RecordingSpec(
        offset_s=OFFSET_S, seconds=seconds, drift_ppm=drift_ppm, frames=PLACED, waypoints=200, tracker_hz=500.0
    )
    sim = simulated_recording(spec)
    start = time.perf_counter()
    result = align(sim.cfg.chain, sim.recording)
    took = time.perf_counter() - start
    rec = sim.recording
    t = (rec.joint_stamps - rec.joint_stamps[0]) * 1e-9
    found = result.offset_s + result.skew_ppm * 1e-6 * t
    worst = 1e3 * float(np.max(np.abs(found - (OFFSET_S + drift_ppm * 1e-6 * t))))
    return [
        f"{seconds / 60:.0f} min, {drift_ppm:g} ppm drift, tracker placed (tracker at 500 Hz)",
        f"{drift_ppm:g} ppm",
        f"{result.skew_ppm:.2f} ppm",
        f"{result.skew_ppm - drift_ppm:+.2f} ppm; the offset within {worst:.3f} ms everywhere",
        _seconds([took]),
    ]


def _seconds(times: list[float]) -> str:
    return f"{min(times):.1f}-{max(times):.1f} s" if len(times) > 1 else f"{times[0]:.1f} s"


def main() -> None:
    rows = [
        offset_row("30 s, tracker at the base, seeds 1/2/3", None),
        offset_row("30 s, tracker placed, seeds 1/2/3", PLACED),
        offset_row("2 min, tracker placed, seeds 1/2/3", PLACED, seconds=120.0),
        drift_row(),
    ]
    for row in rows:
        print(row, flush=True)
    body = (
        "Simulated raw recordings of the UR10 cell (`simulation/recording.py`: its truth robot, tracker noise "
        "15 µm, joints at 110 Hz, tracker at 3 kHz unless said); `align` finds the tracker's clock from the data, "
        "in whatever frame the tracker measures. The recorder runs the same alignment when it stops "
        "(`test/nodes/test_recorder_real_cell.py` checks it live, with the sim cell and the recorder nodes). "
        "Skew is estimated from 2 minutes on: over 30 s the error model's misfit looks like a few ppm.\n\n"
        + table(["case", "true", "found (error of each)", "worst error", "align time"], rows)
        + "\n\nRecorder memory over long recordings: the `recorder_8h` section (Recorder memory over long sessions)."
    )
    write_section("real_cell_clock", "Recording on a real cell: clock offset and skew in the tracker's own frame", body)


if __name__ == "__main__":
    main()
