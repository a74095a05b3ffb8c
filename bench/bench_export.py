"""What each exported file keeps.

- ``export``: the real UR10 (series A) trained with ``train``'s recipe on four fifths of its poses, each export
  format judged on the held-out fifth (contiguous blocks) in the tracker frame, at the probe, beside the full
  model and the uncalibrated URDF.
- ``export_round_trip``: a virtual UR10 whose truth moves every joint origin and the flange, calibrated; each
  file written, read back as its users read it (the UR file built into a URDF the way ur_description's xacro
  builds it, the DH table composed from its YAML by hand), and compared with the stage's rigid FK over 10,000
  configurations.

Usage: python -m bench.bench_export [--steps S] [--sections export export_round_trip]
"""

from __future__ import annotations

import argparse
import tempfile
from dataclasses import replace
from pathlib import Path

import numpy as np
import yaml
from scipy.spatial.transform import Rotation

from bench.bench_real import fit_recipe, load_series
from bench.report import table, write_section
from hybrid_kinematics_ros.calibration import train
from hybrid_kinematics_ros.calibration.export import (
    FORMATS,
    LEFT_BEHIND,
    Exported,
    export,
    held_out_errors,
    split_along_axis,
)
from hybrid_kinematics_ros.calibration.fit import split
from hybrid_kinematics_ros.io.pairs import Pairs
from hybrid_kinematics_ros.kinematics import fk, se3
from hybrid_kinematics_ros.kinematics.chain import chain_from_urdf
from hybrid_kinematics_ros.kinematics.robot_config import load_robot_config
from hybrid_kinematics_ros.kinematics.ur_kinematics import read_ur_kinematics, urdf_from_ur_kinematics
from hybrid_kinematics_ros.model.hybrid import HybridModel
from hybrid_kinematics_ros.model.parametric import model_from_manifest
from hybrid_kinematics_ros.simulation.cell import VirtualCell
from hybrid_kinematics_ros.simulation.sampling import sample_joints


def trained_on_a(steps: int, out: Path | None = None) -> tuple[HybridModel, Pairs, Pairs]:
    """The real UR10's model of series A with ``train``'s recipe on four fifths (contiguous blocks): the model,
    its training pairs and the held-out fifth. ``out``: the model directory to keep."""
    cfg = load_robot_config("ur10")
    train_pairs, _, held_out = split(load_series("A", cfg.chain.joint_names), 0, (0.0, 0.2))
    model, *_ = fit_recipe(cfg, [train_pairs], train.PRESETS["fast"], (), 10.0, steps, out=out)
    return model, train_pairs, held_out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--steps", type=int, default=6000, help="optimiser steps per net")
    parser.add_argument("--sections", nargs="+", default=["export", "export_round_trip"])
    args = parser.parse_args()
    if "export_round_trip" in args.sections:
        round_trip(min(args.steps, 1000))
    if "export" in args.sections:
        real(args.steps)


def real(steps: int) -> None:
    model, train_pairs, test = trained_on_a(steps)
    rows = []
    for form in FORMATS:
        exported = export(model, form)
        errors = held_out_errors(model, exported, [test])
        if not rows:
            for name, label in (("nominal", "URDF model, uncalibrated"), ("hybrid", "full model (served)")):
                rows.append([label, "", *_figures(errors[name])])
        beyond = [item for item in exported.left if item != LEFT_BEHIND and form != "dh"]
        notes = ["the file's notes name the parallel axes, the base and the tool frame"] if form == "dh" else []
        rows.append([f"exported {form}", "; ".join(beyond + notes), *_figures(errors["exported"])])
        if form == "ur-kinematics":  # as a UR user deploys it: the file, and the printed TCP offset
            with_tcp = replace(exported, chain=exported.chain.with_tool(exported.tip_correction))
            errors = held_out_errors(model, with_tcp, [test])
            rows.append(["exported ur-kinematics and its TCP offset", "", *_figures(errors["exported"])])
    head = ["model", "left behind besides the elastic terms and the nets", "pos. mean (mm)", "pos. p95 (mm)"]
    head.append("ori. mean (deg)")
    body = f"Real UR10, series A: {len(train_pairs)} poses to train, {len(test)} held out.\n\n" + table(head, rows)
    write_section("export", "What each exported file keeps (bench_export)", body)


