"""Time alignment of a 110 Hz joint stream with a 3 kHz tracker stream into calibration pairs.

The tracker's clock is given or estimated (``calibration/clock.py``). Each joint stamp then gets the tracker
pose interpolated at that instant (linear in position, slerp in rotation; position only for a plain
reflector, whose quaternions are zero) from the two bracketing samples. Unusable raw samples (NaN, repeated
stamps, non-unit quaternions) are dropped first. There is no extrapolation, no bridging of gaps longer than
``max_gap_s`` (a broken beam), and no sample taken while the joints move faster than ``max_joint_speed``.
Every rejection is counted by reason. Static mode averages one pair per still window.
"""

from __future__ import annotations

from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from scipy.ndimage import maximum_filter1d, minimum_filter1d
from scipy.spatial.transform import Rotation, Slerp

from hybrid_kinematics_ros.calibration.clock import NS, Clock, estimate_clock
from hybrid_kinematics_ros.calibration.errors import CalibrationError
from hybrid_kinematics_ros.io.pairs import RAW_JOINTS_TOPIC, RAW_POSE_TOPIC, Pairs
from hybrid_kinematics_ros.io.raw_bag import RawRecording, read_raw
from hybrid_kinematics_ros.kinematics.chain import Chain
from hybrid_kinematics_ros.kinematics.se3 import matrix_from_pose


@dataclass(frozen=True)
class AlignOptions:
    max_gap_s: float = 0.02  # longest tracker gap bridged by interpolation
    max_joint_speed: float = 1.0  # rad/s, any joint
    offset_s: float | None = None  # known tracker-minus-robot clock offset at the first joint stamp; None: estimate
    skew_ppm: float = 0.0  # with offset_s: the known tracker clock's skew against the robot's
    max_offset_s: float = 0.5  # search range of the estimate
    # static mode: still while no joint moves more than this within still_window_s (or 6 sigma of the
    # encoder noise measured in the data, if more): a few counts of a 20-bit encoder (6e-6 rad a count)
    still_tolerance_rad: float = 2e-5
    still_window_s: float = 0.1
    still_min_s: float = 0.0  # > 0: static mode, one averaged pair per still window at least this long


ALL = (-(2**62), 2**62)  # a stamp range (ns) that holds every stamp


@dataclass(frozen=True)
class Window:
    """The part of a longer recording that one :func:`align` call answers for (windowed alignment).

    Joint states with stamps in ``[joint_lo, joint_hi)`` (robot clock) give pairs and count as rejected;
    tracker samples count as rejected in ``[tracker_lo, tracker_hi)`` (tracker clock). Samples outside are
    context: they bracket, interpolate and give derivatives and still windows, but are the neighbouring
    window's to pair and count. In static mode a still window belongs to the window its first sample is in.
    """

    joint_lo: int = ALL[0]
    joint_hi: int = ALL[1]
    tracker_lo: int = ALL[0]
    tracker_hi: int = ALL[1]


@dataclass
class AlignResult:
    pairs: Pairs
    offset_s: float  # tracker minus robot clock at the first joint stamp
    rejected: Counter = field(default_factory=Counter)
    skew_ppm: float = 0.0  # how fast the offset grows: 1 ppm is 1 µs per second


