"""Training of the two residual nets: presets, targets, the training loop and parallel workers.

Targets follow the paper's Fig. 2: the position net learns ``Δp = p_true − p_model`` (added to the analytic
position) and the orientation net the axis-angle vector of ``R_true · R_modelᵀ`` (the rotation of eq. 1's
``T_diff``). Keeping the position additive means an orientation-net error never leaks into position.
Losses are the paper's: the mean Euclidean norm of the error of each 3-vector.
"""

from __future__ import annotations

import math
import multiprocessing as mp
import queue
import time
from collections.abc import Callable
from dataclasses import dataclass, replace
from functools import partial
from typing import Any

import numpy as np
import torch
from scipy import stats

from hybrid_kinematics_ros.calibration.errors import CalibrationError
from hybrid_kinematics_ros.calibration.nets import InputSpan, ResidualNet
from hybrid_kinematics_ros.kinematics import se3
from hybrid_kinematics_ros.kinematics.chain import Chain
from hybrid_kinematics_ros.kinematics.elastic import ElasticChain
from hybrid_kinematics_ros.model.nets import to_joint1_frame

KINDS = ("position", "orientation")
UNIT = {"position": ("mm", 1e3), "orientation": ("deg", 180.0 / math.pi)}


@dataclass(frozen=True)
class Preset:
    name: str
    arch: str  # one architecture, or several, simplest first, comma-separated: chosen on validation (train_net)
    optimizer: str  # "adam" or "adagrad"
    lr: float
    batch: int
    sincos: bool  # sin/cos joint features beside the normalised joints
    turn: bool  # learn the residual in the frame that turns with joint 1
    cosine: bool  # cosine learning-rate decay to zero at max_epochs (or by the time budget, if they will not fit)
    max_epochs: int  # with a generous time budget, a schedule that machine load does not change
    patience: int  # epochs without validation improvement before stopping; 0: never stop early
    full_range: bool  # normalise over the joint limits (else over the range seen in the data)
    members: int = 1  # nets averaged per residual, each from its own seed, one after the other
    # with members = 1: the ensemble the ladder tries of the size served, after the sizes (1: none; train_net)
    ensemble: int = 1

    @property
    def added(self) -> int:
        """The members the ensemble rung adds to the size served: none when ``members`` fixes the ensemble."""
        return self.ensemble - 1 if self.members == 1 else 0

    @property
    def nets(self) -> int:
        """The most nets :func:`train_net` trains per residual: every size (each of ``members`` nets) and the
        ensemble rung's added members. A budget per net times this is one for the whole ladder."""
        return len(candidates(self.arch)) * self.members + self.added


PRESETS = {
    "fast": Preset(
        "fast", "mlp:64x2:silu,mlp:256x3:silu", "adam", 1e-2, 1024, True, True, True, 100_000, 0, False, ensemble=4
    ),
    "paper": Preset("paper", "D4w", "adagrad", 5e-3, 128, False, False, False, 300, 10, True),
}


def residual_targets(
    base: ElasticChain, q: np.ndarray, T: np.ndarray, target: np.ndarray | None = None
) -> dict[str, np.ndarray]:
    """Base-frame targets ``{"position": Δp (N, 3) m, "orientation": ω (N, 3) rad}`` against ``base``.

    ``target`` (m, tip frame): position-only pairs measure the point there, so ``Δp`` is that point's
    error; with the orientation uncorrected it is also the served tip's position correction.
    """
    model = base.fk(q)
    return {
        "position": T[:, :3, 3] - se3.point_at(model, target),
        "orientation": se3.rotvec(T[:, :3, :3] @ np.swapaxes(model[:, :3, :3], 1, 2)),
    }


def joint1_axis(chain: Chain) -> np.ndarray | None:
    """Joint 1's axis in the base frame, or None when joint 1 is prismatic."""
    return chain.pre[0, :3, :3] @ chain.axes[0] if chain.revolute[0] else None


@dataclass
class NetJob:
    """Everything one worker needs to train one net (picklable)."""

    kind: str
    preset: Preset
    q_train: np.ndarray
    y_train: np.ndarray
    q_val: np.ndarray
    y_val: np.ndarray
    lower: np.ndarray
    upper: np.ndarray
    axis: np.ndarray | None
    max_seconds: float
    seed: int
    n_joints: int | None = None  # q_* hold condition columns after the joints when fewer than their width
    # condition columns offered, not given: the net ignores them unless its ladder's conditions rung shows
    # their worth (train_net); ``offered_label`` names them in the history, ``take_offered``: read them
    offered: tuple[int, ...] = ()
    offered_label: str = ""
    take_offered: bool = False


