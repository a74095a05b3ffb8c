"""Update a calibration from a few new poses, in seconds, without retraining.

The parent model is kept whole (its nets, bounds and joint error map); what moves is its parametric stage's
identified parameters, the cyclic joint errors among them, and the tracker stations. The stations of the new
poses are placed through the parent (:func:`~hybrid_kinematics_ros.calibration.verify.place_station`) when it
does not know them, and each gets a small correction of its tracker placement and target. The stage's
parameters change from the parent's values against a prior that holds each by its σ (the parent's
:class:`~.parametric.Uncertainty`), weighted by a factor. A few poses cannot say how much the robot changed
since the parent's calibration, so the factor is chosen from the new poses themselves: each candidate is fitted
on all but one of ``FOLDS`` contiguous blocks and judged on the one left out, by the error the fit weighs
(position and orientation × the parent's orientation length); an infinite factor, the stations alone, is among the
candidates.

The problem is linear: the nets depend on the joints only, and the stage's parameters and the stations'
corrections are small, so the poses move linearly in them about the parent. What the new poses still show after
it, each net may learn by a couple of hundred steps from the parent's (:mod:`~.retune`), as far as the same held-out
blocks say it helps; 0 steps keeps the net.
"""

from __future__ import annotations

import copy
import hashlib
import json
import shutil
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
import torch
from scipy.spatial.transform import Rotation

from hybrid_kinematics_ros.calibration import retune
from hybrid_kinematics_ros.calibration.errors import CalibrationError
from hybrid_kinematics_ros.calibration.parametric import GEOMETRY_KINDS, SCALE, orientation_length
from hybrid_kinematics_ros.calibration.referencing import reference_stations
from hybrid_kinematics_ros.calibration.verify import MIN_REFERENCE_POSES, place_station
from hybrid_kinematics_ros.io.model_dir import MANIFEST, NET_FILES, sha256_file
from hybrid_kinematics_ros.io.pairs import Pairs
from hybrid_kinematics_ros.kinematics import se3
from hybrid_kinematics_ros.model.hybrid import HybridModel
from hybrid_kinematics_ros.model.parametric import model_from_manifest
from hybrid_kinematics_ros.model.referencing import Referencing

FOLDS = 4  # contiguous blocks of the new poses that choose the prior's weight
MIN_POSES = 20  # fewer cannot place a station and leave blocks to judge on
PRIOR_WEIGHTS = (*10.0 ** np.arange(-6, 3.1, 0.25), np.inf)  # the prior's weight, in the parent's information
STEP = 1e-3  # of each parameter's scaled unit: the finite difference of the stage's columns
STATION_STEP = 1e-6  # m or rad: the same for the stations' corrections
CHANGES_LISTED = 10  # the largest changes (in σ) that model.json and the summary name
RANK_TOLERANCE = 1e-10  # of the largest singular value: the stations' corrections the new poses cannot see
Fold = tuple[np.ndarray, np.ndarray]  # the poses fitted on and the block held out


