"""The hybrid model: analytic FK from the URDF, corrected by the residual nets of a model directory.

``p = p_model + Δp(q)`` and ``R = exp(ω(q)) · R_model`` (paper Fig. 2). ``model`` is the URDF chain, or,
when the model directory holds a parametric stage, the identified elasto-geometric chain. Without nets
it is that model alone, so nodes and IK use one type whether or not a calibration exists.

Outside the joint range the nets were trained on, ``range_policy`` decides: ``warn`` (use the nets;
callers flag it), ``parametric`` (drop the nets there), ``refuse`` (callers fail such requests; see
:meth:`HybridModel.check_range`) or ``bound`` (each net serves where its error bound is below the parametric
stage's alone, see :meth:`HybridModel.error_bounds`; no radius to choose). A trajectory covers a thin part of
that box, and away from it the nets extrapolate; with ``coverage_radius`` set, the calibrated range is the
configurations within that distance of a training configuration instead.

A loaded model is a value: nothing changes it after load. Its condition channels (temperature, the joints'
approach directions) hold the values it computes with by default; a call can give its own per row
(``conditions``), and :meth:`HybridModel.with_conditions`, :meth:`HybridModel.with_condition` and
:meth:`HybridModel.with_approach` give another value that shares every loaded part. A caller that serves
several threads (the kinematics node) keeps the current values itself and computes each answer with a model of
them.
"""

from __future__ import annotations

import copy
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import torch
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from hybrid_kinematics_ros.io.errors import DataError
from hybrid_kinematics_ros.io.model_dir import load_model_dir
from hybrid_kinematics_ros.kinematics import approach, fk
from hybrid_kinematics_ros.kinematics.chain import Chain, chain_from_urdf
from hybrid_kinematics_ros.kinematics.elastic import ElasticChain
from hybrid_kinematics_ros.kinematics.se3 import exp_so3, left_jacobian_so3, pose_errors
from hybrid_kinematics_ros.kinematics.unrolled import Rows, unrolled_fk
from hybrid_kinematics_ros.model import pose_kernel
from hybrid_kinematics_ros.model.bounds import DISTANCE, Bounds, excess
from hybrid_kinematics_ros.model.errors import ModelError
from hybrid_kinematics_ros.model.nets import FastResidual
from hybrid_kinematics_ros.model.parametric import model_from_manifest
from hybrid_kinematics_ros.model.range_policy import RANGE_POLICIES
from hybrid_kinematics_ros.model.referencing import Referencing

# Batches up to this many rows run the nets' compiled evaluators (one matrix product a layer) instead of TorchScript,
# which spends small batches on operator dispatch: the batches of the IK's valley search (a valley's 20-40 traced
# points) and of several solutions, and a service's few configurations.
COMPILED_ROWS = 64