def build_net(job: NetJob) -> ResidualNet:
    p = job.preset
    axis = job.axis if p.turn else None
    local = to_joint1_frame(job.y_train, job.q_train[:, 0], axis)
    mean = local.mean(axis=0)
    scale = float(np.sqrt(np.mean(np.sum((local - mean) ** 2, axis=1)) / 3.0)) or 1.0
    inputs = InputSpan(job.lower, job.upper, job.n_joints, () if job.take_offered else job.offered)
    return ResidualNet(p.arch, inputs, (mean, np.full(3, scale)), p.sincos, axis, p.members)


GATE_CHUNKS = 10  # the validation pairs' chunks the nets' gate takes its noise from (one a block, by default)
GATE_CONFIDENCE = 0.95  # the nets are kept when their gain over the stage is significant at this level
SIZE_RESERVE = 0.05  # of the budget: a larger size trains only if the simpler ones left it at least this


def _predict(net: ResidualNet, q: torch.Tensor) -> np.ndarray:
    net.eval()
    with torch.no_grad():
        out = net(q).numpy()
    net.train()
    return out


def _chunks(n: int) -> np.ndarray:
    """The chunk of each of ``n`` validation pairs: :data:`GATE_CHUNKS` consecutive runs of the recording (one
    a pair when fewer), the unit both the gate's test and the cross-fit's halves count in."""
    if not n:
        return np.zeros(0, dtype=int)
    sizes = [len(c) for c in np.array_split(np.arange(n), min(GATE_CHUNKS, n))]
    return np.repeat(np.arange(len(sizes)), sizes)


def _halves(n: int) -> np.ndarray:
    """The half (0 or 1) of each of ``n`` validation pairs: alternate chunks (:func:`_chunks`), so that each
    half holds whole blocks from all along the recording."""
    return _chunks(n) % 2


def _beats(diff: np.ndarray, tests: int = 1) -> bool:
    """Whether a model's errors beat those of a simpler one significantly; ``diff``: per validation pair, in
    recording order, its error less the simpler one's (at first, less the size of what the stage left: the
    nets against correcting nothing). The simpler model wins unless the gain passes a one-sided t-test at
    :data:`GATE_CONFIDENCE`: the nets add thousands of weights to the stage's hundreds, and a larger net
    many times a smaller one's, so they must show their worth, not merely tie. A ladder of ``tests`` rungs
    tests each at ``1 - (1 - GATE_CONFIDENCE) / tests`` (Bonferroni), so that trying more sizes does not make
    keeping a net that helps nothing likelier than one size would.

    The test is over the means of :data:`GATE_CHUNKS` consecutive chunks of the validation pairs (they come
    in recording order, whole blocks of it), not over single pairs: neighbours along a recording share their
    errors, so single pairs count the same evidence many times over.
    """
    if not len(diff):
        return False  # no validation pair: nothing shows the nets' worth
    chunk = _chunks(len(diff))
    chunks = np.bincount(chunk, diff) / np.bincount(chunk)
    if len(chunks) < 2:
        return bool(np.mean(chunks) < 0.0)
    error = float(np.std(chunks, ddof=1) / np.sqrt(len(chunks)))
    confidence = 1.0 - (1.0 - GATE_CONFIDENCE) / tests
    return bool(np.mean(chunks) < -stats.t.ppf(confidence, len(chunks) - 1) * error)


class _Selection:
    """The epochs a net keeps, chosen on the validation pairs: the best on every pair, which is served, and,
    for the gate, the best on each half of them (:func:`_halves`), or correcting nothing where no epoch beats
    it there. An epoch chosen on some pairs cannot be judged on them: the best of thousands of epochs beats
    nothing on the pairs that chose it even where the net learned only noise. So the gate judges each half by
    the epoch the *other* half chose (a cross-fit). With one validation pair there is no other half, and the
    net is silenced.

    The halves alternate along the recording, so a block at the edge of one half shares some of its errors
    with its neighbour in the other: the cross-fit is honest about the choice of epoch, less so about errors
    that drift slowly along the recording."""

    def __init__(self, y: np.ndarray) -> None:
        self.y = y
        self.nothing = np.linalg.norm(y, axis=1)
        self.best = float(self.nothing.mean()) if len(y) else math.inf  # correcting nothing, to beat
        half = _halves(len(y))
        self.sides = [half == h for h in (0, 1)]
        self.side_best = [float(self.nothing[s].mean()) if s.any() else -math.inf for s in self.sides]
        self.crossed = np.zeros_like(y)  # each pair's correction by the epoch the other half chose
        self.chosen = np.zeros(len(y), dtype=bool)  # whether the other half chose an epoch (else: nothing)

    def update(self, pred: np.ndarray) -> tuple[float, bool]:
        """One epoch's corrections of the validation pairs: their mean error, and whether it is the best yet."""
        err = np.linalg.norm(pred - self.y, axis=1)
        for h, side in enumerate(self.sides):
            if side.any() and err[side].mean() < self.side_best[h]:
                self.side_best[h] = float(err[side].mean())
                self.crossed[self.sides[1 - h]] = pred[self.sides[1 - h]]
                self.chosen[self.sides[1 - h]] = True
        val = float(err.mean()) if len(err) else math.inf
        if val < self.best:
            self.best = val
            return val, True
        return val, False


