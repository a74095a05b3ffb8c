"""A second real robot imported as a user would: the TIAGo's motion-capture points through the shipped spec,
its nominal URDF with a prismatic torso lift from example-robot-data, referenced without losing a posture."""

from __future__ import annotations

import json
import sysconfig
from pathlib import Path

import numpy as np

from hybrid_kinematics_ros.calibration.fit import reference_all
from hybrid_kinematics_ros.io.pairs import read_pairs
from hybrid_kinematics_ros.kinematics.chain import chain_from_urdf
from test.cli.inprocess import cli

SESSION = Path(__file__).resolve().parents[1] / "fixtures" / "tiago-mocap" / "qualisys_2021-11-30_static_postures.csv"
URDF = (
    Path(sysconfig.get_paths()["purelib"])
    / "cmeel.prefix/share/example-robot-data/robots/tiago_description/robots/tiago_no_hand.urdf"
)
LINKS = ("base_footprint", "arm_7_link")


def test_the_tiago_session_imports_whole_and_references_without_outliers(tmp_path):
    link_args = ["--base-link", LINKS[0], "--tip-link", LINKS[1]]
    result = cli(
        "import",
        "--spec",
        "tiago_mocap",
        "--urdf",
        str(URDF),
        *link_args,
        "--csv",
        str(SESSION),
        "--out",
        str(tmp_path / "p"),
    )
    assert result.returncode == 0, result.stderr
    summary = json.loads(result.stdout.strip().splitlines()[-1])
    rows = len(SESSION.read_text().splitlines()) - 1
    assert (summary["imported"], summary["dropped"], summary["position_only"]) == (rows, {}, False)
    chain = chain_from_urdf(URDF, *LINKS)
    assert not chain.revolute[0]  # the torso lift
    pairs = read_pairs(tmp_path / "p", chain.joint_names)
    header = SESSION.read_text().splitlines()[0].split(",")
    first = np.array(SESSION.read_text().splitlines()[1].split(","), dtype=float)
    np.testing.assert_allclose(pairs.q[0], first[[header.index(n) for n in chain.joint_names]])
    # the hand body's origin is its first point (BL)
    np.testing.assert_allclose(pairs.T[0, :3, 3], first[[header.index(c) for c in ("x1", "y1", "z1")]], atol=1e-5)
    (ref,) = reference_all(chain, [pairs]).values()
    assert ref.outliers == 0
