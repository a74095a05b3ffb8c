"""Error bounds on each answer: the conformal quantile, how far a joint lies beyond the trained range, the rate
the bound grows at there, and their coverage on pairs the model never saw, inside its range and beyond."""

from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest

from bench.bench_bounds import shoulder_configurations
from hybrid_kinematics_ros.calibration import bounds as calibration_bounds
from hybrid_kinematics_ros.calibration.evaluate import pose_errors_of
from hybrid_kinematics_ros.kinematics import se3
from hybrid_kinematics_ros.model.bounds import DISTANCE, Bounds, ErrorBound, Scale, excess
from hybrid_kinematics_ros.model.errors import ModelError
from hybrid_kinematics_ros.model.hybrid import HybridModel
from hybrid_kinematics_ros.simulation.cell import VirtualCell


def test_conformal_quantile_is_the_finite_sample_order_statistic():
    scores = np.random.default_rng(0).permutation(np.arange(1.0, 101.0))
    assert calibration_bounds.conformal_quantile(scores, 0.9) == 91.0  # ⌈101 · 0.9⌉ = 91st smallest
    assert calibration_bounds.conformal_quantile(scores, 0.95) == 96.0
    assert calibration_bounds.conformal_quantile(scores[:10], 0.95) == scores[:10].max()  # too few: the largest


def test_growth_rate_recovers_the_slope_of_the_quantile():
    rng = np.random.default_rng(1)
    x = rng.uniform(0.0, 0.5, 4000)
    floor, slope = 1e-5, 2e-4  # m, and m per rad beyond the range
    error = (floor + slope * x) * rng.uniform(0.0, 1.0, len(x))  # the 95 % quantile: 0.95 (floor + slope x)
    rate = calibration_bounds.growth_rate(x, error, 0.95 * floor, 0.95)
    assert 0.85 * 0.95 * slope < rate < 1.15 * 0.95 * slope
    # errors that do not grow beyond the range give no growth; pairs inside it give none either
    assert calibration_bounds.growth_rate(x, rng.uniform(0.0, floor, len(x)), floor, 0.95) < 0.05 * slope
    assert calibration_bounds.growth_rate(np.zeros(100), error[:100], floor, 0.95) == 0.0


def test_excess_is_zero_inside_the_range_and_goes_the_short_way_round():
    lower, upper = np.array([-1.0, 0.0, -4.0]), np.array([1.0, 0.5, 4.0])
    revolute = np.array([True, False, True])
    x = excess(np.array([[0.3, 0.2, 0.0], [1.2, 0.7, 0.0], [-1.0 + 2 * np.pi, -0.1, 3.0]]), lower, upper, revolute)
    np.testing.assert_allclose(x[0], 0.0)
    np.testing.assert_allclose(x[1], [0.2, 0.2, 0.0])  # beyond the upper end; a range over a turn: never beyond
    np.testing.assert_allclose(x[2], [0.0, 0.1, 0.0], atol=1e-12)  # a whole turn on is the same joint angle
    # beyond the upper end of [-1, 1] by 2.5 rad is nearer to the lower end, the other way round: 2π − 2 − 2.5
    np.testing.assert_allclose(excess(np.array([[3.5, 0.0, 0.0]]), lower, upper, revolute)[0, 0], 2 * np.pi - 4.5)


