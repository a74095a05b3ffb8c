"""The tracker's clock against the robot's, estimated from the motion both streams see.

The tracker stamps its samples with its own clock, ``t_tracker = t_robot + offset + skew · t``, and measures
in its own frame. Both clock parameters are found from the data (:func:`estimate_clock`): first from the tip
speed, which is the same in every frame, then, with the tracker frame fitted, from the positions jointly with
a model of the nominal FK's error (:func:`error_features`). Pairing the streams with a known clock is
``calibration/alignment.py``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.linalg import svd
from scipy.optimize import minimize_scalar

from hybrid_kinematics_ros.calibration.errors import CalibrationError
from hybrid_kinematics_ros.io.raw_bag import RawRecording
from hybrid_kinematics_ros.kinematics import fk
from hybrid_kinematics_ros.kinematics.chain import Chain

NS = 1e-9


@dataclass(frozen=True)
class Clock:
    """The tracker clock against the robot's: ``t_tracker = t_robot + offset_s + skew · (t_robot − ref_ns)``.

    A constant offset is not enough on a real cell: two free-running quartz clocks drift apart by tens of
    ppm, 20 ppm being 12 ms after 10 minutes.
    """

    offset_s: float  # at ref_ns
    skew: float = 0.0  # dimensionless; 1e-6 is 1 ppm
    ref_ns: int = 0

    @property
    def skew_ppm(self) -> float:
        return self.skew * 1e6

    def offset_at(self, stamps_ns: np.ndarray) -> np.ndarray:
        """Offset (s) at robot stamps (ns)."""
        return self.offset_s + self.skew * (np.asarray(stamps_ns) - self.ref_ns) * NS

    def to_tracker(self, stamps_ns: np.ndarray) -> np.ndarray:
        """Robot stamps (ns) in the tracker's clock (ns)."""
        stamps_ns = np.asarray(stamps_ns, dtype=np.int64)
        return stamps_ns + np.round(self.offset_at(stamps_ns) * 1e9).astype(np.int64)


