"""Accuracy statistics of the analytic and hybrid models against measured poses, and the paper's plots."""

from __future__ import annotations

import itertools
from pathlib import Path
from typing import Any

import numpy as np

from hybrid_kinematics_ros.io.pairs import Pairs
from hybrid_kinematics_ros.kinematics import se3
from hybrid_kinematics_ros.model.hybrid import HybridModel
from hybrid_kinematics_ros.model.referencing import to_base_frame

COVERAGE_BINS_RAD = (0.0, 0.05, 0.1, 0.2, 0.4, 0.8, 1.6, np.inf)


def error_stats(pos_mm: np.ndarray, rot_deg: np.ndarray) -> dict[str, float]:
    if len(pos_mm) == 0:
        return {"count": 0}
    out: dict[str, float] = {"count": len(pos_mm)}
    for name, values in (("position_mm", pos_mm), ("orientation_deg", rot_deg)):
        if np.all(np.isnan(values)):
            continue
        out[f"{name}_mean"] = float(np.mean(values))
        out[f"{name}_median"] = float(np.median(values))
        out[f"{name}_p95"] = float(np.percentile(values, 95))
        out[f"{name}_p99"] = float(np.percentile(values, 99))
        out[f"{name}_max"] = float(np.max(values))
    return out


def in_base_frame(model: HybridModel, pairs: Pairs) -> Pairs:
    """``pairs`` in the base frame, moved with the referencing of their tracker station if they are in one."""
    return to_base_frame([pairs], model.chain, model.referencings)


