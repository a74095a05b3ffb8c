"""A portfolio of virtual cells: robots, effects, trackers and data amounts that a change to the model must
serve alike (``bench/bench_portfolio.py``, and the guard tests in ``test/calibration/test_portfolio.py``).

Each cell measures the true robot along a random walk of the joints, as a measurement program visits its
poses, one pose every ``seconds_per_pose``; training and test pairs are separate walks. On top of the
ground-truth robot (:mod:`simulation.truth`) a cell can add what real cells show and the simulator's robot
does not:

- backlash: each joint stops on the side of its play it arrived from (``half_backlash_rad``; the
  physical play of ``simulation.backlash``, not the approach labels the nets get);
- stiffness that depends on the torque's sign: the spring is ``asymmetry`` softer one way than the other
  (an extra deflection ``asymmetry · c · |τ|``, which a symmetric compliance cannot carry);
- thermal drift of the arm: its reach grows by ``thermal_ppm`` (10⁻⁶) over the session as it warms,
  ``1 − exp(−t / 1 h)``; no joint angle explains it;
- a tracker frame with a target off the flange, and broken-beam outliers in the training pairs;
- a plain reflector: position only;
- a URDF centimetres off the robot (``truth``: millimetres at each joint origin, half a degree of turn and
  an arm that bends twenty times more than the UR10's), as on a lift or a long column, where what the
  nominal model misses dwarfs a broken beam;
- a task path: the tool held at one orientation while the arm moves over a surface (``path="surface"``),
  as cells calibrated along drilling or inspection paths are, optionally with a few poses turned by 30°
  (``turned``) to determine the target's offset from the flange.

The **floor** of a cell is what a perfect model of the joints (and approach sides) would still score: the
error of the noise-free, drift-free truth against the test measurements.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
from scipy.spatial.transform import Rotation

from hybrid_kinematics_ros.io.pairs import Pairs
from hybrid_kinematics_ros.kinematics import fk, se3
from hybrid_kinematics_ros.kinematics.robot_config import RobotConfig, load_robot_config
from hybrid_kinematics_ros.simulation.backlash import play
from hybrid_kinematics_ros.simulation.errors import SimulationError
from hybrid_kinematics_ros.simulation.sampling import joint_range
from hybrid_kinematics_ros.simulation.tracker import Tracker
from hybrid_kinematics_ros.simulation.truth import TrueRobot

TRACKER_FAR = {  # a tracker 3 m from the base, the target 0.1 m off the flange
    "base_to_tracker": {"xyz": [2.6, -1.2, 0.5], "rpy": [0.0, 0.01, 2.4]},
    "flange_to_target": {"xyz": [0.03, -0.02, 0.1], "rpy": [0.2, 0.0, -0.4]},
}


@dataclass(frozen=True)
class CellSpec:
    name: str
    robot: str = "ur10"
    poses: int = 2000
    test_poses: int = 600
    effects: dict[str, bool] = field(default_factory=dict)  # the truth's effects switched (default: the YAML's)
    truth: dict[str, dict[str, Any]] = field(default_factory=dict)  # the truth's sections' values overridden
    tracker: dict[str, Any] | None = None  # tracker frames (TRACKER_FAR, say); None: the base frame
    position_noise_mm: float = 0.015
    orientation_noise_deg: float = 0.001
    plain_reflector: bool = False
    half_backlash_rad: tuple[float, ...] = ()
    asymmetry: float = 0.0
    thermal_ppm: float = 0.0
    outliers: float = 0.0  # fraction of the training pairs
    seconds_per_pose: float = 6.0
    step_rad: float = 0.4  # the walk's largest move of a joint between poses
    path: str = "walk"  # "walk": every joint wanders; "surface": the tool keeps one orientation
    turned: int = 0  # surface: training poses whose tool is turned by TURN_RAD about its x or y axis
    seed: int = 0

    @property
    def approach(self) -> bool:
        """Whether the joints' approach sides matter here (the nets then take them)."""
        return bool(self.half_backlash_rad)


@dataclass(frozen=True)
class Cell:
    spec: CellSpec
    config: RobotConfig
    train: Pairs
    test: Pairs
    floor: dict[str, float]  # mean and p95 of the floor, position mm and orientation deg


def _walk(config: RobotConfig, count: int, rng: np.random.Generator, step: float) -> np.ndarray:
    lower, upper = joint_range(config.chain, 0.8)
    q = np.empty((count, config.chain.dof))
    q[0] = rng.uniform(lower, upper)
    for i in range(1, count):
        q[i] = np.clip(q[i - 1] + rng.uniform(-step, step, config.chain.dof), lower, upper)
    return q