@dataclass
class _Fitted:
    """One net's training run: the weights served and what the gate may judge them by."""

    state: dict[str, torch.Tensor]  # the epoch best on every validation pair (or the last one, if none was)
    beat: bool  # whether any epoch beat correcting nothing on every validation pair
    crossed: np.ndarray  # (N_val, 3): each validation pair's correction by the epoch the *other* half chose
    chosen: np.ndarray  # (N_val,): whether that half chose an epoch; where not, ``crossed`` is zero (nothing)
    history: list[dict]
    clocked: bool = False  # whether the clock, not the steps, ended the run


def candidates(arch: str) -> list[str]:
    """The architectures a preset's ``arch`` offers, simplest first: one, or several separated by commas."""
    found = [a.strip() for a in arch.split(",") if a.strip()]
    if not found:
        raise CalibrationError(f"architecture '{arch}': name at least one (D4w, mlp:64x2:silu, ...)")
    return found


@dataclass
class _Trained:
    """One architecture trained (a single net or an ensemble), before the choice among them."""

    net: ResidualNet
    history: list[dict]
    beat: bool  # whether it beats correcting nothing on every validation pair, as served
    crossed: np.ndarray  # (N_val, 3): each validation pair's correction by the epochs the *other* half chose
    chosen: np.ndarray  # (N_val,): whether that half chose an epoch; where not, ``crossed`` is zero (nothing)
    clocked: bool = False  # whether the clock ended its run (a longer one was possible: :func:`train_net`)


def train_net(job: NetJob, report: Callable[[dict], None] | None = None) -> tuple[ResidualNet, list[dict]]:
    """Train one residual net, choosing its size, whether to average an ensemble and whether to correct at all
    on validation; returns the net served and the per-epoch history.

    The preset's architectures (:func:`candidates`, simplest first) train one after the other, and the ladder
    starts at correcting nothing: each rung is served only if its errors beat those of the rung served so far
    significantly (:func:`_beats`, at a level that counts the rungs), judged by a cross-fit of the epoch's
    choice (:class:`_Selection`). So the nets do not make the model worse where it can be checked, and a
    larger net must show its worth over a smaller one. With little or unstructured data the net is silenced
    (outputs zero: real UR10, 250 pairs; 300 poses of a virtual cell). The last rung, with the preset's
    ``ensemble`` > 1, is an ensemble of the size served: that net and ``ensemble - 1`` more from their own
    seeds, each with a rung's share of the budget (:func:`_train_members`); averaging takes out what a
    net owes to its seed, which a few thousand real pairs leave large. With ``members`` > 1 every rung is an
    ensemble of that many instead, and none is added. Where the clock, not the steps, ended the served net's
    run, time may be what it lacks, not a seed's luck: the first added member is then that net trained on
    (the rest of one longer schedule), and if it alone beats the net significantly, one more cycle takes
    all the time left instead of members (``cycles``).
    Condition channels offered (``job.offered``: the pairs carry them, nobody named them) are a rung of their
    own after the sizes: the size served, reading them, against that net without them; the rungs after it
    build their nets as it decided, and the last entry says so (``offered``: their names, ``takes_offered``).

    The history counts epochs and seconds on across the rungs; each entry carries its ``arch`` (an added
    member's entries their ``member``, a cycle's their ``cycle``), and the last one the choice: the
    architecture ``served`` (``silenced`` when none; its ``best_val_*`` figures), the ``members`` it averages,
    its ``cycles`` when more than one and, with several rungs, ``sizes``: each rung's crossed mean validation
    error and whether it was kept.
    """
    archs = candidates(job.preset.arch)
    for arch in archs[1:]:  # a misspelt larger size fails now, not after the smaller one has trained
        build_net(replace(job, preset=replace(job.preset, arch=arch)))
    ladder = _Ladder(job, report, archs)
    ladder.sizes(archs)
    if job.offered:
        ladder.offered()
    if ladder.ensemble > 1:
        ladder.averaged()
    return ladder.finish()