def test_the_scale_follows_errors_that_depend_on_the_configuration():
    """Errors twice as large where one joint's sine is high: the fitted scale finds it, and the conformal
    quantile of the errors over their scale covers the hard and the easy configurations alike, where one
    quantile for all over-covers the easy ones and under-covers the hard ones."""
    rng = np.random.default_rng(2)
    revolute = np.ones(6, dtype=bool)
    q = rng.uniform(-np.pi, np.pi, (6000, 6))
    truth = np.exp(0.5 * np.sin(q[:, 1]) + 0.3 * np.cos(q[:, 3]))
    error = 1e-5 * truth * np.linalg.norm(rng.normal(size=(len(q), 3)), axis=1)
    fit, val, test = slice(0, 3000), slice(3000, 4000), slice(4000, None)
    scale = calibration_bounds.fit_scale(q[fit], error[fit], revolute)
    assert np.corrcoef(np.log(scale(q[test], revolute)), np.log(truth[test]))[0, 1] > 0.95
    assert np.median(scale(q[fit], revolute)) == pytest.approx(1.0, abs=0.02)
    assert scale(q[fit], revolute).max() == pytest.approx(scale.upper)  # clipped to the range it took
    k = calibration_bounds.conformal_quantile(error[val] / scale(q[val], revolute), 0.95)
    flat = calibration_bounds.conformal_quantile(error[val], 0.95)
    hard = truth[test] > np.quantile(truth[test], 0.75)
    covered = error[test] <= k * scale(q[test], revolute)
    assert 0.92 < covered.mean() < 0.98
    assert covered[hard].mean() > 0.9 and covered[~hard].mean() > 0.9
    assert np.mean(error[test][hard] <= flat) < 0.88  # one quantile for all misses the hard ones
    # errors of zero (a noise-free fit): one scale everywhere
    assert np.all(calibration_bounds.fit_scale(q[fit], np.zeros(3000), revolute)(q[test], revolute) == 1.0)


def test_manifest_round_trip_and_a_malformed_section_names_the_fix():
    scale = Scale(np.array([0.1, 0.2, -0.3, 0.0, 0.5]), 0.7, 1.6)
    made = Bounds(0.95, ErrorBound(1e-4, np.array([2e-4, 1e-5]), scale), None, {"validation_pairs": 7})
    again = Bounds.from_manifest(made.manifest())
    assert again.position.quantile == made.position.quantile and again.orientation is None
    np.testing.assert_array_equal(again.position.rates, made.position.rates)
    np.testing.assert_array_equal(again.position.scale.weights, scale.weights)
    assert (again.position.scale.lower, again.position.scale.upper) == (0.7, 1.6)
    assert again.figures == made.figures
    q, revolute = np.array([[0.3, 1.2], [-2.0, 0.1]]), np.array([True, False])
    x = np.array([[0.0, 0.0], [0.1, 0.0]])
    np.testing.assert_allclose(again.of(q, x, revolute)[0], made.of(q, x, revolute)[0])
    # a section written before the scale: one quantile inside the range
    older = made.manifest()
    del older["position"]["scale"]
    np.testing.assert_allclose(Bounds.from_manifest(older).of(q, x, revolute)[0], [1e-4, 1e-4 + 2e-5])
    with pytest.raises(ModelError, match="retrain"):
        Bounds.from_manifest({"level": 0.95, "distance": DISTANCE, "position": {"quantile_m": 1e-4}})


def test_bounds_hold_on_pairs_the_model_never_saw(trained):
    _, model, manifest, test_pairs = trained
    assert model.bounds is not None and manifest["bounds"]["level"] == 0.95
    pos_mm, rot_deg = pose_errors_of(model, test_pairs)["hybrid"]
    position, orientation = model.error_bounds(test_pairs.q)
    covered = np.mean(pos_mm <= 1e3 * position), np.mean(rot_deg <= np.degrees(orientation))
    # calibrated at 95 % on the validation blocks; these test blocks never reached the model
    assert min(covered) >= 0.85, covered
    assert np.median(1e3 * position) < 5.0 * np.median(pos_mm)  # a bound, not a wall