SURFACE_SPAN_RAD = 0.5  # surface: the first three joints stay this close to the home configuration
TURN_RAD = np.radians(30.0)
SURFACE_JITTER_RAD = np.radians(0.02)  # surface: the commanded orientation's scatter about each axis (a taught path)


def _surface(spec: CellSpec, config: RobotConfig, count: int, rng: np.random.Generator, turned: int) -> np.ndarray:
    """A walk over a surface with the tool at one orientation: the first three joints wander about a home
    configuration, the wrist joints hold the nominal tool orientation it has there, within a taught path's
    scatter (``SURFACE_JITTER_RAD``). ``turned`` poses,
    spread over the walk, hold it turned by ``TURN_RAD`` about the tool's x or y axis, alternately."""
    chain = config.chain
    lower, upper = joint_range(chain, 0.8)
    home = np.random.default_rng([spec.seed, 0]).uniform(lower, upper)  # every walk of the cell shares it
    home[4] = 0.5 * (lower[4] + upper[4]) + 1.2  # the wrist well away from its singularity
    jitter = Rotation.from_rotvec(rng.normal(0.0, SURFACE_JITTER_RAD, (count, 3))).as_matrix()
    goal = fk.fk(chain, home[None])[0, :3, :3] @ jitter
    for k, i in enumerate(np.linspace(0, count - 1, turned).astype(int) if turned else ()):
        axis = np.eye(3)[k % 2]
        goal[i] = goal[i] @ Rotation.from_rotvec(TURN_RAD * axis).as_matrix()
    q = np.tile(home, (count, 1))
    for i in range(1, count):
        moved = q[i - 1, :3] + rng.uniform(-spec.step_rad, spec.step_rad, 3)
        q[i, :3] = np.clip(moved, home[:3] - SURFACE_SPAN_RAD, home[:3] + SURFACE_SPAN_RAD)
    for _ in range(50):  # Newton on the wrist joints: the orientation error, turned into joint steps
        tip, jac = fk.fk_and_jacobian(chain, q)
        miss = Rotation.from_matrix(goal @ np.swapaxes(tip[:, :3, :3], 1, 2)).as_rotvec()
        q[:, 3:] += np.linalg.solve(jac[:, 3:, 3:], miss[..., None])[..., 0]
    miss = se3.rotation_angle(goal @ np.swapaxes(fk.fk(chain, q)[:, :3, :3], 1, 2))
    if np.max(miss) > 1e-9:
        raise SimulationError(f"surface path: the wrist cannot hold the tool orientation ({np.max(miss):.2g} rad off)")
    return q


def _stats(pos_mm: np.ndarray, rot_deg: np.ndarray | None) -> dict[str, float]:
    out = {"position_mm_mean": float(np.mean(pos_mm)), "position_mm_p95": float(np.percentile(pos_mm, 95))}
    if rot_deg is not None:
        out |= {
            "orientation_deg_mean": float(np.mean(rot_deg)),
            "orientation_deg_p95": float(np.percentile(rot_deg, 95)),
        }
    return out


