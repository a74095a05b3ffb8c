"""Time alignment of a 110 Hz joint stream with a 3 kHz tracker stream into calibration pairs.

The tracker stamps its samples with its own clock, ``t_tracker = t_robot + offset``. The offset is found
from the data: the tip speed computed from the joints (nominal FK) and the speed measured by the tracker
are the same curve in two clocks, so the best shift between them is the offset. A coarse grid search
over the speed profiles is refined by a bounded scalar minimisation on the interpolated curves.

Each joint stamp then gets the tracker pose interpolated at that instant (linear in position, slerp in
rotation) from the two bracketing samples. There is no extrapolation, no bridging of gaps longer than
``max_gap_s`` (a broken beam), and no sample taken while the joints move faster than ``max_joint_speed``.
Every rejection is counted by reason.
"""

from __future__ import annotations

from collections import Counter
from dataclasses import dataclass, field

import numpy as np
from scipy.optimize import minimize_scalar
from scipy.spatial.transform import Rotation

from hybrid_kinematics_ros.calibration.errors import CalibrationError
from hybrid_kinematics_ros.io.pairs import Pairs
from hybrid_kinematics_ros.io.raw_bag import RawRecording
from hybrid_kinematics_ros.kinematics import fk
from hybrid_kinematics_ros.kinematics.chain import Chain
from hybrid_kinematics_ros.kinematics.se3 import matrix_from_pose

NS = 1e-9


@dataclass(frozen=True)
class AlignOptions:
    max_gap_s: float = 0.02  # longest tracker gap bridged by interpolation
    max_joint_speed: float = 1.0  # rad/s, any joint
    offset_s: float | None = None  # known tracker-minus-robot clock offset; None: estimate it
    max_offset_s: float = 0.5  # search range of the estimate
    still_speed: float = 1e-4  # rad/s: below this the robot stands still (static mode)
    still_min_s: float = 0.0  # > 0: static mode, one averaged pair per still window at least this long


@dataclass
class AlignResult:
    pairs: Pairs
    offset_s: float
    rejected: Counter = field(default_factory=Counter)


def estimate_offset(chain: Chain, rec: RawRecording, max_offset_s: float = 0.5, window_s: float = 1.0) -> float:
    """Tracker-minus-robot clock offset (s) from the data.

    The tracker positions, shifted by a trial offset, are compared with the nominal FK of the joints. The
    nominal model is off by millimetres, but that error changes slowly with the configuration, so a
    linear trend is removed from the mismatch in windows of ``window_s``. What remains is dominated by
    ``velocity × timing error`` and vanishes at the right offset. A grid search is refined by a bounded
    scalar minimisation. Tracker positions are averaged over one joint period first, against the noise.
    """
    tj = (rec.joint_stamps - rec.joint_stamps[0]) * NS
    tp = (rec.pose_stamps - rec.joint_stamps[0]) * NS
    per_window = max(3, round(window_s / max(float(np.median(np.diff(tj))), 1e-6)))
    if len(tj) < 2 * per_window or len(tp) < 20:
        raise CalibrationError("too few samples to estimate the clock offset; record longer or give it explicitly")
    p_fk = fk.fk(chain, rec.q)[:, :3, 3]
    if np.ptp(p_fk, axis=0).max() < 1e-3:
        raise CalibrationError("the robot does not move: the clock offset cannot be estimated; give it explicitly")
    smooth = max(1, round(np.median(np.diff(tj)) / max(np.median(np.diff(tp)), 1e-9)))
    positions, times = rec.positions, tp
    if smooth > 1 and len(tp) > 2 * smooth:
        kernel = np.ones(smooth) / smooth
        positions = np.column_stack([np.convolve(positions[:, i], kernel, mode="valid") for i in range(3)])
        times = np.convolve(times, kernel, mode="valid")
    max_gap = 5.0 * float(np.median(np.diff(times)))  # beam breaks: interpolating across them is no data
    blocks = len(tj) // per_window
    used = blocks * per_window
    t_blocks = tj[:used].reshape(blocks, per_window)
    t_centred = t_blocks - t_blocks.mean(axis=1, keepdims=True)
    t_norm = np.sum(t_centred**2, axis=1, keepdims=True)

    def mismatch(offset: float) -> float:
        query = tj[:used] + offset
        valid = _bridged(query, times, max_gap)
        if valid.mean() < 0.5:
            return 1e9  # (m²) no overlap: worse than any real mismatch, and finite for the minimiser
        moved = np.column_stack([np.interp(query, times, positions[:, i]) for i in range(3)])
        e = (moved - p_fk[:used]).reshape(blocks, per_window, 3)
        e = e - e.mean(axis=1, keepdims=True)
        slope = np.einsum("bw,bwk->bk", t_centred, e) / t_norm
        residual = e - t_centred[..., None] * slope[:, None, :]
        ok = valid.reshape(blocks, per_window).all(axis=1)
        return float(np.mean(residual[ok] ** 2))

    grid = np.arange(-max_offset_s, max_offset_s + 1e-12, 0.002)
    costs = np.array([mismatch(o) for o in grid])
    if np.all(costs >= 1e9):
        raise CalibrationError("the joint and tracker streams do not overlap in time")
    best = float(grid[int(np.argmin(costs))])
    coarse = float(minimize_scalar(mismatch, bounds=(best - 0.003, best + 0.003), method="bounded").x)
    return _refine_offset(chain, tj, rec.q, p_fk, times, positions, coarse, max_gap)