class _Ladder:
    """:func:`train_net`'s rungs in one budget: what is served so far (its errors on the validation pairs to
    beat), the history of every rung and each rung's verdict."""

    def __init__(self, job: NetJob, report: Callable[[dict], None] | None, archs: list[str]) -> None:
        self.job, self.report = job, report
        self.ensemble = job.preset.added + 1
        self.offers = bool(job.offered)
        self.shares = len(archs) + self.offers + job.preset.added  # the added members take a rung's share each
        self.tests = len(archs) + self.offers + (self.ensemble > 1)
        self.unit, self.factor = UNIT[job.kind]
        self.served: _Trained | None = None
        self.served_arch, self.served_members = archs[0], job.preset.members  # silenced, the simplest carries zeros
        self.served_cycles = 1  # the training runs of the net served, each on from the last (one longer run)
        self.taken = False  # whether the net served reads the offered condition columns
        self.nothing = np.linalg.norm(job.y_val, axis=1)
        self.served_err = self.nothing
        self.history: list[dict] = []
        self.rungs: list[dict] = []  # each rung's crossed validation error and whether it was kept
        self.first: ResidualNet | None = None
        self.start = time.perf_counter()

    def left(self) -> float:
        return self.job.max_seconds - (time.perf_counter() - self.start)

    def short(self, left: float) -> bool:
        """Whether ``left`` seconds are too few for another rung."""
        return left < SIZE_RESERVE * self.job.max_seconds

    def skip(self, label: str, why: str | None = None) -> None:
        entry = {"arch": label, f"crossed_val_{self.unit}": None, "kept": False, "trained": False}
        self.rungs.append(entry if why is None else {**entry, "why": why})

    def rung(
        self, label: str, arch: str, run: Callable[[float, Callable | None], _Trained], seconds: float, cycle: int = 1
    ) -> tuple[_Trained, bool]:
        """Train one rung of ``arch`` in ``seconds``, record it as ``label``, and say whether the ladder keeps it
        (``(trained, kept)``). ``cycle`` > 1: the rung trains the net served on, its entries say which cycle."""
        job, history = self.job, self.history
        epochs, elapsed = (history[-1]["epoch"], history[-1]["seconds"]) if history else (0, 0.0)

        def counted(e: dict) -> dict:
            out = _counted_on(e, epochs, elapsed, arch)
            if job.take_offered:  # a net that reads the offered columns: its entries say so (fit._best)
                out["reads_offered"] = True
            return out if cycle == 1 else {**out, "cycle": cycle}

        relay = None if self.report is None else (lambda e: self.report(counted(e)))
        trained = run(seconds, relay)
        history.extend(counted(e) for e in trained.history)
        err = np.linalg.norm(trained.crossed - job.y_val, axis=1)
        kept = trained.beat and _beats(err - self.served_err, self.tests)
        val = float(err.mean()) * self.factor if len(err) else None
        self.rungs.append({"arch": label, f"crossed_val_{self.unit}": val, "kept": kept})
        if kept:
            self.served_err = err
        return trained, kept

    def fit_one(self, job: NetJob, seconds: float, relay: Callable | None) -> _Trained:
        fit = _train_members if job.preset.members > 1 else _train_one
        return fit(replace(job, max_seconds=seconds), relay)

    def with_arch(self, arch: str, **changes: Any) -> NetJob:
        return replace(self.job, preset=replace(self.job.preset, arch=arch, **changes))

    def sizes(self, archs: list[str]) -> None:
        """The preset's sizes, simplest first, each in an equal share; the last one, whatever time is left."""
        for i, arch in enumerate(archs):
            left = self.left()
            if i and self.short(left):  # the simpler sizes took the budget: serve what they gave
                self.skip(arch)
                continue
            seconds = left if i == self.shares - 1 else min(left, self.job.max_seconds / self.shares)
            one = self.with_arch(arch)
            trained, kept = self.rung(arch, arch, lambda t, r, one=one: self.fit_one(one, t, r), seconds)
            self.first = self.first or trained.net
            if kept:
                self.served, self.served_arch = trained, arch

    def offered(self) -> None:
        """The condition channels offered (not given): the size served (the simplest, if none was: a channel can
        explain what the joints cannot) from the same seed, reading them, against the net served without."""
        label = f"{self.served_arch} + {self.job.offered_label}"
        left = self.left()
        if self.short(left):
            self.skip(label)
            return
        # one share even when it is the last rung: no longer a run than the net it is judged against
        seconds = min(left, self.job.max_seconds / self.shares)
        self.job = replace(self.job, take_offered=True)
        one = self.with_arch(self.served_arch)
        trained, kept = self.rung(label, self.served_arch, lambda t, r: self.fit_one(one, t, r), seconds)
        if kept:
            self.served, self.taken = trained, True
        else:
            self.job = replace(self.job, take_offered=False)  # the rungs after it build nets without the columns

    @property
    def name(self) -> str:
        """The served net's rung, as labelled."""
        return self.served_arch + (f" + {self.job.offered_label}" if self.taken else "")

    def averaged(self) -> None:
        """The last rung: one longer run where the clock ended the served net's (:meth:`cycles`), else an
        ensemble of the size served."""
        label = f"{self.name} x{self.ensemble}"
        if self.served is None or self.short(self.left()):  # nothing to average, or no time to
            self.skip(label, "no size served" if self.served is None else "the sizes took the budget")
            return
        single, continued = self.served, None
        if single.clocked and self.ensemble > 2:
            continued = self.cycles(single)
        left = self.left()
        if self.served is not single or self.short(left):
            why = "one longer run beat the net" if self.served is not single else "the longer run took the budget"
            self.skip(label, why)
            return
        many = self.with_arch(self.served_arch, members=self.ensemble)
        # judged against the single net as its member 0 counts in the ensemble: as served, where the other half
        # chose no epoch of it (zero there would favour the ensemble by the served epoch's own pairs)
        self.served_err = np.linalg.norm(_filled(single, self.job.q_val) - self.job.y_val, axis=1)
        run = lambda t, r: _train_members(replace(many, max_seconds=t), r, single, continued)  # noqa: E731
        trained, kept = self.rung(label, self.served_arch, run, left)
        if kept:
            self.served, self.served_members = trained, self.ensemble

    def cycles(self, single: _Trained) -> _Trained | None:
        """The clock ended the served net's run, so the time left may serve one longer run better than members:
        the first added member is that net trained on, as the rest of one longer schedule (:func:`_fit`; batches
        in member 1's order). If it alone beats the net significantly, time is what the net lacks: one more cycle
        takes all the time left, and no member is added. Else it is member 1 (a snapshot), returned."""
        job = self.job
        on = replace(self.with_arch(self.served_arch), seed=job.seed + MEMBER_SEED_STRIDE)
        trained_for = single.history[-1]["seconds"]
        continued = None
        for cycle in (2, 3):  # the first with a rung's share; the second, if the first won, all the rest
            left = self.left()
            if self.short(left):
                break
            seconds = min(left, job.max_seconds / self.shares) if cycle == 2 else left
            # Each cycle is one more rung judged; the sizes were judged before a cycle was known to be tried, so
            # along one path the ladder's level is exceeded by at most a sixth (Bonferroni sums: 1/3 + 1/3 + 1/4
            # + 1/4 of 1 - GATE_CONFIDENCE with two sizes).
            self.tests += 1
            # judged against the net as served: the cycle starts from weights chosen on every validation pair, so
            # its crossed errors share that choice, as the served net's do
            self.served_err = np.linalg.norm(_predict(self.served.net, torch.tensor(job.q_val)) - job.y_val, axis=1)
            # the rest of one cosine schedule over the whole run so far and this cycle
            resume = trained_for / (trained_for + seconds)
            run = partial(_continue, on, self.served.net, resume)
            continued, kept = self.rung(f"{self.name}, {cycle} cycles", self.served_arch, run, seconds, cycle)
            if not kept:
                break
            self.served, self.served_cycles = continued, cycle
            trained_for += continued.history[-1]["seconds"]
        return continued

    def finish(self) -> tuple[ResidualNet, list[dict]]:
        """The net served and the history, its last entry carrying the choice."""
        served, history, unit = self.served, self.history, self.unit
        net = self.first if served is None else served.net
        history[-1] = {k: v for k, v in history[-1].items() if k not in ("silenced", "served")}
        history[-1].update({"served": self.served_arch, "members": self.served_members})
        if self.offers:
            history[-1].update({"offered": self.job.offered_label, "takes_offered": self.taken})
        if self.served_cycles > 1:
            history[-1]["cycles"] = self.served_cycles
        if served is None:  # what is served is correcting nothing: its figures, not those of a size trained
            net.silence()
            best = float(self.nothing.mean()) * self.factor if len(self.nothing) else None
            history[-1].update({f"best_val_{unit}": best, "silenced": True})
        else:  # the served net's validation figures, not those of a later rung's last epoch
            history[-1].update({k: v for k, v in served.history[-1].items() if k.startswith("best_val_")})
        if len(self.rungs) > 1:
            history[-1]["sizes"] = self.rungs
        net.eval()
        return net, history