def test_one_configurations_bound_is_the_batch_paths(shoulder_model):
    """A service's call (one configuration, in Python floats) gives the batch path's bound, inside the trained
    range, at its ends and beyond them (where the one-configuration path hands over to the batch path)."""
    _, model, inside, beyond = shoulder_model
    within = np.clip(inside.q[:20], model.trained_lower, model.trained_upper)  # every joint inside: the fast path
    at_end = within[:5].copy()
    at_end[:, 1] = model.trained_lower[1]  # on the end of the shoulder's range: still inside
    for q in (*within, *at_end, *beyond.q[:10]):
        one = model.error_bounds(q)
        batch = model.error_bounds(np.vstack([q, q]))  # two rows: the numpy path
        for a, b in zip(one, batch, strict=True):
            assert a.shape == (1,)
            # the nets' members evaluate a batch through one matrix product a layer, one row through
            # matrix-vector products: float32 sums in another order (a relative 1e-8 in the spread)
            np.testing.assert_allclose(a, b[:1], rtol=1e-6, atol=0)
    assert model.error_bounds(beyond.q[0])[0][0] > 2 * model.error_bounds(inside.q[0])[0][0]


def test_bounds_grow_beyond_the_trained_range_with_the_error(shoulder_model):
    _, model, inside, beyond = shoulder_model
    assert model.bounds is not None
    # the stage extrapolates the shoulder worst: its rate is the steepest
    assert int(np.argmax(model.bounds.position.rates)) == 1
    errors = {name: pose_errors_of(model, pairs)["hybrid"] for name, pairs in (("inside", inside), ("beyond", beyond))}
    bounds = {name: model.error_bounds(pairs.q) for name, pairs in (("inside", inside), ("beyond", beyond))}
    pos_mm, rot_deg = errors["beyond"]
    position, orientation = bounds["beyond"]
    assert np.median(pos_mm) > 10 * np.median(errors["inside"][0])  # the model is far worse beyond its range
    covered = np.mean(pos_mm <= 1e3 * position), np.mean(rot_deg <= np.degrees(orientation))
    assert min(covered) >= 0.9, covered
    assert np.median(position) > 10 * np.median(bounds["inside"][0])  # and says so


def test_the_bound_policy_serves_each_net_where_its_bound_beats_the_stage(shoulder_model, ur10):
    """``out_of_range_policy: bound``: inside the trained range the nets serve; beyond it each net serves
    where its bound (grown by its unchecked change there) is below the stage's alone, every answer carries
    the bound of what served it, and far beyond, where the nets extrapolate worse than the stage, it beats
    ``warn`` and is as good as the stage alone."""
    out, _, inside, _ = shoulder_model
    model = HybridModel.load(out)
    far = VirtualCell.from_config(ur10, noise=False).pairs(shoulder_configurations(300, (1.0, 2.5), seed=3), seed=3)
    assert model.bounds.has_stage
    assert model.bounds.position.stage_quantile > model.bounds.position.quantile  # the nets help inside
    answers = {}
    for policy in ("warn", "bound"):
        by = model.with_range_policy(policy)
        answers[policy] = {
            name: (by.fk(p.q), by.error_bounds(p.q), pose_errors_of(by, p)["hybrid"])
            for name, p in (("inside", inside), ("far", far))
        }
    np.testing.assert_array_equal(answers["bound"]["inside"][0], answers["warn"]["inside"][0])
    use = by._nets_apply(by.same_turn(far.q))
    assert 0 < use[:, 0].sum() < len(far)  # the position net is dropped where its bound is the larger
    stage_pose, hybrid_pose, served = model.fk(far.q, nets=False), answers["warn"]["far"][0], answers["bound"]["far"][0]
    np.testing.assert_allclose(served[~use[:, 0], :3, 3], stage_pose[~use[:, 0], :3, 3], atol=1e-12)
    np.testing.assert_allclose(served[use[:, 0], :3, 3], hybrid_pose[use[:, 0], :3, 3], atol=1e-12)
    stage_bound = model.bounds.of(
        far.q,
        excess(far.q, model.trained_lower, model.trained_upper, ur10.chain.revolute),
        ur10.chain.revolute,
        stage=True,
    )[0]
    np.testing.assert_allclose(answers["bound"]["far"][1][0][~use[:, 0]], stage_bound[~use[:, 0]])
    pos_mm = {policy: answers[policy]["far"][2][0] for policy in answers}
    # it beats the nets everywhere (warn), and is within a few per cent of the stage everywhere
    assert pos_mm["bound"].mean() < 0.97 * pos_mm["warn"].mean()
    assert pos_mm["bound"].mean() < 1.03 * pose_errors_of(model, far)["parametric"][0].mean()
    assert np.mean(pos_mm["bound"] <= 1e3 * answers["bound"]["far"][1][0]) >= 0.9
    # another payload than the nets were trained with: their bound does not know it, so the stage serves
    heavy = model.with_range_policy("bound").with_payload(12.0, np.array([0.0, 0.0, 0.1]))
    np.testing.assert_array_equal(heavy.fk(inside.q[:20]), heavy.fk(inside.q[:20], nets=False))
    assert not np.array_equal(model.fk(inside.q[:20]), model.fk(inside.q[:20], nets=False))


