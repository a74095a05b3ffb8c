"""From pairs bags to a model directory: split, targets, the two nets, test metrics and the manifest."""

from __future__ import annotations

import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import asdict, dataclass, field, replace
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
from hybrid_kinematics_ros.calibration.floor import measurement_floor, tracker_line
from hybrid_kinematics_ros.calibration.parametric import HARMONIC_PRIOR, ParametricResult, identify, linearise
from hybrid_kinematics_ros.calibration.recipe import Recipe
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
    floor_summary,
    pooled_floor,
    read_pairs,
)
from hybrid_kinematics_ros.kinematics import approach
from hybrid_kinematics_ros.kinematics.chain import Chain
from hybrid_kinematics_ros.kinematics.elastic import ElasticChain
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


Sets = tuple[list[Pairs], list[Pairs], list[Pairs]]  # training, validation and test pairs, one Pairs per frame


def _silent(_: str) -> None:
    pass


@dataclass(frozen=True)
class Hooks:
    """What the caller of :func:`fit` hears while it runs (the nets' ``progress`` records, ``log`` lines) and
    what it records of its data in the manifest's ``data`` section (``data_summary``: the bags, what was
    dropped, how the sets were split)."""

    progress: Callable[[dict], None] | None = None
    log: Callable[[str], None] = _silent
    data_summary: Mapping[str, Any] = field(default_factory=dict)


QUIET = Hooks()  # no progress, no log lines, no data summary


@dataclass(frozen=True)
class Stage:
    """What the nets learn on: the stage (or the URDF chain), the referencings it was fitted with and, when
    one was identified and served, its result and the training pairs it kept (``train``, one per frame;
    None: all of them)."""

    base: ElasticChain
    refs: dict[str, Referencing]
    result: ParametricResult | None = None
    train: list[Pairs] | None = None


@dataclass(frozen=True)
class Trained:
    """The nets, their training histories, the inputs they take and, when channels were offered, which net
    took them."""

    nets: dict
    histories: dict[str, list[dict]]
    inputs: Inputs
    offered: dict[str, Any] | None = None


@dataclass(frozen=True)
class Inputs:
    """The nets' inputs: the joints, then condition channels (the first ``forced`` always taken, the rest
    offered), each normalised over ``lower`` … ``upper``."""

    conditions: tuple[str, ...]
    forced: int
    lower: np.ndarray
    upper: np.ndarray

    def without_offered(self, dof: int) -> Inputs:
        keep = dof + self.forced
        return Inputs(self.conditions[: self.forced], self.forced, self.lower[:keep], self.upper[:keep])


