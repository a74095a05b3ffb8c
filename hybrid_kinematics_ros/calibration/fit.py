"""From pairs bags to a model directory: split, targets, the two nets, test metrics and the manifest."""

from __future__ import annotations

import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import asdict, replace
from pathlib import Path
from typing import Any

import numpy as np
from scipy import stats

from hybrid_kinematics_ros.calibration import bounds as bounds_module
from hybrid_kinematics_ros.calibration import capacity as capacity_module
from hybrid_kinematics_ros.calibration import train
from hybrid_kinematics_ros.calibration.alignment import align_raw
from hybrid_kinematics_ros.calibration.errors import CalibrationError
from hybrid_kinematics_ros.calibration.evaluate import evaluate, pose_errors_of, target_errors
from hybrid_kinematics_ros.calibration.parametric import HARMONIC_PRIOR, ParametricResult, identify, linearise
from hybrid_kinematics_ros.calibration.referencing import (
    anchor_stations,
    reference_stations,
    refine_stations,
    station_labels,
)
from hybrid_kinematics_ros.io.model_dir import save_model_dir
from hybrid_kinematics_ros.io.pairs import (
    JOINTS_TOPIC,
    RAW_JOINTS_TOPIC,
    RAW_POSE_TOPIC,
    Pairs,
    bag_topics,
    read_pairs,
)
from hybrid_kinematics_ros.kinematics.chain import Chain
from hybrid_kinematics_ros.kinematics.elastic import ElasticChain
from hybrid_kinematics_ros.model import approach
from hybrid_kinematics_ros.model.bounds import Bounds, excess
from hybrid_kinematics_ros.model.hybrid import HybridModel
from hybrid_kinematics_ros.model.referencing import Referencing, to_base_frame

COVERAGE_SPACING = 0.005  # rad: the grid the stored training configurations are thinned on


def load_stations(bags: Sequence[str | Path], chain: Chain, raw_frame_id: str | None = None) -> list[Pairs]:
    """Pairs from pairs bags or raw recordings (aligned on the fly), one :class:`Pairs` per frame: each
    tracker station (and the base link, if some bags are in it), in the order first seen.

    ``raw_frame_id`` names the frame of raw recordings' pairs (e.g. the base link when the tracker frame
    is the robot base, as in the simulated cell).

    Each bag's pairs carry the joints' approach directions (:meth:`Pairs.with_approach`), from their own order.
    """
    parts: dict[str, list[Pairs]] = {}
    for bag in bags:
        topics = bag_topics(bag)
        if JOINTS_TOPIC not in topics and RAW_JOINTS_TOPIC in topics and RAW_POSE_TOPIC in topics:
            pairs = align_raw(bag, chain, frame_id=raw_frame_id)[0].pairs
        else:
            pairs = read_pairs(bag, chain.joint_names)
        parts.setdefault(pairs.frame_id, []).append(pairs.with_approach())
    return [Pairs.concatenate(group) for group in parts.values()]


def load_pairs(
    bags: Sequence[str | Path],
    chain: Chain,
    raw_frame_id: str | None = None,
    referencings: Mapping[str, Referencing] | None = None,
) -> Pairs:
    """Pairs in the base frame from bags in it or in any referenced tracker frame (see :func:`load_stations`)."""
    return to_base_frame(load_stations(bags, chain, raw_frame_id), chain, referencings or {})


def reference_all(
    chain: Chain, stations: Sequence[Pairs], shared_targets: Sequence[Sequence[str]] = (), seed: int = 0
) -> dict[str, Referencing]:
    """A referencing for every station in a tracker frame. Stations named together in ``shared_targets``
    share one target transform (the target stayed on the flange while the tracker moved); every other
    station gets its own."""
    tracker = {p.frame_id: p for p in stations if p.frame_id != chain.base_link}
    groups: list[list[str]] = []
    for names in shared_targets:
        unknown = [n for n in names if n not in tracker]
        if unknown:
            raise CalibrationError(
                f"shared target: no training pairs in frame(s) {', '.join(unknown)} "
                f"(tracker frames: {', '.join(tracker) or 'none'})"
            )
        groups.append(list(names))
    grouped = {n for g in groups for n in g}
    groups += [[n] for n in tracker if n not in grouped]
    out: dict[str, Referencing] = {}
    for group in groups:
        for ref in reference_stations(chain, [tracker[n] for n in group], seed=seed):
            out[ref.frame_id] = ref
    return out


