"""A residual net must beat correcting nothing on validation, or it is silenced: the nets never make the
stage before them worse where it can be checked."""

from __future__ import annotations

from dataclasses import replace
from types import SimpleNamespace

import numpy as np
import pytest
import torch

from hybrid_kinematics_ros.calibration import nets, train
from hybrid_kinematics_ros.calibration.errors import CalibrationError
from hybrid_kinematics_ros.calibration.fit import _best


def _job(sign: float) -> train.NetJob:
    rng = np.random.default_rng(0)
    q_train, q_val = rng.uniform(-2.0, 2.0, (600, 6)), rng.uniform(-2.0, 2.0, (150, 6))

    def residual(q: np.ndarray) -> np.ndarray:  # m: a smooth error of joint 2, 0.1 mm
        return 1e-4 * np.column_stack([np.sin(2 * q[:, 1]), np.cos(q[:, 1]), np.sin(q[:, 1] + q[:, 2])])

    preset = replace(train.PRESETS["fast"], arch="mlp:32x2:silu", batch=64, max_epochs=60, ensemble=1)
    lower, upper = np.full(6, -2.0), np.full(6, 2.0)
    # sign -1: validation says the opposite of training, so whatever the net learns makes it worse there
    return train.NetJob(
        "position", preset, q_train, residual(q_train), q_val, sign * residual(q_val), lower, upper, None, 60.0, 0, 6
    )


