"""The real TIAGo: a torso lift (prismatic) and a 7-joint arm, measured by motion capture (four points of a hand
body, 6-D) in 221 static postures over four sessions of one week (../shared/datasets/tiago-mocap, Apache-2.0,
figaroh-examples: Thanh Nguyen, CNRS, Toward). Read from the raw CSV files with the shipped import spec, against
example-robot-data's nominal URDF, as a user would."""

from __future__ import annotations

import sysconfig
from pathlib import Path

from hybrid_kinematics_ros.io.import_spec import load_spec_dict, spec_from_dict
from hybrid_kinematics_ros.io.importer import import_table
from hybrid_kinematics_ros.io.pairs import Pairs
from hybrid_kinematics_ros.kinematics.chain import chain_from_urdf
from hybrid_kinematics_ros.kinematics.robot_config import RobotConfig

DATA = Path(__file__).resolve().parents[2] / "shared" / "datasets" / "tiago-mocap" / "raw"
URDF = (
    Path(sysconfig.get_paths()["purelib"])
    / "cmeel.prefix/share/example-robot-data/robots/tiago_description/robots/tiago_no_hand.urdf"
)
SESSIONS = ("2021-11-26", "2021-11-30-1403", "2021-11-30-1504", "2021-11-30")  # in time order
BASE_LINK, TIP_LINK = "base_footprint", "arm_7_link"


def tiago_config() -> RobotConfig:
    chain = chain_from_urdf(URDF, BASE_LINK, TIP_LINK)
    return RobotConfig("tiago", URDF, URDF, BASE_LINK, TIP_LINK, chain)


def load_session(session: str, joints: tuple[str, ...]) -> Pairs:
    spec = spec_from_dict(load_spec_dict("tiago_mocap"), "tiago_mocap")
    table = DATA / f"qualisys_{session}_static_postures.csv"
    return import_table(table, spec, joints).pairs.with_approach()