def test_the_bound_policy_needs_the_stages_bounds(trained):
    _, model, manifest, _ = trained
    older = json.loads(json.dumps(manifest))
    for kind in ("position", "orientation"):
        del older["bounds"][kind]["stage_quantile_" + ("m" if kind == "position" else "rad")]
    assert HybridModel(model.chain, model.nets, older).bounds.position.stage_quantile is None
    with pytest.raises(ModelError, match="retrain"):
        HybridModel(model.chain, model.nets, older, range_policy="bound")


def test_under_another_payload_the_bound_adds_what_no_measurement_checked(shoulder_model, ur10):
    """Another payload than the calibrated one: no bound was calibrated for it (the stage's error grows too).
    The bound is the stage's calibrated one plus the move the payload made in the stage's answer, plus the
    nets' correction where they serve (``warn``); on both paths, and it holds on pairs measured with that
    payload, where the bounds calibrated under the trained payload do not."""
    out, *_ = shoulder_model
    model = HybridModel.load(out)
    assert model.range_policy == "warn"
    mass, com = 15.0, np.array([0.0, 0.05, 0.15])
    heavy = model.with_payload(mass, com)
    cell = VirtualCell.from_config(replace(ur10, payload_mass=mass, payload_com=com), noise=False)
    pairs = cell.pairs(shoulder_configurations(300, (-2.0, -1.0), seed=5), seed=5)
    q = heavy.same_turn(pairs.q)  # the turn the nets were trained on, as every bound takes it
    x = excess(q, heavy.trained_lower, heavy.trained_upper, ur10.chain.revolute)
    stage = heavy.bounds.of(q, x, ur10.chain.revolute, stage=True)
    moved_mm, moved_deg = se3.pose_errors(heavy.fk(q, nets=False), model.fk(q, nets=False))
    dp, w = heavy.residuals(q)
    for policy, nets in (("warn", 1.0), ("parametric", 0.0)):
        served = heavy.with_range_policy(policy)
        position, orientation = served.error_bounds(pairs.q)
        np.testing.assert_allclose(position, stage[0] + 1e-3 * moved_mm + nets * np.linalg.norm(dp, axis=1), rtol=1e-9)
        np.testing.assert_allclose(
            orientation, stage[1] + np.radians(moved_deg) + nets * np.linalg.norm(w, axis=1), rtol=1e-9
        )
        one = served.error_bounds(pairs.q[0])  # a service's single configuration: the same bound
        np.testing.assert_allclose(one[0], position[:1], rtol=1e-6)  # the nets in float32 on either path
        pos_mm, rot_deg = pose_errors_of(served, pairs)["hybrid"]
        covered = np.mean(pos_mm <= 1e3 * position), np.mean(rot_deg <= np.degrees(orientation))
        assert min(covered) >= 0.9, (policy, covered)
    pos_mm, rot_deg = pose_errors_of(heavy, pairs)["hybrid"]
    own = model.error_bounds(pairs.q)  # what the calibrated bounds claim: they do not hold here
    assert np.mean(pos_mm <= 1e3 * own[0]) < 0.5
