"""The parametric stage's capacity, chosen from the data being calibrated.

How many parameters a stage can carry depends on the robot and on how many poses pin them down: 40
harmonics per joint and a joint error map on 0.01 rad knots suit thousands of real UR10 poses and over-fit
hundreds.
So every size is chosen by cross-validation over **contiguous blocks** of the training pairs (neighbours
along a recording never sit on both sides; each fold holds out a contiguous fifth of the recording), and the
simpler candidate wins unless a richer one is better by more than the validation noise (the standard error
of the per-block differences: the one-standard-error rule) and by more than a micrometre. The choices are
made one after the other, each on top of the ones before:

1. the elastic terms: geometry only, plus joint compliance, plus its cubic term, plus a term in the
   torque's size (stiffer one way than the other), plus link bending;
2. the number of harmonics of the cyclic joint errors (0: none), then their prior;
3. whether the joints' approach directions matter (backlash): a shift of each joint by a constant times
   its direction, fitted with the stage; if it wins, the nets take the directions as inputs;
   1 to 3 again, each given the others, until none changes (bending judged without the gears' errors hides
   in them, and backlash judged without the directions passes for cyclic errors);
4. the joint error map's knot spacing (0: none), then its smoothness, held out differently: every fifth of
   :data:`MAP_BLOCKS` short blocks, as the train/validation/test split holds out its blocks. The map is a
   local correction: it corrects a joint at the angles the pairs near it visited, between measured poses,
   which is what those blocks measure. A held-out fifth of the recording asks it about angles no pair near
   them pinned, where every knot spacing falls back to its smoothness, and the coarser one wins by default
   (on the real UR10's series A, a coarser map than between blocks, and a worse hybrid on A's held-out
   blocks);
5. the weight of the orientation residuals against the position ones (``orientation_length``, m per rad).
   Least squares weighs each kind of residual best by the inverse of its spread, so the weight starts as
   the data's own ratio: the median position residual (m) over the median orientation residual (rad) that
   the stage chosen by 1 to 4 leaves on every pair, 1 to 4 chosen again at it until it changes by less
   than :data:`WEIGHT_TOLERANCE`. Then the weights :data:`WEIGHT_FACTORS` times it get their own
   capacity, and the held-out errors decide, with orientation weighed at the data's ratio in every
   candidate's score: the data's ratio stays unless another weight is better beyond the noise. The
   residuals on the fitted pairs, not held-out ones, give the ratio: held-out errors carry the parameters'
   estimation error, which the weight itself shapes (on a short virtual RX160 walk their ratio tips the
   elastic terms' choice from bending to the signed compliance, at a cost in position).
   A fixed 1 m per rad over-weighs orientation on the real UR10, whose ratio is well below 1: the data's
   weight gives a clearly smaller position error for slightly more orientation error. On short virtual
   walks the held-out errors choose the largest weight offered (orientation pins the bending down), smaller
   errors of both kinds than a weight of 1 (BENCHMARKS.md, "The orientation residuals' weight").

The chosen stage's learning curve (:func:`learning_curve`) then says whether more poses or a richer model
would help: its held-out error with each fold trained on a quarter, a half and all of its training blocks,
and what it leaves on the pairs it was fitted on.

Each candidate is solved on the problem linearised at the nominal model (:class:`Linearisation`; its
error is about a micrometre for milliradian parameters), so a candidate on a fold costs one small solve
instead of an identification: one selection takes seconds, and the orientation weight's several of them
about a minute on thousands of pairs. The test pairs never enter it.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from scipy.linalg import cho_factor, cho_solve

from hybrid_kinematics_ros.calibration.errors import CalibrationError
from hybrid_kinematics_ros.calibration.parametric import (
    ORIENTATION_LENGTH,
    STATION_KINDS,
    Linearisation,
    map_design,
    robust_scales,
    solve_joint_map,
)
from hybrid_kinematics_ros.kinematics.elastic import JointMap

BLOCKS = 20  # contiguous blocks of the training pairs; each is validated once
# Fold f holds out the blocks [f · BLOCKS / FOLDS, (f + 1) · BLOCKS / FOLDS): a fifth of the recording at once, not
# every fifth block. A held-out block between two training blocks measures interpolation along the recording;
# a held-out fifth measures how the stage carries to poses the rest did not visit, as the model is used.
# Dense data choose alike either way; a short walk does not: between the blocks it takes more harmonics than
# carry to another walk.
FOLDS = 5
ELASTIC = {  # each level adds to the one before
    "geometry": ("zero", "translation", "rotation"),
    "compliance": ("zero", "translation", "rotation", "compliance"),
    "cubic": ("zero", "translation", "rotation", "compliance", "cubic"),
    "signed": ("zero", "translation", "rotation", "compliance", "cubic", "signed"),
    "bending": ("zero", "translation", "rotation", "compliance", "cubic", "signed", "bending"),
}
HARMONICS = (0, 2, 5, 10, 20, 40)  # candidates, simplest first
HARMONIC_PRIORS = (300.0, 30.0, 3.0)  # in pairs; a stronger prior is the simpler model
MAP_STEPS = (0.0, 0.08, 0.04, 0.02, 0.01)  # rad; 0: no map, then ever finer
MAP_SMOOTHNESS = (0.3, 0.03, 0.003)  # a smoother map is the simpler model
START = {"harmonic_prior": 30.0, "map_smoothness": 0.03}  # the value a setting has before its turn comes
# A richer candidate must win by more than this too (m): a micrometre is about the error of the linearised
# problem the candidates are solved on, and below a laser tracker's resolution. On noise-free data the
# standard error alone lets 40 harmonics beat the true 2 by a fraction of a micrometre, and the extra 38 then
# extrapolate wildly.
RESOLUTION = 1e-6
# The joint error map's folds: every fifth of this many blocks (fit.SPLIT_BLOCKS, the split's own unit).
MAP_BLOCKS = 100
ROUNDS = 3  # turns of choosing the elastic terms and the cyclic errors, each given the other
WEIGHT_ROUNDS = 3  # at most this many selections with the orientation weight from the one before
WEIGHT_TOLERANCE = 0.1  # the weight is settled when a selection changes it by less than this share
CURVE_SHARES = (0.25, 0.5, 1.0)  # of each fold's training blocks: the learning curve's points
WEIGHT_FACTORS = (1 / 3, 3.0, 1 / 9, 9.0)  # the weights tried about the data's ratio, nearest first (the simpler)


@dataclass
class Capacity:
    """The chosen sizes, as :func:`~calibration.parametric.identify` takes them, and how each was decided."""

    elastic: str
    harmonics: int
    harmonic_prior: float
    map_step: float
    map_smoothness: float
    decisions: list[dict[str, Any]] = field(default_factory=list)  # one per setting, with every candidate's figures
    approach: bool = False  # the nets take the joints' approach directions
    orientation_length: float = ORIENTATION_LENGTH  # m per rad: the orientation residuals' weight in the fit
    curve: dict[str, Any] | None = None  # the chosen stage's learning curve (:func:`learning_curve`)

    @property
    def kinds(self) -> tuple[str, ...]:
        cyclic = ("harmonic",) if self.harmonics > 0 or self.map_step > 0 else ()
        return ELASTIC[self.elastic] + cyclic + (("backlash",) if self.approach else ())

    def identify_options(self) -> dict[str, Any]:
        return {
            "kinds": self.kinds,
            "harmonics": self.harmonics,
            "harmonic_prior": self.harmonic_prior,
            "map_step": self.map_step,
            "map_smoothness": self.map_smoothness,
            "orientation_length": self.orientation_length,
        }

    def manifest(self) -> dict[str, Any]:
        return {
            "method": f"cross-validation over {BLOCKS} contiguous blocks of the training pairs ({FOLDS} folds, each a "
            f"contiguous fifth of the recording; for the joint error map, every fifth of {MAP_BLOCKS} blocks); "
            f"the simplest candidate within one standard error (or {RESOLUTION * 1e3:g} mm) of the best",
            "chosen": {
                "elastic": self.elastic,
                "harmonics": self.harmonics,
                "harmonic_prior": self.harmonic_prior,
                "map_step": self.map_step,
                "map_smoothness": self.map_smoothness,
                "approach": self.approach,
                "orientation_length": self.orientation_length,
            },
            "decisions": self.decisions,
            **({"learning_curve": self.curve} if self.curve is not None else {}),
        }


def summary(section: dict[str, Any]) -> str:
    """One line of a model's ``capacity`` section: each setting, chosen or given."""
    return ", ".join(
        f"{d['setting']} {d['chosen']}" + (" (given)" if d.get("given") else "") for d in section["decisions"]
    )