def identify_stations(
    chain: Chain,
    stations: Sequence[Pairs],
    refs: dict[str, Referencing],
    payload: tuple[float, np.ndarray] = (0.0, np.zeros(3)),
    seed: int = 0,
    capacity: Mapping[str, Any] | None = None,
    choose: bool = True,
    gravity: np.ndarray | None = None,
) -> tuple[dict[str, Referencing], ParametricResult]:
    """The parametric stage from the pairs of every station, each referenced (``refs``, from
    :func:`reference_all`): identified with a correction of each station's placement and target mount
    (the nominal model's referencing absorbs a different share of the robot's errors at each station),
    which then moves into the referencings; and the base anchored at the first joint
    (:func:`anchor_stations`). Returns the referencings and the stage.

    ``choose``: the stage's capacity is chosen from these pairs (:func:`capacity.select_capacity`; the
    result's ``capacity`` says how), except for the settings given in ``capacity`` (``elastic``,
    ``harmonics``, ``harmonic_prior``, ``map_step``, ``map_smoothness``, ``approach``). Without ``choose``,
    settings not given take :func:`parametric.identify`'s defaults. Whether the nets take the joints'
    approach directions (``approach``) is chosen when the pairs carry them."""
    base = to_base_frame(stations, chain, refs)
    labels = station_labels(refs, any(p.frame_id == chain.base_link for p in stations))
    placement, mount = (
        np.concatenate([np.full(len(p), labels.get(p.frame_id, (-1, -1))[k]) for p in stations]) for k in (0, 1)
    )
    common = {
        "payload_mass": payload[0],
        "payload_com": payload[1],
        "gravity": gravity,
        "directions": approach_of(base),
        "position_only": base.position_only,
        "seed": seed,
        "target": _target_offsets(base),
        "placement": placement,
        "mount": mount,
    }
    given = {k: v for k, v in (capacity or {}).items() if v is not None}
    chosen = None
    if choose:
        linear = linearise(chain, base.q, base.T, harmonics=max(capacity_module.HARMONICS), **common)
        chosen = capacity_module.select_capacity(linear, len(base), given)
        options = chosen.identify_options()
    else:
        options = capacity_module.options_from(given)
    result = identify(chain, base.q, base.T, **common, **options)
    result.capacity = None if chosen is None else chosen.manifest()
    result.options = options
    if not refs:
        return refs, result
    anchored, result = anchor_stations(chain, list(refine_stations(refs, labels, result).values()), result)
    return {ref.frame_id: ref for ref in anchored}, result


SPLIT_BLOCKS = 100  # time blocks a split cuts the pairs into, by default


def approach_of(pairs: Pairs) -> np.ndarray | None:
    """``(N, n)``: the pairs' approach directions (:meth:`Pairs.with_approach`), or None if they carry none."""
    channels = approach.channel_names(pairs.joint_names)
    if not all(c in pairs.conditions for c in channels):
        return None
    return np.column_stack([pairs.conditions[c] for c in channels])