@dataclass(frozen=True)
class Problem:
    """The new poses' residuals about the parent (``residual`` ``(N, w)``, position m then orientation rad ×
    ``length``, at the target in the base frame) and how they change per unit of each column
    (``jacobian`` ``(N, w, P)``): first the stage's parameters (``params``, indices into the manifest's list, per
    ``unit`` SI), then each station's corrections (its tracker's placement, its target's offset and, with a 6-D
    probe, turn). ``information`` ``(p,)``: the parent's on the stage's parameters, for a weight of one (the
    stations' corrections are free). ``inputs`` ``(N, k)``: the nets' inputs at the new poses."""

    residual: np.ndarray
    jacobian: np.ndarray
    information: np.ndarray
    params: list[int]
    unit: np.ndarray
    refs: list[Referencing]
    station: np.ndarray  # (N,) which of ``refs`` each pose was measured from
    position_only: bool
    length: float  # m per rad: the orientation residuals' weight, as the parent's stage was fitted with
    inputs: np.ndarray

    def fitted(self, rows: np.ndarray | slice = slice(None)) -> Ridge:
        """The fit on pose ``rows``, for any prior weight."""
        return Ridge.of(self, rows)

    def missed(self, kind: str, x: np.ndarray) -> np.ndarray:
        """``(N, 3)``: what the ``kind`` net would have to add after the columns' values ``x`` (m or rad)."""
        left = self.residual - self.jacobian @ x
        return left[:, :3] if kind == "position" else left[:, 3:] / self.length

    def errors(self, x: np.ndarray, rows: np.ndarray | slice = slice(None)) -> np.ndarray:
        """``(N, 3)``: each pose's error after the columns' values ``x``: the weighed one (position and
        orientation × ``length``, mm), position (mm) and orientation (deg; nan for position only)."""
        left = self.residual[rows] - self.jacobian[rows] @ x
        position = 1e3 * np.linalg.norm(left[:, :3], axis=1)
        if self.position_only:
            return np.column_stack([position, position, np.full(len(left), np.nan)])
        turn = np.degrees(np.linalg.norm(left[:, 3:], axis=1) / self.length)
        return np.column_stack([1e3 * np.linalg.norm(left, axis=1), position, turn])

    def stations_moved(self, x: np.ndarray) -> list[Referencing]:
        """The stations' referencings with their corrections ``x`` applied."""
        count = 9 if self.position_only else 12
        out = []
        for k, ref in enumerate(self.refs):
            move = np.zeros(12)
            move[:count] = x[len(self.params) + k * count : len(self.params) + (k + 1) * count]
            placement = se3.from_rotvec(move[:3], move[3:6])[0]
            mount = se3.from_rotvec(move[6:9], move[9:])[0]
            out.append(
                replace(
                    ref,
                    base_to_tracker=placement @ ref.base_to_tracker,
                    flange_to_target=ref.flange_to_target @ mount,
                    method="placed by update",
                )
            )
        return out


@dataclass(frozen=True)
class Ridge:
    """A problem's least-squares fit on some poses for every prior weight, from one SVD each: the stations'
    columns, free at every weight, are projected out, and the stage's columns whitened by their prior, so
    that a weight only scales the singular values' filter."""

    stage: np.ndarray  # the stage's columns on the rows (M, p)
    target: np.ndarray  # (M,)
    root: np.ndarray  # (p,): the prior's square root at a weight of one
    filtered: tuple[np.ndarray, np.ndarray, np.ndarray]  # the whitened, projected stage: Vᵀ, s and Uᵀ·target
    stations: tuple[np.ndarray, np.ndarray, np.ndarray]  # the stations' columns' SVD (U, s, Vᵀ), rank kept

    @classmethod
    def of(cls, problem: Problem, rows: np.ndarray | slice) -> Ridge:
        design = problem.jacobian[rows].reshape(-1, problem.jacobian.shape[2])
        target = problem.residual[rows].reshape(-1)
        count = len(problem.params)
        u, s, vt = np.linalg.svd(design[:, count:], full_matrices=False)
        rank = int(np.sum(s > s[0] * RANK_TOLERANCE)) if len(s) else 0
        u, s, vt = u[:, :rank], s[:rank], vt[:rank]
        root = np.sqrt(problem.information)
        stage = design[:, :count]
        whitened = (stage - u @ (u.T @ stage)) / root
        wu, ws, wvt = np.linalg.svd(whitened, full_matrices=False)
        return cls(stage, target, root, (wvt, ws, wu.T @ (target - u @ (u.T @ target))), (u, s, vt))

    def solve(self, weight: float) -> np.ndarray:
        """The columns' values for the prior ``weight`` (inf: the stations alone)."""
        vt, s, projected = self.filtered
        stage = np.zeros(len(self.root)) if np.isinf(weight) else vt.T @ (s / (s**2 + weight) * projected) / self.root
        u, su, uvt = self.stations
        return np.r_[stage, uvt.T @ ((u.T @ (self.target - self.stage @ stage)) / su)]


