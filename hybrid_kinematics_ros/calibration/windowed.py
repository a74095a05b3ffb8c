"""Alignment in windows while a recording goes on, in memory bounded whatever its length.

The paper recorded for 8 hours; holding a whole recording costs 0.7 GB an hour at 3 kHz + 110 Hz. A
:class:`StreamingAligner` keeps only the samples that the next window still needs and hands back pairs
window by window:

* The recording is cut into segments of ``segment_s`` of joint time. A segment is done once the streams
  have reached ``context_s`` past its end.
* The clock offset is estimated on the segment with ``context_s`` on either side (the ``estimate_clock``
  of a whole recording, on that window, offset only), centred on the offset the earlier windows predict.
* The segment is paired with a clock line (offset and skew) fitted, robustly, through the window
  estimates of the last ``clock_memory_s``: the skew comes from how the offsets move from window to
  window (20 ppm is 1.2 ms a minute), and a slow, non-linear drift of free-running clocks over hours is
  followed rather than forced onto one line.
* Each segment is paired by :func:`align` with the samples around it as context (brackets, derivatives,
  still windows across its edges); rejections are counted once, by the segment a sample belongs to.

A recording shorter than one segment and its context is aligned exactly as :func:`align` aligns it.
Memory: the retained samples stay below ``(segment_s + 2 context_s + poll interval)`` of both streams
plus one storage block each (:attr:`StreamingAligner.retained`); the window estimates (16 bytes a
minute) and the counters are all that grows.
"""

from __future__ import annotations

import ctypes
import threading
from collections import Counter
from dataclasses import dataclass, field

import numpy as np

from hybrid_kinematics_ros.calibration.alignment import ALL, AlignOptions, AlignResult, Window, align, clean
from hybrid_kinematics_ros.calibration.clock import NS, Clock, estimate_clock
from hybrid_kinematics_ros.calibration.errors import CalibrationError
from hybrid_kinematics_ros.io.columns import Columns
from hybrid_kinematics_ros.io.raw_bag import RawRecording
from hybrid_kinematics_ros.kinematics.chain import Chain

SEGMENT_S = 60.0
CONTEXT_S = 30.0
CLOCK_MEMORY_S = 600.0
NARROW_S = 0.02  # search range of a window's estimate around the predicted offset
TRACKER_MARGIN_S = 1.0
WINDOW_SKEW_MIN_S = 60.0


@dataclass(frozen=True)
class ClockEstimate:
    """One window's clock: tracker minus robot clock (s) at robot stamp ``stamp_ns``, and its own skew."""

    stamp_ns: int
    offset_s: float
    skew: float = 0.0  # dimensionless, from the window alone (noisier than the line through the offsets)


@dataclass
class SegmentPairs:
    """The pairs and rejections of one segment, with the receive time of each pair's joint state."""

    result: AlignResult
    log_ns: np.ndarray
    clock: Clock


@dataclass
class _State:
    next_lo: int | None = None  # robot stamp where the next segment starts; None: at the first sample
    tracker_from: int = ALL[0]  # tracker stamp from which tracker rejections are still to be counted
    retry_at: int = ALL[0]  # with no clock yet: the joint stamp at which to try estimating again
    estimates: list[ClockEstimate] = field(default_factory=list)


def fit_clock(estimates: list[ClockEstimate], ref_ns: int) -> Clock:
    """A clock line through window estimates (one estimate: its own offset and skew).

    The skew comes from how the offsets move from window to window: two windows a minute apart, each
    within tens of µs, give it to about a ppm, better than one window's own skew. From three estimates on,
    those more than 4 robust σ (and 50 µs) off the line are left out: a window of slow motion can be
    milliseconds off.
    """
    if len(estimates) == 1:
        e = estimates[0]
        return Clock(e.offset_s + e.skew * (ref_ns - e.stamp_ns) * NS, e.skew, ref_ns)
    t = np.array([(e.stamp_ns - ref_ns) * NS for e in estimates])
    o = np.array([e.offset_s for e in estimates])
    design = np.column_stack([np.ones_like(t), t])
    coef = np.linalg.lstsq(design, o, rcond=None)[0]
    if len(t) >= 3:
        r = o - design @ coef
        inlier = np.abs(r) <= max(4.0 * 1.4826 * np.median(np.abs(r - np.median(r))), 5e-5)
        if inlier.sum() >= 2 and np.ptp(t[inlier]) > 0:
            coef = np.linalg.lstsq(design[inlier], o[inlier], rcond=None)[0]
    return Clock(float(coef[0]), float(coef[1]), ref_ns)