def split(
    pairs: Pairs, seed: int, fractions: tuple[float, float] = (0.1, 0.1), blocks: int | None = SPLIT_BLOCKS
) -> tuple[Pairs, Pairs, Pairs]:
    """Reproducible train/validation/test split (validation and test fractions given), by time blocks.

    Pairs recorded along a trajectory are milliseconds apart and nearly equal: a split by single pairs
    puts the neighbours of every test pair into training, and the test error measures interpolation
    between them. So the pairs, as read (bag by bag, each in stamp order), are cut into ``blocks``
    contiguous blocks, and whole blocks are drawn for validation and test. ``blocks=None`` draws single
    pairs (the old, optimistic split). :func:`split_summary` says which was used, for ``model.json``.
    """
    n = len(pairs)
    if n < 10:
        raise CalibrationError(
            f"frame '{pairs.frame_id}': only {n} pairs; at least 10 are needed to train, validate and test"
        )
    rng = np.random.default_rng(seed)
    n_val = max(1, int(n * fractions[0])) if fractions[0] > 0 else 0
    n_test = max(1, int(n * fractions[1])) if fractions[1] > 0 else 0
    if blocks is None or blocks >= n:
        perm = rng.permutation(n)
    else:
        chunks = np.array_split(np.arange(n), blocks)  # pairs come in bag order, each bag in stamp order
        perm = np.concatenate([chunks[i] for i in rng.permutation(len(chunks))])
    val, test = perm[:n_val], perm[n_val : n_val + n_test]
    train = np.sort(perm[n_val + n_test :])
    return pairs.subset(train), pairs.subset(np.sort(val)), pairs.subset(np.sort(test))


def split_summary(blocks: int | None, separate_val: bool, separate_test: bool) -> dict[str, Any]:
    """How the validation and test sets were chosen, for ``model.json``."""

    def how(separate: bool) -> str:
        if separate:
            return "separate bags"
        return "random pairs" if blocks is None else f"contiguous time blocks (1 in {blocks} of the pairs each)"

    return {"validation": how(separate_val), "test": how(separate_test)}