def _gain(crossed: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Per validation pair: the error after the correction less that of correcting nothing (the first rung)."""
    return np.linalg.norm(crossed - y, axis=1) - np.linalg.norm(y, axis=1)


def test_a_net_that_only_hurts_on_validation_is_silenced():
    job = _job(-1.0)
    net, history = train.train_net(job)
    assert history[-1]["silenced"]
    out = net(torch.tensor(job.q_val)).detach().numpy()
    assert not out.any()  # exactly zero: the model serves the stage before the nets


def test_a_net_that_helps_is_kept():
    job = _job(1.0)
    net, history = train.train_net(job)
    assert "silenced" not in history[-1]
    nothing = np.linalg.norm(job.y_val, axis=1).mean()
    err = np.linalg.norm(net(torch.tensor(job.q_val)).detach().numpy() - job.y_val, axis=1).mean()
    assert err < 0.5 * nothing


def test_the_gate_counts_a_block_of_the_recording_once():
    """Along a recording, neighbours share their errors: a net that helps on half of the validation blocks
    and hurts on the other half helps on average, by less than the blocks' spread. Counted by single pairs
    (1,000 of them, 100 a block) that average looks certain; counted by blocks it is noise, and the stage wins."""
    blocks, per_block = 10, 100
    y = np.tile([[1e-4, 0.0, 0.0]], (blocks * per_block, 1))  # what the stage leaves: 0.1 mm
    # the net's error per block, as a share of y: 0 (it fixes the block) or 1.8 (it overshoots)
    share = np.repeat(np.where(np.arange(blocks) % 2 == 0, 0.0, 1.8), per_block)
    answers = y * (1.0 - share[:, None])
    diff = _gain(answers, y)
    assert diff.mean() < -3 * diff.std(ddof=1) / np.sqrt(len(diff))  # by single pairs: beats nothing
    assert not train._beats(diff)
    # the same mean gain, the same in every block: the net is kept
    steady = y * (1.0 - np.full(len(y), 0.9)[:, None])
    assert train._beats(_gain(steady, y))


def test_the_gate_judges_each_half_by_the_epoch_the_other_half_chose():
    """The epoch served is the one the validation pairs chose, so they cannot also judge it. Two epochs that
    each fit one half of the validation pairs (by chance, say) and miss the other look perfect on the pairs
    that chose them; the gate judges each half by the other half's choice, and silences them."""
    y = np.random.default_rng(1).normal(0.0, 1e-4, (300, 3))  # what the stage leaves
    half = train._halves(len(y))
    assert set(np.bincount(half)) == {150}  # alternate chunks of the recording
    assert (np.diff(half) != 0).sum() == train.GATE_CHUNKS - 1
    selection = train._Selection(y)
    nothing = np.linalg.norm(y, axis=1)
    first = np.where(half[:, None] == 0, y, -0.5 * y)  # fixes half 0, overshoots half 1
    second = np.where(half[:, None] == 1, y, -0.6 * y)  # fixes half 1, overshoots half 0
    assert selection.update(0.5 * y) == (pytest.approx(0.5 * nothing.mean()), True)  # a fair epoch first
    assert selection.update(first)[1] is False  # 0 on half 0, 1.5 times what the stage left on half 1
    assert selection.update(second)[1] is False
    # half 0 chose `first`, half 1 `second`; each judges the other's choice
    np.testing.assert_array_equal(selection.crossed[half == 1], first[half == 1])
    np.testing.assert_array_equal(selection.crossed[half == 0], second[half == 0])
    assert not train._beats(_gain(selection.crossed, y))
    # judged on the pairs that chose them, the same choices looked perfect
    assert train._beats(_gain(np.where(half[:, None] == 0, first, second), y))


def test_a_net_is_kept_only_on_a_significant_gain():
    """A mean gain within the spread of the chunks' means does not keep the nets (1.2 standard errors passed
    the former rule, 1.7 would pass a normal test at 95 %); a larger one over the same spread does (2.0 fails a
    two-sided test at 95 %: the test is one-sided, a t over the 10 chunks). Two sizes tried, each test asks
    for more."""
    rng = np.random.default_rng(2)
    chunk = np.repeat(np.arange(train.GATE_CHUNKS), 100)
    spread = rng.normal(0.0, 1.0, train.GATE_CHUNKS)
    spread = (spread - spread.mean()) / spread.std(ddof=1)  # mean 0, standard deviation 1
    # the mean gain, in standard errors of the chunks
    for gain_in_errors, kept in ((1.2, False), (1.7, False), (2.0, True), (3.0, True)):
        share = 0.1 * (gain_in_errors / np.sqrt(train.GATE_CHUNKS) + spread[chunk])
        assert train._beats(-share * 1e-4) is kept
        # a ladder of two sizes tests each at 97.5 %: 2.0 standard errors no longer keep a net (t 2.26 at 9)
        assert train._beats(-share * 1e-4, tests=2) is (gain_in_errors > 2.5)


@pytest.mark.parametrize("members", [1, 3])
def test_the_served_net_is_gated_by_the_crossed_choice(monkeypatch, members):
    """The net served beats nothing on every validation pair; whether it is kept is up to the crossed choice
    alone, for a single net and an ensemble alike (where a half chose no epoch of a member, the member as served
    stands in: it cannot correct nothing)."""
    job = _job(1.0)
    job = replace(job, preset=replace(job.preset, members=members))
    trained = train._fit(replace(job, preset=replace(job.preset, members=1)), None)
    assert trained.beat
    for crossed, chosen, kept in (
        (job.y_val, np.ones(len(job.y_val), bool), True),  # the other half's choice fixes every pair
        (-job.y_val, np.ones(len(job.y_val), bool), False),  # it doubles every error
        (np.zeros_like(job.y_val), np.zeros(len(job.y_val), bool), members > 1),  # no half chose an epoch
    ):
        fitted = train._Fitted(trained.state, True, crossed, chosen, [dict(e) for e in trained.history])
        monkeypatch.setattr(train, "_fit", lambda *_a, f=fitted: f)
        net, history = train.train_net(job)
        assert ("silenced" not in history[-1]) is kept, (crossed[:1], chosen[:1])
        assert bool(net(torch.tensor(job.q_val)).detach().numpy().any()) is kept


SMALL, LARGE = "mlp:8x1:silu", "mlp:32x2:silu"


@pytest.mark.parametrize(
    "small, large, served",
    [
        (0.5, 0.5, SMALL),  # the larger net ties: the smaller serves
        (0.5, 0.0, LARGE),  # the larger fixes what the smaller leaves: it serves
        (2.0, 0.5, LARGE),  # the smaller only hurts; the larger beats nothing
        (2.0, 2.0, None),  # neither beats nothing: silenced
    ],
)
def test_the_net_size_is_a_ladder_from_nothing(monkeypatch, small, large, served):
    """The sizes train simplest first; each serves only if it beats the rung served before it (at first,
    correcting nothing) significantly, on its crossed validation errors (a share of what the stage left)."""
    job = _job(1.0)
    job = replace(job, preset=replace(job.preset, arch=f"{SMALL}, {LARGE}"))
    rng = np.random.default_rng(3)
    noise = rng.normal(0.0, 0.02, job.y_val.shape) * 1e-4

    def trained(one: train.NetJob, _report: object) -> train._Trained:
        share = small if one.preset.arch == SMALL else large
        net = train.build_net(one)
        history = [{"kind": "position", "epoch": 1, "seconds": 0.1, "val_mm": 1.0, "best_val_mm": 1.0}]
        return train._Trained(net, history, True, job.y_val * (1.0 - share) + noise, np.ones(len(job.y_val), bool))

    monkeypatch.setattr(train, "_train_one", trained)
    net, history = train.train_net(job)
    assert [s["arch"] for s in history[-1]["sizes"]] == [SMALL, LARGE]
    assert [e["arch"] for e in history] == [SMALL, LARGE]
    if served is None:
        assert history[-1]["silenced"] and history[-1]["served"] == SMALL
        assert not net(torch.tensor(job.q_val)).detach().numpy().any()
    else:
        assert "silenced" not in history[-1] and history[-1]["served"] == served
        assert sum(p.numel() for p in net.body.parameters()) == sum(
            p.numel() for p in train.build_net(replace(job, preset=replace(job.preset, arch=served))).body.parameters()
        )


def test_the_served_size_is_rebuilt_from_a_worker(tmp_path):
    """Trained in worker processes, each net comes back at the size chosen there, with its choice recorded."""
    job = replace(_job(1.0), preset=replace(_job(1.0).preset, arch=f"{SMALL},{LARGE}", max_epochs=20))
    nets, histories = train.train_pair({"position": job, "orientation": replace(job, kind="orientation", seed=1)})
    for kind, history in histories.items():
        arch = history[-1]["served"]
        assert arch in (SMALL, LARGE) and len(history[-1]["sizes"]) == 2
        width = int(arch.split(":")[1].split("x")[0])
        first = next(m for m in nets[kind].body.modules() if isinstance(m, torch.nn.Linear))
        assert first.out_features == width


def test_a_larger_size_the_budget_has_no_room_for_is_not_trained(monkeypatch):
    """When the simpler size took the budget, the larger one is recorded as not trained (no error), and
    the simpler one serves if it beat correcting nothing. The clock is the training's own: each size
    "takes" the whole budget."""
    job = replace(_job(1.0), preset=replace(_job(1.0).preset, arch=f"{SMALL},{LARGE}"))
    clock = iter(np.arange(0.0, 100.0) * job.max_seconds)
    monkeypatch.setattr(train.time, "perf_counter", lambda: float(next(clock)))
    trained_archs = []

    def trained(one: train.NetJob, _report: object) -> train._Trained:
        trained_archs.append(one.preset.arch)
        history = [{"kind": "position", "epoch": 1, "seconds": 0.1, "val_mm": 1.0, "best_val_mm": 1.0}]
        return train._Trained(train.build_net(one), history, True, 0.5 * job.y_val, np.ones(len(job.y_val), bool))

    monkeypatch.setattr(train, "_train_one", trained)
    net, history = train.train_net(job)
    assert trained_archs == [SMALL]
    assert history[-1]["served"] == SMALL and "silenced" not in history[-1]
    assert net(torch.tensor(job.q_val)).detach().numpy().any()
    assert history[-1]["sizes"][1] == {"arch": LARGE, "crossed_val_mm": None, "kept": False, "trained": False}


@pytest.mark.parametrize(
    "single, many, members",
    [
        (0.5, 0.5, 1),  # the ensemble ties: the single net serves
        (0.5, 0.1, 3),  # the ensemble fixes what the single net leaves: it serves
        (2.0, 0.1, None),  # no size beats nothing: no ensemble is tried, the net is silenced
    ],
)
def test_an_ensemble_of_the_size_served_is_the_last_rung(monkeypatch, single, many, members):
    """After the sizes, the preset's ``ensemble`` rung averages the size served (here the larger, the smaller
    no better than nothing) with more members, and serves only if it beats that size significantly; where no
    size was served there is nothing to average."""
    job = _job(1.0)
    job = replace(job, preset=replace(job.preset, arch=f"{SMALL},{LARGE}", ensemble=3))
    noise = np.random.default_rng(3).normal(0.0, 0.02, job.y_val.shape) * 1e-4
    ones = np.ones(len(job.y_val), bool)
    calls, singles = [], {}

    def one(j: train.NetJob, _report: object) -> train._Trained:
        calls.append(("one", j.preset.arch))
        share = 2.0 if j.preset.arch == SMALL else single
        history = [{"kind": "position", "epoch": 1, "seconds": 0.1, "val_mm": 1.0, "best_val_mm": 1.0}]
        crossed = job.y_val * (1 - share) + noise
        singles[j.preset.arch] = train._Trained(train.build_net(j), history, True, crossed, ones)
        return singles[j.preset.arch]

    def averaged(j: train.NetJob, _report: object, first=None, continued=None) -> train._Trained:
        calls.append(("members", j.preset.arch, j.preset.members, first))
        history = [{"kind": "position", "epoch": 1, "seconds": 0.1, "val_mm": 1.0, "best_val_mm": 0.5, "member": 2}]
        return train._Trained(train.build_net(j), history, True, job.y_val * (1.0 - many) + noise, ones)

    monkeypatch.setattr(train, "_train_one", one)
    monkeypatch.setattr(train, "_train_members", averaged)
    net, history = train.train_net(job)
    sizes = history[-1]["sizes"]
    assert [s["arch"] for s in sizes] == [SMALL, LARGE, f"{LARGE if members else SMALL} x3"]
    if members is None:
        assert history[-1]["silenced"] and len(calls) == 2
        assert sizes[2]["trained"] is False and sizes[2]["why"] == "no size served"
        return
    assert calls[2][:3] == ("members", LARGE, 3) and calls[2][3] is singles[LARGE]  # the served net is member 0
    assert history[-1]["members"] == members and history[-1]["served"] == LARGE and "silenced" not in history[-1]
    assert isinstance(net.body, nets.Ensemble) == (members > 1)
    assert history[-1]["best_val_mm"] == (0.5 if members > 1 else 1.0)  # the figures of the rung served


class _Fixed(torch.nn.Module):
    """A net that answers the validation pairs with fixed corrections."""

    def __init__(self, answers: np.ndarray) -> None:
        super().__init__()
        self.answers = torch.tensor(answers)

    def forward(self, q: torch.Tensor) -> torch.Tensor:
        return self.answers


def test_the_ensemble_is_judged_against_the_single_net_as_it_counts_in_the_ensemble(monkeypatch):
    """Where the other half chose no epoch of the served net, its crossed correction is nothing, but as the
    ensemble's member 0 it counts as served. An ensemble that adds nothing to it must not win by that
    difference: the rung's baseline is the single net as it counts in the ensemble."""
    job = replace(_job(1.0), preset=replace(_job(1.0).preset, ensemble=3))
    served = 0.5 * job.y_val  # the served epoch's corrections: half of what the stage left
    chosen = train._chunks(len(job.y_val)) % 2 == 0  # the other half chose no epoch on alternate chunks
    crossed = np.where(chosen[:, None], job.y_val, 0.0)
    ones = np.ones(len(job.y_val), bool)
    history = [{"kind": "position", "epoch": 1, "seconds": 0.1, "val_mm": 1.0, "best_val_mm": 1.0}]
    single = train._Trained(_Fixed(served), history, True, crossed, chosen)

    def averaged(j: train.NetJob, _report: object, first=None, continued=None) -> train._Trained:
        assert first is single and continued is None  # its run was not ended by the clock
        same = train._filled(first, j.q_val)  # three members that each answer as member 0 counts
        return train._Trained(train.build_net(j), [{**history[0], "member": 2}], True, same, ones)

    monkeypatch.setattr(train, "_train_one", lambda j, r: single)
    monkeypatch.setattr(train, "_train_members", averaged)
    _, out = train.train_net(job)
    assert "silenced" not in out[-1]  # the single net beats nothing by the chunks the other half chose
    assert out[-1]["sizes"][1]["kept"] is False and out[-1]["members"] == 1


def test_the_ensemble_rung_keeps_the_served_net_as_its_first_member():
    """The ensemble rung trains only the added members, from their own seeds; the net already served is
    member 0, unchanged, and the ensemble serves the members' average."""
    job = replace(_job(1.0), preset=replace(_job(1.0).preset, max_epochs=8))
    single = train._train_one(job, None)
    trained = train._train_members(replace(job, preset=replace(job.preset, members=3)), None, single)
    bodies = list(trained.net.body.members)
    for a, b in zip(bodies[0].state_dict().values(), single.net.body.state_dict().values(), strict=True):
        assert torch.equal(a, b)
    assert not torch.equal(bodies[1][0].weight, bodies[0][0].weight)
    assert sorted({e["member"] for e in trained.history}) == [1, 2]
    features = trained.net.features(torch.tensor(job.q_val))
    with torch.no_grad():
        mean = torch.stack([b(features) for b in bodies]).mean(0)
        assert torch.allclose(trained.net.body(features), mean, atol=1e-6)


def test_a_workers_ensemble_is_rebuilt_with_its_members():
    """A worker sends back plain weights; the net is rebuilt with the size and the members its ladder chose,
    not the preset's single net."""
    job = replace(_job(1.0), preset=replace(_job(1.0).preset, max_epochs=4))
    many = replace(job, preset=replace(job.preset, members=2))
    trained = train._train_members(many, None)
    state = {k: v.numpy() for k, v in trained.net.state_dict().items()}
    history = [{**trained.history[-1], "served": job.preset.arch, "members": 2}]
    net = train.rebuilt(job, history, state)
    q = torch.tensor(job.q_val)
    with torch.no_grad():
        assert torch.equal(net(q), trained.net.eval()(q))
    with pytest.raises(RuntimeError):  # as the preset's single net, the weights do not fit
        train.rebuilt(job, [{**history[0], "members": 1}], state)


def test_given_members_fix_the_ensemble():
    """``--members`` fixes the ensemble, 1 included: the ladder then adds none of its own."""
    assert train.preset("fast").ensemble > 1
    assert train.preset("fast", members=1).ensemble == 1
    assert train.preset("fast", members=4).ensemble == 1
    with pytest.raises(CalibrationError, match="ensemble = 0"):
        train.preset("fast", ensemble=0)


@pytest.mark.parametrize("members, ensemble, nets", [(1, 3, 4), (2, 3, 4), (1, 1, 2)])
def test_a_budget_per_net_times_the_presets_nets_is_the_ladders(monkeypatch, members, ensemble, nets):
    """``Preset.nets`` counts what the ladder trains: the first rung's share of the budget, per net it
    trains, is the whole budget over that count (so ``bench_real``'s cap per net means what it says), and a
    fixed ensemble adds no rung of its own."""
    job = _job(1.0)
    job = replace(job, preset=replace(job.preset, arch=f"{SMALL},{LARGE}", members=members, ensemble=ensemble))
    assert job.preset.nets == nets
    ones = np.ones(len(job.y_val), bool)
    per_net: list[float] = []

    def trained(j: train.NetJob, _report: object, first=None, continued=None) -> train._Trained:
        per_net.append(j.max_seconds / j.preset.members)
        history = [{"kind": "position", "epoch": 1, "seconds": 0.1, "val_mm": 1.0, "best_val_mm": 1.0}]
        return train._Trained(train.build_net(j), history, True, 0.5 * job.y_val, ones)

    monkeypatch.setattr(train, "_train_one", trained)
    monkeypatch.setattr(train, "_train_members", trained)
    _, history = train.train_net(job)
    assert per_net[0] == pytest.approx(job.max_seconds / nets)
    assert len(history[-1]["sizes"]) == 2 + (members == 1 and ensemble > 1)


@pytest.mark.parametrize("longer", [True, False])
def test_a_net_the_clock_stopped_is_trained_on_before_members_are_added(monkeypatch, longer):
    """Where the clock, not the steps, ended the served net's run, the time left may serve one longer run
    better than an ensemble: the first added member is that net trained on from its weights. If it beats
    the net significantly the next cycle takes all the time left and no member is added (``longer``); else
    it joins the ensemble as member 1 and the fresh members share what is left."""
    job = _job(1.0)
    job = replace(job, preset=replace(job.preset, arch=f"{SMALL},{LARGE}", ensemble=3))
    noise = np.random.default_rng(3).normal(0.0, 0.02, job.y_val.shape) * 1e-4
    ones = np.ones(len(job.y_val), bool)
    calls: list[tuple] = []
    history = [{"kind": "position", "epoch": 1, "seconds": 0.1, "val_mm": 1.0, "best_val_mm": 1.0}]

    trained: list[train._Trained] = []
    levels: list[int] = []  # the Bonferroni count of each rung judged

    def answering(j: train.NetJob, corrections: np.ndarray) -> torch.nn.Module:
        net = train.build_net(j)  # a net of the size asked for, answering the validation pairs as given
        net.forward = lambda q: torch.tensor(corrections)
        return net

    def one(j: train.NetJob, _report: object, start=None, resume=0.0) -> train._Trained:
        calls.append(("one", j.preset.arch, j.max_seconds, start, resume))
        clock[0] += j.max_seconds
        cycle = sum(c[0] == "one" and c[1] == LARGE for c in calls)  # 1: the size's own run, 2, 3: on from it
        share = 2.0 if j.preset.arch == SMALL else 0.5 * (0.5 if longer else 1.0) ** (cycle - 1)
        corrections = job.y_val * (1 - share) + noise
        ran = [{**history[0], "seconds": j.max_seconds}]
        trained.append(train._Trained(answering(j, corrections), ran, True, corrections, ones, True))
        return trained[-1]

    def averaged(j: train.NetJob, _report: object, first=None, continued=None) -> train._Trained:
        calls.append(("members", j.preset.members, j.max_seconds, first, continued))
        clock[0] += j.max_seconds
        return train._Trained(train.build_net(j), [{**history[0], "member": 2}], True, job.y_val * 0.9, ones)

    def beats(diff: np.ndarray, tests: int = 1) -> bool:
        levels.append(tests)
        return judge(diff, tests)

    clock = [0.0]  # each run takes all the time it is given
    judge = train._beats
    monkeypatch.setattr(train, "time", SimpleNamespace(perf_counter=lambda: clock[0]))
    monkeypatch.setattr(train, "_train_one", one)
    monkeypatch.setattr(train, "_train_members", averaged)
    monkeypatch.setattr(train, "_beats", beats)
    net, out = train.train_net(job)
    shares = job.preset.nets
    assert calls[2][1] == LARGE and calls[2][2] == pytest.approx(job.max_seconds / shares)  # a rung's share
    assert calls[2][3] is trained[1].net and calls[2][4] == pytest.approx(0.5)  # on from the net served, half-way
    assert levels == [3, 3, 4, 5 if longer else 4]  # each cycle is one more rung judged
    sizes = [s["arch"] for s in out[-1]["sizes"]]
    if longer:
        assert [c[0] for c in calls] == ["one"] * 4  # no member: the next cycles took the time
        assert calls[3][2] == pytest.approx(job.max_seconds * (1 - 3 / shares))  # all that was left
        assert calls[3][3] is trained[2].net  # on from the cycle before
        assert calls[3][4] == pytest.approx(2 / (2 + shares - 3))  # the rest of one schedule over all three
        assert sizes == [SMALL, LARGE, f"{LARGE}, 2 cycles", f"{LARGE}, 3 cycles", f"{LARGE} x3"]
        assert out[-1]["cycles"] == 3 and out[-1]["members"] == 1 and out[-1]["served"] == LARGE
        assert out[-1]["sizes"][-1]["why"] == "one longer run beat the net"
        assert not isinstance(net.body, nets.Ensemble)
    else:
        members = calls[3]
        assert members[0] == "members" and members[1] == 3
        assert members[3] is trained[1] and members[4] is trained[2]  # the net served, then its continuation
        assert members[2] == pytest.approx(job.max_seconds * (1 - 3 / shares))
        assert sizes == [SMALL, LARGE, f"{LARGE}, 2 cycles", f"{LARGE} x3"]
        assert "cycles" not in out[-1] and out[-1]["members"] == 3


def test_a_run_says_whether_the_clock_ended_it_and_trains_on_from_given_weights():
    """``clocked``: a run the budget cut short, not one that took all its steps; a continuation starts from
    the weights it is given, at the learning rate of where it resumes its schedule (at its end: none, so it
    keeps them; at its start it moves them)."""
    job = _job(1.0)
    short = train._train_one(replace(job, preset=replace(job.preset, max_epochs=2)), None)
    assert not short.clocked
    cut = replace(job, preset=replace(job.preset, max_epochs=10**6), max_seconds=0.2)
    assert train._train_one(cut, None).clocked
    on = replace(job, preset=replace(job.preset, max_epochs=2), seed=5)
    kept = train._train_one(on, None, short.net, resume=1.0)
    for a, b in zip(kept.net.state_dict().values(), short.net.state_dict().values(), strict=True):
        assert torch.equal(a, b)
    moved = train._train_one(on, None, short.net, resume=0.0)
    assert not torch.equal(moved.net.body[0].weight, short.net.body[0].weight)


@pytest.mark.parametrize("cycles, epochs, best", [(3, 6, 5), (1, 2, 2)])
def test_the_manifest_counts_the_epochs_of_the_cycles_served(cycles, epochs, best):
    """A net trained on serves the epochs of its cycles, counted on from its first; where the continuation
    lost (it joined an ensemble that lost too), only the first run's epochs are the served net's."""

    def entry(epoch: int, val: float, **extra) -> dict:
        return {"kind": "position", "epoch": epoch, "seconds": epoch, "val_mm": val, "arch": LARGE, **extra}

    history = [entry(1, 0.5, arch=SMALL), entry(2, 0.4), entry(3, 0.3), entry(4, 0.35, cycle=2)]
    history += [entry(5, 0.25, cycle=2), entry(6, 0.2, cycle=3), entry(7, 0.22, cycle=3), entry(8, 0.1, member=2)]
    history[-1].update({"served": LARGE, "members": 1, "best_val_mm": 0.2})
    if cycles > 1:
        history[-1]["cycles"] = cycles
    out = _best(history)
    assert out["epochs"] == epochs and out["best_epoch"] == best and out.get("cycles", 1) == cycles


def test_the_best_epoch_of_a_smaller_size_trained_on_is_counted_in_its_own_runs():
    """A smaller size served and trained on: the larger size's epochs lie between its cycles and are not
    its own, and the weights served come from the last cycle (even where an earlier epoch scored lower)."""

    def entry(epoch: int, val: float, arch: str, **extra) -> dict:
        return {"kind": "position", "epoch": epoch, "seconds": epoch, "val_mm": val, "arch": arch, **extra}

    history = [entry(1, 0.5, SMALL), entry(2, 0.2, SMALL), entry(3, 0.1, LARGE), entry(4, 0.1, LARGE)]
    history += [entry(5, 0.3, SMALL, cycle=2), entry(6, 0.25, SMALL, cycle=2), entry(7, 0.27, SMALL, cycle=2)]
    history[-1].update({"served": SMALL, "members": 1, "cycles": 2, "best_val_mm": 0.25})
    out = _best(history)
    assert out["epochs"] == 5 and out["best_epoch"] == 4