@dataclass(frozen=True)
class Updated:
    """The new model's manifest, what the update did (``record``, also in the manifest as ``update``) and the
    nets it tuned (kind -> TorchScript module; the others are the parent's)."""

    manifest: dict[str, Any]
    record: dict[str, Any]
    nets: dict[str, torch.jit.ScriptModule] = field(default_factory=dict)

    def lines(self) -> list[str]:
        r = self.record
        weight = "the stations alone" if r["prior_weight"] is None else f"prior weight {r['prior_weight']:.3g}"
        chosen = r["held_out_by_weight"]["inf" if r["prior_weight"] is None else f"{r['prior_weight']:.3g}"]
        alone = r["held_out_by_weight"]["inf"]
        out = [
            f"{r['poses']} poses; {weight}, chosen on {FOLDS} held-out blocks of them (means: {_means(chosen)}; "
            f"the stations alone: {_means(alone)})"
        ]
        out += [
            f"  {c['name']}: {c['from']:+.4g} -> {c['to']:+.4g} {c['unit']} ({c['sigmas']:.1f} σ)" for c in r["changed"]
        ]
        for kind, tuning in r["nets"].items():
            unit = "mm" if kind == "position" else "deg"
            errors = tuning["held_out_by_steps"]
            chosen = f"tuned {tuning['steps']} steps" if tuning["steps"] else "kept"
            out.append(
                f"{kind} net: {chosen} (held-out {errors[str(tuning['steps'])]:.4f} {unit}; kept: {errors['0']:.4f})"
            )
        return out


def _means(errors: dict[str, float | None]) -> str:
    turn = "" if errors["orientation_deg"] is None else f", {errors['orientation_deg']:.4f} deg"
    return f"{errors['position_mm']:.4f} mm{turn}"


def update(model: HybridModel, stations: Sequence[Pairs]) -> Updated:
    """A child of ``model`` fitted to the new poses ``stations`` (one :class:`Pairs` per frame)."""
    section = model.manifest.get("parametric")
    if not section or "uncertainty" not in section:
        raise CalibrationError(
            "the model has no parametric stage with parameter σ to update: retrain it with this version's train"
        )
    count = sum(len(p) for p in stations)
    if count < MIN_POSES:
        raise CalibrationError(f"{count} new poses; an update needs at least {MIN_POSES}")
    problem = _problem(model, section, stations)
    blocks = np.array_split(np.arange(count), FOLDS)
    folds = [(np.concatenate(blocks[:k] + blocks[k + 1 :]), block) for k, block in enumerate(blocks)]
    ridges = [problem.fitted(rest) for rest, _ in folds]
    held_out = {w: _held_out(problem, w, folds, ridges) for w in PRIOR_WEIGHTS}  # weighed, position, orientation
    weight = min(held_out, key=lambda w: held_out[w][0])
    x = problem.fitted().solve(weight)
    nets, tunings = _retuned(model, problem, x, folds, [r.solve(weight) for r in ridges])
    manifest, changed = _child_manifest(model, stations, problem, x)
    for kind, tuning in tunings.items():
        manifest["nets"][kind]["update_steps"] = tuning["steps"]
    record = {
        "poses": count,
        "stations": [ref.frame_id for ref in problem.refs],
        "prior_weight": None if np.isinf(weight) else float(weight),
        "held_out_position_mm_mean": float(held_out[weight][1]),
        "stations_only_position_mm_mean": float(held_out[np.inf][1]),
        "held_out_by_weight": {
            ("inf" if np.isinf(w) else f"{w:.3g}"): {"weighed_mm": e[0], "position_mm": e[1], "orientation_deg": e[2]}
            for w, e in held_out.items()
        },
        "position_mm_mean": float(np.mean(problem.errors(x)[:, 1])),
        "changed": changed,
        "nets": tunings,
    }
    manifest["parent"] = {"path": str(model.path), "sha256": _digest(model)}
    manifest["update"] = record
    return Updated(manifest, record, nets)


def write_updated(model: HybridModel, updated: Updated, out: Path) -> Path:
    """The child model directory at ``out``: the parent's files with the tuned nets and the updated
    ``model.json``."""
    check_out(out)
    shutil.copytree(model.path, out)
    manifest = copy.deepcopy(updated.manifest)
    for kind, net in updated.nets.items():
        net.save(str(out / NET_FILES[kind]))
        manifest["nets"][kind] |= {"file": NET_FILES[kind], "sha256": sha256_file(out / NET_FILES[kind])}
    (out / MANIFEST).write_text(json.dumps(manifest, indent=2) + "\n")
    return out


def check_out(out: Path) -> None:
    """Refuse a child directory that exists: an update never writes over a model."""
    if out.exists():
        raise CalibrationError(f"{out} exists already: choose a new directory, the parent model stays as it is")


