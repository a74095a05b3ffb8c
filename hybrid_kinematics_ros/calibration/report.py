"""An accuracy report a calibration engineer can hand in: one HTML page with PNG plots.

It opens with a summary block (:mod:`calibration.summary`) that fits the first screen: the robot and the
data, before and after, ISO 9283 AP and RP, the capacity chosen, the working range and a verdict against
the user's tolerance. Then the evidence, section by section: the errors of each model (URDF,
parametric, hybrid) with their distributions; errors over the workspace; inside and outside the
calibrated joint range; ISO 9283-style pose accuracy (AP) and repeatability (RP) where the test data
repeats poses; the referencing; the parametric stage's parameters; and the data-amount curve when one
is given.
"""

from __future__ import annotations

import html
import json
from pathlib import Path
from typing import Any

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from hybrid_kinematics_ros.calibration import capacity as capacity_module
from hybrid_kinematics_ros.calibration.evaluate import evaluate, measured_targets, plot_distributions, pose_errors_of
from hybrid_kinematics_ros.calibration.summary import MODELS, NO_TOLERANCE, DataSource, Tolerance, summarise
from hybrid_kinematics_ros.io.pairs import Pairs
from hybrid_kinematics_ros.kinematics.elastic import JointMap
from hybrid_kinematics_ros.model.hybrid import HybridModel

# Readings of one commanded pose differ by a few encoder counts (6e-6 rad a count at 20 bits) and the
# servo's error; commanded poses of an ISO 9283 cycle are degrees apart.
REPEAT_TOLERANCE_RAD = 1e-4


def repeated_poses(q: np.ndarray, tolerance_rad: float = REPEAT_TOLERANCE_RAD) -> np.ndarray:
    """A group label per row: joint vectors within ``tolerance_rad`` of each other (every joint), directly
    or through a chain of such neighbours, are one commanded pose."""
    pairs_ = cKDTree(q).query_pairs(tolerance_rad, p=np.inf, output_type="ndarray")
    graph = coo_matrix((np.ones(len(pairs_)), (pairs_[:, 0], pairs_[:, 1])), shape=(len(q), len(q)))
    return connected_components(graph, directed=False)[1]


def iso9283(
    model: HybridModel, pairs: Pairs, min_repeats: int = 3, tolerance_rad: float = REPEAT_TOLERANCE_RAD
) -> list[dict[str, Any]]:
    """Pose accuracy and repeatability (ISO 9283, positions) for each commanded pose measured repeatedly.

    AP is the distance from the barycentre of the measured positions to the commanded position (what the
    model says the joints reach), for the URDF and the hybrid model; RP is ``l̄ + 3 s_l`` with ``l`` the
    distances of the measurements to their barycentre, which no model changes.
    """
    inverse = repeated_poses(pairs.q, tolerance_rad)
    counts = np.bincount(inverse)
    targets = measured_targets(pairs)
    out = []
    for group in np.flatnonzero(counts >= min_repeats):
        rows = np.flatnonzero(inverse.ravel() == group)
        measured = targets[rows, :3, 3]
        centre = measured.mean(axis=0)
        spread = np.linalg.norm(measured - centre, axis=1)
        q = pairs.q[rows].mean(axis=0, keepdims=True)  # the commanded pose, as well as the readings tell
        entry = {"pose": len(out) + 1, "repeats": len(rows), "joints_rad": q[0].round(4).tolist()}
        for name, T in (("analytic", model.fk(q, analytic=True)), ("hybrid", model.fk(q))):
            entry[f"AP_{name}_mm"] = float(1e3 * np.linalg.norm(centre - (T[0] @ pairs.targets[rows[0]])[:3, 3]))
        entry["RP_mm"] = float(1e3 * (spread.mean() + 3 * spread.std(ddof=1)))
        out.append(entry)
    return out