def align(
    chain: Chain,
    rec: RawRecording,
    options: AlignOptions | None = None,
    frame_id: str | None = None,
    *,
    clock: Clock | None = None,
    window: Window | None = None,
) -> AlignResult:
    """Calibration pairs at the joint stamps, with the tracker poses interpolated there.

    ``clock``: the tracker's clock, known already (windowed alignment); it overrides ``options.offset_s``.
    ``window``: answer for that part of ``rec`` only (see :class:`Window`); a window without a pair then
    gives empty pairs instead of an error.
    """
    o = options or AlignOptions()
    w = window or Window()
    rec, rejected, position_only = clean(_in_chain_order(rec, chain), w)
    if clock is None and o.offset_s is not None:
        clock = Clock(o.offset_s, o.skew_ppm * 1e-6, int(rec.joint_stamps[0]))
    elif clock is None:
        clock = estimate_clock(chain, rec, o.max_offset_s)
    t_query = clock.to_tracker(rec.joint_stamps)  # joint stamps in the tracker's clock
    b, a, keep = _brackets(rec, t_query, o, w, rejected)
    if not keep.any():
        if window is not None:
            empty = _no_pairs(chain, frame_id or rec.pose_frame, position_only)
            return AlignResult(empty, float(clock.offset_at(rec.joint_stamps[:1])[0]), +rejected, clock.skew_ppm)
        raise CalibrationError(f"no joint state could be paired with a tracker pose: rejected {dict(+rejected)}")
    T = _interpolated(rec, b[keep], a[keep], t_query[keep], position_only)
    frame = frame_id or rec.pose_frame
    pairs = Pairs(rec.q[keep], T, rec.joint_stamps[keep], chain.joint_names, frame, position_only=position_only)
    if o.still_min_s > 0:
        starts = (w.joint_lo, w.joint_hi) if window is not None else None
        pairs = static_pairs(pairs, still_mask(rec.q, rec.joint_stamps, o)[keep], o, starts)
    offset = float(clock.offset_at(rec.joint_stamps[:1])[0])
    return AlignResult(pairs, offset, +rejected, float(clock.skew_ppm))