def _sorted(stamps: np.ndarray, values: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """By stamp (stable); the arrays themselves when they are in order already, as they nearly always are."""
    if len(stamps) < 2 or bool(np.all(stamps[1:] >= stamps[:-1])):
        return stamps, values
    order = np.argsort(stamps, kind="stable")
    return stamps[order], values[order]


def release_memory() -> None:
    """Give freed heap memory back to the system (glibc ``malloc_trim``; nothing elsewhere).

    A segment's alignment allocates and frees tens of MB of arrays; glibc keeps such freed memory in the
    worker thread's arena for reuse, where it stays as resident memory (a plateau of a few hundred MB over
    a long recording).
    """
    if _TRIM is not None:
        _TRIM(0)


def _malloc_trim():
    try:
        return ctypes.CDLL(None).malloc_trim
    except (OSError, AttributeError):  # not glibc
        return None


_TRIM = _malloc_trim()


class StreamingAligner:
    """Joint states and tracker poses in, calibration pairs out segment by segment; see the module doc.

    ``add_joints`` and ``add_pose`` may be called from one thread while ``poll`` runs in another (the
    recorder's executor and its worker); ``poll`` itself is not reentrant. Joint positions come in the
    chain's joint order.
    """

    def __init__(
        self,
        chain: Chain,
        options: AlignOptions | None = None,
        frame_id: str | None = None,
        segment_s: float = SEGMENT_S,
        context_s: float = CONTEXT_S,
        clock_memory_s: float = CLOCK_MEMORY_S,
        max_pending_s: float = 300.0,
    ) -> None:
        self.chain, self.options, self.frame_id = chain, options or AlignOptions(), frame_id
        self.segment_ns, self.context_ns = int(segment_s * 1e9), int(context_s * 1e9)
        self.clock_memory_ns, self.max_pending_ns = int(clock_memory_s * 1e9), int(max_pending_s * 1e9)
        # positions and (receive time − stamp): small, so exact as a float
        self.joints = Columns(chain.dof + 1, block=2048)
        self.poses = Columns(7, block=8192)
        self.frame = ""
        self.rejected: Counter = Counter()
        self.pairs = 0
        self.first_stamp: int | None = None
        self.peak_retained = 0
        self._lock = threading.Lock()
        self._state = _State()

    # ------------------------------------------------------------------ input
    def add_joints(self, stamp_ns: int, q, receive_ns: int | None = None) -> None:
        with self._lock:
            self.joints.append(stamp_ns, (*q, 0 if receive_ns is None else receive_ns - stamp_ns))

    def add_pose(self, stamp_ns: int, values, frame: str) -> None:
        """``values``: x, y, z (m), qx, qy, qz, qw (zeros for a plain reflector)."""
        with self._lock:
            self.poses.append(stamp_ns, values)
            self.frame = frame

    @property
    def retained(self) -> int:
        """Samples (joint states plus tracker poses) held in memory now."""
        return self.joints.retained + self.poses.retained

    def recent(self, joints: int, poses: int) -> tuple[tuple[np.ndarray, np.ndarray], tuple[np.ndarray, np.ndarray]]:
        """Copies of the last ``joints`` joint rows (positions, then receive time − stamp) and ``poses`` poses."""
        with self._lock:
            return self.joints.view(joints), self.poses.view(poses)

    @property
    def estimates(self) -> list[ClockEstimate]:
        return list(self._state.estimates)

    def clock(self, at_ns: int | None = None) -> Clock | None:
        """The clock line at robot stamp ``at_ns`` (the latest estimates if None); None before any."""
        if self.options.offset_s is not None:
            return Clock(self.options.offset_s, self.options.skew_ppm * 1e-6, self.first_stamp or 0)
        est = self._state.estimates
        if at_ns is not None:
            est = [e for e in est if e.stamp_ns >= at_ns - self.clock_memory_ns] or est[-1:]
        else:
            est = [e for e in est if e.stamp_ns >= est[-1].stamp_ns - self.clock_memory_ns] if est else []
        return fit_clock(est, self.first_stamp or 0) if est else None

    def summary_clock(self) -> Clock | None:
        """One clock line through every window estimate, at the first joint stamp: what a report gives."""
        if self.options.offset_s is not None:
            return self.clock()
        est = self._state.estimates
        return fit_clock(est, self.first_stamp or 0) if est else None

    # ------------------------------------------------------------------ alignment
    def poll(self, final: bool = False) -> list[SegmentPairs]:
        """Align every segment whose data is complete (with ``final``: everything left)."""
        out: list[SegmentPairs] = []
        while True:
            with self._lock:
                (jt, jv), (pt, pv) = self.joints.view(), self.poses.view()
                frame = self.frame
                self.peak_retained = max(self.peak_retained, self.retained)
            if not len(jt) or not len(pt):
                return out
            jt, jv = _sorted(jt, jv)
            pt, pv = _sorted(pt, pv)
            segment = self._segment(jt, jv, pt, pv, frame, final)
            del jt, jv, pt, pv
            if segment is None:
                return out
            release_memory()  # a segment's transient arrays, tens of MB
            if segment.result.pairs is not None:
                out.append(segment)
            if self._state.next_lo is None:  # the last segment was done
                return out

    def _segment(self, jt, jv, pt, pv, frame: str, final: bool) -> SegmentPairs | None:
        s, o = self._state, self.options
        first = s.next_lo is None and not s.estimates and s.tracker_from == ALL[0]
        if self.first_stamp is None:
            self.first_stamp = int(jt[0])
        lo = int(jt[0]) if s.next_lo is None else s.next_lo
        end = int(jt[-1])
        last = final and end < lo + self.segment_ns + self.context_ns
        if not final and end < lo + self.segment_ns + self.context_ns:
            return None
        hi = ALL[1] if last else lo + self.segment_ns
        guess = self.clock(lo)
        if not final:
            need = (guess or Clock(0.0)).to_tracker(hi + self.context_ns) + (0 if guess else int(o.max_offset_s * 1e9))
            if pt[-1] < need:
                return None
        if first and last:  # all of it in one window: exactly what align does with the whole recording
            rec = RawRecording(
                jt, self.chain.joint_names, jv[:, :-1], pt, frame, pv[:, :3], pv[:, 3:], False, Counter()
            )
            try:
                result = align(self.chain, rec, o, self.frame_id)
            except CalibrationError:
                s.next_lo = None
                raise
            clock = Clock(result.offset_s, result.skew_ppm * 1e-6, int(jt[0]))
            s.estimates.append(ClockEstimate(int(jt[0]), result.offset_s, result.skew_ppm * 1e-6))
            return self._done(SegmentPairs(result, self._log_times(result, jt, jv), clock), None)
        if o.offset_s is None:
            if guess is None and end < s.retry_at and not final:
                return None
            window_hi = hi + self.context_ns if guess is not None else end  # no clock yet: all that waits
            estimate = self._estimate(jt, jv, pt, pv, frame, lo - self.context_ns, window_hi, guess)
            if estimate is not None:
                s.estimates.append(estimate)
            elif guess is None and not final and end - lo < self.max_pending_ns:
                s.retry_at = end + self.segment_ns // 2
                return None  # wait for motion, up to max_pending_s
        clock = self.clock(lo if hi == ALL[1] else (lo + hi) // 2)
        if clock is None:  # nothing to pair with: counted, and the raw data is in the bag for a later align
            n = int(np.sum((jt >= (lo if s.next_lo is not None else ALL[0])) & (jt < hi)))
            self.rejected["no_clock_estimate"] += n
            return self._done(SegmentPairs(AlignResult(None, float("nan")), np.zeros(0, np.int64), None), hi)
        return self._done(self._align(jt, jv, pt, pv, frame, lo, hi, clock), hi)

    def _done(self, segment: SegmentPairs, hi: int | None) -> SegmentPairs:
        s = self._state
        if segment.result.pairs is not None:
            self.rejected.update(segment.result.rejected)
            self.pairs += len(segment.result.pairs)
        if hi is None or hi == ALL[1]:
            s.next_lo = None
            s.tracker_from = ALL[1]
            return segment
        s.next_lo = hi
        if segment.clock is not None:
            s.tracker_from = int(segment.clock.to_tracker(hi))
        keep_from = hi - self.context_ns - int(TRACKER_MARGIN_S * 1e9)
        guess = self.clock(hi) or Clock(0.0)
        margin = int((TRACKER_MARGIN_S + (0.0 if self.clock(hi) else self.options.max_offset_s)) * 1e9)
        with self._lock:
            self.joints.drop_before(keep_from)
            self.poses.drop_before(int(guess.to_tracker(keep_from)) - margin)
        return segment

    def _estimate(self, jt, jv, pt, pv, frame, lo: int, hi: int, guess: Clock | None) -> ClockEstimate | None:
        """The offset at the middle of ``[lo, hi]`` (robot clock), searched near the guess if there is one."""
        j = slice(int(np.searchsorted(jt, lo, side="left")), int(np.searchsorted(jt, hi, side="right")))
        if j.stop - j.start < 3:
            return None
        mid = int(jt[j.start] + jt[j.stop - 1]) // 2
        predicted = 0.0 if guess is None else float(guess.offset_at(np.array([mid]))[0])
        shift = round(predicted * 1e9)
        searches = ([NARROW_S] if guess is not None else []) + [self.options.max_offset_s]
        for search in searches:
            margin = int((search + TRACKER_MARGIN_S) * 1e9)
            p = slice(
                int(np.searchsorted(pt, lo + shift - margin, side="left")),
                int(np.searchsorted(pt, hi + shift + margin, side="right")),
            )
            rec = RawRecording(
                jt[j], self.chain.joint_names, jv[j, :-1], pt[p] - shift, frame, pv[p, :3], pv[p, 3:], False, Counter()
            )
            try:
                rec = clean(rec)[0]
                rec.quats = rec.quats[:0]  # the estimate needs no orientations: 11 MB less while it runs
                clock = estimate_clock(self.chain, rec, search, skew_min_span_s=WINDOW_SKEW_MIN_S)
            except CalibrationError:
                return None
            found = float(clock.offset_at(np.array([mid]))[0])
            # near the edge of the narrow range: maybe no real minimum there (a clock jump); search it all
            if search is searches[-1] or abs(found) < 0.8 * search:
                return ClockEstimate(mid, found + shift * 1e-9, clock.skew)
        return None

    def _align(self, jt, jv, pt, pv, frame, lo: int, hi: int, clock: Clock) -> SegmentPairs:
        """Pairs of the joint states in ``[lo, hi)``, with the samples around them as context."""
        s, o = self._state, self.options
        if o.still_min_s > 0:  # still windows run across the edges
            i0, i1 = np.searchsorted(jt, [lo - self.context_ns, hi + self.context_ns])
        else:  # one sample either side: the same central differences as with the whole recording
            i0 = max(0, int(np.searchsorted(jt, lo)) - 1)
            i1 = int(np.searchsorted(jt, hi)) + 1 if hi != ALL[1] else len(jt)
        i1 = min(i1, len(jt))
        t_lo, t_hi = clock.to_tracker(np.array([jt[i0], jt[i1 - 1]]))
        margin = self.context_ns
        p = slice(
            int(np.searchsorted(pt, t_lo - margin, side="left")), int(np.searchsorted(pt, t_hi + margin, side="right"))
        )
        rec = RawRecording(
            jt[i0:i1], self.chain.joint_names, jv[i0:i1, :-1], pt[p], frame, pv[p, :3], pv[p, 3:], False, Counter()
        )
        first = s.next_lo is None
        window = Window(
            ALL[0] if first else lo,
            hi,
            s.tracker_from,
            ALL[1] if hi == ALL[1] else int(clock.to_tracker(hi)),
        )
        result = align(self.chain, rec, o, self.frame_id, clock=clock, window=window)
        return SegmentPairs(result, self._log_times(result, jt[i0:i1], jv[i0:i1]), clock)

    @staticmethod
    def _log_times(result: AlignResult, jt: np.ndarray, jv: np.ndarray) -> np.ndarray:
        """Receive times of the joint states the pairs come from (their stamps, where none was given)."""
        stamps = result.pairs.stamps
        if not len(jt):
            return stamps
        index = np.clip(np.searchsorted(jt, stamps), 0, len(jt) - 1)
        return np.where(jt[index] == stamps, stamps + np.round(jv[index, -1]).astype(np.int64), stamps)