def _workspace_plot(errors: dict[str, tuple[np.ndarray, np.ndarray]], pairs: Pairs, path: Path) -> Path:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    p = pairs.T[:, :3, 3]
    fig, axes = plt.subplots(1, 2, figsize=(11, 4.5))
    for ax, (i, j), label in zip(axes, ((0, 1), (0, 2)), ("top view (x, y)", "side view (x, z)"), strict=True):
        pos = errors["hybrid"][0]
        sc = ax.scatter(p[:, i], p[:, j], c=pos, s=4, cmap="viridis", vmax=np.percentile(pos, 99))
        ax.set_title(label)
        ax.set_xlabel(f"{'xyz'[i]} (m)")
        ax.set_ylabel(f"{'xyz'[j]} (m)")
        ax.set_aspect("equal")
        fig.colorbar(sc, ax=ax, label="hybrid position error (mm)")
    fig.suptitle("Hybrid model error over the workspace")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path


def _scale_words(figures: dict[str, Any]) -> str:
    """How much the bound's scale varies over the training configurations, if the model has one."""
    spread = figures.get("position_scale_p5_p95")
    if spread is None:
        return ""
    return f" ({spread[0]:.2f}-{spread[1]:.2f}× that over 90 % of the training configurations: where the stage fits)"


def _bounds_section(model: HybridModel, pairs: Pairs, errors: dict[str, Any], out_dir: Path) -> list[str]:
    """Each test pair's error against its bound (:mod:`model.bounds`), with the share under it."""
    bounds = model.error_bounds(pairs.q)
    if bounds is None:
        return []
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    pos_mm, rot_deg = errors["hybrid"]
    kinds = [("position", pos_mm, 1e3 * bounds[0], "mm")]
    if bounds[1] is not None:
        kinds.append(("orientation", rot_deg, np.degrees(bounds[1]), "deg"))
    fig, axes = plt.subplots(1, len(kinds), figsize=(5.5 * len(kinds), 4.5), squeeze=False)
    rows = []
    for ax, (kind, error, bound, unit) in zip(axes[0], kinds, strict=True):
        under = float(np.mean(error <= bound))
        rows.append([kind, f"{np.median(bound):.4f} {unit}", f"{np.median(error):.4f} {unit}", f"{100 * under:.1f} %"])
        ax.scatter(bound, error, s=4, alpha=0.5)
        top = float(max(bound.max(), error.max()))
        ax.plot([0, top], [0, top], "k--", lw=1, label="error = bound")
        ax.set_xlabel(f"{kind} bound ({unit})")
        ax.set_ylabel(f"{kind} error ({unit})")
        ax.set_title(f"{kind}: {100 * under:.1f} % under the bound")
        ax.legend()
    fig.tight_layout()
    path = out_dir / "bounds.png"
    fig.savefig(path, dpi=100)
    plt.close(fig)
    level = model.bounds.level
    rates = model.bounds.position.rates
    steepest = int(np.argmax(rates))
    return [
        "<h2>Error bounds</h2>",
        f"<p>Each answer of the model carries a bound meant to hold for {100 * level:.0f} % of real errors: "
        f"{1e3 * model.bounds.position.quantile:.4f} mm inside the trained joint range at a typical "
        f"configuration{_scale_words(model.bounds.figures)} (calibrated on the validation blocks), growing beyond "
        "it at rates measured on the stage's extrapolation, at most "
        f"{1e3 * rates[steepest]:.3g} mm per rad ({model.joint_names[steepest]}). On these test pairs:</p>",
        _table(["kind", "median bound", "median error", "errors under their bound"], rows),
        f"<img src='{path.name}' alt='bounds'>",
    ]


def _curve_plot(curve: list[dict[str, Any]], path: Path) -> Path:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(11, 4))
    labels = sorted({row["label"] for row in curve})
    for ax, key, unit in zip(axes, ("position_mm_mean", "orientation_deg_mean"), ("mm", "deg"), strict=True):
        for label in labels:
            rows = sorted((r for r in curve if r["label"] == label and key in r), key=lambda r: r["samples"])
            ax.loglog([r["samples"] for r in rows], [r[key] for r in rows], "o-", label=label)
        ax.set_xlabel("training samples")
        ax.set_ylabel(f"mean test error ({unit})")
        ax.grid(True, which="both", alpha=0.3)
        ax.legend()
    fig.suptitle("Accuracy against the amount of training data")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path