def fit(
    chain: Chain,
    train_pairs: Pairs | Sequence[Pairs],
    val_pairs: Pairs | Sequence[Pairs],
    test_pairs: Pairs | Sequence[Pairs],
    out: Path,
    preset: train.Preset,
    max_minutes: float,
    seed: int = 0,
    arch: dict[str, str] | None = None,
    data_summary: dict[str, Any] | None = None,
    progress: Callable[[dict], None] | None = None,
    parallel: bool = True,
    parametric: bool = False,
    payload: tuple[float, np.ndarray] = (0.0, np.zeros(3)),
    log: Callable[[str], None] = lambda _: None,
    shared_targets: Sequence[Sequence[str]] = (),
    conditions: Sequence[str] = (),
    capacity: Mapping[str, Any] | None = None,
    choose_capacity: bool = True,
    gravity: np.ndarray | None = None,
    offered: Sequence[str] | None = None,
) -> tuple[HybridModel, dict[str, Any]]:
    """Reference, identify, train both nets within ``max_minutes`` (side by side), write the model directory.

    Each set of pairs may come from several tracker stations (one :class:`Pairs` per frame). Every
    tracker frame is referenced first (:func:`reference_all`); with ``parametric`` the elasto-geometric
    stage is identified next, from all stations together, and the nets learn what it leaves.
    Position-only pairs train the position net alone. ``conditions`` names condition channels of the
    pairs (``temperature``, say) that the nets take as inputs beside the joints; ``offered`` names channels
    each net takes only where its validation errors show their worth (:func:`train.train_net`), a channel no
    net takes leaves the model's inputs. None (the default): with no channel named in ``conditions``, every
    channel all the pairs carry but the joints' approach directions (those the stage decides); else none.
    ``capacity`` and
    ``choose_capacity``: the stage's size, given or chosen from the training pairs (:func:`identify_stations`).
    ``gravity``: m/s² in the base frame (None: a floor mount), for the stage's joint torques.
    """
    manifest: dict[str, Any] = {}
    raw = [[p] if isinstance(p, Pairs) else list(p) for p in (train_pairs, val_pairs, test_pairs)]
    refs = reference_all(chain, raw[0], shared_targets, seed)
    for ref in refs.values():
        log(f"referenced frame '{ref.frame_id}': rms {ref.rms_position_mm:.4f} mm ({ref.outliers} outliers)")
        for note in ref.undetermined:
            log(f"frame '{ref.frame_id}': {note}")
    rigid_refs = refs  # the rigid-only candidate: the URDF model with the tracker and target fitted to it
    if refs:
        manifest["rigid_referencing"] = [ref.manifest() for ref in refs.values()]
    train_pairs, val_pairs, test_pairs = (to_base_frame(p, chain, refs) for p in raw)
    position_only = train_pairs.position_only
    base = ElasticChain.rigid(chain)
    if parametric:
        start = time.perf_counter()
        refs, result = identify_stations(chain, raw[0], refs, payload, seed, capacity, choose_capacity, gravity)
        verdict = rigid_verdict(chain, raw[1], (result.model, refs), rigid_refs)
        if verdict is not None and not verdict["better"]:
            log(
                "parametric stage: not served, worse on the validation pairs than the URDF model with only the "
                f"tracker and target fitted ({verdict['candidate_mm']:.4f} mm against {verdict['rigid_mm']:.4f} mm)"
            )
            manifest["stage_not_served"] = verdict
            parametric, refs = False, rigid_refs
    if parametric:
        if result.capacity is not None:
            manifest["capacity"] = result.capacity
            log("parametric stage capacity (cross-validated): " + capacity_module.summary(result.capacity))
        if refs:
            train_pairs, val_pairs, test_pairs = (to_base_frame(p, chain, refs) for p in raw)
        base = result.model
        channels = approach.channel_names(chain.joint_names)
        if base.backlash is not None and not set(channels) & set(conditions):
            conditions = (*conditions, *channels)  # the stage's backlash terms and the nets take the directions
        manifest["parametric"] = {**result.manifest(), "seconds": round(time.perf_counter() - start, 1)}
        log(
            f"parametric stage: {int(result.identifiable.sum())} of {len(result.params)} parameters identifiable; "
            f"rms {result.rms_before['position_mm']:.4f} -> {result.rms_after['position_mm']:.4f} mm"
        )
    if refs:
        manifest["referencing"] = [ref.manifest() for ref in refs.values()]
    # position-only: the models predict the target points, wherever each station's target sat
    target = _target_offsets(train_pairs)
    lower, upper = train_pairs.q.min(axis=0), train_pairs.q.max(axis=0)
    norm_lower, norm_upper = (chain.lower, chain.upper) if preset.full_range else (lower, upper)
    norm_lower = np.where(np.isfinite(norm_lower), norm_lower, lower)
    norm_upper = np.where(np.isfinite(norm_upper), norm_upper, upper)
    if offered is None:
        named = [c for c in conditions if not approach.is_channel(c)]
        carried = set.intersection(*(set(p.conditions) for p in (train_pairs, val_pairs, test_pairs)))
        varied = {c for c in carried if np.ptp(train_pairs.conditions[c]) > 0}  # a constant one teaches nothing
        offered = () if named else tuple(sorted(c for c in varied if not approach.is_channel(c)))
        every = set().union(*(set(p.conditions) for p in (train_pairs, val_pairs, test_pairs)))
        unused = sorted(c for c in every - set(offered) - set(conditions) if not approach.is_channel(c))
        if unused:
            why = "channels were named" if named else "missing from some of the pairs, or constant in training"
            log(f"condition channels not offered to the nets: {', '.join(unused)} ({why})")
    offered = tuple(c for c in offered if c not in conditions)
    forced = len(conditions)
    conditions = (*conditions, *offered)
    x_train, x_val = (_net_inputs(p, conditions) for p in (train_pairs, val_pairs))
    if conditions:  # condition columns follow the joints, normalised over the range seen in training
        c = x_train[:, chain.dof :]
        directions = np.array([approach.is_channel(name) for name in conditions])  # always over -1 … +1
        low, high = np.where(directions, -1.0, c.min(axis=0)), np.where(directions, 1.0, c.max(axis=0))
        norm_lower, norm_upper = np.r_[norm_lower, low], np.r_[norm_upper, high]
    # what the stage leaves, with its backlash terms shifting the joints the way each pair arrived
    y_train = train.residual_targets(
        base, base.approached(train_pairs.q, approach_of(train_pairs)), train_pairs.T, target
    )
    y_val = train.residual_targets(
        base, base.approached(val_pairs.q, approach_of(val_pairs)), val_pairs.T, _target_offsets(val_pairs)
    )
    arch = arch or {}
    kinds = ("position",) if position_only else train.KINDS
    jobs = {}
    for seed_offset, kind in enumerate(kinds):
        p = replace(preset, arch=arch.get(kind) or preset.arch)
        jobs[kind] = train.NetJob(
            kind,
            p,
            x_train,
            y_train[kind],
            x_val,
            y_val[kind],
            norm_lower,
            norm_upper,
            train.joint1_axis(chain),
            60.0 * max_minutes,
            seed + seed_offset,
            chain.dof,
            offered=tuple(range(chain.dof + forced, chain.dof + len(conditions))),
            offered_label=", ".join(offered),
        )
    start = time.perf_counter()
    nets, histories = train.train_pair(jobs, progress=progress, parallel=parallel)
    seconds = time.perf_counter() - start
    for kind, history in histories.items():
        if history[-1].get("silenced"):
            log(f"{kind} net: no better than the stage before it on validation, so it corrects nothing")
    if offered:
        taken = [kind for kind, history in histories.items() if history[-1].get("takes_offered")]
        manifest["offered_conditions"] = {"channels": list(offered), "taken_by": taken}
        log(
            f"condition channels offered ({', '.join(offered)}): "
            + (f"taken by the {' and '.join(taken)} net" if taken else "no net is better with them on validation")
        )
        if not taken:  # out of the inputs: the node then needs no value for them
            dropped = tuple(range(chain.dof + forced, chain.dof + len(conditions)))
            for net in nets.values():
                net.drop_inputs(dropped)
            conditions = conditions[:forced]
            norm_lower, norm_upper = norm_lower[: chain.dof + forced], norm_upper[: chain.dof + forced]
    manifest.update(
        {
            "base_link": chain.base_link,
            "tip_link": chain.tip_link,
            "joint_names": list(chain.joint_names),
            "tool": chain.tool.tolist(),
            "joint_limits": {"lower": chain.lower.tolist(), "upper": chain.upper.tolist()},
            "trained_range": {"lower": lower.tolist(), "upper": upper.tolist()},
            "position_only": position_only,
        }
    )
    if conditions:
        manifest["conditions"] = {
            name: {
                # an approach direction is unknown (0) until the joint moves; other channels: the training mean
                "default": 0.0 if approach.is_channel(name) else float(np.mean(train_pairs.conditions[name])),
                "lower": float(lo),
                "upper": float(hi),
            }
            for name, lo, hi in zip(conditions, norm_lower[chain.dof :], norm_upper[chain.dof :], strict=True)
        }
    coverage = thinned(train_pairs.q)
    model = HybridModel(chain, nets, manifest, coverage=coverage)
    stage_options = result.options if parametric else {"kinds": capacity_module.ELASTIC["geometry"], "harmonics": 0}
    try:
        bounds = calibrate_bounds(chain, model, train_pairs, val_pairs, stage_options, payload, gravity)
    except (CalibrationError, np.linalg.LinAlgError) as exc:  # too few pairs to measure the growth: no bounds
        log(f"no error bounds: {exc}")
    else:
        manifest["bounds"] = bounds.manifest()
        steepest = int(np.argmax(bounds.position.rates))
        log(
            f"error bounds ({bounds.level:.0%}): {1e3 * bounds.position.quantile:.4f} mm inside the trained range "
            "at a typical configuration, "
            f"growing beyond it by up to {1e3 * bounds.position.rates[steepest]:.3g} mm per rad "
            f"({chain.joint_names[steepest]})"
        )
    # eager nets here; the saved TorchScript is checked against them. "analytic": the rigid-only candidate
    errors = [pose_errors_of(model, p) for p in raw[2] if len(p)]
    errors = (
        {k: tuple(np.concatenate([e[k][i] for e in errors]) for i in (0, 1)) for k in errors[0]} if errors else None
    )
    metrics = evaluate(model, test_pairs, errors) if errors else evaluate(model, test_pairs)
    guard = None if errors is None else worse_than_rigid(errors["hybrid"][0], errors["analytic"][0])
    manifest.update(
        {
            "nets": {kind: {"epochs": len(histories[kind]), **_best(histories[kind])} for kind in jobs},
            "preset": asdict(preset),
            "seed": seed,
            "training_seconds": round(seconds, 1),
            "data": {
                **(data_summary or {}),
                "train": len(train_pairs),
                "val": len(val_pairs),
                "test": len(test_pairs),
                "frame_ids": [p.frame_id for p in raw[0]],
            },
            "metrics": {"test": metrics},
        }
    )
    if position_only:
        manifest["note"] = "position-only data: orientation is not corrected (no orientation net)"
    if guard is not None:
        manifest["rigid_candidate"] = guard
    save_model_dir(out, manifest, chain.urdf_text, nets, coverage=coverage)
    if guard is not None and guard["worse"]:
        raise CalibrationError(
            f"{out}: the model is worse on the test pairs than the URDF model with only the tracker and target "
            f"fitted ({guard['served_mm']:.4f} mm against {guard['rigid_mm']:.4f} mm, p = {guard['p_value']:.2g}); "
            "do not serve it: check the referencing notes in its report and measure more varied poses"
        )
    return HybridModel.load(out), manifest