def _digest(model: HybridModel) -> str:
    return hashlib.sha256((Path(model.path) / "model.json").read_bytes()).hexdigest()


def _held_out(problem: Problem, weight: float, folds: list[Fold], ridges: list[Ridge]) -> list[float]:
    """The mean held-out errors (weighed mm, position mm, orientation deg) of ``weight`` over the folds."""
    errors = [problem.errors(ridge.solve(weight), block) for (_, block), ridge in zip(folds, ridges, strict=True)]
    mean = np.mean(np.concatenate(errors), axis=0)
    return [float(v) if np.isfinite(v) else None for v in mean]


def _retuned(
    model: HybridModel, problem: Problem, x: np.ndarray, folds: list[Fold], fold_x: list[np.ndarray]
) -> tuple[dict[str, torch.jit.ScriptModule], dict[str, Any]]:
    """Each net tuned on what the updated stage leaves, by the count of steps the held-out folds choose (the
    stage refitted without each fold); none for a parent without its training configurations."""
    if model.coverage is None:
        return {}, {}
    draw = np.random.default_rng(0).permutation(len(model.coverage))[: retune.ANCHORS]
    anchor_inputs = model.net_inputs(model.coverage[draw])
    nets, tunings = {}, {}
    for kind, net in model.nets.items():
        if kind == "orientation" and problem.position_only:
            continue
        anchors = retune.Anchors(anchor_inputs, retune.outputs(net, anchor_inputs))
        before = retune.outputs(net, problem.inputs)
        by_fold = [
            _fold_errors(net, kind, problem, fold, fx, anchors, before) for fold, fx in zip(folds, fold_x, strict=True)
        ]
        scale = 1e3 if kind == "position" else np.degrees(1.0)  # mm or deg
        mean = {s: float(scale * np.mean(np.concatenate([e[s] for e in by_fold]))) for s in retune.STEPS}
        steps = min(mean, key=lambda s: mean[s])
        tunings[kind] = {"steps": steps, "held_out_by_steps": {str(s): e for s, e in mean.items()}}
        if steps:
            targets = before + problem.missed(kind, x)
            nets[kind] = retune.tuned(net, problem.inputs, targets, anchors, (steps,))[steps]
    return nets, tunings


def _fold_errors(
    net: torch.jit.ScriptModule,
    kind: str,
    problem: Problem,
    fold: Fold,
    x: np.ndarray,
    anchors: retune.Anchors,
    before: np.ndarray,
) -> dict[int, np.ndarray]:
    """Each held-out pose's error (m or rad) after each count of steps, the net tuned on the fold's other poses."""
    rest, block = fold
    missed = problem.missed(kind, x)
    out = {}
    for steps, tuned in retune.tuned(net, problem.inputs[rest], before[rest] + missed[rest], anchors).items():
        added = retune.outputs(tuned, problem.inputs[block]) - before[block]
        out[steps] = np.linalg.norm(missed[block] - added, axis=1)
    return out