def _continue(job: NetJob, net: ResidualNet, resume: float, seconds: float, report: Callable | None) -> _Trained:
    """``net`` trained on for ``seconds``, finishing the schedule it would have had as one longer run."""
    return _train_one(replace(job, max_seconds=seconds), report, net, resume)


def _counted_on(entry: dict, epochs: int, seconds: float, arch: str | None = None, member: int | None = None) -> dict:
    """A history entry of one run among several (architectures or members), its epochs and seconds counted on."""
    out = {**entry, "epoch": entry["epoch"] + epochs, "seconds": round(entry["seconds"] + seconds, 2)}
    if arch is not None:
        out["arch"] = arch
    if member is not None:
        out["member"] = member
    return out


def _filled(trained: _Trained, q_val: np.ndarray) -> np.ndarray:
    """``trained``'s crossed corrections of the validation pairs, with the net as served where the other half
    chose no epoch of it: as a member of an ensemble it cannot correct nothing there."""
    out = trained.crossed.copy()
    if not trained.chosen.all():
        out[~trained.chosen] = _predict(trained.net, torch.tensor(q_val))[~trained.chosen]
    return out


def _relay(report: Callable[[dict], None], epochs: int, seconds: float, member: int, entry: dict) -> None:
    report(_counted_on(entry, epochs, seconds, member=member))


