"""The figures a report opens with: the robot and the data, before and after, ISO 9283, the capacity, the
working range and a verdict against the user's tolerance.

A customer reads the first screen of a report and decides from it; the sections below it are the evidence.
So everything here is a plain value (it also goes into ``report.json``) built from figures computed
elsewhere: the error statistics of :func:`calibration.evaluate.evaluate`, the ISO 9283 entries of
:func:`calibration.report.iso9283` and the model's manifest. The one piece of maths of its own is the verdict.
"""

from __future__ import annotations

import math
import xml.etree.ElementTree as ET
from collections.abc import Sequence
from dataclasses import dataclass
from datetime import UTC, datetime
from typing import Any

import numpy as np

from hybrid_kinematics_ros.io.pairs import Pairs
from hybrid_kinematics_ros.kinematics.approach import is_channel
from hybrid_kinematics_ros.model.hybrid import HybridModel

# The verdict asks this share of the test poses to lie within the tolerance: the p95 a calibration is
# usually quoted at, and a figure a few outliers (a broken beam, a bumped reflector) cannot decide.
VERDICT_SHARE = 0.95
# Stamps before this are not calendar dates (a simulated clock starts near zero).
FIRST_CALENDAR_STAMP_NS = 946_684_800 * 10**9  # 2000-01-01 UTC
MODELS = ("analytic", "parametric", "hybrid")


def robot_name(model: HybridModel) -> str:
    """The URDF's ``<robot name>``: what the customer calls the robot; the model folder if the URDF has none."""
    try:
        name = ET.fromstring(model.chain.urdf_text).get("name") if model.chain.urdf_text else None
    except ET.ParseError:
        name = None
    return name or (model.path.name if model.path else "robot")


def date_range(stamps_ns: np.ndarray) -> tuple[str, str] | None:
    """The first and last stamp as UTC dates, or None when the stamps are not calendar dates."""
    if len(stamps_ns) == 0 or int(np.min(stamps_ns)) < FIRST_CALENDAR_STAMP_NS:
        return None

    def day(ns: int) -> str:
        return datetime.fromtimestamp(ns / 1e9, tz=UTC).strftime("%Y-%m-%d %H:%M")

    return day(int(np.min(stamps_ns))), day(int(np.max(stamps_ns)))


def share_quantile(values: np.ndarray, share: float = VERDICT_SHARE) -> float:
    """The smallest value that ``share`` of ``values`` lie at or below (an order statistic, not interpolated):
    with it, "p95 within the tolerance" and "95 % of the poses within it" are the same statement."""
    if len(values) == 0:
        return math.nan
    return float(np.sort(values)[_needed(len(values), share) - 1])


def _needed(count: int, share: float) -> int:
    """How many of ``count`` poses make up ``share`` of them, rounded up (at least one)."""
    return max(1, math.ceil(share * count - 1e-9))


def verdict(
    pos_mm: np.ndarray,
    rot_deg: np.ndarray,
    tolerance_mm: float,
    tolerance_deg: float | None = None,
    share: float = VERDICT_SHARE,
) -> dict[str, Any]:
    """PASS when at least ``share`` of the poses lie within ``tolerance_mm`` (and ``tolerance_deg``, if given
    and the data has orientation: both on the same pose), else FAIL; with the line a report prints.

    The test counts poses, so "95 % within 0.1 mm" means what it says. The p95 beside it is
    :func:`share_quantile`, the error that 95 % of the poses lie within; it can differ from the tables'
    interpolated p95 in the third digit.
    """
    has_rot = tolerance_deg is not None and not np.all(np.isnan(rot_deg))
    within = pos_mm <= tolerance_mm
    if has_rot:
        within &= rot_deg <= tolerance_deg
    count = int(np.sum(within))
    passed = len(within) > 0 and count >= _needed(len(within), share)
    fraction = count / len(within) if len(within) else 0.0
    p95_mm = share_quantile(pos_mm, share)
    limit = f"{tolerance_mm:g} mm"
    p95 = f"{p95_mm:.3g} mm"
    if has_rot:
        limit += f" and {tolerance_deg:g} deg"
        p95 += f", {share_quantile(rot_deg, share):.3g} deg"
    shown = math.floor(1000 * fraction + 1e-9) / 10  # floored: a share just short never prints as met
    required = f"{100 * share:g} %"
    figures = f"(p{100 * share:g} {p95}; {shown:g} % within)"
    line = (
        f"PASS: {required} of test poses within {limit} {figures}"
        if passed
        else f"FAIL: fewer than {required} of test poses within {limit} {figures}"
    )
    out: dict[str, Any] = {
        "passed": passed,
        "line": line,
        "share_required": share,
        "share_within": fraction,
        "poses": len(within),
        "tolerance_mm": tolerance_mm,
        "p95_position_mm": p95_mm,
    }
    if tolerance_deg is not None:
        out["tolerance_deg"] = tolerance_deg
        out["orientation_checked"] = has_rot
    return out