def error_features(chain: Chain, q: np.ndarray) -> np.ndarray:
    """``(N, 3, m)``: a linear model of the nominal FK's position error, first order in the geometry.

    Columns: the rotation of every joint frame (a constant offset of that frame's origin), the lever
    ``−[p_tip − p_k]×`` of every frame (a small rotation of that frame), the positional Jacobian (joint
    zero offsets), and per-axis ``[1, sin kq, cos kq]`` (k = 1, 2) for what depends on the configuration
    otherwise, such as joint compliance.
    """
    frames = fk.joint_frames(chain, q)
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


def _refine_offset(
    chain: Chain,
    tj,
    q,
    p_fk,
    times,
    positions,
    offset: float,
    max_gap: float,
    rounds: int = 3,
    window_s: float = 20.0,
) -> float:
    """Joint least squares of the offset and a model of the nominal FK's error (:func:`error_features`).

    ``p_tracker(t + offset) − p_fk(t) ≈ F(q) β + v(t) δ``: the model error depends on the configuration
    only, the timing error ``v δ`` on the velocity, and vanishes while the robot stands still. ``β`` is
    fitted per window of ``window_s``: over a long recording one first-order model cannot follow the
    error across the whole workspace, and what it misses leaks into ``δ`` (0.12 ms after 10 minutes
    with one global fit, against 0.2 ms allowed). ``δ`` is shared; it comes from the velocity and
    mismatch residuals after each window's own fit (Frisch-Waugh-Lovell).
    """
    v = np.gradient(p_fk, tj, axis=0)
    features = error_features(chain, q)
    window = np.floor((tj - tj[0]) / window_s).astype(int)
    n_windows = window[-1] + 1
    if n_windows > 1 and np.sum(window == n_windows - 1) < 0.5 * np.sum(window == 0):
        window[window == n_windows - 1] = n_windows - 2  # a short last window joins the one before
    for _ in range(rounds):
        query = tj + offset
        valid = _bridged(query, times, max_gap)
        num = den = 0.0
        for w in np.unique(window):
            idx = np.flatnonzero(valid & (window == w))
            if 3 * len(idx) <= 2 * features.shape[2]:
                continue  # too few equations to fit this window's model
            moved = np.column_stack([np.interp(query[idx], times, positions[:, i]) for i in range(3)])
            design = features[idx].reshape(-1, features.shape[2])
            rhs = np.column_stack([(moved - p_fk[idx]).reshape(-1), v[idx].reshape(-1)])
            fitted = design @ np.linalg.lstsq(design, rhs, rcond=None)[0]
            r_e, r_v = (rhs - fitted).T
            num, den = num + r_v @ r_e, den + r_v @ r_v
        if den <= 0.0:
            raise CalibrationError("too few samples to estimate the clock offset; record longer or give it explicitly")
        # p_tracker(t + offset) = p_true(t + offset − true offset): δ is the excess of the trial offset
        offset -= num / den
    return offset