def _train_one(
    job: NetJob, report: Callable[[dict], None] | None, start: ResidualNet | None = None, resume: float = 0.0
) -> _Trained:
    """A single net of ``job.preset.arch``: the epoch best on every validation pair, and the crossed choice.
    ``start``, ``resume``: a net of that size to train on from, and where in its schedule (:func:`_fit`)."""
    fitted = _fit(job, report, None if start is None else start.state_dict(), resume)
    net = build_net(job)
    net.load_state_dict(fitted.state)
    return _Trained(net, fitted.history, fitted.beat, fitted.crossed, fitted.chosen, fitted.clocked)


def _fit(
    job: NetJob, report: Callable[[dict], None] | None, weights: dict | None = None, resume: float = 0.0
) -> _Fitted:
    """The training loop of one net (one body), keeping the best epoch on every validation pair and on each
    half of them (:func:`_halves`). ``weights``: to train on from, else the seed's; ``resume``: the
    share of a longer cosine schedule already run, which this run finishes: a net resumed so scores as one
    run of the whole length, where a restart at the full rate loses much of what the longer run gains."""
    torch.manual_seed(job.seed)
    p = job.preset
    net = build_net(job)
    if weights is not None:
        net.load_state_dict(weights)
    axis = job.axis if p.turn else None
    mean, scale = net.target_mean.numpy(), net.target_scale.numpy()
    y_std = (to_joint1_frame(job.y_train, job.q_train[:, 0], axis) - mean) / scale
    data = (torch.tensor(job.q_train), torch.tensor(y_std, dtype=torch.float32))
    q_val = torch.tensor(job.q_val)
    selection = _Selection(job.y_val)
    if p.optimizer == "adam":
        opt: torch.optim.Optimizer = torch.optim.Adam(net.parameters(), lr=p.lr)
    else:
        opt = torch.optim.Adagrad(net.parameters(), lr=p.lr)
    n = len(job.q_train)
    batch = min(p.batch, n)
    gen = torch.Generator().manual_seed(job.seed)
    schedule = _Schedule(p.lr if p.cosine else None, p.max_epochs * (n // batch), job.max_seconds, resume)
    state, history, stale = None, [], 0
    unit, factor = UNIT[job.kind]
    out_of_time = False
    for epoch in range(1, p.max_epochs + 1):
        total, steps, out_of_time = _epoch(net, opt, schedule, data, torch.randperm(n, generator=gen), batch)
        if steps == 0:
            break
        val, improved = selection.update(_predict(net, q_val))
        if improved:
            state = {k: v.clone() for k, v in net.state_dict().items()}
            stale = 0
        else:
            stale += 1
        entry = {
            "kind": job.kind,
            "epoch": epoch,
            "seconds": round(schedule.elapsed(), 2),
            "loss": total / steps,
            f"val_{unit}": val * factor,
            f"best_val_{unit}": selection.best * factor,
        }
        history.append(entry)
        if report:
            report(entry)
        if out_of_time or (p.patience and stale >= p.patience):
            break
    if not history:
        raise CalibrationError(f"{job.kind} net: no training step fitted in the time budget; give more time")
    if state is None:
        last = {k: v.clone() for k, v in net.state_dict().items()}
        return _Fitted(last, False, selection.crossed, selection.chosen, history, out_of_time)
    return _Fitted(state, True, selection.crossed, selection.chosen, history, out_of_time)


class _Schedule:
    """The learning rate along one cosine schedule (``lr`` its start; None: the optimiser's own rate
    throughout) and the time budget of ``max_seconds``.

    The schedule runs by steps, so that a run is the same on a loaded machine, unless the steps will not fit
    the time budget: then by time as well. That is decided once, when 5 % of the budget has gone (the first
    steps' pace, start-up included, says nothing). ``resume``: the share already run by an earlier fit."""

    def __init__(self, lr: float | None, total_steps: int, max_seconds: float, resume: float) -> None:
        self.lr, self.total_steps, self.max_seconds, self.resume = lr, total_steps, max_seconds, resume
        self.done_steps = 0
        self.time_limited: bool | None = None
        self.start = time.perf_counter()

    def elapsed(self) -> float:
        return time.perf_counter() - self.start

    def rate(self, elapsed: float) -> float | None:
        """The learning rate of the next step, ``elapsed`` seconds into the budget."""
        if self.lr is None:
            return None
        if self.time_limited is None and elapsed >= 0.05 * self.max_seconds:
            self.time_limited = elapsed / max(self.done_steps, 1) * self.total_steps > self.max_seconds
        progress = self.done_steps / self.total_steps
        if self.time_limited:
            progress = max(progress, elapsed / self.max_seconds)
        progress = self.resume + (1.0 - self.resume) * progress
        return self.lr * 0.5 * (1.0 + math.cos(math.pi * progress))


def _epoch(
    net: ResidualNet,
    opt: torch.optim.Optimizer,
    schedule: _Schedule,
    data: tuple[torch.Tensor, torch.Tensor],
    perm: torch.Tensor,
    batch: int,
) -> tuple[float, int, bool]:
    """One pass over the training pairs ``data`` (joints, standardised targets) in batches, in ``perm``'s
    order: the summed batch losses, the steps taken, and whether the time budget ran out."""
    q_train, y_train = data
    total, steps = 0.0, 0
    for s in range(0, len(q_train) - batch + 1, batch):
        elapsed = schedule.elapsed()
        if elapsed >= schedule.max_seconds:
            return total, steps, True
        rate = schedule.rate(elapsed)
        if rate is not None:
            for group in opt.param_groups:
                group["lr"] = rate
        idx = perm[s : s + batch]
        loss = torch.linalg.vector_norm(net.standardised(q_train[idx]) - y_train[idx], dim=1).mean()
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        total += loss.item()
        steps += 1
        schedule.done_steps += 1
    return total, steps, False


MEMBER_SEED_STRIDE = 1000  # member i trains from seed + i * this: apart from the other net's seed (+1)


def _train_members(
    job: NetJob,
    report: Callable[[dict], None] | None,
    first: _Trained | None = None,
    continued: _Trained | None = None,
) -> _Trained:
    """Each member as a single net from its own seed, with an equal share of the steps and the time budget;
    the ensemble, their average, is judged as a single net: each half of the validation pairs by the members
    the other half chose (a member cannot correct nothing, so where a half chose no epoch of it, by the member
    as served). ``first``: a single net of the same architecture already trained, from ``job.seed``, which is
    member 0 (the ladder's ensemble rung); ``continued``, with ``first``: that net trained on, member 1 (a
    snapshot of one longer run); the others share the budget. History entries carry ``member``; their epochs
    and seconds count on across members."""
    k = job.preset.members
    given = [t for t in (first, continued) if t is not None]
    added = k - len(given)
    single = replace(job, preset=replace(job.preset, members=1), max_seconds=job.max_seconds / added)
    history: list[dict] = []
    net = build_net(job)
    q_val = torch.tensor(job.q_val)
    crossed = np.zeros_like(job.y_val)
    for i, target in enumerate(net.body.members):
        if i < len(given):
            member, own = given[i].net, _filled(given[i], job.q_val)
        else:
            epochs, seconds = (history[-1]["epoch"], history[-1]["seconds"]) if history else (0, 0.0)
            relay = None if report is None else partial(_relay, report, epochs, seconds, i)
            member_job = replace(single, seed=job.seed + i * MEMBER_SEED_STRIDE)
            fitted = _fit(member_job, relay)
            history += [_counted_on(e, epochs, seconds, member=i) for e in fitted.history]
            member = build_net(member_job)
            member.load_state_dict(fitted.state)
            own = _filled(_Trained(member, fitted.history, fitted.beat, fitted.crossed, fitted.chosen), job.q_val)
        target.load_state_dict(member.body.state_dict())
        crossed += own / k  # the members share the output's scale: the ensemble is their average
    unit, factor = UNIT[job.kind]
    nothing = float(np.linalg.norm(job.y_val, axis=1).mean()) if len(job.y_val) else math.inf
    err = np.linalg.norm(_predict(net, q_val) - job.y_val, axis=1)
    val = float(err.mean()) if len(err) else math.inf
    history[-1] = {**history[-1], f"val_{unit}": val * factor, f"best_val_{unit}": min(val, nothing) * factor}
    return _Trained(net, history, val < nothing, crossed, np.ones(len(crossed), dtype=bool))


def _worker(job: NetJob, progress: mp.Queue) -> tuple[dict, list[dict]]:
    torch.set_num_threads(1)
    net, history = train_net(job, report=progress.put)
    return {k: v.numpy() for k, v in net.state_dict().items()}, history


def train_pair(
    jobs: dict[str, NetJob], progress: Callable[[dict], None] | None = None, parallel: bool = True
) -> tuple[dict[str, ResidualNet], dict[str, list[dict]]]:
    """Train the position and orientation nets, one process and one thread each when ``parallel``.

    Two single-threaded processes beat one process with two threads on a shared 2-core machine. Workers
    send back plain weights; the eager nets are rebuilt here (TorchScript only when a model is saved).
    """
    histories: dict[str, list[dict]] = {}
    nets: dict[str, ResidualNet] = {}
    if parallel and len(jobs) > 1:
        ctx = mp.get_context("spawn")
        with ctx.Manager() as manager:
            q = manager.Queue()
            with ctx.Pool(len(jobs), maxtasksperchild=1) as pool:
                pending = {k: pool.apply_async(_worker, (job, q)) for k, job in jobs.items()}
                while pending:
                    try:
                        entry = q.get(timeout=0.2)
                        if progress:
                            progress(entry)
                    except queue.Empty:
                        pass
                    for k in [k for k, r in pending.items() if r.ready()]:
                        state, histories[k] = pending.pop(k).get()
                        nets[k] = rebuilt(jobs[k], histories[k], state)
                while not q.empty() and progress:
                    progress(q.get())
    else:
        for kind, job in jobs.items():
            nets[kind], histories[kind] = train_net(job, report=progress)
    return nets, histories


def rebuilt(job: NetJob, history: list[dict], state: dict[str, np.ndarray]) -> ResidualNet:
    """The net a worker trained for ``job``, from its weights: of the size it chose and with the members it
    averages (``history[-1]``), not the preset's."""
    last = history[-1]
    net = build_net(replace(job, preset=replace(job.preset, arch=last["served"], members=last["members"])))
    net.load_state_dict({name: torch.from_numpy(v) for name, v in state.items()})
    return net.eval()


def preset(name: str, **overrides: object) -> Preset:
    """A preset with ``overrides`` (None: the preset's). ``members`` given fixes the ensemble: the ladder then
    tries none of its own."""
    if name not in PRESETS:
        raise CalibrationError(f"unknown preset '{name}'; choose one of {', '.join(PRESETS)}")
    given = {k: v for k, v in overrides.items() if v is not None}
    if "members" in given:
        given.setdefault("ensemble", 1)
    chosen = replace(PRESETS[name], **given)
    if chosen.members < 1:
        raise CalibrationError(f"members = {chosen.members}: an ensemble needs at least 1 net")
    if chosen.ensemble < 1:
        raise CalibrationError(f"ensemble = {chosen.ensemble}: the ensemble rung needs at least 1 net (1: none)")
    return chosen