def fit(
    chain: Chain,
    train_pairs: Pairs | Sequence[Pairs],
    val_pairs: Pairs | Sequence[Pairs],
    test_pairs: Pairs | Sequence[Pairs],
    out: Path,
    recipe: Recipe,
    hooks: Hooks = QUIET,
) -> tuple[HybridModel, dict[str, Any]]:
    """Reference, identify the stage, train both nets side by side, and write the model directory ``out``.

    Each set of pairs may come from several tracker stations (one :class:`Pairs` per frame). Every tracker
    frame is referenced first (:func:`reference_all`); with ``recipe.parametric`` the elasto-geometric stage
    is identified next, from all stations together, and served only where it beats the rigid-only model
    (the URDF model with its own referencing) on the validation pairs; the nets learn what it leaves.
    Position-only pairs train the position net alone. The served model is checked against the rigid-only
    one on the test pairs: if it is worse (:func:`worse_than_rigid`), the model is written and
    :class:`CalibrationError` says not to serve it.
    """
    log = hooks.log
    raw: Sets = tuple([p] if isinstance(p, Pairs) else list(p) for p in (train_pairs, val_pairs, test_pairs))
    manifest: dict[str, Any] = {"recipe": recipe.manifest()}
    rigid_refs = reference_all(chain, raw[0], recipe.shared_targets, recipe.seed)
    for ref in rigid_refs.values():
        log(f"referenced frame '{ref.frame_id}': rms {ref.rms_position_mm:.4f} mm ({ref.outliers} outliers)")
        for note in ref.undetermined:
            log(f"frame '{ref.frame_id}': {note}")
    if rigid_refs:
        manifest["rigid_referencing"] = [ref.manifest() for ref in rigid_refs.values()]
    stage = _stage(chain, raw, rigid_refs, recipe, manifest, log)
    if stage.refs:
        manifest["referencing"] = [ref.manifest() for ref in stage.refs.values()]
    if stage.train is not None:
        raw = (stage.train, raw[1], raw[2])
    sets = tuple(to_base_frame(p, chain, stage.refs) for p in raw)
    inputs = _inputs(chain, recipe, stage, sets, log)
    start = time.perf_counter()
    trained = _train_nets(chain, recipe, stage.base, sets[:2], inputs, hooks)
    manifest["training_seconds"] = round(time.perf_counter() - start, 1)
    manifest |= _model_manifest(chain, sets[0], trained, recipe)
    coverage = thinned(sets[0].q)
    model = HybridModel(chain, trained.nets, manifest, coverage=coverage)
    _bounds(chain, model, sets, stage, recipe, manifest, log)
    # eager nets here; the saved TorchScript is checked against them. "analytic" is the rigid-only model
    errors = _test_errors(model, raw[2])
    manifest["metrics"] = {"test": evaluate(model, sets[2], errors) if errors else evaluate(model, sets[2])}
    _floors(chain, raw, rigid_refs, manifest, log)
    guard = None if errors is None else worse_than_rigid(errors["hybrid"][0], errors["analytic"][0])
    manifest["data"] = {
        **hooks.data_summary,
        **{name: len(p) for name, p in zip(("train", "val", "test"), sets, strict=True)},
        "frame_ids": [p.frame_id for p in raw[0]],
    }
    if sets[0].position_only:
        manifest["note"] = "position-only data: orientation is not corrected (no orientation net)"
    if guard is not None:
        manifest["rigid_candidate"] = guard
    save_model_dir(out, manifest, chain.urdf_text, trained.nets, coverage=coverage)
    if guard is not None and guard["worse"]:
        raise CalibrationError(
            f"{out}: the model is worse on the test pairs than the URDF model with only the tracker and target "
            f"fitted ({guard['served_mm']:.4f} mm against {guard['rigid_mm']:.4f} mm, p = {guard['p_value']:.2g}); "
            "do not serve it: check the referencing notes in its report and measure more varied poses"
        )
    return HybridModel.load(out), manifest


def _floors(
    chain: Chain, raw: Sets, rigid_refs: dict[str, Referencing], manifest: dict[str, Any], log: Callable[[str], None]
) -> None:
    """The floors of this data (from its repeated joints, and the tracker's own where the pairs carry it) into
    ``manifest``, each told against the held-out error, and what the learning curve says more poses would do."""
    floor = measurement_floor(_by_frame(raw), chain, rigid_refs)
    manifest["floor"] = None if floor is None else floor.manifest()
    tracker = pooled_floor(raw[0])
    if tracker is not None:
        manifest["tracker_floor"] = floor_summary(tracker)
    held_out = manifest["metrics"]["test"]["hybrid"].get("position_mm_mean")
    if floor is not None and held_out is not None:
        log(floor.line(held_out))
    elif floor is None:
        log("no measurement floor: no two poses repeat the same joints (within 1 mrad); repeat a few to know it")
    if tracker is not None and held_out is not None:
        log(tracker_line(tracker, held_out))
    curve = manifest.get("capacity", {}).get("learning_curve")
    if curve is not None:
        log(capacity_module.curve_line(curve, None if floor is None else floor.position_mm))