class HybridModel:
    def __init__(
        self,
        chain: Chain,
        nets: dict[str, torch.jit.ScriptModule] | None = None,
        manifest: dict[str, Any] | None = None,
        path: Path | None = None,
        range_policy: str = "warn",
        coverage: np.ndarray | None = None,
    ) -> None:
        self.chain = chain
        self.coverage = None if coverage is None else np.asarray(coverage, dtype=float)
        self._tree: cKDTree | None = None
        self._coverage_radius: float | None = None
        self.nets = dict(nets or {})
        self.manifest = dict(manifest or {})
        self.path = path
        self._fast = {kind: FastResidual.from_module(net) for kind, net in self.nets.items()}
        self._pose_cache: tuple | None = None  # (the stage it was built for, _pose_operands)
        self._init_range(chain)
        section = self.manifest.get("parametric")
        self.base = model_from_manifest(chain, section) if section else ElasticChain.rigid(chain)
        self._rigid_base = self.base.chain if self.base.is_rigid else None  # fk_single's shortcut
        # fk_rows: generated float code, for the URDF chain and for the model when it is that chain alone
        self._rows_analytic = unrolled_fk(chain)
        if self._rigid_base is None or self.nets:
            self._rows_model = None
        else:
            self._rows_model = self._rows_analytic if self._rigid_base is chain else unrolled_fk(self._rigid_base)
        self._init_referencings()
        self._init_conditions(chain)
        self.payload_changed = False  # serving another payload than the nets were trained with (with_payload)
        self._trained_base = self.base  # the stage under the calibrated payload (what its bounds hold for)
        section = self.manifest.get("bounds")
        # bounds of another distance measure are not read: their numbers mean something else; such a model
        # serves without bounds
        self.bounds = Bounds.from_manifest(section) if section and section.get("distance") == DISTANCE else None
        self._range_policy = self._checked_policy(range_policy)
        # the compiled one-configuration paths load (or, on a fresh checkout, compile) here, not in a first request
        mid = chain.mid_limits()
        self.fk_single(mid)
        self.fk_and_jacobian_single(mid)

    def _init_range(self, chain: Chain) -> None:
        """The trained joint range (the chain's limits where the manifest has none), and what the range checks
        read of it."""
        rng = self.manifest.get("trained_range")
        self.trained_lower = np.asarray(rng["lower"], dtype=float) if rng else chain.lower
        self.trained_upper = np.asarray(rng["upper"], dtype=float) if rng else chain.upper
        self._range = (self.trained_lower - 1e-9, self.trained_upper + 1e-9)
        # A revolute joint's q and q ± 2π are one pose: such joints are taken to the turn of the trained range
        # (where it spans at most a turn) before anything reads them, so both get one correction.
        self._periodic = chain.revolute & (self.trained_upper - self.trained_lower <= 2 * np.pi)
        self._turn_centre = np.zeros(chain.dof)  # only the periodic joints' is read; a continuous one's range is ±inf
        periodic = self._periodic
        self._turn_centre[periodic] = 0.5 * (self.trained_lower[periodic] + self.trained_upper[periodic])
        self._range_lists = (self._range[0].tolist(), self._range[1].tolist())
        self._trained_lists = (self.trained_lower.tolist(), self.trained_upper.tolist())  # error_bounds' exact test
        self._revolute_list = chain.revolute.tolist()

    def _init_referencings(self) -> None:
        """Each tracker station's referencing, and the nominal model's own."""
        section = self.manifest.get("referencing") or []
        refs = [Referencing.from_manifest(r) for r in ([section] if isinstance(section, dict) else section)]
        self.referencings = {r.frame_id: r for r in refs}  # one per tracker station
        self.referencing = refs[0] if refs else None  # the first station's
        # the nominal model's own referencing (the tracker and the target fitted to the URDF model alone):
        # the "before" every report compares with; models without one compare with the served referencing
        rigid = self.manifest.get("rigid_referencing")
        self.rigid_referencings = (
            {r.frame_id: r for r in map(Referencing.from_manifest, rigid)} if rigid else self.referencings
        )

    def _init_conditions(self, chain: Chain) -> None:
        """The condition channels the nets take after the joints, their defaults, and where the joints'
        approach directions sit among them."""
        conditions = self.manifest.get("conditions") or {}
        self.condition_names = tuple(conditions)  # condition channels the nets take after the joints
        self._values = _frozen([float(conditions[c]["default"]) for c in self.condition_names])
        # where the joints' approach directions sit among them, in joint order (None: the nets take none)
        names = approach.channel_names(chain.joint_names)
        self.approach_index = (
            np.array([self.condition_names.index(n) for n in names]) if names[0] in self.condition_names else None
        )

    @property
    def range_policy(self) -> str:
        return self._range_policy

    def with_range_policy(self, value: str) -> HybridModel:
        """This model serving outside its calibrated range by policy ``value`` (:data:`RANGE_POLICIES`)."""
        clone = self._clone()
        clone._range_policy = self._checked_policy(value)
        return clone

    def _checked_policy(self, value: str) -> str:
        if value not in RANGE_POLICIES:
            raise ModelError(f"range policy '{value}' is not one of {', '.join(RANGE_POLICIES)}")
        if value == "bound" and self.nets and (self.bounds is None or not self.bounds.has_stage):
            raise ModelError(
                f"range policy 'bound' compares the nets' error bounds with the parametric stage's, and model "
                f"{self.path or ''} carries no bounds of its stage alone; retrain it with this version"
            )
        return value

    @property
    def coverage_radius(self) -> float | None:
        """Joint-space distance (rad) to the nearest training configuration beyond which a configuration
        counts as outside the calibrated range; None: the per-joint trained range alone decides."""
        return self._coverage_radius

    def with_coverage_radius(self, value: float | None) -> HybridModel:
        """This model with the calibrated range within ``value`` rad of a training configuration (None: the
        per-joint trained range)."""
        if value is not None:
            if not (np.isfinite(value) and value > 0):
                raise ModelError(f"coverage radius {value} must be a positive number of radians")
            if self.coverage is None:
                raise ModelError(
                    f"model {self.path or ''} stores no training configurations (coverage.npy); "
                    "retrain it with this version to use a coverage radius"
                )
        clone = self._clone()
        clone._coverage_radius = None if value is None else float(value)
        return clone

    def with_gravity(self, gravity: np.ndarray) -> HybridModel:
        """This model with the parametric stage's gravity ``(3,)`` m/s² in the base frame (a wall or ceiling
        mount)."""
        clone = self._clone()
        clone.base = replace(self.base, gravity=np.asarray(gravity, dtype=float))
        return clone

    def _clone(self) -> HybridModel:
        """A shallow copy for a ``with_*`` value: it shares the loaded parts."""
        return copy.copy(self)

    def coverage_distance(self, q: np.ndarray) -> np.ndarray | None:
        """``(B,)`` Euclidean joint-space distance (rad) to the nearest training configuration; None when
        the model stores none."""
        if self.coverage is None:
            return None
        if self._tree is None:
            self._tree = cKDTree(self.coverage)
        return self._tree.query(np.atleast_2d(q))[0]

    def error_bounds(
        self, q: np.ndarray, conditions: np.ndarray | None = None
    ) -> tuple[np.ndarray, np.ndarray | None] | None:
        """Bounds on the answers' errors at configurations ``q (B, n)``: position (m) and orientation (rad;
        None for a position-only model), each meant to hold for ``bounds.level`` of answers
        (:mod:`model.bounds`); None when the model carries no bounds. Each is the bound of what serves there
        under the range policy: the nets' (beyond the trained range they grow by the part of the nets'
        correction that comes from beyond it, :meth:`_extrapolation`) or, where they are dropped, the
        parametric stage's alone."""
        if self.bounds is None:
            return None
        if self.payload_changed:
            return self._payload_bounds(q, conditions)
        q = np.asarray(q, dtype=float)
        if q.size == len(self._revolute_list) and (not self.nets or not self._by_range):
            one = q.ravel().tolist()  # one configuration (a service's call): inside the trained range, no growth
            lower, upper = self._trained_lists
            if all(lo <= v <= hi for lo, v, hi in zip(lower, one, upper, strict=True)):
                position, orientation = self.bounds.inside_one(one, self._revolute_list)
                return np.array([position]), None if orientation is None else np.array([orientation])
        q = self.same_turn(np.atleast_2d(q))
        x = excess(q, self.trained_lower, self.trained_upper, self.chain.revolute)
        nets = self.bounds.of(q, x, self.chain.revolute)
        if not self.nets or (not x.any() and not self._by_range):
            return nets  # no nets, or all inside the trained range where they always serve
        grown = self._grown(q, x, conditions, nets)
        served = self._nets_apply(q, conditions, grown=grown)
        if served is True:
            return grown
        stage = self.bounds.of(q, x, self.chain.revolute, stage=True)
        out = [
            None if g is None else np.where(use, g, alone) for g, alone, use in zip(grown, stage, served.T, strict=True)
        ]
        return out[0], out[1]

    def _payload_bounds(self, q: np.ndarray, conditions: np.ndarray | None) -> tuple[np.ndarray, np.ndarray | None]:
        """:meth:`error_bounds` under another payload than the calibrated one (:meth:`with_payload`), where no
        bound was calibrated: what no measurement checked is added to the stage's calibrated bound (the
        triangle inequality, as beyond the trained range): the move of the stage's answer that the payload
        change made, and, where the nets serve, their whole correction. Loose, but it holds where a bound
        calibrated under the old payload would cover none of the new errors (``test_bounds.py``)."""
        q = self.same_turn(np.atleast_2d(np.asarray(q, dtype=float)))
        x = excess(q, self.trained_lower, self.trained_upper, self.chain.revolute)
        position, orientation = self.bounds.of(
            q, x, self.chain.revolute, stage=bool(self.nets) and self.bounds.has_stage
        )
        reached = self._approached(q, conditions)
        moved_mm, moved_deg = pose_errors(self.base.fk(reached), self._trained_base.fk(reached))
        unchecked = [1e-3 * moved_mm, np.radians(moved_deg)]
        served = self._nets_apply(q, conditions) if self.nets else False
        if served is not False:
            use = np.broadcast_to(served, (len(q), 2))
            for k, r in enumerate(self.residuals(q, conditions)):
                unchecked[k] = unchecked[k] + use[:, k] * np.linalg.norm(r, axis=1)
        return position + unchecked[0], None if orientation is None else orientation + unchecked[1]

    def _extrapolation(
        self,
        q: np.ndarray,
        x: np.ndarray,
        conditions: np.ndarray | None,
        at: tuple[np.ndarray, np.ndarray] | None = None,
    ) -> np.ndarray:
        """``(B, 2)``: how much of the position (m) and orientation (rad) nets' corrections at ``q (B, n)``
        (taken to the trained turn) comes from beyond the trained range: their change from the nearest
        configuration inside it (each joint clipped to its range). 0 inside. The nets' error beyond the
        range is the stage's there, grown at the measured rates, less this part of a correction nothing
        checked: the triangle inequality adds it to their bound. ``at``: the residuals at ``q``, when the
        caller has them (the nets then run once more, at the clipped rows only)."""
        out = np.zeros((len(q), 2))
        rows = np.flatnonzero(x.any(axis=1))
        if len(rows) == 0:
            return out
        c = None if conditions is None else np.broadcast_to(conditions, (len(q), len(self.condition_names)))[rows]
        inside = np.clip(q[rows], self.trained_lower, self.trained_upper)
        there = self.residuals(q[rows], c) if at is None else (at[0][rows], at[1][rows])
        edge = self.residuals(inside, c)
        for k in range(2):
            out[rows, k] = np.linalg.norm(there[k] - edge[k], axis=1)
        return out

    def _grown(
        self,
        q: np.ndarray,
        x: np.ndarray,
        conditions: np.ndarray | None,
        nets: tuple[np.ndarray, np.ndarray | None] | None = None,
        at: tuple[np.ndarray, np.ndarray] | None = None,
    ) -> tuple[np.ndarray, np.ndarray | None]:
        """The nets' bounds at ``q`` (``nets``: the bounds inside, when known), grown by
        :meth:`_extrapolation`."""
        if nets is None:
            nets = self.bounds.of(q, x, self.chain.revolute)
        ext = self._extrapolation(q, x, conditions, at)
        return nets[0] + ext[:, 0], None if nets[1] is None else nets[1] + ext[:, 1]

    @property
    def is_corrected(self) -> bool:
        """True when the model differs from the URDF: nets, a parametric stage, or both."""
        return bool(self.nets) or not self.base.is_rigid

    @property
    def has_parametric(self) -> bool:
        return "parametric" in self.manifest

    def check_range(self, q: np.ndarray) -> None:
        """Under the ``refuse`` policy, raise for configurations outside the trained range, naming them."""
        if self.range_policy != "refuse" or not self.nets:
            return
        q = np.atleast_2d(q)
        inside = self.in_calibrated_range(q)
        if not inside.all():
            row = int(np.flatnonzero(~inside)[0])
            raise ModelError(
                f"configuration {row} lies outside the calibrated joint range "
                f"({self.describe_outside(q[row])}) and the range policy is 'refuse'"
            )

    def describe_outside(self, q: np.ndarray) -> str:
        """Why one configuration lies outside the calibrated range (the joints outside the trained range,
        or its distance to the training data), for messages."""
        q = self.same_turn(np.asarray(q, dtype=float))
        if self.payload_changed and self.nets:
            return f"the payload is {self.base.payload_mass:g} kg, not the one the nets were trained with"
        if self.coverage_radius is not None:
            return (
                f"{float(self.coverage_distance(q)[0]):.3f} rad from the nearest training configuration "
                f"(coverage radius {self.coverage_radius:.3f} rad)"
            )
        out = []
        for name, v, lo, hi in zip(self.joint_names, q, self.trained_lower, self.trained_upper, strict=True):
            if not lo - 1e-9 <= v <= hi + 1e-9:
                out.append(f"{name} = {v:.4f} rad, trained on [{lo:.4f}, {hi:.4f}]")
        return "; ".join(out)

    @property
    def _by_range(self) -> bool:
        """The nets serve inside the calibrated range only: the ``parametric`` policy, and ``bound`` with another
        payload than the nets were trained with (their bound does not know it; none is inside then)."""
        return self.range_policy == "parametric" or (self.range_policy == "bound" and self.payload_changed)

    def _nets_apply(
        self,
        q: np.ndarray,
        conditions: np.ndarray | None = None,
        at: tuple[np.ndarray, np.ndarray] | None = None,
        grown: tuple[np.ndarray, np.ndarray | None] | None = None,
    ) -> np.ndarray | bool:
        """Where the nets correct ``q (B, n)`` (taken to the trained turn) under the range policy: True
        (everywhere) or ``(B, 2)`` for the position and orientation nets. Inside the calibrated range under
        ``parametric``; under ``bound``, where their bound (:meth:`_grown`; ``grown`` when the caller has it,
        ``at`` the residuals at ``q`` when it has those) is below the stage's, so always inside the trained
        range."""
        if self._by_range:
            return np.repeat(self.in_calibrated_range(q)[:, None], 2, axis=1)
        if self.range_policy != "bound":
            return True
        x = excess(q, self.trained_lower, self.trained_upper, self.chain.revolute)
        if not x.any():
            return True
        if grown is None:
            grown = self._grown(q, x, conditions, at=at)
        stage = self.bounds.of(q, x, self.chain.revolute, stage=True)
        use = np.ones((len(q), 2), dtype=bool)
        for k in range(2):
            if grown[k] is not None:
                use[:, k] = grown[k] < stage[k]
        return use

    @classmethod
    def load(
        cls, path: str | Path, expect_urdf: str | None = None, expect_joint_names: tuple[str, ...] | None = None
    ) -> HybridModel:
        """Load a model directory; refuse it if it was trained for another URDF or other joints.

        ``expect_urdf`` (a path, ``package://`` or XML text, e.g. the ``robot_description``) is compared by
        its kinematics between the model's base and tip links (:meth:`Chain.first_difference`), not by its
        bytes: xacro's or another tool's output of the same robot is accepted.

        Raises:
            DataError: missing, corrupt or mismatched files, with the file named.
        """
        files = load_model_dir(path)
        m = files.manifest
        trained_chain = chain_from_urdf(files.urdf_text, m["base_link"], m["tip_link"])
        chain = trained_chain.with_tool(np.asarray(m["tool"], dtype=float))
        chain = chain.with_limits(m["joint_limits"]["lower"], m["joint_limits"]["upper"])
        if tuple(m["joint_names"]) != chain.joint_names:
            raise DataError(
                f"{files.path}: model.json joints {m['joint_names']} differ from the URDF's chain "
                f"{list(chain.joint_names)}"
            )
        if expect_urdf is not None:
            # A robot_description from xacro or another tool is never byte-identical: compare the kinematics.
            expected = chain_from_urdf(expect_urdf, m["base_link"], m["tip_link"])
            difference = trained_chain.first_difference(expected)
            if difference:
                raise DataError(
                    f"{files.path} was trained for another URDF: {difference}; retrain or use the matching URDF"
                )
        if expect_joint_names is not None and tuple(expect_joint_names) != chain.joint_names:
            raise DataError(
                f"{files.path} was trained for joints {list(chain.joint_names)}, not {list(expect_joint_names)}"
            )
        return cls(chain, files.nets, m, Path(path), coverage=files.coverage)

    @property
    def joint_names(self) -> tuple[str, ...]:
        return self.chain.joint_names

    @property
    def has_orientation(self) -> bool:
        return "orientation" in self.nets

    def with_payload(self, mass: float, com: np.ndarray) -> HybridModel:
        """This model serving another payload (kg; centre of mass in the tip frame, m): the parametric
        stage's deflections follow it (its gravity torques are recomputed), the nets stay as trained. Their
        correction is then extrapolated, so with nets no configuration counts as inside the calibrated
        range (``parametric`` policy: the stage alone serves; ``refuse``: nothing does)."""
        com = np.asarray(com, dtype=float)
        if not (np.isfinite(mass) and mass >= 0.0) or com.shape != (3,) or not np.all(np.isfinite(com)):
            raise ModelError(f"payload {mass} kg at {com.tolist()} m: give a mass >= 0 and three finite numbers")
        if not self.base.is_elastic:
            raise ModelError(
                "the model has no elastic parametric stage (no compliance) to follow a payload; retrain it with "
                "the payload the robot carries"
            )
        clone = self._clone()
        clone.base = replace(self.base, payload_mass=float(mass), payload_com=com)
        trained_mass, trained_com = self.trained_payload
        clone.payload_changed = not (mass == trained_mass and np.allclose(com, trained_com, rtol=0.0, atol=1e-9))
        return clone

    @property
    def trained_payload(self) -> tuple[float, np.ndarray]:
        """The payload the stage was identified and the nets trained with (kg; m in the tip frame)."""
        section = (self.manifest.get("parametric") or {}).get("payload") or {}
        return float(section.get("mass", 0.0)), np.asarray(section.get("com", np.zeros(3)), dtype=float)

    def _approached(self, q: np.ndarray, conditions: np.ndarray | None = None) -> np.ndarray:
        """The joints as the stage's backlash terms leave them, for the approach directions in ``conditions``
        (per row) or the current ones; unchanged for a stage without backlash terms."""
        if self.base.backlash is None or self.approach_index is None:
            return q
        values = self.condition_values if conditions is None else np.asarray(conditions, dtype=float)
        return self.base.approached(q, values[..., self.approach_index])

    def same_turn(self, q: np.ndarray) -> np.ndarray:
        """``q (…, n)`` with each revolute joint outside the trained range moved by whole turns to the
        equivalent angle nearest it (within π of its centre); joints inside are returned unchanged, bit for
        bit. The URDF pose is the same; the nets, the joint error map and the range checks then see the
        angles they were trained on, so q and q ± 2π get one correction."""
        q = np.asarray(q, dtype=float)
        if q.ndim == 1:  # one configuration (every FK service call): the usual answer, inside, in Python floats
            lower, upper = self._range_lists
            if all(lo <= v <= hi for lo, v, hi in zip(lower, q.tolist(), upper, strict=True)):
                return q
        outside = self._periodic & ((q < self._range[0]) | (q > self._range[1]))
        if not outside.any():
            return q
        turns = np.where(outside, np.floor((q - self._turn_centre + np.pi) / (2 * np.pi)), 0.0)
        return np.where(turns != 0, q - 2 * np.pi * turns, q)

    def in_calibrated_range(self, q: np.ndarray) -> np.ndarray:
        """``(B,)`` True where every joint lies inside the range the nets were trained on; with a coverage
        radius, True where a training configuration lies within it instead (the finer test of the two)."""
        q = self.same_turn(np.atleast_2d(q))
        if self.payload_changed and self.nets:
            return np.zeros(len(q), dtype=bool)
        if self._coverage_radius is not None:
            return self.coverage_distance(q) <= self._coverage_radius
        lower, upper = self._range
        return ((q >= lower) & (q <= upper)).all(axis=1)

    def in_calibrated_range_one(self, q: np.ndarray | list[float]) -> bool:
        """:meth:`in_calibrated_range` of one finite configuration ``(n,)`` (or a list), compared in Python floats (the
        services' path, where each numpy call costs microseconds)."""
        if self._coverage_radius is not None or (self.payload_changed and self.nets):
            return bool(self.in_calibrated_range(q)[0])
        lower, upper = self._range_lists
        values = q if isinstance(q, list) else q.tolist()
        if all(lo <= v <= hi for lo, v, hi in zip(lower, values, upper, strict=True)):
            return True
        return bool(self.in_calibrated_range(np.array(values))[0])  # another turn of a revolute joint

    def with_condition(self, name: str, value: float) -> HybridModel:
        """This model computing with ``value`` for the condition channel ``name`` (e.g. the cell's temperature)."""
        if name not in self.condition_names:
            raise ModelError(
                f"the model takes no condition '{name}' (it takes {', '.join(self.condition_names) or 'none'})"
            )
        if not np.isfinite(value):
            raise ModelError(f"condition '{name}' = {value} is not a finite number")
        values = self._values.copy()
        values[self.condition_names.index(name)] = float(value)
        return self.with_conditions(values)

    def with_conditions(self, values: np.ndarray | list[float]) -> HybridModel:
        """This model computing with the condition values ``(k,)``, one per :attr:`condition_names`."""
        values = np.array(values, dtype=float)
        if values.shape != self._values.shape:
            raise ModelError(f"{len(values)} condition values given; the model takes {len(self._values)}")
        if np.array_equal(values, self._values):
            return self
        clone = self._clone()
        clone._values = _frozen(values)
        return clone

    def with_approach(self, directions: np.ndarray | None) -> HybridModel:
        """This model computing with the joints' approach directions ``(n,)`` in {-1, 0, +1}
        (:mod:`kinematics.approach`); itself for None or a model whose nets do not take them."""
        if directions is None or self.approach_index is None:
            return self
        values = self._values.copy()
        values[self.approach_index] = directions
        return self.with_conditions(values)

    @property
    def approach(self) -> np.ndarray | None:
        """The joints' approach directions ``(n,)`` this model computes with, or None for a model whose nets do
        not take them."""
        return None if self.approach_index is None else self._values[self.approach_index].copy()

    @property
    def condition_values(self) -> np.ndarray:
        """``(k,)``: the condition values this model computes with (read-only)."""
        return self._values

    @property
    def condition_defaults(self) -> dict[str, float]:
        """What each condition channel is when nobody sets it: the training mean (an approach direction: 0)."""
        conditions = self.manifest.get("conditions") or {}
        return {name: float(conditions[name]["default"]) for name in self.condition_names}

    def conditions_with_approach(self, directions: np.ndarray) -> np.ndarray | None:
        """``(N, k)``: the current condition values, with the approach directions ``(N, n)`` per row; None
        for a model without condition channels."""
        if not self.condition_names:
            return None
        rows = np.tile(self.condition_values, (len(directions), 1))
        if self.approach_index is not None:
            rows[:, self.approach_index] = directions
        return rows

    def conditions_of(self, pairs_conditions: dict[str, np.ndarray], count: int) -> np.ndarray | None:
        """``(count, k)``: the model's condition channels from measured ones (evaluation); None if it has none."""
        if not self.condition_names:
            return None
        missing = [c for c in self.condition_names if c not in pairs_conditions]
        if missing:
            raise ModelError(
                f"the model takes {', '.join(self.condition_names)}, but the pairs carry no {', '.join(missing)}"
            )
        return np.column_stack([np.broadcast_to(pairs_conditions[c], (count,)) for c in self.condition_names])

    def net_inputs(self, q: np.ndarray, conditions: np.ndarray | None = None) -> np.ndarray:
        """The nets' input: the joints, then the condition channels (given per row, else the current values)."""
        if not self.condition_names:
            return q
        if q.ndim == 1:
            return np.concatenate((q, self.condition_values if conditions is None else conditions))
        c = np.broadcast_to(
            self.condition_values if conditions is None else conditions, (len(q), len(self.condition_names))
        )
        return np.column_stack([q, c])

    def residuals(self, q: np.ndarray, conditions: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """``(Δp, ω)``, each ``(B, 3)`` in m and rad; zeros where a net is absent. ``conditions (B, k)``:
        the condition channels per configuration, else the current values."""
        x = self.net_inputs(np.atleast_2d(q), conditions)
        zeros = np.zeros((len(x), 3))
        if len(x) <= COMPILED_ROWS and all(self._fast.values()):
            fast = self._fast
            return (
                fast["position"](x) if "position" in fast else zeros,
                fast["orientation"](x) if "orientation" in fast else zeros,
            )
        qt = torch.as_tensor(x, dtype=torch.float64)
        with torch.no_grad():
            dp = self.nets["position"](qt).numpy() if "position" in self.nets else zeros
            w = self.nets["orientation"](qt).numpy() if "orientation" in self.nets else zeros
        return dp, w

    def correct(self, T: np.ndarray, dp: np.ndarray, w: np.ndarray) -> np.ndarray:
        """Apply the residuals ``(B, 3)`` to the model's poses ``(B, 4, 4)``."""
        out = np.array(T, dtype=float, copy=True)
        out[:, :3, 3] += dp
        if self.has_orientation:
            out[:, :3, :3] = Rotation.from_rotvec(w).as_matrix() @ out[:, :3, :3]
        return out

    def fk(
        self, q: np.ndarray, analytic: bool = False, nets: bool = True, conditions: np.ndarray | None = None
    ) -> np.ndarray:
        """Tip poses ``(B, 4, 4)``: hybrid; the URDF model alone when ``analytic``; no nets when not ``nets``.
        ``conditions (B, k)``: the condition channels per configuration (else the current values)."""
        q = fk.check_joints(self.chain, q)
        if analytic:
            return fk.fk(self.chain, q)
        q = self.same_turn(q)
        T = self.base.fk(self._approached(q, conditions))
        if not nets or not self.nets:
            return T
        dp, w = self.residuals(q, conditions)
        use = self._nets_apply(q, conditions, at=(dp, w))
        if use is True:
            return self.correct(T, dp, w)
        return self.correct(T, dp * use[:, :1], w * use[:, 1:])

    def fk_single(self, q: np.ndarray, analytic: bool = False) -> np.ndarray:
        """One pose ``(4, 4)`` on the low-overhead path: with MLP nets one compiled call
        (:mod:`~hybrid_kinematics_ros.model.pose_kernel`), else the stage's kernel and the nets'."""
        q = np.asarray(q, dtype=float)
        if analytic:
            return fk.fk_single(self.chain, q)
        q = self.same_turn(q)
        reached = self._approached(q)
        if not self.nets:
            return self.base.fk_single(reached) if self._rigid_base is None else fk.fk_single(self._rigid_base, reached)
        use = self._nets_apply(q[None])
        position, orientation = (True, True) if use is True else use[0]
        compiled = self._pose_operands()
        if compiled is not None:
            stage, p_net, o_net = compiled
            x = np.ascontiguousarray(self.net_inputs(q))
            return pose_kernel.hybrid_pose(
                np.ascontiguousarray(reached),
                x,
                *stage,
                position and "position" in self.nets,
                p_net,
                orientation and "orientation" in self.nets,
                o_net,
            )
        T = self.base.fk_single(reached) if self._rigid_base is None else fk.fk_single(self._rigid_base, reached)
        if not (position or orientation):
            return T
        if not all(self._fast.values()):
            dp, w = self.residuals(q[None])
            return self.correct(T[None], dp * position, w * orientation)[0]
        x = self.net_inputs(q)
        if "position" in self._fast and position:
            T[:3, 3] += self._fast["position"](x)
        if "orientation" in self._fast and orientation:
            T[:3, :3] = exp_so3(self._fast["orientation"](x)) @ T[:3, :3]
        return T

    def _pose_operands(self) -> tuple | None:
        """``pose_kernel.hybrid_pose``'s operands after the joints and the nets' input: the stage's, then the
        position and the orientation net's (an absent net's slot holds the other's, unused); None where the
        kernel does not apply (a joint error map, or a net that is no plain MLP). Built once per stage: a
        model serving another payload (:meth:`with_payload`) has another."""
        cached = self._pose_cache
        if cached is None or cached[0] is not self.base:
            fast = [f for f in self._fast.values() if f is not None]
            stage = self.base.pose_operands
            if stage is None or len(fast) != len(self._fast):
                operands = None
            else:
                p_net, o_net = (self._fast.get(kind, fast[0]).kernel_operands for kind in ("position", "orientation"))
                operands = (stage, p_net, o_net)
            self._pose_cache = cached = (self.base, operands)
        return cached[1]

    def link_pose(self, link: str, q: np.ndarray, analytic: bool = False) -> np.ndarray:
        """``(4, 4)``: where ``link`` of the chain is at joints ``q (n,)``, in the base frame. The tip link, and
        every link fixed to it, come from this model's tip pose (what the robot really does there), or the
        URDF model's when ``analytic``; links between the joints from the URDF (the stage and the nets correct
        the tip only)."""
        frames = self.chain.link_frames
        if link not in frames:
            raise ModelError(f"'{link}' is not a link of the chain (its links: {', '.join(frames)})")
        k, offset = frames[link]
        q = np.asarray(q, dtype=float)
        if k == self.chain.dof - 1:
            return self.fk_single(q, analytic=analytic) @ np.linalg.inv(self.chain.post) @ offset
        if k < 0:
            return offset.copy()
        return fk.joint_frames(self.chain, q[None])[0, k] @ offset

    def fk_rows(self, q: list[float], analytic: bool = False) -> Rows:
        """:meth:`fk_single` as the top three rows of the 4x4 in Python floats, for ``n`` finite joint
        values: without numpy (see ``unrolled.py``) when the pose needs none, i.e. no nets and no
        parametric stage (or ``analytic``); else through :meth:`fk_single`."""
        rows_fk = self._rows_analytic if analytic else self._rows_model
        if rows_fk is None:
            return self.fk_single(np.array(q, dtype=float), analytic=analytic)[:3].tolist()
        return rows_fk(q)

    def fk_and_jacobian(self, q: np.ndarray, analytic: bool = False) -> tuple[np.ndarray, np.ndarray]:
        """Poses ``(B, 4, 4)`` and the geometric Jacobian ``(B, 6, n)`` of the hybrid (or analytic) model.

        The nets' part comes from autograd through the TorchScript modules.
        """
        q = fk.check_joints(self.chain, q)
        if analytic:
            return fk.fk_and_jacobian(self.chain, q)
        q = self.same_turn(q)
        T, J = self.base.fk_and_jacobian(self._approached(q))
        if not self.nets:
            return T, J
        qt = torch.tensor(self.net_inputs(q), requires_grad=True)
        grads, values = {}, {}
        for kind, net in self.nets.items():
            out = net(qt)
            rows = [torch.autograd.grad(out[:, i].sum(), qt, retain_graph=i < 2)[0] for i in range(3)]
            grads[kind] = torch.stack(rows, dim=1).numpy()[:, :, : self.chain.dof]
            values[kind] = out.detach().numpy()
        zeros = np.zeros((len(q), 3))
        dp, w = values.get("position", zeros), values.get("orientation", zeros)
        use = self._nets_apply(q, at=(dp, w))
        if use is not True:
            mask = {"position": use[:, :1].astype(float), "orientation": use[:, 1:].astype(float)}
            dp, w = dp * mask["position"], w * mask["orientation"]
            grads = {kind: g * mask[kind][:, :, None] for kind, g in grads.items()}
        hybrid = self.correct(T, dp, w)
        J = J.copy()
        if "position" in grads:
            J[:, :3] += grads["position"]
        if "orientation" in grads:
            r = Rotation.from_rotvec(w).as_matrix()
            # p = p_m + Δp is unchanged by the rotation; the angular part is ω_R = R ω_m + J_l(ω) dω/dq
            J[:, 3:] = r @ J[:, 3:] + left_jacobian_so3(w) @ grads["orientation"]
        return hybrid, J

    def fk_and_jacobian_single(self, q: np.ndarray, analytic: bool = False) -> tuple[np.ndarray, np.ndarray]:
        """One configuration: pose ``(4, 4)`` and geometric Jacobian ``(6, n)``, numpy throughout for MLP nets."""
        q = np.asarray(q, dtype=float)
        if analytic:
            return fk.fk_and_jacobian_single(self.chain, q)
        q = self.same_turn(q)
        T, J = self.base.fk_and_jacobian_single(self._approached(q))
        if not self.nets:
            return T, J
        use = self._nets_apply(q[None])
        position, orientation = (True, True) if use is True else use[0]
        if not (position or orientation):
            return T, J
        if not all(self._fast.values()) or not (position and orientation):
            T, J = self.fk_and_jacobian(q[None])
            return T[0], J[0]
        x, n = self.net_inputs(q), self.chain.dof
        if "position" in self._fast:
            dp, ddp = self._fast["position"].value_and_jacobian(x)
            T[:3, 3] += dp
            J[:3] += ddp[:, :n]
        if "orientation" in self._fast:
            w, dw = self._fast["orientation"].value_and_jacobian(x)
            dw = dw[:, :n]
            r = exp_so3(w)
            T[:3, :3] = r @ T[:3, :3]
            J[3:] = r @ J[3:] + left_jacobian_so3(w) @ dw
        return T, J

    @classmethod
    def analytic_only(cls, chain: Chain) -> HybridModel:
        return cls(chain)


def _frozen(values: np.ndarray | list[float]) -> np.ndarray:
    """A read-only copy of condition values: a model's own never change."""
    out = np.array(values, dtype=float)
    out.flags.writeable = False
    return out