def estimate_offset(chain: Chain, rec: RawRecording, max_offset_s: float = 0.5) -> float:
    """Tracker-minus-robot clock offset (s) at the middle of the recording; see :func:`estimate_clock`."""
    clock = estimate_clock(chain, rec, max_offset_s)
    return float(clock.offset_at(np.array([(rec.joint_stamps[0] + rec.joint_stamps[-1]) // 2]))[0])


SKEW_MIN_SPAN_S = 120.0


def estimate_clock(
    chain: Chain,
    rec: RawRecording,
    max_offset_s: float = 0.5,
    window_s: float = 1.0,
    skew_min_span_s: float = SKEW_MIN_SPAN_S,
) -> Clock:
    """The tracker's clock (offset and skew) from the data, in whatever frame the tracker measures.

    1. Coarse offset from the tip speed ``|v|``: the speed is the same in every rigid frame, so the FK
       speed in the base frame and the tracker's in its own frame are one curve in two clocks.
    2. The tracker frame (and the target's offset on the flange) by linear least squares at that offset,
       which puts the tracker positions into the base frame.
    3. There, the position mismatch (a linear trend removed in windows of ``window_s``, which takes out
       the nominal FK's slowly varying error) is minimised near the coarse offset.
    4. :class:`_Refinement` solves for offset and skew jointly with a model of the FK's error; the frame
       is fitted again with the refined clock and the refinement repeated. The skew is estimated on
       recordings of ``skew_min_span_s`` or more only: over a shorter one the FK error model's misfit looks
       like a skew of a real clock's size, and moves the offset as much as that skew would.

    Tracker positions are averaged over one joint period first, against the noise.
    """
    streams = _Streams.of(chain, rec, window_s)
    clock = Clock(streams.speed_offset(max_offset_s), 0.0, 0)
    base, target = _to_base_frame(streams, clock)
    clock = Clock(streams.position_offset(base, target, clock.offset_s), 0.0, 0)
    refine = _Refinement(streams, skew=streams.tj[-1] - streams.tj[0] >= skew_min_span_s)
    for _ in range(2):
        clock = refine(target, base, clock)
        base, target = _to_base_frame(streams, clock)
    clock = refine(target, base, clock)
    return Clock(clock.offset_s, clock.skew, int(rec.joint_stamps[0]))


@dataclass(frozen=True)
class _Streams:
    """Both streams on the robot's time axis (s from its first joint state): the joints with their FK
    frames, and the tracker positions averaged over one joint period (``times``, ``positions``). A query
    between two tracker samples more than ``max_gap`` apart (a beam break) is no data."""

    chain: Chain
    tj: np.ndarray
    q: np.ndarray
    frames: np.ndarray
    times: np.ndarray
    positions: np.ndarray
    max_gap: float
    per_window: int  # joint states in one window of the position mismatch

    @classmethod
    def of(cls, chain: Chain, rec: RawRecording, window_s: float) -> _Streams:
        tj = (rec.joint_stamps - rec.joint_stamps[0]) * NS
        tp = (rec.pose_stamps - rec.joint_stamps[0]) * NS
        per_window = max(3, round(window_s / max(float(np.median(np.diff(tj))), 1e-6))) if len(tj) > 1 else 3
        if len(tj) < 2 * per_window or len(tp) < 20:
            raise CalibrationError("too few samples to estimate the clock offset; record longer or give it explicitly")
        frames = fk.joint_frames(chain, rec.q)
        if np.ptp(frames[:, -1, :3, 3], axis=0).max() < 1e-3:
            raise CalibrationError("the robot does not move: the clock offset cannot be estimated; give it explicitly")
        smooth = max(1, round(np.median(np.diff(tj)) / max(np.median(np.diff(tp)), 1e-9)))
        positions, times = rec.positions, tp
        if smooth > 1 and len(tp) > 2 * smooth:
            kernel = np.ones(smooth) / smooth
            step = max(1, smooth // 3)  # the averages change smoothly: keep about three a joint period, for speed
            # one column at a time, thinned at once: the full averages of 2 minutes at 3 kHz are 12 MB a column
            positions = np.column_stack(
                [np.convolve(positions[:, i], kernel, mode="valid")[::step].copy() for i in range(3)]
            )
            times = np.convolve(times, kernel, mode="valid")[::step].copy()
        max_gap = 5.0 * float(np.median(np.diff(times)))  # beam breaks: interpolating across them is no data
        return cls(chain, tj, rec.q, frames, times, positions, max_gap, per_window)

    @property
    def tip(self) -> np.ndarray:
        return self.frames[:, -1]

    def at(self, query: np.ndarray, positions: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """The (averaged) tracker positions, or ``positions`` on the same times, at robot times ``query``,
        and where they are data."""
        pos = self.positions if positions is None else positions
        valid = _bridged(query, self.times, self.max_gap)
        return np.column_stack([np.interp(query, self.times, pos[:, i]) for i in range(3)]), valid

    def speed_offset(self, max_offset_s: float) -> float:
        """Step 1: the offset (s) on a 2 ms grid within ``±max_offset_s`` that matches the tip speeds best,
        on at most the middle two minutes (enough to land within the next step's ±10 ms, whatever the drift)."""
        tj = self.tj
        middle = np.flatnonzero(np.abs(tj - 0.5 * (tj[0] + tj[-1])) <= 60.0)
        t_mid = tj[middle]
        v_fk = np.linalg.norm(np.gradient(self.tip[middle, :3, 3], t_mid, axis=0), axis=1)

        def speed_mismatch(offset: float) -> float:
            moved, valid = self.at(t_mid + offset)
            valid = valid & np.r_[valid[1:], False] & np.r_[False, valid[:-1]]  # gradients next to a gap: no data
            if valid.mean() < 0.5:
                return np.inf
            v = np.linalg.norm(np.gradient(moved, t_mid, axis=0), axis=1)
            return float(np.mean((v - v_fk)[valid] ** 2))

        grid = np.arange(-max_offset_s, max_offset_s + 1e-12, 0.002)
        costs = np.array([speed_mismatch(o) for o in grid])
        if not np.isfinite(costs).any():
            raise CalibrationError("the joint and tracker streams do not overlap in time")
        return float(grid[int(np.argmin(costs))])

    def position_offset(self, base: np.ndarray, target: np.ndarray, near_s: float) -> float:
        """Step 3: the offset (s) within 10 ms of ``near_s`` where the tracker positions in the base frame
        (``base``) match the FK's target positions best, a linear trend removed in each window."""
        p_target = p_tip_all(self.tip, target)
        blocks = len(self.tj) // self.per_window
        used = blocks * self.per_window
        t_blocks = self.tj[:used].reshape(blocks, self.per_window)
        t_centred = t_blocks - t_blocks.mean(axis=1, keepdims=True)
        t_norm = np.sum(t_centred**2, axis=1, keepdims=True)

        def mismatch(offset: float) -> float:
            moved, valid = self.at(self.tj[:used] + offset, base)
            if valid.mean() < 0.5:
                return 1e9  # (m²) no overlap: worse than any real mismatch, and finite for the minimiser
            e = (moved - p_target[:used]).reshape(blocks, self.per_window, 3)
            e = e - e.mean(axis=1, keepdims=True)
            slope = np.einsum("bw,bwk->bk", t_centred, e) / t_norm
            residual = e - t_centred[..., None] * slope[:, None, :]
            ok = valid.reshape(blocks, self.per_window).all(axis=1)
            return float(np.mean(residual[ok] ** 2))

        near = near_s + np.arange(-0.01, 0.01 + 1e-12, 0.001)
        best = float(near[int(np.argmin([mismatch(o) for o in near]))])
        return float(minimize_scalar(mismatch, bounds=(best - 0.0015, best + 0.0015), method="bounded").x)


def _to_base_frame(streams: _Streams, clock: Clock) -> tuple[np.ndarray, np.ndarray]:
    """Tracker positions in the base frame and the target's offset on the flange, for a trial clock.

    ``p_tip + R_tip t = R p_tracker + c`` is linear in the tracker frame ``(R, c)`` and the target's
    offset ``t`` on the flange; ``R`` is solved for unconstrained, projected onto the rotations, and ``c``
    and ``t`` solved again for it. Position-only data is enough.
    """
    tip, tj = streams.tip, streams.tj
    moved, valid = streams.at(tj + clock.offset_s + clock.skew * tj)
    idx = np.flatnonzero(valid)
    idx = idx[:: max(1, len(idx) // 5000)]
    if len(idx) < 20:
        raise CalibrationError("too few tracker samples overlap the joint states to relate the tracker frame")
    r_tip, p_tip = tip[idx, :3, :3], tip[idx, :3, 3]
    m = len(idx)
    design = np.zeros((m, 3, 15))
    for k in range(3):
        design[:, k, 3 * k : 3 * k + 3] = moved[idx]
        design[:, k, 9 + k] = 1.0
    design[:, :, 12:] = -r_tip
    if np.linalg.matrix_rank(design.reshape(-1, 15), tol=1e-6) < 15:
        raise CalibrationError(
            "the motion spans too little of the workspace to relate the tracker frame to the robot's; "
            "give the clock offset explicitly"
        )
    x = np.linalg.lstsq(design.reshape(-1, 15), p_tip.reshape(-1), rcond=None)[0]
    u, _, vt = np.linalg.svd(x[:9].reshape(3, 3))
    rot = u @ np.diag([1.0, 1.0, np.linalg.det(u @ vt)]) @ vt
    rest = np.concatenate([np.tile(np.eye(3), (m, 1, 1)), -r_tip], axis=2).reshape(-1, 6)
    c_t = np.linalg.lstsq(rest, (p_tip - moved[idx] @ rot.T).reshape(-1), rcond=None)[0]
    return streams.positions @ rot.T + c_t[:3], c_t[3:]


def p_tip_all(tip: np.ndarray, target: np.ndarray) -> np.ndarray:
    """Positions of a target at ``target`` (flange frame) for tip poses ``(N, 4, 4)``."""
    return tip[:, :3, 3] + tip[:, :3, :3] @ target


def error_features(chain: Chain, q: np.ndarray, frames: np.ndarray | None = None) -> np.ndarray:
    """``(N, 3, m)``: a linear model of the nominal FK's position error, first order in the geometry.

    Columns: the rotation of every joint frame (a constant offset of that frame's origin), the lever
    ``−[p_tip − p_k]×`` of every frame (a small rotation of that frame), the positional Jacobian (joint
    zero offsets), and per-axis ``[1, sin kq, cos kq]`` (k = 1, 2) for what depends on the configuration
    otherwise, such as joint compliance.
    """
    frames = fk.joint_frames(chain, q) if frames is None else frames
    tip = frames[:, -1, :3, 3]
    n = len(q)
    blocks = [frames[:, k, :3, :3] for k in range(frames.shape[1])]
    for k in range(frames.shape[1] - 1):
        lever = tip - frames[:, k, :3, 3]
        skew = np.zeros((n, 3, 3))
        skew[:, 0, 1], skew[:, 0, 2], skew[:, 1, 2] = -lever[:, 2], lever[:, 1], -lever[:, 0]
        skew[:, 1, 0], skew[:, 2, 0], skew[:, 2, 1] = lever[:, 2], -lever[:, 1], lever[:, 0]
        blocks.append(-skew)
    blocks.append(fk.jacobian_from_frames(chain, frames)[:, :3])
    phi = np.hstack([np.ones((n, 1)), np.sin(q), np.cos(q), np.sin(2 * q), np.cos(2 * q)])
    per_axis = np.zeros((n, 3, 3 * phi.shape[1]))
    for axis in range(3):
        per_axis[:, axis, axis * phi.shape[1] : (axis + 1) * phi.shape[1]] = phi
    blocks.append(per_axis)
    return np.concatenate(blocks, axis=2)


def _bridged(query: np.ndarray, times: np.ndarray, max_gap: float) -> np.ndarray:
    """True where ``query`` lies between two samples of ``times`` at most ``max_gap`` apart."""
    after = np.clip(np.searchsorted(times, query), 1, len(times) - 1)
    inside = (query >= times[0]) & (query <= times[-1])
    return inside & (times[after] - times[after - 1] <= max_gap)


REFINE_ROUNDS = 3  # Gauss-Newton steps of the clock; each window's basis is computed once
REFINE_WINDOW_S = 20.0  # the span of one FK error model


class _Refinement:
    """Step 4, joint least squares of offset, skew and a model of the nominal FK's error (:func:`error_features`).

    ``p_tracker(t + o(t)) − p_fk(t) ≈ F(q) β + v(t) (δ + σ (t − t̄))``: the model error depends on the
    configuration only, the timing error on the velocity, and vanishes while the robot stands still.
    ``β`` is fitted per window of ``REFINE_WINDOW_S``: over a long recording one first-order model cannot
    follow the error across the whole workspace, and what it misses leaks into the clock (after ten minutes,
    with one global fit, most of the timing error allowed). ``δ`` and ``σ`` are shared; they come from
    the velocity and mismatch residuals after each window's own fit (Frisch-Waugh-Lovell).

    Memory stays that of one window: the features are built per window, and only the velocity columns
    projected off each window's model are kept (:func:`_projected_velocity`), not the model's basis; the
    mismatch needs no projection of its own, ``(P r₁)ᵀ m = r₁ᵀ m`` for the projected columns ``r₁``.
    (Every window's features and bases at once would take gigabytes on an hour-long recording.)
    """

    def __init__(self, streams: _Streams, skew: bool) -> None:
        self.s = streams
        self.fit_skew = skew
        self.cache: dict = {}  # each window's projected velocity columns, reused by every call

    def __call__(self, target: np.ndarray, positions: np.ndarray, clock: Clock) -> Clock:
        """The clock refined from ``clock``, with the tracker ``positions`` in the base frame and the
        target at ``target`` on the flange."""
        s = self.s
        tj = s.tj
        p_fk = p_tip_all(s.tip, target)
        window = self._windows()
        t_mid = 0.5 * (tj[0] + tj[-1])
        offset, skew = clock.offset_s + clock.skew * t_mid, clock.skew  # at t_mid: offset and skew uncorrelated
        # samples usable within ±5 ms of the starting clock: a fixed set, so each window's basis is computed once
        start = tj + offset + skew * (tj - t_mid)
        valid = np.logical_and.reduce([_bridged(start + d, s.times, s.max_gap) for d in (-0.005, 0.0, 0.005)])
        # the velocity of the target is linear in its offset on the flange: v = v_tip + Σ_k v_(R e_k) target_k
        weights = np.r_[1.0, target]
        n_features = error_features(s.chain, s.q[:1], s.frames[:1]).shape[2]
        for _ in range(REFINE_ROUNDS):
            query = tj + offset + skew * (tj - t_mid)
            normal, rhs_total = np.zeros((2, 2)), np.zeros(2)
            for w in np.unique(window):
                idx = np.flatnonzero(valid & (window == w))
                if 3 * len(idx) <= 2 * n_features:
                    continue  # too few equations to fit this window's model
                moved = np.column_stack([np.interp(query[idx], s.times, positions[:, i]) for i in range(3)])
                parts = _projected_velocity(s, idx, t_mid, (w, idx.tobytes()), self.cache)
                r = parts @ weights  # (3 n, 2): velocity and velocity · (t − t̄), off the window's model
                normal += r.T @ r
                rhs_total += r.T @ (moved - p_fk[idx]).reshape(-1)
            step = self._step(normal, rhs_total)
            # p_tracker(t + o) = p_true(t + o − true o): the step is the excess of the trial clock
            offset, skew = offset - step[0], skew - step[1]
        return Clock(offset - skew * t_mid, skew, 0)

    def _windows(self) -> np.ndarray:
        """Each joint state's window; a short last window joins the one before."""
        tj = self.s.tj
        window = np.floor((tj - tj[0]) / REFINE_WINDOW_S).astype(int)
        n_windows = window[-1] + 1
        if n_windows > 1 and np.sum(window == n_windows - 1) < 0.5 * np.sum(window == 0):
            window[window == n_windows - 1] = n_windows - 2
        return window

    def _step(self, normal: np.ndarray, rhs: np.ndarray) -> np.ndarray:
        """The (offset, skew) step from the normal equations; no skew when it is not fitted or the motion
        stays in one place."""
        if normal[0, 0] <= 0.0:
            raise CalibrationError("too few samples to estimate the clock offset; record longer or give it explicitly")
        if not self.fit_skew or normal[1, 1] * normal[0, 0] - normal[0, 1] ** 2 <= 1e-12 * normal[1, 1] * normal[0, 0]:
            return np.array([rhs[0] / normal[0, 0], 0.0])
        return np.linalg.solve(normal, rhs)


def _projected_velocity(streams: _Streams, idx: np.ndarray, t_mid: float, key: tuple, cache: dict) -> np.ndarray:
    """``(3 n, 2, 4)``: the parts of the target's velocity (tip, and the flange's three axes) and the same
    times ``t − t̄``, projected off the span of one window's FK error features, cached by ``key``.

    The span is the one of an SVD basis, computed once per window's samples (the factorisation is most of
    the refinement's cost). Directions down to 1e-13 of the largest singular value are kept: the weak ones
    carry model structure, and dropping those below 1e-10 moves the offset by about a tenth of a millisecond
    on a short recording (so does a basis from the Gram matrix, which squares the condition number). scipy's
    divide-and-conquer SVD: numpy's least squares is many times slower here.
    """
    if key not in cache:
        # the gradient at a window's samples needs their neighbours: it is taken on the whole series, lazily
        tj, frames = streams.tj, streams.frames
        if "velocity" not in cache:
            tip = frames[:, -1]
            cache["velocity"] = np.stack(
                [np.gradient(tip[:, :3, 3], tj, axis=0)] + [np.gradient(tip[:, :3, k], tj, axis=0) for k in range(3)],
                axis=2,
            )  # (N, 3, 4)
        v = cache["velocity"][idx]
        dt = (tj[idx] - t_mid)[:, None, None]
        columns = np.stack([v, v * dt], axis=2).reshape(-1, 2, 4)  # (3 n, 2, 4)
        design = error_features(streams.chain, streams.q[idx], frames[idx]).reshape(3 * len(idx), -1)
        u, s, _ = svd(design, full_matrices=False, lapack_driver="gesdd")
        del design
        u = u[:, s > 1e-13 * s[0]]
        flat = columns.reshape(len(u), -1)
        cache[key] = (flat - u @ (u.T @ flat)).reshape(columns.shape)
    return cache[key]