def options_from(given: dict[str, Any]) -> dict[str, Any]:
    """:func:`~calibration.parametric.identify`'s options for the settings ``given`` (the others left to
    its defaults), without a selection."""
    names = ("harmonics", "harmonic_prior", "map_step", "map_smoothness", "orientation_length")
    out = {k: given[k] for k in names if k in given}
    elastic = _elastic_kinds(given["elastic"]) if "elastic" in given else ELASTIC["bending"]
    out["kinds"] = (*elastic, "harmonic", *(("backlash",) if given.get("approach") else ()))
    return out


def _elastic_kinds(name: str) -> tuple[str, ...]:
    if name not in ELASTIC:
        raise CalibrationError(f"elastic terms '{name}': choose one of {', '.join(ELASTIC)}")
    return ELASTIC[name]


def harmonic_ridge(lin: Linearisation, harmonic_prior: float) -> np.ndarray:
    """``(P,)``: the stage's prior on each column of ``lin`` in normal-equation units (scaled parameters):
    ``harmonic_prior`` pairs' worth on each harmonic, none on the other terms."""
    kind = np.array([p.kind for p in lin.params])
    return np.where(kind == "harmonic", harmonic_prior * lin.scale**2, 0.0)


def _blocks(lin: Linearisation, total: int, blocks: int = BLOCKS) -> np.ndarray:
    """The block of each drawn pair, from its place among the ``total`` training pairs."""
    return np.minimum(lin.pick * blocks // max(total, 1), blocks - 1)


@dataclass
class _Normal:
    """The robust-weighted normal equations of every pair over the identifiable columns; each fold's are
    these less its held-out pairs' (one product over every pair, then one over each fold's fifth)."""

    columns: np.ndarray  # identifiable columns (indices into lin.params)
    jacobian: np.ndarray  # (N, width, len(columns))
    weight: np.ndarray  # (N, width): the robust weights
    normal: np.ndarray
    gradient: np.ndarray


def _normal(lin: Linearisation) -> _Normal:
    columns = np.flatnonzero(lin.identifiable)
    jac = lin.jacobian[:, :, columns]
    res = lin.residual
    # Robust weights (soft L1 at a scale from what the fit leaves, as the identification's loss) from one fit
    # of every column on every pair: a broken-beam outlier then weighs alike in every candidate.
    flat = jac.reshape(-1, len(columns))
    z = _solve(flat.T @ flat, flat.T @ res.ravel())
    fitted = res + jac @ z
    weight = 1.0 / np.sqrt(1.0 + (fitted / robust_scales(fitted)) ** 2)
    w_all = weight.reshape(-1)
    return _Normal(columns, jac, weight, flat.T @ (w_all[:, None] * flat), flat.T @ (w_all * res.reshape(-1)))


@dataclass
class _Folds:
    """Per fold: the robust-weighted normal equations of its training pairs, and its held-out pairs."""

    lin: Linearisation
    block: np.ndarray
    normal: list[np.ndarray]
    gradient: list[np.ndarray]
    columns: np.ndarray  # identifiable columns (indices into lin.params) the normal equations hold
    held: list[np.ndarray]  # per fold: the held-out pairs (bool over the linearisation's pairs)
    held_jacobian: list[np.ndarray]  # per fold: the Jacobian of its held-out pairs over ``columns``
    jacobian: np.ndarray  # (N, width, len(columns)): the linearisation's Jacobian over those columns

    @classmethod
    def build(
        cls,
        lin: Linearisation,
        total: int,
        base: _Normal,
        interleaved: bool = False,
        blocks: int = BLOCKS,
    ) -> _Folds:
        """The folds of ``lin``: each a contiguous fifth of the recording, or, ``interleaved``, every fifth
        block. ``base``: the normal equations over every pair (:func:`_normal`), formed once for every fold
        design. ``blocks`` is capped at one block a pair, so that no fold is ever empty of training pairs."""
        blocks = min(blocks, len(lin.pick))
        block = _blocks(lin, total, blocks)
        columns, jac, weight = base.columns, base.jacobian, base.weight
        res = lin.residual
        fold = block % FOLDS if interleaved else block * FOLDS // blocks
        held = [fold == f for f in range(FOLDS)]
        held_jacobian = [jac[h] for h in held]
        normal, gradient = [], []
        for h, jh in zip(held, held_jacobian, strict=True):
            a = jh.reshape(-1, len(columns))
            w = weight[h].reshape(-1)
            normal.append(base.normal - a.T @ (w[:, None] * a))
            gradient.append(base.gradient - a.T @ (w * res[h].reshape(-1)))
        return cls(lin, block, normal, gradient, columns, held, held_jacobian, jac)

    def held_out(self, f: int) -> np.ndarray:
        return self.held[f]

    def solve(self, f: int, use: np.ndarray, prior: np.ndarray) -> np.ndarray:
        """Scaled parameter values (over ``columns``, zero where not ``use``) fitted on fold ``f``'s training
        pairs; ``prior`` (over ``columns``): the ridge on each, in normal-equation units."""
        idx = np.flatnonzero(use)
        z = np.zeros(len(self.columns))
        a = self.normal[f][np.ix_(idx, idx)] + np.diag(prior[idx])
        z[idx] = _solve(a, self.gradient[f][idx])
        return z

    def residual(self, f: int, z: np.ndarray, rows: np.ndarray | None = None) -> np.ndarray:
        """``(M, width)``: the residuals of fold ``f``'s held-out pairs (or ``rows``) after ``z``."""
        if rows is None:
            return self.lin.residual[self.held[f]] + self.held_jacobian[f] @ z
        return self.lin.residual[rows] + self.jacobian[rows] @ z


def _solve(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``a⁻¹ (−b)``: the Gauss-Newton step from zero, with a whisper of ridge for columns that are
    independent on all pairs but not on a fold's."""
    if len(b) == 0:
        return np.zeros(0)
    jitter = 1e-10 * max(float(np.mean(np.diag(a))), 1e-300)
    return -cho_solve(cho_factor(a + jitter * np.eye(len(b))), b)


def _scores(res: np.ndarray, block: np.ndarray) -> dict[int, float]:
    """Mean held-out error per block, m (orientation weighed in as in the fit)."""
    err = np.linalg.norm(res, axis=1)
    return {int(b): float(np.mean(err[block == b])) for b in np.unique(block)}


def _figures(res: np.ndarray, orientation_length: float) -> dict[str, float]:
    out = {"val_position_mm": float(1e3 * np.mean(np.linalg.norm(res[:, :3], axis=1)))}
    if res.shape[1] == 6:
        out["val_orientation_deg"] = float(np.degrees(np.mean(np.linalg.norm(res[:, 3:], axis=1))) / orientation_length)
    return out


def _choose(
    setting: str,
    labels: Sequence[Any],
    residuals: Sequence[np.ndarray],
    block: np.ndarray,
    orientation_length: float = ORIENTATION_LENGTH,
) -> tuple[int, dict]:
    """The simplest candidate (``labels`` come simplest first) whose per-block held-out error is within one
    standard error of the best's, or within :data:`RESOLUTION`; the decision with every candidate's figures."""
    per_block = np.array([[s for _, s in sorted(_scores(r, block).items())] for r in residuals])
    mean = per_block.mean(axis=1)
    best = int(np.argmin(mean))
    diff = per_block - per_block[best]
    noise = np.std(diff, axis=1, ddof=1) / np.sqrt(diff.shape[1]) if diff.shape[1] > 1 else np.zeros(len(labels))
    chosen = int(np.flatnonzero(diff.mean(axis=1) <= np.maximum(noise, RESOLUTION))[0])  # the best qualifies
    rows = [
        {
            "candidate": label,
            **_figures(r, orientation_length),
            "val_score_mm": float(1e3 * m),
            "worse_than_best_mm": float(1e3 * (m - mean[best])),
            "noise_mm": float(1e3 * se),
        }
        for label, r, m, se in zip(labels, residuals, mean, noise, strict=True)
    ]
    return chosen, {"setting": setting, "chosen": labels[chosen], "best": labels[best], "candidates": rows}


SETTINGS = ("elastic", "harmonics", "harmonic_prior", "map_step", "map_smoothness", "approach", "orientation_length")


def select_capacity(
    lin: Linearisation,
    total: int,
    fixed: dict[str, Any] | None = None,
    map_ridge: float | None = None,
) -> Capacity:
    """Choose the stage's capacity by cross-validation on ``lin`` (linearised with every elastic term and
    the most harmonics of :data:`HARMONICS`), drawn from ``total`` training pairs in recording order.

    ``fixed``: settings the user gave (:data:`SETTINGS`); they are not chosen, only recorded.

    When ``lin`` holds backlash columns (linearised with the pairs' approach directions), ``approach`` is
    chosen too: whether the stage's backlash terms, and the directions as the nets' inputs, earn their place.
    With orientation rows, the orientation residuals' weight is chosen last (the module text, item 5).
    """
    chosen = _chosen_capacity(lin, total, fixed, map_ridge)
    weighed = lin.reweighted(chosen.orientation_length) if lin.residual.shape[1] == 6 else lin
    chosen.curve = learning_curve(_Selection(weighed, total, {}, map_ridge), chosen)
    return chosen


def _chosen_capacity(lin: Linearisation, total: int, fixed: dict[str, Any] | None, map_ridge: float | None) -> Capacity:
    """:func:`select_capacity`'s choice."""
    fixed = {k: v for k, v in (fixed or {}).items() if v is not None}
    unknown = set(fixed) - set(SETTINGS)
    if unknown:
        raise CalibrationError(f"unknown capacity settings {sorted(unknown)}")
    _elastic_kinds(fixed.get("elastic", "geometry"))
    if lin.residual.shape[1] != 6:
        return _select(lin, total, fixed, map_ridge)[0]
    if "orientation_length" in fixed:
        length = float(fixed["orientation_length"])
        if not np.isfinite(length) or length <= 0:
            raise CalibrationError(f"orientation_length {length:g}: give a positive weight in m per rad")
        chosen = _select(lin.reweighted(length), total, fixed, map_ridge)[0]
        chosen.decisions.append({"setting": "orientation_length", "chosen": length, "given": True})
        return chosen
    # the data's own ratio of the two kinds' errors: the maximum-likelihood weight, to a fixed point
    ratios = []
    chosen, left, held = _select(lin, total, fixed, map_ridge)
    for _ in range(WEIGHT_ROUNDS + 1):
        pos, rot = (np.median(np.linalg.norm(left[:, k], axis=1)) for k in (slice(0, 3), slice(3, 6)))
        ratio = float(f"{pos / max(rot / lin.orientation_length, 1e-12):.3g}")
        ratios.append({"weight": lin.orientation_length, "ratio": ratio})
        if len(ratios) > WEIGHT_ROUNDS or abs(np.log(ratio / lin.orientation_length)) < np.log1p(WEIGHT_TOLERANCE):
            break
        lin = lin.reweighted(ratio)
        chosen, left, held = _select(lin, total, fixed, map_ridge)
    # then the weights about it, each with the capacity chosen at it, judged on held-out errors in the same
    # units (orientation at the data's ratio); the data's ratio stays unless another is better beyond the noise,
    # and of the others within the noise of the best, the nearest to it wins
    data = lin.orientation_length
    labels, options, residuals = [data], [chosen], [held]
    for factor in WEIGHT_FACTORS:
        weight = float(f"{data * factor:.3g}")
        other, _, other_held = _select(lin.reweighted(weight), total, fixed, map_ridge)
        labels.append(weight)
        options.append(other)
        residuals.append(other_held * np.r_[np.ones(3), np.full(3, data / weight)])
    block = _blocks(lin, total, min(BLOCKS, len(lin.pick)))
    best, decision = _choose("orientation_length", labels, residuals, block, data)
    chosen = options[best]
    chosen.decisions.append(
        {
            **decision,
            "method": "the data's ratio (m per rad): the median position error (m) over orientation error (rad) "
            "that the stage chosen at the ratio before leaves on every pair, until it settles (ratios); then that and "
            f"{len(WEIGHT_FACTORS)} weights about it, each with its own capacity, on held-out blocks with "
            "orientation weighed at the data's ratio",
            "ratios": ratios,
        }
    )
    return chosen


def learning_curve(selection: _Selection, chosen: Capacity) -> dict[str, Any]:
    """Whether more poses or a richer model would help the stage: its held-out position error (each contiguous
    fifth of the recording, as the capacity is judged) when each fold trains on a share of its training
    blocks (every fourth, every other, all: the poses thinned evenly over the recording), and the error it
    leaves on the pairs it was fitted on. ``gain_mm`` and ``gain_noise_mm``: what the last doubling of the
    poses removed from the held-out error, and that difference's standard error over the blocks."""
    use = selection.stage_columns(chosen.elastic, chosen.harmonics, chosen.approach)
    prior = selection.prior(chosen.harmonic_prior)
    held, fitted = [], []
    for share in CURVE_SHARES:
        left, on_fitted = selection.thinned_residuals(use, prior, round(1 / share))
        held.append(np.linalg.norm(left[:, :3], axis=1))
        fitted.append(on_fitted)
    block = selection.folds.block
    blocks = np.unique(block)
    gained = np.array([np.mean(held[-2][block == b] - held[-1][block == b]) for b in blocks])
    return {
        "shares": list(CURVE_SHARES),
        "held_out_position_mm": [float(1e3 * np.mean(h)) for h in held],
        "fitted_position_mm": [float(1e3 * f) for f in fitted],
        "gain_mm": float(1e3 * gained.mean()),
        "gain_noise_mm": float(1e3 * gained.std(ddof=1) / np.sqrt(len(gained))) if len(gained) > 1 else 0.0,
    }


def curve_line(curve: dict[str, Any], floor_mm: float | None) -> str:
    """What :func:`learning_curve` says, in one line of ``train``'s summary and the report."""
    points = ", ".join(
        f"{share:.0%} {mm:.4f}" for share, mm in zip(curve["shares"], curve["held_out_position_mm"], strict=True)
    )
    gain, noise = curve["gain_mm"], curve["gain_noise_mm"]
    more = "more poses would help" if gain > 2.0 * noise else "more poses would not measurably help"
    fitted = curve["fitted_position_mm"][-1]
    floor = "" if not floor_mm else f", {fitted / floor_mm:.1f}x the floor"
    return (
        f"the stage's learning curve (held-out position mm, by share of the training poses): {points}; the last "
        f"doubling gained {gain:.4f} ± {noise:.4f} mm: {more}. On the poses it was fitted to it leaves "
        f"{fitted:.4f} mm{floor}: what it leaves there, a richer model (or the nets) must take"
    )


def _select(
    lin: Linearisation, total: int, fixed: dict[str, Any], map_ridge: float | None
) -> tuple[Capacity, np.ndarray, np.ndarray]:
    """The capacity chosen at ``lin``'s orientation weight; the residuals ``(N, width)`` that the chosen stage
    and joint error map, fitted on every pair, leave of them; the chosen stage's held-out residuals (each a
    contiguous fifth of the recording, as the elastic terms and the cyclic errors are judged)."""
    return _Selection(lin, total, fixed, map_ridge).run()


class _Selection:
    """One capacity selection over a linearised stage: the settings given (``fixed``), the decisions made, and
    the cross-validated residuals each candidate leaves."""

    def __init__(self, lin: Linearisation, total: int, fixed: dict[str, Any], map_ridge: float | None) -> None:
        self.lin, self.total, self.fixed = lin, total, fixed
        self.ridge = {} if map_ridge is None else {"ridge": map_ridge}
        self.base = _normal(lin)
        self.folds = _Folds.build(lin, total, base=self.base)
        params = [lin.params[c] for c in self.folds.columns]
        self.kind = np.array([p.kind for p in params])
        self.freq = np.array([p.component // 2 + 1 if p.kind == "harmonic" else 0 for p in params])
        if max(self.freq, default=0) < max(fixed.get("harmonics", 0), 0):
            raise CalibrationError(f"harmonics {fixed['harmonics']}: the linearisation holds only {max(self.freq)}")
        self.settings = {**START, **{k: fixed[k] for k in ("harmonic_prior", "map_smoothness") if k in fixed}}
        self.made: dict[str, dict[str, Any]] = {}  # the latest decision of each setting, in the order first made

    def stage_columns(self, elastic: str, harmonics: int, backlash: bool = False) -> np.ndarray:
        kinds = (*ELASTIC[elastic], *STATION_KINDS, *(("backlash",) if backlash else ()))
        return np.isin(self.kind, kinds) | ((self.kind == "harmonic") & (self.freq <= harmonics))

    def prior(self, harmonic_prior: float) -> np.ndarray:
        return harmonic_ridge(self.lin, harmonic_prior)[self.folds.columns]

    def stage_residuals(
        self, elastic: str, harmonics: int, harmonic_prior: float, backlash: bool = False
    ) -> np.ndarray:
        """``(N, width)``: every pair's residual, from the fold that held it out."""
        use = self.stage_columns(elastic, harmonics, backlash)
        out = np.zeros_like(self.lin.residual)
        for f in range(FOLDS):
            z = self.folds.solve(f, use, self.prior(harmonic_prior))
            out[self.folds.held_out(f)] = self.folds.residual(f, z)
        return out

    def thinned_residuals(self, use: np.ndarray, prior: np.ndarray, every: int) -> tuple[np.ndarray, float]:
        """Every pair's held-out residual ``(N, width)`` with each fold trained on every ``every``-th of its
        training blocks, and the mean position error (m) on the pairs the folds were trained on."""
        folds, base = self.folds, self.base
        idx = np.flatnonzero(use)
        out, on_fitted = np.zeros_like(self.lin.residual), []
        for f in range(FOLDS):
            training = ~folds.held[f]
            kept_blocks = np.unique(folds.block[training])[::every]
            dropped = training & ~np.isin(folds.block, kept_blocks)
            a = base.jacobian[dropped][:, :, idx].reshape(-1, len(idx))
            w = base.weight[dropped].reshape(-1)
            normal = folds.normal[f][np.ix_(idx, idx)] - a.T @ (w[:, None] * a) + np.diag(prior[idx])
            gradient = folds.gradient[f][idx] - a.T @ (w * self.lin.residual[dropped].reshape(-1))
            z = np.zeros(len(folds.columns))
            z[idx] = _solve(normal, gradient)
            out[folds.held[f]] = folds.residual(f, z)
            kept = np.flatnonzero(training & ~dropped)
            on_fitted.append(np.linalg.norm(folds.residual(f, z, kept)[:, :3], axis=1))
        return out, float(np.mean(np.concatenate(on_fitted)))

    def decide(
        self, setting: str, labels: Sequence[Any], evaluate: Callable[[Any], np.ndarray], round_: int = 1
    ) -> Any:
        """The setting given, else the label whose held-out residuals win (:func:`_choose`)."""
        if setting in self.fixed:
            self.made[setting] = {"setting": setting, "chosen": self.fixed[setting], "given": True}
            return self.fixed[setting]
        residuals = [evaluate(label) for label in labels]
        chosen, decision = _choose(setting, labels, residuals, self.folds.block, self.lin.orientation_length)
        self.made[setting] = {**decision, "round": round_}
        return labels[chosen]

    def stage(self) -> tuple[str, int, bool]:
        """The elastic terms, the cyclic errors and the backlash term, chosen in turn, each given the others,
        until none changes (at most ROUNDS): judged without the gears' errors, a geared robot's bending hides in
        what they leave, and judged without the approach directions, backlash passes for cyclic errors."""
        settings, freq = self.settings, self.freq
        elastic, harmonics, backlash = "geometry", 0, False
        for round_ in range(1, ROUNDS + 1):
            before = (elastic, harmonics, settings["harmonic_prior"], backlash)
            elastic = self.decide(
                "elastic",
                list(ELASTIC),
                lambda e, h=harmonics, b=backlash: self.stage_residuals(e, h, settings["harmonic_prior"], b),
                round_,
            )
            harmonics = self.decide(
                "harmonics",
                [h for h in HARMONICS if h <= max(freq, default=0)],
                lambda h, e=elastic, b=backlash: self.stage_residuals(e, h, settings["harmonic_prior"], b),
                round_,
            )
            if harmonics > 0:
                settings["harmonic_prior"] = self.decide(
                    "harmonic_prior",
                    list(HARMONIC_PRIORS),
                    lambda p, e=elastic, h=harmonics, b=backlash: self.stage_residuals(e, h, p, b),
                    round_,
                )
            elif "harmonic_prior" not in self.fixed:
                self.made.pop("harmonic_prior", None)  # an earlier round's, for harmonics no longer fitted
            if "backlash" in self.kind or "approach" in self.fixed:
                backlash = bool(
                    self.decide(
                        "approach",
                        [False, True],
                        lambda b, e=elastic, h=harmonics: self.stage_residuals(e, h, settings["harmonic_prior"], b),
                        round_,
                    )
                )
            if (elastic, harmonics, settings["harmonic_prior"], backlash) == before:
                break
        return elastic, harmonics, backlash

    def map_left(
        self, train: np.ndarray, res_train: np.ndarray, rows: np.ndarray, res_rows: np.ndarray, step, smoothness
    ) -> np.ndarray:
        """What a joint error map of knot spacing ``step`` (0: none), fitted on the pairs ``train`` (bool)
        from their residuals ``res_train``, leaves of the residuals ``res_rows`` of the pairs ``rows``."""
        if step <= 0:
            return res_rows
        lin = self.lin
        q = lin.q[train]
        lower = q.min(axis=0) - step
        knots = int(np.floor((q.max(axis=0) - lower) / step).max()) + 2
        empty = JointMap(lower, step, np.zeros((q.shape[1], knots)))
        design = map_design(empty, q, lin.joint_rows[train])
        values = solve_joint_map(design, res_train.ravel(), len(q), q.shape[1], knots, smoothness, **self.ridge)
        design = map_design(empty, lin.q[rows], lin.joint_rows[rows])
        return res_rows - (design @ values.ravel()).reshape(res_rows.shape)

    def joint_map(self, use: np.ndarray) -> float:
        """The joint error map's knot spacing (and smoothness, in the settings), each fold's map fitted on what
        that fold's stage (columns ``use``) leaves of its training pairs (and, with approach directions, of the
        backlash they explain: the nets will carry that part)."""
        # from here on the decisions are judged on these folds (every fifth of MAP_BLOCKS blocks)
        folds = self.folds = _Folds.build(self.lin, self.total, interleaved=True, base=self.base, blocks=MAP_BLOCKS)
        stage = [folds.solve(f, use, self.prior(self.settings["harmonic_prior"])) for f in range(FOLDS)]
        # what each fold's stage leaves of its held-out and of its training pairs (the same for every map)
        left = [(folds.residual(f, stage[f]), folds.residual(f, stage[f], ~folds.held_out(f))) for f in range(FOLDS)]

        def mapped(step: float, smoothness: float) -> np.ndarray:
            out = np.zeros_like(self.lin.residual)
            for f in range(FOLDS):
                held = folds.held_out(f)
                res_val, res_train = left[f]
                out[held] = self.map_left(~held, res_train, held, res_val, step, smoothness)
            return out

        settings = self.settings
        map_step = self.decide("map_step", list(MAP_STEPS), lambda s: mapped(s, settings["map_smoothness"]))
        if map_step > 0:
            settings["map_smoothness"] = self.decide(
                "map_smoothness", list(MAP_SMOOTHNESS), lambda m: mapped(map_step, m)
            )
        return map_step

    def run(self) -> tuple[Capacity, np.ndarray, np.ndarray]:
        """:func:`_select`'s answer."""
        elastic, harmonics, backlash = self.stage()
        settings = self.settings
        held = self.stage_residuals(elastic, harmonics, settings["harmonic_prior"], backlash)
        use = self.stage_columns(elastic, harmonics, backlash)
        map_step = self.joint_map(use)
        chosen = Capacity(
            elastic,
            int(harmonics),
            float(settings["harmonic_prior"]),
            float(map_step),
            float(settings["map_smoothness"]),
            list(self.made.values()),
            backlash,
            self.lin.orientation_length,
        )
        # what the chosen stage and map, fitted on every pair, leave of them
        base, prior = self.base, self.prior(settings["harmonic_prior"])
        idx = np.flatnonzero(use)
        z = np.zeros(len(base.columns))
        z[idx] = _solve(base.normal[np.ix_(idx, idx)] + np.diag(prior[idx]), base.gradient[idx])
        fitted = self.lin.residual + base.jacobian @ z
        every = np.ones(len(fitted), dtype=bool)
        return chosen, self.map_left(every, fitted, every, fitted, map_step, settings["map_smoothness"]), held