def _in_chain_order(rec: RawRecording, chain: Chain) -> RawRecording:
    """``rec`` with its joints in the chain's order; a recording of other joints is an error."""
    names = tuple(rec.joint_names)
    if set(names) != set(chain.joint_names):
        raise CalibrationError(f"the recording has joints {list(names)}, the robot {list(chain.joint_names)}")
    order = [names.index(n) for n in chain.joint_names]
    return RawRecording(
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


def _brackets(
    rec: RawRecording, t_query: np.ndarray, o: AlignOptions, w: Window, rejected: Counter
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The tracker samples before and after each joint stamp (``t_query``, in the tracker's clock), and
    which joint stamps pair; the others are counted in ``rejected`` by reason (only those in the window)."""
    # the bracketing samples: before <= t < after, or both at t when a sample falls exactly on it
    after = np.searchsorted(rec.pose_stamps, t_query, side="left")
    last = len(rec.pose_stamps) - 1
    exact = (after <= last) & (rec.pose_stamps[np.minimum(after, last)] == t_query)
    before = np.where(exact, after, after - 1)
    outside = (before < 0) | (after >= len(rec.pose_stamps))
    mine = (rec.joint_stamps >= w.joint_lo) & (rec.joint_stamps < w.joint_hi)  # what this call counts
    rejected["outside_tracker_stream"] += int((outside & mine).sum())
    b, a = np.clip(before, 0, last), np.clip(after, 0, last)
    gap = (rec.pose_stamps[a] - rec.pose_stamps[b]) * NS
    long_gap = ~outside & (gap > o.max_gap_s)
    rejected["tracker_gap"] += int((long_gap & mine).sum())
    speed = np.abs(np.gradient(rec.q, rec.joint_stamps * NS, axis=0)).max(axis=1)
    fast = ~outside & ~long_gap & ~(speed <= o.max_joint_speed)  # NaN is fast, not slow
    rejected["moving_too_fast"] += int((fast & mine).sum())
    keep = ~outside & ~long_gap & ~fast
    if o.still_min_s <= 0:
        keep &= mine  # (static mode: context samples complete still windows across the window's edges)
    return b, a, keep


def _interpolated(rec: RawRecording, b: np.ndarray, a: np.ndarray, tq: np.ndarray, position_only: bool) -> np.ndarray:
    """``(N, 4, 4)``: the tracker poses at ``tq`` between samples ``b`` and ``a``: positions linearly,
    orientations by Slerp (identity placeholders for position-only data, as ``read_pairs`` makes them)."""
    span = (rec.pose_stamps[a] - rec.pose_stamps[b]).astype(float)
    w = np.where(span > 0, (tq - rec.pose_stamps[b]) / np.where(span > 0, span, 1.0), 0.0)
    position = (1 - w)[:, None] * rec.positions[b] + w[:, None] * rec.positions[a]
    if position_only:
        return matrix_from_pose(position, np.tile([0.0, 0.0, 0.0, 1.0], (len(position), 1)))
    # the samples around the pairs only (two minutes of 3 kHz poses cost Slerp ~100 MB): each pair's
    # bracket, and the sample before it, which Slerp interpolates from when a stamp falls on a sample
    used = np.unique(np.r_[np.maximum(b - 1, 0), b, a])
    if len(used) < 2:
        used = np.unique(np.r_[used, min(int(used[0]) + 1, len(rec.pose_stamps) - 1)])
    t0 = rec.pose_stamps[0]
    slerp = Slerp((rec.pose_stamps[used] - t0) * NS, Rotation.from_quat(rec.quats[used]))
    return matrix_from_pose(position, slerp((tq - t0) * NS).as_quat())


def clean(rec: RawRecording, window: Window | None = None) -> tuple[RawRecording, Counter, bool]:
    """Drop unusable raw samples, counted by reason as :func:`read_pairs` does: non-finite values, repeated
    stamps (the first is kept; a zero time step makes derivatives NaN), and quaternions off unit length.

    Zero quaternions on every finite sample mean a plain reflector: position only (the third value).
    ``window``: count only the samples in its ranges (the others are counted by the neighbouring windows).
    """
    w = window or Window()
    rejected: Counter = Counter()
    jt, q = _unique_stamps(rec.joint_stamps, rec.q, "joint_state", rejected, (w.joint_lo, w.joint_hi))
    finite = np.all(np.isfinite(q), axis=1)
    in_j = (jt >= w.joint_lo) & (jt < w.joint_hi)
    rejected["joint_state_nan_or_inf"] += int(np.sum(~finite & in_j))
    jt, q = _keep(finite, jt, q)
    # the tracker: one mask for every reason, and the arrays copied once at most (two minutes at 3 kHz are
    # 20 MB a copy), counted as if the reasons were applied one after the other
    pt, positions, quats = rec.pose_stamps, rec.positions, rec.quats
    if len(pt) > 1 and not bool(np.all(pt[1:] >= pt[:-1])):
        order = np.argsort(pt, kind="stable")
        pt, positions, quats = pt[order], positions[order], quats[order]
    counted = (pt >= w.tracker_lo) & (pt < w.tracker_hi)
    first = np.r_[True, np.diff(pt) != 0][: len(pt)]
    rejected["tracker_duplicate_stamp"] += int(np.sum(~first & counted))
    finite = first & np.all(np.isfinite(positions), axis=1)
    position_only = bool(np.any(finite)) and bool(np.all(np.all(quats == 0.0, axis=1)[finite]))
    if not position_only:
        finite &= np.all(np.isfinite(quats), axis=1)
    rejected["tracker_nan_or_inf"] += int(np.sum(first & ~finite & counted))
    keep = finite
    if not position_only:
        norms = np.linalg.norm(quats, axis=1)
        keep = finite & (np.abs(norms - 1.0) < 1e-3)
        rejected["tracker_non_unit_quaternion"] += int(np.sum(finite & ~keep & counted))
    pt, positions = _keep(keep, pt, positions)
    quats = quats[keep] if position_only else quats[keep] / norms[keep, None]
    if not len(jt) or not len(pt):
        raise CalibrationError(f"no usable samples: {len(jt)} joint states, {len(pt)} tracker poses; {dict(+rejected)}")
    cleaned = RawRecording(jt, rec.joint_names, q, pt, rec.pose_frame, positions, quats, rec.truncated, rec.counts)
    return cleaned, rejected, position_only


def _unique_stamps(
    stamps: np.ndarray, values: np.ndarray, what: str, rejected: Counter, counted: tuple[int, int] = ALL
) -> tuple:
    """Samples sorted by stamp with repeated stamps dropped (the first kept); those in ``counted`` counted."""
    if len(stamps) > 1 and not bool(np.all(stamps[1:] >= stamps[:-1])):
        order = np.argsort(stamps, kind="stable")
        stamps, values = stamps[order], values[order]
    first = np.r_[True, np.diff(stamps) != 0]
    rejected[f"{what}_duplicate_stamp"] += int(np.sum(~first & (stamps >= counted[0]) & (stamps < counted[1])))
    return _keep(first, stamps, values)


def _keep(mask: np.ndarray, stamps: np.ndarray, values: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The rows where ``mask`` holds; the arrays themselves when it holds everywhere (a copy of two minutes
    of tracker poses is 20 MB, and clean samples are the rule)."""
    if bool(np.all(mask)):
        return stamps, values
    return stamps[mask], values[mask]


def still_mask(q: np.ndarray, stamps: np.ndarray, o: AlignOptions) -> np.ndarray:
    """True where the robot stands still: no joint moves more than a tolerance within ``still_window_s``.

    A speed threshold does not work on real encoders: a 110 Hz difference of readings quantised to 6e-6
    rad is 7e-4 rad/s of noise, above any sensible "still" speed. The displacement within a window is
    bounded by a few counts instead. The tolerance is ``still_tolerance_rad`` or 6 σ of the encoder
    noise, whichever is larger; σ comes from the second differences of the readings (white noise gives
    them a variance of 6 σ²; their median absolute deviation ignores the motion, which is smooth).
    """
    if len(q) < 3:
        return np.zeros(len(q), dtype=bool)
    period = float(np.median(np.diff(stamps))) * NS
    size = max(3, round(o.still_window_s / max(period, 1e-9)) | 1)  # odd: a centred window
    second = np.diff(q, 2, axis=0)
    mad = np.median(np.abs(second - np.median(second, axis=0)), axis=0)
    sigma = 1.4826 * mad / np.sqrt(6.0)
    tolerance = np.maximum(o.still_tolerance_rad, 6.0 * sigma)
    spread = maximum_filter1d(q, size, axis=0, mode="nearest") - minimum_filter1d(q, size, axis=0, mode="nearest")
    return np.all(spread <= tolerance, axis=1)


def static_pairs(pairs: Pairs, still: np.ndarray, o: AlignOptions, starts: tuple[int, int] | None = None) -> Pairs:
    """Static mode (the paper's industrial experiment): one pair per still window, averaged over it.

    ``starts``: keep only the still windows whose first stamp is in ``[lo, hi)`` (windowed alignment; then
    no still window is no error).
    """
    edges = np.flatnonzero(np.diff(np.r_[0, still.astype(int), 0]))
    q, T, stamps = [], [], []
    for start, end in zip(edges[::2], edges[1::2], strict=True):
        if (pairs.stamps[end - 1] - pairs.stamps[start]) * NS < o.still_min_s:
            continue
        if starts is not None and not starts[0] <= pairs.stamps[start] < starts[1]:
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
        if starts is not None:
            return _no_pairs_like(pairs)
        raise CalibrationError(f"static mode: no still window of at least {o.still_min_s} s")
    return Pairs(
        np.array(q), np.array(T), np.array(stamps), pairs.joint_names, pairs.frame_id, position_only=pairs.position_only
    )


def _no_pairs(chain: Chain, frame_id: str, position_only: bool) -> Pairs:
    empty = (np.zeros((0, chain.dof)), np.zeros((0, 4, 4)), np.zeros(0, np.int64))
    return Pairs(*empty, chain.joint_names, frame_id, position_only=position_only)


def _no_pairs_like(pairs: Pairs) -> Pairs:
    return pairs.subset(np.zeros(0, dtype=int))


def align_raw(
    bag: str | Path,
    chain: Chain,
    options: AlignOptions | None = None,
    frame_id: str | None = None,
    joints_topic: str = RAW_JOINTS_TOPIC,
    tracker_topic: str = RAW_POSE_TOPIC,
) -> tuple[AlignResult, RawRecording]:
    """Align a raw recording (joint states and tracker poses) into pairs; returns the result and the
    recording it read."""
    rec = read_raw(bag, joints_topic, tracker_topic, chain.joint_names)
    return align(chain, rec, options, frame_id), rec