def _stage(
    chain: Chain,
    raw: Sets,
    rigid_refs: dict[str, Referencing],
    recipe: Recipe,
    manifest: dict[str, Any],
    log: Callable[[str], None],
) -> Stage:
    """The stage the nets learn on: identified when the recipe says so and better than the rigid-only model
    on the validation pairs, else the URDF chain with its own referencing. Records it in ``manifest``.

    With ``recipe.drop_outliers``, the training pairs the first fit leaves far off (its outliers) are left out
    and the referencing, the capacity and the stage fitted again without them, once; the stage carries the
    pairs it kept, which the nets then learn from."""
    rigid = Stage(ElasticChain.rigid(chain), rigid_refs)
    if not recipe.parametric:
        return rigid
    start = time.perf_counter()
    refs, result = _identify(chain, raw[0], rigid_refs, recipe)
    kept, dropped = None, result
    if recipe.drop_outliers and len(result.outliers):
        kept = without(raw[0], result.outliers)
        again = reference_all(chain, kept, recipe.shared_targets, recipe.seed)
        refs, result = _identify(chain, kept, again, recipe)
    verdict = rigid_verdict(chain, raw[1], (result.model, refs), rigid_refs)
    if verdict is not None and not verdict["better"]:
        log(
            "parametric stage: not served, worse on the validation pairs than the URDF model with only the "
            f"tracker and target fitted ({verdict['candidate_mm']:.4f} mm against {verdict['rigid_mm']:.4f} mm)"
        )
        manifest["stage_not_served"] = verdict
        return rigid
    if result.capacity is not None:
        manifest["capacity"] = result.capacity
        log("parametric stage capacity (cross-validated): " + capacity_module.summary(result.capacity))
    manifest["parametric"] = {**result.manifest(), "seconds": round(time.perf_counter() - start, 1)}
    if kept is not None:
        manifest["parametric"]["dropped"] = dropped.manifest()["outliers"]
        log(
            f"parametric stage: {len(dropped.outliers)} training pairs beyond {1e3 * dropped.outlier_limit:.4f} mm "
            "of what it leaves dropped as outliers; the referencing and the stage fitted again without them"
        )
    log(
        f"parametric stage: {int(result.identifiable.sum())} of {len(result.params)} parameters identifiable; "
        f"rms {result.rms_before['position_mm']:.4f} -> {result.rms_after['position_mm']:.4f} mm; "
        f"{len(result.outliers)} pairs beyond {1e3 * result.outlier_limit:.4f} mm of what it leaves, down-weighted as "
        "outliers"
    )
    return Stage(result.model, refs, result, kept)


def _identify(
    chain: Chain, stations: Sequence[Pairs], rigid_refs: dict[str, Referencing], recipe: Recipe
) -> tuple[dict[str, Referencing], ParametricResult]:
    """:func:`identify_stations` as the recipe says."""
    return identify_stations(
        chain,
        stations,
        rigid_refs,
        recipe.payload,
        recipe.seed,
        recipe.capacity,
        recipe.choose_capacity,
        recipe.gravity_vector,
    )


def without(stations: Sequence[Pairs], drop: np.ndarray) -> list[Pairs]:
    """The ``stations`` without the pairs ``drop`` (indices into all of them, in order); a station that
    would be left empty is kept whole, so that every tracker frame stays referenced."""
    out, first = [], 0
    for p in stations:
        keep = np.setdiff1d(np.arange(len(p)), np.asarray(drop) - first)
        first += len(p)
        out.append(p.subset(keep) if len(keep) else p)
    return out