def iso_summary(entries: Sequence[dict[str, Any]]) -> dict[str, Any] | None:
    """The worst pose of the ISO 9283 entries: the figure a cell is accepted on."""
    if not entries:
        return None
    return {
        "poses": len(entries),
        "repeats": sorted({e["repeats"] for e in entries}),
        "AP_analytic_mm_max": max(e["AP_analytic_mm"] for e in entries),
        "AP_hybrid_mm_max": max(e["AP_hybrid_mm"] for e in entries),
        "RP_mm_max": max(e["RP_mm"] for e in entries),
    }


def capacity_lines(manifest: dict[str, Any]) -> list[str]:
    """One short line per stage setting and net: what was chosen, and the validation figure that chose it."""
    lines = [] if "parametric" in manifest else ["no parametric stage"]
    if manifest.get("stage_not_served"):
        lines = ["parametric stage not served (worse than the URDF model with only the tracker and target fitted)"]
    refs = manifest.get("referencing") or []
    for ref in [refs] if isinstance(refs, dict) else refs:  # a model of one station may hold one section
        if ref.get("undetermined"):
            lines.append(
                f"target offset partly held at the config's tool in frame '{ref['frame_id']}' (see Referencing)"
            )
    for d in (manifest.get("capacity") or {}).get("decisions", []):
        if d.get("given"):
            lines.append(f"{d['setting']} {d['chosen']} (given)")
            continue
        chosen = next((c for c in d["candidates"] if c["candidate"] == d["chosen"]), None)
        figure = f", validation {chosen['val_position_mm']:.3g} mm" if chosen else ""
        lines.append(f"{d['setting']} {d['chosen']} (of {len(d['candidates'])}{figure})")
    for kind, net in (manifest.get("nets") or {}).items():
        if net.get("silenced"):
            lines.append(f"{kind} net off (no better than the stage on validation)")
            continue
        unit = "deg" if kind == "orientation" else "mm"
        best = net.get(f"best_val_{unit}")
        figure = f", validation {best:.3g} {unit}" if isinstance(best, (int, float)) else ""
        lines.append(f"{kind} net {net.get('arch', '')}{figure}")
    return lines


def working_range(model: HybridModel) -> dict[str, Any]:
    """The joint range the training data covered (model.json's ``trained_range``), in deg (mm for a
    prismatic joint), and the range of each condition channel the nets take."""
    revolute = np.asarray(model.chain.revolute, dtype=bool)
    scale = np.where(revolute, 180.0 / np.pi, 1e3)
    joints = [
        {
            "joint": name,
            "unit": "deg" if rev else "mm",
            "lower": float(lo * s),
            "upper": float(hi * s),
        }
        for name, rev, lo, hi, s in zip(
            model.joint_names, revolute, model.trained_lower, model.trained_upper, scale, strict=True
        )
    ]
    conditions = {
        name: {"lower": c["lower"], "upper": c["upper"]}
        for name, c in (model.manifest.get("conditions") or {}).items()
        if not is_channel(name)
    }
    return {"recorded": "trained_range" in model.manifest, "joints": joints, "conditions": conditions}


@dataclass(frozen=True)
class DataSource:
    """Where the test pairs come from: their ``bags`` and the ``stations`` (frames) they were measured in."""

    bags: Sequence[str]
    stations: Sequence[str] = ()


@dataclass(frozen=True)
class Tolerance:
    """The user's tolerance the verdict judges the hybrid model by: ``mm`` (None: no verdict) and ``deg``
    (None: position alone)."""

    mm: float | None = None
    deg: float | None = None


NO_TOLERANCE = Tolerance()  # no verdict


def summarise(
    model: HybridModel,
    pairs: Pairs,
    report: dict[str, Any],
    errors: dict[str, tuple[np.ndarray, np.ndarray]],
    iso: Sequence[dict[str, Any]],
    source: DataSource,
    tolerance: Tolerance = NO_TOLERANCE,
) -> dict[str, Any]:
    """The summary block's figures. ``report``: :func:`evaluate`'s statistics of these ``pairs``;
    ``errors``: :func:`pose_errors_of`'s per-pose errors (the verdict's input)."""
    dates = date_range(pairs.stamps)
    hybrid_pos, hybrid_rot = errors["hybrid"]
    return {
        "robot": robot_name(model),
        "chain": [model.chain.base_link, model.chain.tip_link],
        "data": {
            "bags": list(source.bags),
            "poses": len(pairs),
            "stations": list(source.stations),
            "from": dates[0] if dates else None,
            "to": dates[1] if dates else None,
        },
        "errors": {name: report[name] for name in MODELS if report.get(name, {}).get("count")},
        "iso9283": iso_summary(iso),
        "capacity": capacity_lines(model.manifest),
        "floor": model.manifest.get("floor"),
        "tracker_floor": model.manifest.get("tracker_floor"),
        "learning_curve": (model.manifest.get("capacity") or {}).get("learning_curve"),
        "working_range": {**working_range(model), "inside": report["inside_calibrated_range"]},
        "verdict": None if tolerance.mm is None else verdict(hybrid_pos, hybrid_rot, tolerance.mm, tolerance.deg),
    }
