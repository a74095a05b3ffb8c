"""Outliers are judged on what the stage leaves, not on what the nominal model misses: a robot whose URDF is
centimetres off keeps every good pair, and the broken beams among its pairs are found and left out."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from hybrid_kinematics_ros.calibration.evaluate import target_errors
from hybrid_kinematics_ros.calibration.fit import identify_stations, reference_all
from hybrid_kinematics_ros.model.referencing import to_base_frame
from hybrid_kinematics_ros.simulation.portfolio import CENTIMETRES_OFF, TRACKER_FAR, CellSpec, build_cell

CAPACITY = {"elastic": "bending", "harmonics": 0, "map_step": 0.0}  # capacity is not what these tests choose
EVERY = 20  # one pair in this many has a broken beam


@pytest.fixture(scope="module")
def cell():
    spec = CellSpec("centimetres off", poses=400, test_poses=200, truth=CENTIMETRES_OFF, tracker=TRACKER_FAR)
    return build_cell(spec)


def broken(pairs):
    """The pairs with one in :data:`EVERY` moved by a broken beam (a few millimetres), and which those are."""
    bad = np.arange(0, len(pairs), EVERY)
    T = pairs.T.copy()
    T[bad, :3, 3] += np.random.default_rng(5).normal(0.0, 3e-3, (len(bad), 3))
    return replace(pairs, T=T), bad


def stage_error(cell, pairs) -> tuple[float, np.ndarray]:
    """The stage's held-out mean position error (mm) when identified from ``pairs``, and the outliers it names."""
    chain = cell.config.chain
    refs, result = identify_stations(chain, [pairs], reference_all(chain, [pairs]), capacity=CAPACITY, choose=False)
    base = to_base_frame([cell.test], chain, refs)
    return float(np.mean(target_errors(base, result.model.fk(base.q))[0])), result.outliers


def test_the_nominal_models_error_is_not_counted_as_outliers(cell):
    ref = next(iter(reference_all(cell.config.chain, [cell.train]).values()))
    assert ref.rms_position_mm > 3.0  # the URDF model misses by millimetres to centimetres
    assert ref.outliers < 0.01 * len(cell.train)


def test_broken_beams_are_found_on_what_the_stage_leaves_and_do_not_move_it(cell):
    clean_mm, clean_outliers = stage_error(cell, cell.train)
    pairs, bad = broken(cell.train)
    broken_mm, found = stage_error(cell, pairs)
    assert len(clean_outliers) < 0.01 * len(pairs)
    assert np.isin(bad, found).mean() >= 0.9  # hidden under centimetres of model error, found under the stage's
    assert np.isin(found, bad).mean() >= 0.8
    assert broken_mm < 1.1 * clean_mm