def _inputs(chain: Chain, recipe: Recipe, stage: Stage, sets: tuple[Pairs, ...], log: Callable[[str], None]) -> Inputs:
    """The nets' condition channels and the ranges every input is normalised over.

    The stage's backlash terms give the nets the joints' approach directions too. Offered channels (None in
    the recipe: every channel all the sets carry that varies in training, unless channels are named) are
    taken by a net only where its validation errors show their worth (:func:`train.train_net`).
    """
    train_pairs = sets[0]
    conditions = recipe.conditions
    channels = approach.channel_names(chain.joint_names)
    if stage.base.backlash is not None and not set(channels) & set(conditions):
        conditions = (*conditions, *channels)
    offered = recipe.offered
    if offered is None:
        named = [c for c in conditions if not approach.is_channel(c)]
        carried = set.intersection(*(set(p.conditions) for p in sets))
        varied = {c for c in carried if np.ptp(train_pairs.conditions[c]) > 0}  # a constant one teaches nothing
        offered = () if named else tuple(sorted(c for c in varied if not approach.is_channel(c)))
        every = set().union(*(set(p.conditions) for p in sets))
        unused = sorted(c for c in every - set(offered) - set(conditions) if not approach.is_channel(c))
        if unused:
            why = "channels were named" if named else "missing from some of the pairs, or constant in training"
            log(f"condition channels not offered to the nets: {', '.join(unused)} ({why})")
    offered = tuple(c for c in offered if c not in conditions)
    lower, upper = train_pairs.q.min(axis=0), train_pairs.q.max(axis=0)
    norm_lower, norm_upper = (chain.lower, chain.upper) if recipe.preset.full_range else (lower, upper)
    norm_lower = np.where(np.isfinite(norm_lower), norm_lower, lower)
    norm_upper = np.where(np.isfinite(norm_upper), norm_upper, upper)
    every_channel = (*conditions, *offered)
    if every_channel:  # condition columns follow the joints, normalised over the range seen in training
        c = _net_inputs(train_pairs, every_channel)[:, chain.dof :]
        directions = np.array([approach.is_channel(name) for name in every_channel])  # always over -1 … +1
        low, high = np.where(directions, -1.0, c.min(axis=0)), np.where(directions, 1.0, c.max(axis=0))
        norm_lower, norm_upper = np.r_[norm_lower, low], np.r_[norm_upper, high]
    return Inputs(every_channel, len(conditions), norm_lower, norm_upper)


def _train_nets(
    chain: Chain,
    recipe: Recipe,
    base: ElasticChain,
    sets: tuple[Pairs, Pairs],
    inputs: Inputs,
    hooks: Hooks,
) -> Trained:
    """Both nets on what ``base`` leaves of the training pairs, side by side; the inputs without the offered
    channels when no net took them (the node then needs no value for them)."""
    x = [_net_inputs(p, inputs.conditions) for p in sets]
    # what the stage leaves, with its backlash terms shifting the joints the way each pair arrived
    y = [train.residual_targets(base, base.approached(p.q, approach_of(p)), p.T, _target_offsets(p)) for p in sets]
    offered_columns = tuple(range(chain.dof + inputs.forced, chain.dof + len(inputs.conditions)))
    offered = inputs.conditions[inputs.forced :]
    kinds = ("position",) if sets[0].position_only else train.KINDS
    jobs = {
        kind: train.NetJob(
            kind,
            replace(recipe.preset, arch=recipe.arch.get(kind) or recipe.preset.arch),
            x[0],
            y[0][kind],
            x[1],
            y[1][kind],
            inputs.lower,
            inputs.upper,
            train.joint1_axis(chain),
            60.0 * recipe.max_minutes,
            recipe.seed + seed_offset,
            chain.dof,
            offered=offered_columns,
            offered_label=", ".join(offered),
        )
        for seed_offset, kind in enumerate(kinds)
    }
    nets, histories = train.train_pair(jobs, progress=hooks.progress)
    for kind, history in histories.items():
        if history[-1].get("silenced"):
            hooks.log(f"{kind} net: no better than the stage before it on validation, so it corrects nothing")
    if not offered:
        return Trained(nets, histories, inputs)
    taken = [kind for kind, history in histories.items() if history[-1].get("takes_offered")]
    hooks.log(
        f"condition channels offered ({', '.join(offered)}): "
        + (f"taken by the {' and '.join(taken)} net" if taken else "no net is better with them on validation")
    )
    record = {"channels": list(offered), "taken_by": taken}
    if taken:
        return Trained(nets, histories, inputs, record)
    for net in nets.values():
        net.drop_inputs(offered_columns)
    return Trained(nets, histories, inputs.without_offered(chain.dof), record)