def align(
    chain: Chain, rec: RawRecording, options: AlignOptions | None = None, frame_id: str | None = None
) -> AlignResult:
    """Calibration pairs at the joint stamps, with the tracker poses interpolated there."""
    o = options or AlignOptions()
    names = tuple(rec.joint_names)
    if set(names) != set(chain.joint_names):
        raise CalibrationError(f"the recording has joints {list(names)}, the robot {list(chain.joint_names)}")
    order = [names.index(n) for n in chain.joint_names]
    rec = RawRecording(
        rec.joint_stamps,
        chain.joint_names,
        rec.q[:, order],
        rec.pose_stamps,
        rec.pose_frame,
        rec.positions,
        rec.quats,
        rec.truncated,
        rec.counts,
    )
    rejected: Counter = Counter()
    norms = np.linalg.norm(rec.quats, axis=1)
    good = np.all(np.isfinite(rec.positions), axis=1) & np.isfinite(norms) & (np.abs(norms - 1) < 1e-3)
    rejected["tracker_sample_invalid"] += int((~good).sum())
    rec.positions, rec.pose_stamps = rec.positions[good], rec.pose_stamps[good]
    rec.quats = rec.quats[good] / norms[good, None]
    offset = o.offset_s if o.offset_s is not None else estimate_offset(chain, rec, o.max_offset_s)
    t_query = rec.joint_stamps + round(offset * 1e9)  # joint stamps in the tracker's clock
    # the bracketing samples: before <= t < after, or both at t when a sample falls exactly on it
    after = np.searchsorted(rec.pose_stamps, t_query, side="left")
    last = len(rec.pose_stamps) - 1
    exact = (after <= last) & (rec.pose_stamps[np.minimum(after, last)] == t_query)
    before = np.where(exact, after, after - 1)
    outside = (before < 0) | (after >= len(rec.pose_stamps))
    rejected["outside_tracker_stream"] += int(outside.sum())
    b, a = np.clip(before, 0, len(rec.pose_stamps) - 1), np.clip(after, 0, len(rec.pose_stamps) - 1)
    gap = (rec.pose_stamps[a] - rec.pose_stamps[b]) * NS
    long_gap = ~outside & (gap > o.max_gap_s)
    rejected["tracker_gap"] += int(long_gap.sum())
    speed = np.abs(np.gradient(rec.q, rec.joint_stamps * NS, axis=0)).max(axis=1)
    fast = ~outside & ~long_gap & (speed > o.max_joint_speed)
    rejected["moving_too_fast"] += int(fast.sum())
    keep = ~outside & ~long_gap & ~fast
    if not keep.any():
        raise CalibrationError(f"no joint state could be paired with a tracker pose: rejected {dict(+rejected)}")
    b, a, tq = b[keep], a[keep], t_query[keep]
    span = (rec.pose_stamps[a] - rec.pose_stamps[b]).astype(float)
    w = np.where(span > 0, (tq - rec.pose_stamps[b]) / np.where(span > 0, span, 1.0), 0.0)
    position = (1 - w)[:, None] * rec.positions[b] + w[:, None] * rec.positions[a]
    rb, ra = Rotation.from_quat(rec.quats[b]), Rotation.from_quat(rec.quats[a])
    rotation = rb * Rotation.from_rotvec((rb.inv() * ra).as_rotvec() * w[:, None])  # slerp per pair
    T = matrix_from_pose(position, rotation.as_quat())
    pairs = Pairs(rec.q[keep], T, rec.joint_stamps[keep], chain.joint_names, frame_id or rec.pose_frame)
    if o.still_min_s > 0:
        pairs = static_pairs(pairs, speed[keep], o)
    return AlignResult(pairs, float(offset), +rejected)


def static_pairs(pairs: Pairs, speed: np.ndarray, o: AlignOptions) -> Pairs:
    """Static mode (the paper's industrial experiment): one pair per still window, averaged over it."""
    still = speed < o.still_speed
    edges = np.flatnonzero(np.diff(np.r_[0, still.astype(int), 0]))
    q, T, stamps = [], [], []
    for start, end in zip(edges[::2], edges[1::2], strict=True):
        if (pairs.stamps[end - 1] - pairs.stamps[start]) * NS < o.still_min_s:
            continue
        sl = slice(start, end)
        q.append(pairs.q[sl].mean(axis=0))
        mean_rot = Rotation.from_matrix(pairs.T[sl, :3, :3]).mean()
        t = np.eye(4)
        t[:3, :3] = mean_rot.as_matrix()
        t[:3, 3] = pairs.T[sl, :3, 3].mean(axis=0)
        T.append(t)
        stamps.append(pairs.stamps[(start + end) // 2])
    if not q:
        raise CalibrationError(f"static mode: no still window of at least {o.still_min_s} s")
    return Pairs(np.array(q), np.array(T), np.array(stamps), pairs.joint_names, pairs.frame_id)