def rigid_verdict(
    chain: Chain,
    stations: Sequence[Pairs],
    candidate: tuple[ElasticChain, Mapping[str, Referencing]],
    rigid_refs: Mapping[str, Referencing],
) -> dict[str, Any] | None:
    """Whether a stage with its referencings (``candidate``) beats the rigid-only model, the URDF model with
    ``rigid_refs``, on held-out ``stations``: mean position errors at the target (mm); None without pairs."""
    stations = [p for p in stations if len(p)]
    if not stations:
        return None
    stage, refs = candidate
    moved = to_base_frame(stations, chain, refs)
    nominal = to_base_frame(stations, chain, rigid_refs)
    stage_mm = target_errors(moved, stage.fk(stage.approached(moved.q, approach_of(moved))))[0]
    rigid_mm = target_errors(nominal, ElasticChain.rigid(chain).fk(nominal.q))[0]
    mean, rigid_mean = float(np.mean(stage_mm)), float(np.mean(rigid_mm))
    return {"candidate_mm": mean, "rigid_mm": rigid_mean, "better": mean <= rigid_mean}


GUARD_P_VALUE = 0.01  # the served model fails when it is worse than the rigid-only one at this significance


def worse_than_rigid(served_mm: np.ndarray, rigid_mm: np.ndarray) -> dict[str, Any]:
    """The served model against the rigid-only one on the same held-out pairs (position errors, mm): worse
    when its mean is higher and a one-sided Wilcoxon signed-rank test of the pairs' differences says so at
    ``GUARD_P_VALUE``, so that test noise alone does not fail a model that ties a good rigid one."""
    served, rigid = float(np.mean(served_mm)), float(np.mean(rigid_mm))
    differences = served_mm - rigid_mm
    p_value = 1.0
    if np.any(differences != 0):
        p_value = float(stats.wilcoxon(served_mm, rigid_mm, alternative="greater").pvalue)
    return {
        "served_mm": served,
        "rigid_mm": rigid,
        "p_value": p_value,
        "worse": served > rigid and p_value < GUARD_P_VALUE,
    }