def _joint_map_plot(joint_map: JointMap, names: list[str], path: Path) -> Path:
    """Each joint's mapped error against its angle, where the map is not zero (where the joint went)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(11, 4))
    for k, name in enumerate(names):
        angle = np.degrees(joint_map.lower[k] + joint_map.step * np.arange(joint_map.values.shape[1]))
        ax.plot(angle, np.degrees(joint_map.values[k]) * 3600.0, lw=0.8, label=name)
    ax.set_xlabel("joint angle (deg)")
    ax.set_ylabel("joint error (arcsec)")
    ax.grid(True, alpha=0.3)
    ax.legend(ncol=min(len(names), 7), fontsize="small")
    ax.set_title("Joint error map (parametric stage)")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path


def _table(head: list[str], rows: list[list[Any]]) -> str:
    def cell(v: Any) -> str:
        if isinstance(v, float):
            return f"{v:.4g}"
        return html.escape(str(v))

    body = "".join("<tr>" + "".join(f"<td>{cell(v)}</td>" for v in row) + "</tr>" for row in rows)
    return f"<table><tr>{''.join(f'<th>{html.escape(h)}</th>' for h in head)}</tr>{body}</table>"


def _coverage_section(coverage: dict[str, Any] | None) -> list[str]:
    """Errors by distance to the training data, and the coverage radius that serves them best."""
    if coverage is None:
        return []
    base = coverage["fallback"]
    head = ["distance to training data (rad)", "pairs", "hybrid position mean (mm)", f"{base} position mean (mm)"]
    rows = [
        [
            f"{b['from_rad']:g} to {b['to_rad']:g}" if b["to_rad"] is not None else f"over {b['from_rad']:g}",
            b["count"],
            b["hybrid_position_mm_mean"],
            b[f"{base}_position_mm_mean"],
        ]
        for b in coverage["bins"]
    ]
    radius = coverage["suggested_radius_rad"]
    advice = (
        f"Dropping the nets beyond {radius:.3f} rad (kinematics_node parameter <code>coverage_radius_rad</code> "
        "with <code>out_of_range_policy: parametric</code>) gives a mean position error of "
        f"{coverage['position_mm_mean_with_radius']:.4g} mm on these pairs."
        if radius is not None
        else "The nets help at every distance in these pairs: no coverage radius is needed."
    )
    return [
        "<h2>Distance to the training data</h2>",
        f"<p>Joint-space distance from each test configuration to the nearest training configuration: median "
        f"{coverage['distance_rad']['median']:.3f} rad, p95 {coverage['distance_rad']['p95']:.3f} rad. {advice}</p>",
        _table(head, rows),
    ]


def net_label(net: dict) -> str:
    """The net served as its ladder's rung names it (a manifest's ``nets`` entry): its size, an ensemble's
    members, or the cycles of one longer run (:func:`train.train_net`)."""
    members, cycles = net.get("members", 1), net.get("cycles", 1)
    name = net.get("arch", "") + (f" + {net['offered']}" if net.get("takes_offered") else "")
    return name + (f" x{members}" if members > 1 else "") + (f", {cycles} cycles" if cycles > 1 else "")


def _capacity_section(capacity: dict[str, Any] | None, nets: dict[str, Any]) -> list[str]:
    """One table of every capacity choice: each candidate's held-out figures on the training pairs' blocks."""
    if not capacity and not nets:
        return []
    rows = []
    for d in (capacity or {}).get("decisions", []):
        if d.get("given"):
            rows.append([d["setting"], d["chosen"], "given", "", "", "", ""])
            continue
        for c in d["candidates"]:
            rows.append(
                [
                    d["setting"],
                    c["candidate"],
                    "chosen" if c["candidate"] == d["chosen"] else ("best" if c["candidate"] == d["best"] else ""),
                    c["val_position_mm"],
                    c.get("val_orientation_deg", ""),
                    c.get("worse_than_best_mm", ""),
                    c.get("noise_mm", ""),
                ]
            )
    for kind, net in nets.items():
        state = "off: no better than the stage on validation" if net.get("silenced") else "on"
        if "best_epoch" in net:
            state += f", weights of epoch {net['best_epoch']} of {net.get('epochs', '?')} (best on validation)"
        unit = "mm" if kind == "position" else "deg"
        rungs = net.get("sizes", [])
        shown = net_label(net)
        # its rung: the label served, or (the ensemble fixed by --members) the size with any channel it took
        taken = f" + {net['offered']}" if net.get("takes_offered") else ""
        label = shown if any(size["arch"] == shown for size in rungs) else net.get("arch", "") + taken
        for size in rungs:  # the rungs tried, each judged by its crossed validation error
            val = size.get(f"crossed_val_{unit}")
            val = "" if val is None else val
            if size.get("trained") is False:
                decision = "not trained: " + size.get("why", "the smaller sizes took the budget")
            elif not size["kept"]:
                decision = "not significantly better than the rung below"
            elif size["arch"] == label and not net.get("silenced"):
                decision = "served: significantly better than the rung below"
            else:
                decision = "better than the rung below; a later rung beat it"
            figures = (val, "") if unit == "mm" else ("", val)
            rows.append([f"{kind} net size", size["arch"], decision, *figures, "", ""])
        rows.append([f"{kind} net", shown, state, net.get("best_val_mm", ""), net.get("best_val_deg", ""), "", ""])
    head = [
        "setting",
        "candidate",
        "decision",
        "val. position mean (mm)",
        "val. orientation mean (deg)",
        "score above the best (mm)",
        "noise (mm)",
    ]
    return [
        "<h2>Capacity chosen from the data</h2>",
        "<p>" + (capacity or {}).get("method", "") + ". The score weighs orientation at 1 m per rad. A net's sizes "
        "train simplest first, then the size served reading the condition channels the pairs carry (<i>+ name</i>), "
        "then an ensemble of the net served (<i>xK</i>: K nets averaged), each judged on its "
        "crossed validation error against the rung below it: the rung served before it, or, at first, correcting "
        "nothing.</p>",
        _table(head, rows),
    ]


MODEL_LABELS = {"analytic": "URDF model", "parametric": "parametric stage", "hybrid": "hybrid model"}


def _stats_rows(report: dict[str, Any], suffix: str = "") -> list[list[Any]]:
    rows = []
    for name in MODELS:
        stats = report.get(f"{name}{suffix}")
        if not stats or not stats.get("count"):
            continue
        rows.append(
            [
                MODEL_LABELS[name],
                stats["count"],
                stats["position_mm_mean"],
                stats["position_mm_p95"],
                stats["position_mm_max"],
                stats.get("orientation_deg_mean", "n/a"),
                stats.get("orientation_deg_p95", "n/a"),
                stats.get("orientation_deg_max", "n/a"),
            ]
        )
    return rows


STATS_HEAD = [
    "model",
    "pairs",
    "position mean (mm)",
    "position p95 (mm)",
    "position max (mm)",
    "orientation mean (deg)",
    "orientation p95 (deg)",
    "orientation max (deg)",
]
STYLE = """
body { font-family: sans-serif; margin: 1.2em 2em; max-width: 1150px; color: #222; }
h1 { font-size: 1.6em; margin: 0 0 0.4em; }
table { border-collapse: collapse; margin: 0.5em 0 1.5em; }
th, td { border: 1px solid #bbb; padding: 3px 8px; text-align: right; }
th { background: #eee; } td:first-child { text-align: left; }
img { max-width: 100%; } .note { color: #a33; }
#summary { border: 2px solid #888; border-radius: 6px; padding: 0.2em 1em 0.4em; margin-bottom: 1.5em; }
#summary h2 { font-size: 1.2em; margin: 0.4em 0; } #summary p { margin: 0.35em 0; }
#summary table { margin: 0.3em 0 0.5em; } #summary th:first-child { text-align: left; }
#verdict { font-size: 1.15em; font-weight: bold; } .pass { color: #070; } .fail { color: #b00; }
.basis { color: #555; font-size: 0.9em; }
"""


def _summary_section(s: dict[str, Any]) -> list[str]:
    """The block a report opens with (:func:`calibration.summary.summarise`): verdict first, then what it
    stands on. Every figure is one of the sections' below; this block only picks and orders them."""
    hybrid_mm = s["errors"].get("hybrid", {}).get("position_mm_mean")
    parts = [
        *_verdict_lines(s["verdict"]),
        _data_line(s),
        _errors_table(s["errors"]),
        _iso_line(s["iso9283"]),
        _floor_line(s.get("floor"), hybrid_mm),
        *_tracker_floor_line(s.get("tracker_floor"), hybrid_mm),
    ]
    if s.get("learning_curve"):
        floor_mm = (s.get("floor") or {}).get("position_mm")
        line = capacity_module.curve_line(s["learning_curve"], floor_mm)
        parts.append(f"<p><b>More poses or a richer model?</b> {html.escape(line[0].upper() + line[1:])}.</p>")
    capacity = "; ".join(s["capacity"]) or "nothing chosen (no parametric stage, no nets)"
    parts.append(f"<p><b>Capacity chosen from the data</b> {html.escape(capacity)}.</p>")
    parts += _working_range_lines(s["working_range"], s["data"]["poses"])
    return ["<section id='summary'><h2>Summary</h2>", *parts, "</section>"]


def _verdict_lines(verdict: dict[str, Any] | None) -> list[str]:
    """PASS or FAIL against the tolerance and what it is computed on, or how to ask for one."""
    if verdict is None:
        return [
            "<p id='verdict' class='none'>No tolerance given: pass <code>--tolerance-mm</code> "
            "(and <code>--tolerance-deg</code>) for a PASS or FAIL verdict.</p>"
        ]
    on = "position" + (" and orientation" if verdict.get("orientation_checked") else "")
    skipped = (
        " The data has no orientation, so --tolerance-deg was not checked."
        if verdict.get("orientation_checked") is False
        else ""
    )
    return [
        f"<p id='verdict' class='{'pass' if verdict['passed'] else 'fail'}'>{html.escape(verdict['line'])}</p>",
        f"<p class='basis'>The verdict is computed on the hybrid model's {on} errors at the measured target, "
        f"over all {verdict['poses']} poses of the test data: it passes when at least "
        f"{100 * verdict['share_required']:g} % of them lie within the tolerance. Test poses should be held "
        f"out of training.{skipped}</p>",
    ]


def _data_line(s: dict[str, Any]) -> str:
    """The robot, and the test data: how many poses, from where, measured where and when."""
    esc, data = html.escape, s["data"]
    stations = [f for f in data["stations"] if f != s["chain"][0]]
    where = (
        f"{len(stations)} tracker station{'s' if len(stations) > 1 else ''} ({esc(', '.join(stations))})"
        if stations
        else "in the robot's base frame"
    )
    when = (
        f"recorded {data['from']} to {data['to']} UTC"
        if data["from"]
        else "no calendar dates in the stamps (simulated or relative time)"
    )
    return (
        f"<p><b>Robot</b> {esc(s['robot'])} ({esc(s['chain'][0])} → {esc(s['chain'][1])}). "
        f"<b>Data</b> {data['poses']} test poses from {esc(', '.join(data['bags']))}, measured {where}; {when}.</p>"
    )


def _errors_table(errors: dict[str, dict[str, Any]]) -> str:
    """Before and after: each model's position and orientation mean, p95 and max."""
    models = list(errors)
    head = [
        "error",
        *(("before: " if m == "analytic" else "after: " if m == "hybrid" else "") + MODEL_LABELS[m] for m in models),
    ]
    rows = []
    for quantity, unit in (("position", "mm"), ("orientation", "deg")):
        for stat in ("mean", "p95", "max"):
            key = f"{quantity}_{unit}_{stat}"
            if any(key in errors[m] for m in models):
                rows.append([f"{quantity} {stat} ({unit})", *(errors[m].get(key, "n/a") for m in models)])
    return _table(head, rows)


def _iso_line(iso: dict[str, Any] | None) -> str:
    """ISO 9283's pose accuracy and repeatability, where the test data repeats poses."""
    if not iso:
        return "<p><b>ISO 9283</b> AP and RP: the test data repeats no pose.</p>"
    return (
        f"<p><b>ISO 9283</b> over {iso['poses']} poses measured {'/'.join(map(str, iso['repeats']))} times: pose "
        f"accuracy AP up to {iso['AP_analytic_mm_max']:.3g} mm before, {iso['AP_hybrid_mm_max']:.3g} mm after; "
        f"repeatability RP up to {iso['RP_mm_max']:.3g} mm.</p>"
    )


def _working_range_lines(wr: dict[str, Any], poses: int) -> list[str]:
    """The joint range (and conditions) the calibration holds in, and how many test poses lie inside it."""
    joints = wr["joints"]
    parts = [
        "<p><b>Working range</b> the calibration holds in (the training data's joint range"
        + ("" if wr["recorded"] else "; not recorded in model.json, so the joint limits")
        + f"): {wr['inside']} of {poses} test poses lie inside it.</p>",
        _table(
            ["joint", *(f"{j['joint']} ({j['unit']})" for j in joints)],
            [["from", *(round(j["lower"], 1) for j in joints)], ["to", *(round(j["upper"], 1) for j in joints)]],
        ),
    ]
    if wr["conditions"]:
        text = ", ".join(f"{n} {c['lower']:.4g} to {c['upper']:.4g}" for n, c in wr["conditions"].items())
        parts.append(f"<p>Conditions the nets were trained over: {html.escape(text)}.</p>")
    return parts


def write_report(
    model: HybridModel,
    pairs: Pairs,
    out_dir: Path,
    source: DataSource,
    curve: list[dict[str, Any]] | None = None,
    tolerance: Tolerance = NO_TOLERANCE,
) -> tuple[Path, dict[str, Any]]:
    """Write ``index.html`` and its PNGs into ``out_dir``; return the page's path and the summary's figures
    (:func:`calibration.summary.summarise`, with the verdict a caller may print or act on).

    ``source``: the test data's bags and the frames it was measured in (the summary names them);
    ``tolerance``: the user's, which the summary's verdict line judges the hybrid model by.
    """
    out_dir.mkdir(parents=True, exist_ok=True)
    errors = pose_errors_of(model, pairs)  # every model's FK of the test poses, once for the whole page
    report = evaluate(model, pairs, errors)
    iso = iso9283(model, pairs)
    summary = summarise(model, pairs, report, errors, iso, source, tolerance)
    m = model.manifest
    parts = [
        f"<h1>Accuracy report: {html.escape(summary['robot'])}</h1>",
        *_summary_section(summary),
        f"<p>Model {html.escape(str(model.path or 'in memory'))}; joints {html.escape(', '.join(model.joint_names))}. "
        "Errors are measured against the tracker, in the robot's base frame.</p>",
    ]
    if report.get("note"):
        parts.append(f"<p class='note'>{html.escape(report['note'])}</p>")
    parts += ["<h2>Errors before and after calibration</h2>", _table(STATS_HEAD, _stats_rows(report))]
    for path in plot_distributions(model, pairs, out_dir, errors):
        parts.append(f"<img src='{path.name}' alt='{path.stem}'>")
    parts += [
        "<h2>Errors over the workspace</h2>",
        f"<img src='{_workspace_plot(errors, pairs, out_dir / 'workspace.png').name}' alt='workspace'>",
        *_range_section(report, len(pairs)),
        *_coverage_section(report.get("coverage")),
        *_bounds_section(model, pairs, errors, out_dir),  # joints are the same in any frame
        *_iso_section(iso),
        *_referencing_section(model),
        *_parametric_section(m, out_dir),
        *_capacity_section(m.get("capacity"), m.get("nets", {})),
    ]
    if curve:
        parts += [
            "<h2>Accuracy against the amount of data</h2>",
            f"<img src='{_curve_plot(curve, out_dir / 'curve.png').name}' alt='curve'>",
        ]
    page = out_dir / "index.html"
    page.write_text(
        "<!DOCTYPE html><html><head><meta charset='utf-8'><title>Accuracy report</title>"
        f"<style>{STYLE}</style></head><body>{''.join(parts)}</body></html>\n"
    )
    (out_dir / "report.json").write_text(json.dumps({**report, "iso9283": iso, "summary": summary}, indent=2) + "\n")
    return page, summary


def _range_section(report: dict[str, Any], count: int) -> list[str]:
    """The errors inside and outside the joint range the nets were trained on."""
    outside_rows = _stats_rows(report, "_outside_range")
    return [
        "<h2>Inside and outside the calibrated joint range</h2>",
        f"<p>{report['inside_calibrated_range']} of {count} test pairs lie inside the joint range the nets "
        "were trained on. Outside it the nets extrapolate, and their error grows.</p>",
        "<h3>Inside</h3>",
        _table(STATS_HEAD, _stats_rows(report, "_inside_range")),
        "<h3>Outside</h3>",
        _table(STATS_HEAD, outside_rows) if outside_rows else "<p>No test pair lies outside.</p>",
    ]


def _iso_section(iso: list[dict[str, Any]]) -> list[str]:
    parts = ["<h2>ISO 9283 pose accuracy and repeatability</h2>"]
    if iso:
        head = ["pose", "repeats", "AP, URDF model (mm)", "AP, hybrid model (mm)", "RP (mm)"]
        rows = [[e["pose"], e["repeats"], e["AP_analytic_mm"], e["AP_hybrid_mm"], e["RP_mm"]] for e in iso]
        parts.append(_table(head, rows))
    else:
        parts.append("<p>The test data repeats no pose (three or more measurements of one joint vector).</p>")
    return parts


def _referencing_section(model: HybridModel) -> list[str]:
    """Each tracker station's placement and target, in mm and degrees."""
    refs = model.referencings.values()
    parts = ["<h2>Referencing</h2>"]
    for ref in refs:
        rows = []
        for label, t in (
            ("tracker in the base frame", ref.base_to_tracker),
            ("target on the flange", ref.flange_to_target),
        ):
            rpy = np.degrees(Rotation.from_matrix(t[:3, :3]).as_euler("xyz"))
            rows.append([label, *(1e3 * t[:3, 3]).tolist(), *rpy.tolist()])
        head = ["transform", "x (mm)", "y (mm)", "z (mm)", "roll (deg)", "pitch (deg)", "yaw (deg)"]
        parts += [
            f"<p>Method: {html.escape(ref.method)}; frame '{html.escape(ref.frame_id)}'; residual rms "
            f"{ref.rms_position_mm:.4f} mm; {ref.outliers} outliers left out.</p>",
            _table(head, rows),
            *(f"<p><strong>Not determined by the data:</strong> {html.escape(note)}.</p>" for note in ref.undetermined),
        ]
    if refs:
        parts.append(
            '<p>The URDF model ("before") is judged with its own referencing: the tracker and the target fitted '
            "to the nominal model alone.</p>"
        )
    if not refs:
        parts.append("<p>The training data was in the base frame: no referencing was needed.</p>")
    return parts


def _parametric_section(m: dict[str, Any], out_dir: Path) -> list[str]:
    """The stage's identified parameters with their σ, the cyclic errors and the joint error map per joint,
    and what the data could not identify."""
    par = m.get("parametric")
    parts = ["<h2>Parametric stage</h2>"]
    dropped = m.get("stage_not_served")
    if dropped:
        parts.append(
            "<p>Not served: on the validation pairs it was worse than the URDF model with only the tracker and "
            f"target fitted ({dropped['candidate_mm']:.4f} mm against {dropped['rigid_mm']:.4f} mm).</p>"
        )
    if par:
        fitted = [p for p in par["parameters"] if p["identifiable"]]
        free = [p for p in par["parameters"] if not p["identifiable"] and p["kind"] != "harmonic"]
        rows = [[p["name"], p["value"], p.get("sigma", ""), p["unit"]] for p in fitted if p["kind"] != "harmonic"]
        # hundreds of Fourier coefficients of the cyclic joint errors: one line per joint says their size
        for joint in sorted({p["index"] for p in fitted if p["kind"] == "harmonic"}):
            values = np.array([p["value"] for p in fitted if p["kind"] == "harmonic" and p["index"] == joint])
            rms = np.degrees(np.sqrt(0.5 * np.sum(values**2))) * 3600.0
            label = f"cyclic error of joint {joint + 1}, rms over a turn ({len(values)} terms)"
            rows.append([label, rms, "", "arcsec"])
        joint_map = JointMap.from_manifest(par["joint_map"]) if "joint_map" in par else None
        if joint_map is not None:
            for k, name in enumerate(m["joint_names"]):
                rms = np.degrees(np.sqrt(np.mean(joint_map.values[k] ** 2))) * 3600.0
                rows.append([f"joint error map of {name}, rms over its knots", rms, "", "arcsec"])
        parts += [
            f"<p>{len(fitted)} of {len(par['parameters'])} parameters identified; rms position error "
            f"{par['rms_before']['position_mm']:.4f} → {par['rms_after']['position_mm']:.4f} mm.</p>",
            *_outlier_line(par),
            _table(["parameter", "value", "σ", "unit"], rows),
            *_uncertainty_lines(par.get("uncertainty")),
            *(
                [
                    f"<p>Joint error map: knots {np.degrees(joint_map.step):.3f} deg apart.</p>",
                    f"<img src='{_joint_map_plot(joint_map, m['joint_names'], out_dir / 'joint_map.png').name}' "
                    "alt='joint error map'>",
                ]
                if joint_map is not None
                else []
            ),
            "<h3>Not identifiable</h3>",
            _table(["parameter", "why"], [[p["name"], p.get("reason", "")] for p in free]),
        ]
    else:
        parts.append("<p>No parametric stage: the nets correct the URDF model directly.</p>")
    return parts


def _outlier_line(par: dict[str, Any]) -> list[str]:
    """What the stage left far off: the training pairs dropped before it was fitted again, and those it
    down-weighted (neither in an older model)."""
    lines = []
    dropped = par.get("dropped")
    if dropped is not None:
        lines.append(
            f"<p>Dropped: {dropped['pairs']} training pairs lay more than {dropped['beyond_mm']:.4f} mm (five robust "
            "standard deviations) off what the stage left; the referencing, the stage and the nets were fitted "
            "again without them.</p>"
        )
    outliers = par.get("outliers")
    if outliers is not None:
        lines.append(
            f"<p>Outliers: {outliers['pairs']} pairs lie more than {outliers['beyond_mm']:.4f} mm (five robust "
            "standard deviations) off what the stage leaves; they were down-weighted.</p>"
        )
    return lines


def _uncertainty_lines(uncertainty: dict | None) -> list[str]:
    """The condition number and the most correlated pairs, under the parameter table."""
    if not uncertainty:
        return []
    pairs = "; ".join(f"{c['a']} and {c['b']} ({c['correlation']:+.2f})" for c in uncertainty["correlated"])
    return [
        "<p>σ: the spread expected between calibrations on new poses, from the residuals the stage leaves. "
        f"Condition number (of the parameters' correlation matrix): {uncertainty['condition_number']:.1f}. "
        f"Most correlated: {html.escape(pairs)}.</p>"
    ]


def _tracker_floor_line(floor: dict | None, hybrid_mm: float | None) -> list[str]:
    """The tracker's own floor, where the export told it (none otherwise), and how far the test error is above it."""
    if not floor:
        return []
    mm = floor["position_mm"]
    ratio = f": the test mean is {hybrid_mm / mm:.2f}× it" if hybrid_mm and mm else ""
    return [
        f"<p><b>The tracker's own floor</b> {mm:.4f} mm, from {floor['from']}{ratio}. What the "
        "robot does not repeat comes on top of it.</p>"
    ]


def _floor_line(floor: dict | None, hybrid_mm: float | None) -> str:
    """The training data's measurement floor, and how far the test error is above it."""
    if not floor:
        return (
            "<p><b>Measurement floor</b> not known: the training data repeats no configuration "
            "(repeat a few poses to learn it).</p>"
        )
    ratio = f": the test mean is {hybrid_mm / floor['position_mm']:.2f}× it" if hybrid_mm else ""
    return (
        f"<p><b>Measurement floor</b> {floor['position_mm']:.4f} mm, from {floor['pairs']} pairs of repeated "
        f"joints in the training data{ratio}.</p>"
    )