def _by_frame(raw: Sets) -> list[Pairs]:
    """Every set's pairs gathered per tracker frame (train, validation and test of one station together)."""
    frames: dict[str, list[Pairs]] = {}
    for parts in raw:
        for pairs in parts:
            frames.setdefault(pairs.frame_id, []).append(pairs)
    return [Pairs.concatenate(parts) for parts in frames.values()]


def _model_manifest(chain: Chain, train_pairs: Pairs, trained: Trained, recipe: Recipe) -> dict[str, Any]:
    """The manifest's entries on the chain, the trained range, the inputs and the nets."""
    inputs = trained.inputs
    out: dict[str, Any] = {
        "base_link": chain.base_link,
        "tip_link": chain.tip_link,
        "joint_names": list(chain.joint_names),
        "tool": chain.tool.tolist(),
        "joint_limits": {"lower": chain.lower.tolist(), "upper": chain.upper.tolist()},
        "trained_range": {"lower": train_pairs.q.min(axis=0).tolist(), "upper": train_pairs.q.max(axis=0).tolist()},
        "position_only": train_pairs.position_only,
        "nets": {kind: {"epochs": len(history), **_best(history)} for kind, history in trained.histories.items()},
        "preset": asdict(recipe.preset),
        "seed": recipe.seed,
    }
    if trained.offered:
        out["offered_conditions"] = trained.offered
    if inputs.conditions:
        out["conditions"] = {
            name: {
                # an approach direction is unknown (0) until the joint moves; other channels: the training mean
                "default": 0.0 if approach.is_channel(name) else float(np.mean(train_pairs.conditions[name])),
                "lower": float(lo),
                "upper": float(hi),
            }
            for name, lo, hi in zip(
                inputs.conditions, inputs.lower[chain.dof :], inputs.upper[chain.dof :], strict=True
            )
        }
    return out


def _bounds(
    chain: Chain,
    model: HybridModel,
    sets: tuple[Pairs, ...],
    stage: Stage,
    recipe: Recipe,
    manifest: dict[str, Any],
    log: Callable[[str], None],
) -> None:
    """The model's error bounds into ``manifest`` (:func:`calibrate_bounds`), or a log line saying why none."""
    options = stage.result.options if stage.result else {"kinds": capacity_module.ELASTIC["geometry"], "harmonics": 0}
    try:
        bounds = calibrate_bounds(chain, model, sets[0], sets[1], options, recipe.payload, recipe.gravity_vector)
    except (CalibrationError, np.linalg.LinAlgError) as exc:  # too few pairs to measure the growth: no bounds
        log(f"no error bounds: {exc}")
        return
    manifest["bounds"] = bounds.manifest()
    steepest = int(np.argmax(bounds.position.rates))
    log(
        f"error bounds ({bounds.level:.0%}): {1e3 * bounds.position.quantile:.4f} mm inside the trained range "
        "at a typical configuration, "
        f"growing beyond it by up to {1e3 * bounds.position.rates[steepest]:.3g} mm per rad "
        f"({chain.joint_names[steepest]})"
    )


def _test_errors(model: HybridModel, stations: Sequence[Pairs]) -> dict[str, tuple[np.ndarray, np.ndarray]] | None:
    """:func:`pose_errors_of` over every test station, in the order :func:`to_base_frame` joins them."""
    parts = [pose_errors_of(model, p) for p in stations if len(p)]
    if not parts:
        return None
    return {k: tuple(np.concatenate([e[k][i] for e in parts]) for i in (0, 1)) for k in parts[0]}


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
    position_only = val_pairs.position_only
    validation = bounds_module.Validation(
        val_pairs.q,
        excess(val_pairs.q, model.trained_lower, model.trained_upper, chain.revolute),
        (1e-3 * pos_mm, None if position_only else np.radians(rot_deg)),
        (1e-3 * alone_mm, None if position_only else np.radians(alone_deg)),
    )
    return bounds_module.calibrate(lin, ridge, chain.revolute, stage, validation)


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