def build_cell(spec: CellSpec) -> Cell:
    """The cell's training and test pairs and its floor, reproducible from ``spec.seed``."""
    config = load_robot_config(spec.robot)
    if spec.truth:
        sections = {k: v for k, v in config.truth.items() if k not in spec.truth}
        for name, values in spec.truth.items():
            sections[name] = {**config.truth.get(name, {}), **values}
        config = replace(config, truth=sections)
    robot = TrueRobot.from_config(config, enabled=spec.effects or None)
    frames = spec.tracker or {}
    noisy = Tracker.from_config(
        {**frames, "position_noise_mm": spec.position_noise_mm, "orientation_noise_deg": spec.orientation_noise_deg}
    )
    clean = replace(noisy, position_noise=0.0, orientation_noise=0.0)
    n = config.chain.dof
    half = np.zeros(n)
    half[: len(spec.half_backlash_rad)] = spec.half_backlash_rad
    c = robot.elastic.compliance

    def truth(q: np.ndarray) -> np.ndarray:
        """True tip poses at commanded ``q`` along a walk: backlash sides, the torque-sign spring."""
        reached = play(q, half)  # the walk's straight moves: its poses alone give the play exactly
        if spec.asymmetry:
            reached = reached + spec.asymmetry * c * np.abs(robot.gravity_torques(reached))
        return robot.fk(reached)

    def warmed(tip: np.ndarray, t: np.ndarray) -> np.ndarray:
        if not spec.thermal_ppm:
            return tip
        out = tip.copy()
        out[:, :3, 3] *= 1.0 + 1e-6 * spec.thermal_ppm * (1.0 - np.exp(-t / 3600.0))[:, None]
        return out

    def walk(count: int, seed: int, outliers: float) -> tuple[Pairs, np.ndarray]:
        rng = np.random.default_rng([spec.seed, seed])
        if spec.path == "surface":
            q = _surface(spec, config, count, rng, spec.turned if seed == 1 else 0)
        else:
            q = _walk(config, count, rng, spec.step_rad)
        t = spec.seconds_per_pose * np.arange(count)
        tip = truth(q)
        T = noisy.measure(warmed(tip, t), rng)
        bad = rng.random(count) < outliers
        T[bad, :3, 3] += rng.normal(0.0, 1e-3, (int(bad.sum()), 3))  # broken beam: a millimetre off
        if spec.plain_reflector:
            T[:, :3, :3] = np.eye(3)
        stamps = (10**9 * (1.0 + t)).astype(np.int64)
        frame = noisy.frame_id or config.base_link
        pairs = Pairs(q, T, stamps, config.chain.joint_names, frame, position_only=spec.plain_reflector)
        return pairs.with_approach(), clean.measure(tip, rng)

    train, _ = walk(spec.poses, 1, spec.outliers)
    test, exact = walk(spec.test_poses, 2, 0.0)
    pos, rot = se3.pose_errors(test.T, exact)
    return Cell(spec, config, train, test, _stats(pos, None if spec.plain_reflector else rot))


REALISTIC = {  # every effect at once, backlash a third of the backlash cell's
    "tracker": TRACKER_FAR,
    "half_backlash_rad": (1e-4, 1e-4, 1e-4),
    "asymmetry": 0.3,
    "thermal_ppm": 15.0,
    "outliers": 0.004,
}
CENTIMETRES_OFF = {  # a truth's sections overridden: the URDF model misses by centimetres
    "geometric": {"translation_mm": 3.0, "rotation_deg": 0.5, "zero_offset_deg": 0.3},
    "bending": {"rad_per_nm": 2e-5},
}
SURFACE = {"path": "surface", "step_rad": 0.1, "tracker": TRACKER_FAR}  # a task path, the target off the flange
SURFACE_CELLS = (
    CellSpec("UR10: one tool orientation along a surface", **SURFACE),
    CellSpec("UR10: one tool orientation along a surface, plain reflector", plain_reflector=True, **SURFACE),
    CellSpec("UR10: one tool orientation along a surface, 10 poses turned by 30 deg", turned=10, **SURFACE),
)
CELLS = (
    CellSpec("UR10: geometry and compliance", effects={"gear": False, "bending": False}),
    CellSpec("UR10: + gear harmonics and bending"),
    CellSpec("UR10: + backlash, approach sides", half_backlash_rad=(3e-4, 2e-4, 2e-4)),
    CellSpec("UR10: + thermal drift (15 ppm)", thermal_ppm=15.0),
    CellSpec("UR10: + torque-sign stiffness", asymmetry=0.3),
    CellSpec("UR10: tracker 3 m away, 0.4 % outliers", tracker=TRACKER_FAR, outliers=0.004),
    CellSpec("UR10: plain reflector (position only)", tracker=TRACKER_FAR, plain_reflector=True),
    CellSpec("RX160: every effect", robot="rx160"),
    CellSpec("RX160: realistic, 300 poses", robot="rx160", poses=300, **REALISTIC),
    CellSpec("KR16-type (shoulder and elbow offsets): realistic, 4,800 poses", robot="kr16", poses=4800, **REALISTIC),
    CellSpec("UR10: realistic, 300 poses", poses=300, **REALISTIC),
    CellSpec("UR10: realistic, 1,000 poses", poses=1000, **REALISTIC),
    CellSpec("UR10: realistic, 4,800 poses", poses=4800, **REALISTIC),
    CellSpec("UR10: every effect, base frame, 20,000 poses", poses=20_000, position_noise_mm=0.01),
    CellSpec(
        "UR10: URDF centimetres off, plain reflector, realistic, 300 poses",
        poses=300,
        truth=CENTIMETRES_OFF,
        plain_reflector=True,
        **REALISTIC,
    ),
    *SURFACE_CELLS,
)