def round_trip(steps: int, count: int = 10_000) -> None:
    cfg = load_robot_config("ur10")
    cell = VirtualCell.from_config(cfg, seed=7)
    poses = cell.pairs(sample_joints(cfg.chain, 2000, np.random.default_rng(7)), seed=7)
    model, *_ = fit_recipe(cfg, [poses], train.PRESETS["fast"], (), 5.0, steps)
    chain = model.chain
    q = sample_joints(chain, count, np.random.default_rng(8))
    stage = model_from_manifest(chain, model.manifest["parametric"], rigid=True).fk(q)
    truth = cell.robot.actual.post
    flange = se3.inverse(chain.post) @ model_from_manifest(chain, model.manifest["parametric"], rigid=True).chain.post
    _, across = split_along_axis(chain.post @ flange @ se3.inverse(chain.post), chain.axes[-1])
    rows = [["URDF", *_worst(fk.fk(export(model, "urdf").chain, q), stage)]]
    ur_tip = _ur_file_fk(export(model, "ur-kinematics"), chain.urdf_text, q)
    rows.append(["UR kinematics file", *_worst(ur_tip @ se3.inverse(chain.post) @ across @ chain.post, stage)])
    rows.append(["UR kinematics file, the flange across wrist 3 left out", *_worst(ur_tip, stage)])
    for convention in ("standard", "modified"):
        text = export(model, "dh", convention).text
        rows.append([f"DH table, {convention}", *_worst(_dh_text_fk(text, q), stage)])
    head = ["file, read back", "max position (µm)", "max rotation (µrad)"]
    shift, turn = se3.pose_errors(truth[None], cfg.chain.post[None])
    body = (
        f"Virtual UR10 (seed 7), 2,000 poses; its truth moves every joint origin and the flange "
        f"({shift[0]:.3f} mm, {turn[0]:.4f} deg). Each file against the stage's rigid FK at {count:,} "
        "configurations.\n\n" + table(head, rows)
    )
    write_section("export_round_trip", "Exported files read back (bench_export)", body)


def _worst(a: np.ndarray, b: np.ndarray) -> list[str]:
    mm, deg = se3.pose_errors(a, b)
    return [f"{mm.max() * 1e3:.4f}", f"{np.radians(deg.max()) * 1e6:.4f}"]


def _ur_file_fk(exported: Exported, template: str, q: np.ndarray) -> np.ndarray:
    """FK of the UR file as ur_robot_driver's users get it: written, read, built into ur_description's URDF,
    from base_link_inertia (the embedded UR10's base link) to tool0, with tool0 turned to the embedded one's
    (a fixed rotation, the same at every pose)."""
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "calibrated.yaml"
        path.write_text(exported.text)
        built = chain_from_urdf(urdf_from_ur_kinematics(read_ur_kinematics(path), template), *_UR_ENDS)
    zero = np.zeros((1, built.dof))
    return fk.fk(built, q) @ se3.inverse(fk.fk(built, zero)[0]) @ fk.fk(exported.chain, zero)[0]


_UR_ENDS = ("base_link_inertia", "tool0")


def _dh_text_fk(text: str, q: np.ndarray) -> np.ndarray:
    """FK composed by hand from the DH file's YAML: base · A_1 ··· A_n · tool, each A standard
    (Rz(θ) Tz(d) Tx(a) Rx(α)) or modified (Rx(α) Tx(a) Rz(θ) Tz(d))."""
    data = yaml.safe_load(text)

    def pose(entry: dict) -> np.ndarray:
        return se3.from_rotvec(entry["xyz_m"], Rotation.from_euler("xyz", entry["rpy_rad"]).as_rotvec())[0]

    def about(axis: str, angle: np.ndarray) -> np.ndarray:
        return se3.from_rotvec(np.zeros((len(angle), 3)), np.outer(angle, {"x": [1, 0, 0], "z": [0, 0, 1]}[axis]))

    def along(axis: str, length: float) -> np.ndarray:
        return se3.from_rotvec(length * np.array({"x": [1.0, 0, 0], "z": [0, 0, 1.0]}[axis]), np.zeros(3))[0]

    out = np.broadcast_to(pose(data["base"]), (len(q), 4, 4))
    for k, row in enumerate(data["joints"]):
        theta = row["theta_offset_rad"] + q[:, k]
        alpha = np.full(len(q), row["alpha_rad"])
        if data["convention"] == "standard":
            out = out @ about("z", theta) @ along("z", row["d_m"]) @ along("x", row["a_m"]) @ about("x", alpha)
        else:
            out = out @ about("x", alpha) @ along("x", row["a_m"]) @ about("z", theta) @ along("z", row["d_m"])
    return out @ pose(data["tool"])


def _figures(stats: dict) -> list[str]:
    keys = ("position_mm_mean", "position_mm_p95", "orientation_deg_mean")
    return [f"{stats[key]:.4f}" for key in keys]


if __name__ == "__main__":
    main()
