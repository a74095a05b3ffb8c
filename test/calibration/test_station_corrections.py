"""Two tracker stations that saw different parts of the workspace, one robot: the nominal model's
referencing absorbs a different share of the robot's errors at each, and the parametric stage corrects
each station's placement and target mount beside the robot. Judged on held-out poses of each station
against the virtual cell's noise-free truth."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from hybrid_kinematics_ros.calibration import fit as calibration_fit
from hybrid_kinematics_ros.calibration.evaluate import target_errors
from hybrid_kinematics_ros.calibration.fit import identify_stations, reference_all
from hybrid_kinematics_ros.calibration.parametric import _draw
from hybrid_kinematics_ros.calibration.referencing import station_labels
from hybrid_kinematics_ros.io.pairs import Pairs
from hybrid_kinematics_ros.kinematics import se3
from hybrid_kinematics_ros.model.referencing import to_base_frame
from hybrid_kinematics_ros.simulation.cell import VirtualCell
from hybrid_kinematics_ros.simulation.tracker import Tracker

TARGET = {"xyz": [0.02, -0.03, 0.09], "rpy": [0.1, 0.0, 0.4]}
SHARED = [["tracker_a", "tracker_b"]]  # the target stayed on the flange while the tracker moved
# What the capacity selection chooses for these pairs, with and without orientation (2026-11-26); fixed here
# because the stations are under test, not the capacity (test_portfolio tests that): 3 s an identification
# instead of 28, with the same held-out errors.
FIXED = {"capacity": {"elastic": "bending", "harmonics": 2, "harmonic_prior": 3.0, "map_step": 0.0}, "choose": False}
STATIONS = {  # frame: (tracker placement, the half of the shoulder's range its poses used)
    "tracker_a": ({"xyz": [2.4, -1.1, 0.35], "rpy": [0.01, -0.02, 2.2]}, (-2.8, -1.6)),
    "tracker_b": ({"xyz": [-1.8, 1.5, 0.1], "rpy": [0.0, 0.02, -0.7]}, (-1.6, -0.4)),
}


def _pairs(cell: VirtualCell, shoulder: tuple[float, float], count: int, seed: int, noise: bool = True) -> Pairs:
    chain = cell.config.chain
    rng = np.random.default_rng(seed)
    q = rng.uniform(0.9 * chain.lower, 0.9 * chain.upper, (count, chain.dof))
    q[:, 1] = rng.uniform(*shoulder, count)
    tracker = cell.tracker if noise else replace(cell.tracker, position_noise=0.0, orientation_noise=0.0)
    T = tracker.measure(cell.robot.fk(q), np.random.default_rng(seed + 1))
    return Pairs(q, T, np.arange(count), chain.joint_names, cell.frame_id)


@pytest.fixture(scope="module")
def stations(ur10):
    robot = VirtualCell.from_config(ur10).robot  # one robot, seen from two places
    cells = {}
    for frame, (placement, _) in STATIONS.items():
        tracker = Tracker.from_config({**ur10.tracker, "base_to_tracker": placement, "flange_to_target": TARGET})
        cells[frame] = VirtualCell(ur10, robot, replace(tracker, frame_id=frame))
    train = [_pairs(cells[f], shoulder, 1500, seed=10 * k) for k, (f, (_, shoulder)) in enumerate(STATIONS.items())]
    return cells, train


def _points(pairs: Pairs) -> Pairs:
    """What a plain reflector reports of the same measurements: positions only."""
    T = pairs.T.copy()
    T[:, :3, :3] = np.eye(3)
    return replace(pairs, T=T, position_only=True)


def _held_out_errors(ur10, cells, refs, result, points: bool = False) -> dict[str, float]:
    """Mean position error (mm) of the stage on fresh poses of each station, against noise-free measurements."""
    out = {}
    for k, (frame, (_, shoulder)) in enumerate(STATIONS.items()):
        exact = _pairs(cells[frame], shoulder, 500, seed=100 + k, noise=False)
        exact = _points(exact) if points else exact
        base = to_base_frame([exact], ur10.chain, refs)
        out[frame] = float(np.mean(target_errors(base, result.model.fk(base.q))[0]))
    return out


def test_station_corrections_make_the_stations_agree(ur10, stations, monkeypatch):
    cells, train = stations
    payload = (ur10.payload_mass, ur10.payload_com)
    refs, result = identify_stations(ur10.chain, train, reference_all(ur10.chain, train, SHARED), payload, **FIXED)
    assert result.placements.shape == (1, 4, 4) and result.mounts.shape == (0, 4, 4)  # the target is shared
    assert "refined" in refs["tracker_b"].method and "refined" not in refs["tracker_a"].method
    corrected = _held_out_errors(ur10, cells, refs, result)
    # where the trackers stood relative to each other, against the truth
    truth = {f: c.tracker.base_to_tracker for f, c in cells.items()}
    found = se3.inverse(refs["tracker_a"].base_to_tracker) @ refs["tracker_b"].base_to_tracker
    pos, rot = se3.pose_errors(found[None], (se3.inverse(truth["tracker_a"]) @ truth["tracker_b"])[None])

    # the same without the station corrections: every station labelled as the reference
    monkeypatch.setattr(calibration_fit, "station_labels", lambda refs, _: {f: (-1, -1) for f in refs})
    refs0, result0 = identify_stations(ur10.chain, train, reference_all(ur10.chain, train, SHARED), payload, **FIXED)
    uncorrected = _held_out_errors(ur10, cells, refs0, result0)
    found0 = se3.inverse(refs0["tracker_a"].base_to_tracker) @ refs0["tracker_b"].base_to_tracker
    pos0, _ = se3.pose_errors(found0[None], (se3.inverse(truth["tracker_a"]) @ truth["tracker_b"])[None])

    assert max(corrected.values()) < 0.08, (corrected, uncorrected)  # mm; measured 0.003 (0.27 uncorrected)
    assert min(uncorrected.values()) > 3 * max(corrected.values()), (corrected, uncorrected)
    # measured: 0.009 mm and 0.0002° from the truth (1.16 mm uncorrected)
    assert pos[0] < 0.05 and rot[0] < 0.002 and pos0[0] > 5 * pos[0], (pos, rot, pos0)  # mm, deg


def test_plain_reflectors_at_two_stations_are_corrected_too(ur10, stations, monkeypatch):
    cells, train = stations
    points = [_points(p) for p in train]  # each frame its own target: a mount correction for the second
    payload = (ur10.payload_mass, ur10.payload_com)
    refs, result = identify_stations(ur10.chain, points, reference_all(ur10.chain, points), payload, **FIXED)
    assert result.placements.shape == (1, 4, 4) and result.mounts.shape == (1, 4, 4)
    corrected = _held_out_errors(ur10, cells, refs, result, points=True)
    monkeypatch.setattr(calibration_fit, "station_labels", lambda refs, _: {f: (-1, -1) for f in refs})
    refs0, result0 = identify_stations(ur10.chain, points, reference_all(ur10.chain, points), payload, **FIXED)
    uncorrected = _held_out_errors(ur10, cells, refs0, result0, points=True)
    assert max(corrected.values()) < 0.08, (corrected, uncorrected)  # mm; measured 0.006 (0.28 uncorrected)
    assert min(uncorrected.values()) > 3 * max(corrected.values()), (corrected, uncorrected)


def test_labels_share_a_mount_where_the_target_stayed(ur10, stations):
    _, train = stations
    refs = reference_all(ur10.chain, [*train, replace(train[1], frame_id="tracker_d")], [["tracker_a", "tracker_b"]])
    labels = station_labels(refs, base_frame_pairs=False)
    assert labels == {"tracker_a": (-1, -1), "tracker_b": (0, -1), "tracker_d": (1, 0)}
    # pairs in the base frame are the reference: every tracker frame gets its corrections
    assert station_labels(refs, base_frame_pairs=True) == {
        "tracker_a": (0, 0),
        "tracker_b": (1, 0),
        "tracker_d": (2, 1),
    }


def test_the_parametric_fit_draws_each_station_evenly():
    station = np.repeat([-1, 0, 1], [9000, 1200, 300])  # a large series, a middle one, a small one
    pick = _draw(station, 3000, np.random.default_rng(0))
    assert len(pick) == len(set(pick)) == 3000
    assert np.bincount(station[pick] + 1).tolist() == [1500, 1200, 300]  # the smaller ones give all they have
    one = _draw(np.full(500, -1), 200, np.random.default_rng(1))
    np.testing.assert_array_equal(one, np.random.default_rng(1).permutation(500)[:200])  # one station: any 200