def calibrate_bounds(
    chain: Chain,
    model: HybridModel,
    train_pairs: Pairs,
    val_pairs: Pairs,
    stage_options: dict[str, Any],
    payload: tuple[float, np.ndarray],
    gravity: np.ndarray | None,
) -> Bounds:
    """The bound on each answer's error (:mod:`calibration.bounds`): its growth beyond the trained range from
    the stage, linearised over the base-frame training pairs with the options it was identified with, its
    scale from the stage's errors on them, and its size inside from ``model``'s errors on the validation
    pairs."""
    kept = ("kinds", "harmonics", "harmonic_prior", "orientation_length")
    options = {k: v for k, v in stage_options.items() if k in kept}
    lin = linearise(
        chain,
        train_pairs.q,
        train_pairs.T,
        payload_mass=payload[0],
        payload_com=payload[1],
        gravity=gravity,
        directions=approach_of(train_pairs),
        position_only=train_pairs.position_only,
        target=_target_offsets(train_pairs),
        map_step=0.0,
        **options,
    )
    val_conditions = model.conditions_of(val_pairs.conditions, len(val_pairs))
    pos_mm, rot_deg = target_errors(val_pairs, model.fk(val_pairs.q, conditions=val_conditions))
    alone_mm, alone_deg = target_errors(val_pairs, model.fk(val_pairs.q, nets=False, conditions=val_conditions))
    conditions = model.conditions_of(train_pairs.conditions, len(train_pairs))
    stage_mm, stage_deg = target_errors(train_pairs, model.fk(train_pairs.q, nets=False, conditions=conditions))
    stage = (train_pairs.q, 1e-3 * stage_mm, None if train_pairs.position_only else np.radians(stage_deg))
    ridge = capacity_module.harmonic_ridge(lin, float(options.get("harmonic_prior", HARMONIC_PRIOR)))
    return bounds_module.calibrate(
        lin,
        ridge,
        chain.revolute,
        stage,
        val_pairs.q,
        excess(val_pairs.q, model.trained_lower, model.trained_upper, chain.revolute),
        1e-3 * pos_mm,
        None if val_pairs.position_only else np.radians(rot_deg),
        (1e-3 * alone_mm, None if val_pairs.position_only else np.radians(alone_deg)),
    )