def target_errors(pairs: Pairs, tip: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Position (mm) and orientation (deg) errors of modelled tip poses ``tip (N, 4, 4)`` against base-frame
    ``pairs``, at the measured target (:attr:`Pairs.target`, which referencing sets).

    That is the error in the measurement's own frame: a rigid change of frame keeps distances and angles,
    so these are the numbers a user gets by mapping the model's FK into the tracker frame with the stored
    referencing and comparing it with the tracker's readings. Position-only pairs hold the target points
    themselves and give no orientation (NaN).
    """
    pos, rot = se3.pose_errors(measured_targets(pairs), tip @ pairs.targets)
    return (pos, np.full_like(pos, np.nan)) if pairs.position_only else (pos, rot)


def measured_targets(pairs: Pairs) -> np.ndarray:
    """``(N, 4, 4)``: the measured target poses in the base frame (position-only: the points, no rotation)."""
    return pairs.T if pairs.position_only else pairs.T @ pairs.targets


def pose_errors_of(model: HybridModel, pairs: Pairs) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """Errors of the URDF model (``analytic``), the parametric stage alone if any, and the hybrid model,
    at the measured target (:func:`target_errors`). Pairs in the tracker frame the model was referenced
    to are moved into the base frame first: for the URDF model with its own referencing (the tracker and
    the target fitted to it alone, :attr:`HybridModel.rigid_referencings`), so that "before" is the best
    the nominal model does, never one inflated by the stage's base and tool corrections.
    """
    nominal = to_base_frame([pairs], model.chain, model.rigid_referencings)
    out = {"analytic": target_errors(nominal, model.fk(nominal.q, analytic=True))}
    pairs = in_base_frame(model, pairs)
    conditions = model.conditions_of(pairs.conditions, len(pairs))
    if model.has_parametric:
        out["parametric"] = target_errors(pairs, model.fk(pairs.q, nets=False, conditions=conditions))
    out["hybrid"] = target_errors(pairs, model.fk(pairs.q, conditions=conditions))
    return out


def evaluate(
    model: HybridModel, pairs: Pairs, errors: dict[str, tuple[np.ndarray, np.ndarray]] | None = None
) -> dict[str, Any]:
    """Statistics for each model, on all pairs and split by the calibrated joint range; ``errors``: their
    :func:`pose_errors_of`, when the caller has them already."""
    errors = pose_errors_of(model, pairs) if errors is None else errors
    inside = model.in_calibrated_range(pairs.q)
    report: dict[str, Any] = {"pairs": len(pairs), "inside_calibrated_range": int(inside.sum())}
    for name, (pos, rot) in errors.items():
        report[name] = error_stats(pos, rot)
        report[f"{name}_inside_range"] = error_stats(pos[inside], rot[inside])
        report[f"{name}_outside_range"] = error_stats(pos[~inside], rot[~inside])
    distance = model.coverage_distance(pairs.q)
    if distance is not None and model.nets:
        base = "parametric" if "parametric" in errors else "analytic"
        report["coverage"] = coverage_report(distance, errors["hybrid"], errors[base], base)
    if not model.has_orientation and model.nets:
        report["note"] = "no orientation net: orientation is the analytic model's, uncorrected"
    if pairs.position_only:
        report["note"] = "position-only pairs: orientation errors cannot be measured"
    return report


def coverage_report(
    distance: np.ndarray, hybrid: tuple[np.ndarray, np.ndarray], base: tuple[np.ndarray, np.ndarray], base_name: str
) -> dict[str, Any]:
    """The errors by joint-space distance (rad) to the nearest training configuration, and the coverage
    radius that minimises the mean position error when the nets are dropped beyond it.

    Near the training data the nets correct what the ``base`` model (the parametric stage, else the URDF)
    misses; far from it they extrapolate and can do worse. The radius is fitted on these pairs, so give it
    pairs that were not used for training.
    """
    bins = []
    for lo, hi in itertools.pairwise(COVERAGE_BINS_RAD):
        inside = (distance >= lo) & (distance < hi)
        if inside.any():
            row: dict[str, Any] = {"from_rad": lo, "to_rad": None if np.isinf(hi) else hi, "count": int(inside.sum())}
            for name, (pos, rot) in (("hybrid", hybrid), (base_name, base)):
                row[f"{name}_position_mm_mean"] = float(np.mean(pos[inside]))
                if not np.all(np.isnan(rot)):
                    row[f"{name}_orientation_deg_mean"] = float(np.mean(rot[inside]))
            bins.append(row)
    # candidate radii: every distance seen; the mean error if the nets are dropped beyond each one
    order = np.argsort(distance)
    d, h, b = distance[order], hybrid[0][order], base[0][order]
    combined = (np.cumsum(h) + (b.sum() - np.cumsum(b))) / len(d)
    best = int(np.argmin(combined))
    radius = None if best == len(d) - 1 else float(d[best])
    return {
        "distance_rad": {
            "median": float(np.median(distance)),
            "p95": float(np.percentile(distance, 95)),
            "max": float(np.max(distance)),
        },
        "fallback": base_name,
        "bins": bins,
        "suggested_radius_rad": radius,
        "position_mm_mean_with_radius": float(combined[best]),  # the last candidate keeps the nets everywhere
    }


def plot_distributions(
    model: HybridModel, pairs: Pairs, out_dir: Path, errors: dict[str, tuple[np.ndarray, np.ndarray]] | None = None
) -> list[Path]:
    """The paper's Figs. 4 and 8: error distributions of each model, URDF to hybrid (PNG); ``errors`` as in
    :func:`evaluate`."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out_dir.mkdir(parents=True, exist_ok=True)
    errors = pose_errors_of(model, pairs) if errors is None else errors
    colors = {"analytic": "tab:orange", "parametric": "tab:green", "hybrid": "tab:blue"}
    paths = []
    for index, (label, unit) in enumerate((("position", "mm"), ("orientation", "deg"))):
        if pairs.position_only and label == "orientation":
            continue
        fig, axes = plt.subplots(1, len(errors), figsize=(5 * len(errors), 3.8))
        for ax, (name, values) in zip(axes, errors.items(), strict=True):
            values = values[index]
            ax.hist(values, bins=60, color=colors[name], alpha=0.85)
            ax.set_title(f"{name}: mean {values.mean():.4g} {unit}")
            ax.set_xlabel(f"{label} error ({unit})")
            ax.set_ylabel("samples")
        fig.suptitle(f"{label} error distribution, {len(pairs)} pairs")
        fig.tight_layout()
        path = out_dir / f"{label}_error_distribution.png"
        fig.savefig(path, dpi=110)
        plt.close(fig)
        paths.append(path)
    return paths