def _problem(model: HybridModel, section: dict[str, Any], stations: Sequence[Pairs]) -> Problem:
    """The update's linear problem about the parent, its stations placed."""
    position_only = stations[0].position_only
    length = orientation_length(model.manifest)
    if any(p.position_only != position_only for p in stations):
        raise CalibrationError("the new poses mix 6-D and position-only stations: update with one kind at a time")
    for pairs in stations:
        if pairs.frame_id not in model.referencings and len(pairs) < MIN_REFERENCE_POSES:
            raise CalibrationError(
                f"frame '{pairs.frame_id}': {len(pairs)} poses; a station the model does not know needs at least "
                f"{MIN_REFERENCE_POSES} to place it"
            )
    refs = [model.referencings.get(p.frame_id) or place_station(model, p)[0] for p in stations]
    base_link = model.chain.base_link
    pairs = Pairs.concatenate(
        [p.with_poses(ref.base_to_tracker @ p.T, base_link) for ref, p in zip(refs, stations, strict=True)]
    )
    station = np.repeat(np.arange(len(stations)), [len(p) for p in stations])
    conditions = model.conditions_of(pairs.conditions, len(pairs))
    hybrid, stage = model.fk(pairs.q, conditions=conditions), model.fk(pairs.q, nets=False, conditions=conditions)
    targets = np.stack([refs[k].flange_to_target for k in station])

    def residual(tips: np.ndarray = stage, moves: np.ndarray | None = None) -> np.ndarray:
        """Measured minus predicted at the target, for stage ``tips`` and the stations' ``moves`` ``(S, 12)``."""
        moves = np.zeros((len(refs), 12)) if moves is None else moves
        placement = se3.from_rotvec(moves[station, :3], moves[station, 3:6])
        mount = se3.from_rotvec(moves[station, 6:9], moves[station, 9:])
        served = tips.copy()  # the nets' correction, as the parent serves it: a shift and a turn in the base frame
        served[:, :3, 3] += hybrid[:, :3, 3] - stage[:, :3, 3]
        served[:, :3, :3] = hybrid[:, :3, :3] @ np.swapaxes(stage[:, :3, :3], 1, 2) @ tips[:, :3, :3]
        measured, predicted = placement @ pairs.T, served @ targets @ mount
        out = measured[:, :3, 3] - predicted[:, :3, 3]
        if position_only:
            return out
        turn = Rotation.from_matrix(measured[:, :3, :3] @ np.swapaxes(predicted[:, :3, :3], 1, 2)).as_rotvec()
        return np.hstack([out, length * turn])

    r0 = residual()
    params = [i for i, p in enumerate(section["parameters"]) if "sigma" in p]
    unit = np.array([SCALE[section["parameters"][i]["kind"]] for i in params])
    nominal = model_from_manifest(model.chain, section).fk(pairs.q)
    columns = []
    for i, u in zip(params, unit, strict=True):
        moved = list(section["parameters"])  # one entry replaced, the others shared
        moved[i] = {**moved[i], "value": moved[i]["value"] + STEP * u}
        shifted = model_from_manifest(model.chain, dict(section, parameters=moved)).fk(pairs.q)
        columns.append((r0 - residual(shifted @ se3.inverse(nominal) @ stage)) / STEP)  # left motion of the tip
    for k in range(len(refs)):
        for c in range(9 if position_only else 12):  # a reflector's turn on the flange is not seen
            moves = np.zeros((len(refs), 12))
            moves[k, c] = STATION_STEP
            columns.append((r0 - residual(stage, moves)) / STATION_STEP)
    sigma = np.array([section["parameters"][i]["sigma"] for i in params])
    information = (unit / sigma) ** 2 * np.mean(r0**2)
    jacobian = np.stack(columns, axis=-1)
    inputs = model.net_inputs(pairs.q, conditions)
    return Problem(r0, jacobian, information, params, unit, refs, station, position_only, length, inputs)


def _child_manifest(
    model: HybridModel, stations: Sequence[Pairs], problem: Problem, x: np.ndarray
) -> tuple[dict[str, Any], list[dict[str, Any]]]:
    """The parent's manifest with the stage's parameters and the stations moved, and the largest changes."""
    manifest = copy.deepcopy(model.manifest)
    parameters = manifest["parametric"]["parameters"]
    changed = []
    for i, u, value in zip(problem.params, problem.unit, x[: len(problem.params)], strict=True):
        entry, change = parameters[i], float(value * u)
        if change == 0.0:  # held (the stations alone were chosen)
            continue
        entry["value"] += change
        if entry["kind"] in GEOMETRY_KINDS:  # the geometry a URDF export carries moves with it
            entry["rigid_value"] += change
        sigmas = abs(change) / entry["sigma"]
        changed.append(
            {
                "name": entry["name"],
                "unit": entry["unit"],
                "from": entry["value"] - change,
                "to": entry["value"],
                "sigmas": sigmas,
            }
        )
    refs = {r.frame_id: r for r in model.referencings.values()}
    refs.update({r.frame_id: r for r in problem.stations_moved(x)})
    manifest["referencing"] = [r.manifest() for r in refs.values()]
    if "rigid_referencing" in manifest:  # "before" at a new station: the URDF model with its own referencing
        rigid = {r.frame_id: r for r in model.rigid_referencings.values()}
        for pairs in stations:
            if pairs.frame_id not in rigid:
                (rigid[pairs.frame_id],) = reference_stations(model.chain, [pairs])
        manifest["rigid_referencing"] = [r.manifest() for r in rigid.values()]
    return manifest, sorted(changed, key=lambda c: -c["sigmas"])[:CHANGES_LISTED]