def _net_inputs(pairs: Pairs, conditions: Sequence[str]) -> np.ndarray:
    """``(N, n + k)``: the joints, then the named condition channels."""
    missing = [c for c in conditions if c not in pairs.conditions]
    if missing:
        raise CalibrationError(
            f"the pairs carry no {', '.join(missing)} channel (they carry {', '.join(pairs.conditions) or 'none'}); "
            "import or record them with it, or train without it"
        )
    return np.column_stack([pairs.q, *(pairs.conditions[c] for c in conditions)])


def _target_offsets(pairs: Pairs) -> np.ndarray | None:
    """``(N, 3)``: where position-only pairs' targets sit in the tip frame; None for 6-DoF pairs."""
    return pairs.targets[:, :3, 3] if pairs.position_only else None


def thinned(q: np.ndarray, spacing: float = COVERAGE_SPACING) -> np.ndarray:
    """One configuration per ``spacing``-sided cell of joint space: a slow trajectory repeats itself."""
    _, keep = np.unique(np.round(q / spacing), axis=0, return_index=True)
    return q[np.sort(keep)]


def _best(history: list[dict]) -> dict[str, Any]:
    """The net's architecture and validation figures, and the epoch its kept weights come from: how long to
    train and how large a net are chosen on the validation blocks, like whether to correct at all
    (``silenced``; ``members``: 1, or an ensemble's; ``cycles``: the runs of one net trained on from the last;
    ``sizes``: each rung's crossed validation error, :func:`train.train_net`)."""
    last = history[-1]
    kept = ("silenced", "sizes", "members", "cycles", "offered", "takes_offered")
    out = {k: v for k, v in last.items() if k.startswith("best_val_") or k in kept}
    out["arch"] = last["served"]
    reads = bool(last.get("takes_offered"))  # the net served, of that size, with or without the offered channels
    served = [e for e in history if e["arch"] == last["served"] and e.get("reads_offered", False) == reads]
    if out.get("members", 1) == 1:  # the single net, not the members an ensemble rung added to it
        served = [e for e in served if "member" not in e and e.get("cycle", 1) <= last.get("cycles", 1)]
    out["epochs"] = len(served)
    if not last.get("silenced") and out.get("members", 1) == 1:
        key = next(k for k in last if k.startswith("val_"))
        # the weights served come from the last cycle's best epoch (the sizes' epochs may lie between cycles)
        cycle = [e for e in served if e.get("cycle", 1) == last.get("cycles", 1)]
        out["best_epoch"] = served.index(min(cycle, key=lambda e: e[key])) + 1
    return out
