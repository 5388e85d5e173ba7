"""
Bounded, preallocated storage of one pose stream, with cheap per-message validation.

The subscription callback of the node only calls ``StreamBuffer.push`` with Python scalars:
no numpy allocation and no logging per message, because rclpy's executor handles only a few
thousand messages per second. Rejected messages are counted by reason; when the buffer is full
the OLDEST samples are overwritten (and counted as dropped), so a long session keeps the most
recent ``capacity`` samples.
"""

from __future__ import annotations

import math
import threading

from coreg_ros.core.quaternion import UNIT_NORM_TOLERANCE
from coreg_ros.core.types import PoseStream
import numpy as np

#: Reasons a message is rejected, in the order they are checked (one reason per message).
REASONS = ('non_finite', 'non_unit_quaternion', 'frame_id_changed', 'stamp_backwards',
           'duplicate_stamp')

_HINTS = {
    'non_finite': 'position or orientation holds NaN or inf',
    'non_unit_quaternion': (f'quaternion norm differs from 1 by more than {UNIT_NORM_TOLERANCE} '
                            f'(zero quaternion or wrong field order?)'),
    'frame_id_changed': 'header.frame_id differs from the first message of the topic',
    'stamp_backwards': ('header stamp earlier than the previous one (clock jump); call ~/reset '
                        'if the device clock was reset'),
    'duplicate_stamp': 'header stamp equal to the previous one (repeated message)',
}


def reason_hint(reason: str) -> str:
    """One line explaining a rejection reason."""
    return _HINTS.get(reason, reason)


class StreamBuffer:
    """
    Ring buffer of one PoseStamped stream, in arrival order.

    Parameters
    ----------
    capacity : int
        Samples kept; the oldest are overwritten when full.

    Notes
    -----
    Thread-safe: ``push`` (executor thread) and ``snapshot``/``clear`` (service thread) take
    one lock. Accepted stamps strictly increase, which is what pairing needs.

    """

    def __init__(self, capacity: int):
        if capacity < 1:
            raise ValueError(f'capacity must be >= 1, got {capacity}')
        self.capacity = int(capacity)
        self._stamps = np.zeros(self.capacity, dtype=np.int64)
        self._recv = np.zeros(self.capacity, dtype=np.int64)
        # columns x, y, z, qw, qx, qy, qz
        self._vals = np.zeros((self.capacity, 7), dtype=float)
        self._lock = threading.Lock()
        self._clear_locked()
        # Counters run since start-up; ``clear`` forgets samples, not counts.
        self.received = 0
        self.accepted = 0
        self.dropped = 0  # accepted samples overwritten because the buffer was full
        self.rejected = dict.fromkeys(REASONS, 0)

    def _clear_locked(self) -> None:
        self._next = 0          # index the next sample goes to
        self._size = 0          # samples held
        self.frame_id = None
        self._last_stamp = None

    def __len__(self) -> int:
        return self._size

    def push(self, stamp_ns: int, recv_ns: int, x: float, y: float, z: float,
             qw: float, qx: float, qy: float, qz: float, frame_id: str):
        """
        Validate one message and store it.

        Parameters
        ----------
        stamp_ns, recv_ns : int
            Header stamp (device clock) and receive time, ns.
        x, y, z : float
            Position in ``frame_id``, m.
        qw, qx, qy, qz : float
            Orientation (w, x, y, z).
        frame_id : str
            ``header.frame_id``.

        Returns
        -------
        reason : str or None
            None if stored, else the rejection reason (one of ``REASONS``).

        """
        with self._lock:
            self.received += 1
            reason = None
            isf = math.isfinite
            if not (isf(x) and isf(y) and isf(z) and isf(qw) and isf(qx) and isf(qy)
                    and isf(qz)):
                reason = 'non_finite'
            elif abs(math.sqrt(qw * qw + qx * qx + qy * qy + qz * qz) - 1.0) > \
                    UNIT_NORM_TOLERANCE:
                reason = 'non_unit_quaternion'
            elif self.frame_id is not None and frame_id != self.frame_id:
                reason = 'frame_id_changed'
            elif self._last_stamp is not None and stamp_ns <= self._last_stamp:
                reason = 'stamp_backwards' if stamp_ns < self._last_stamp else 'duplicate_stamp'
            if reason is not None:
                self.rejected[reason] += 1
                return reason
            if self.frame_id is None:
                self.frame_id = frame_id
            self._last_stamp = stamp_ns
            i = self._next
            self._stamps[i] = stamp_ns
            self._recv[i] = recv_ns
            v = self._vals[i]
            v[0] = x
            v[1] = y
            v[2] = z
            v[3] = qw
            v[4] = qx
            v[5] = qy
            v[6] = qz
            self._next = i + 1 if i + 1 < self.capacity else 0
            if self._size < self.capacity:
                self._size += 1
            else:
                self.dropped += 1
            self.accepted += 1
            return None

    def push_many(self, stamps_ns: np.ndarray, recv_ns: np.ndarray, position: np.ndarray,
                  quat_wxyz: np.ndarray, frame_id: str) -> dict:
        """
        Validate and store N messages of one frame in arrival order, as N ``push`` calls would.

        Same checks, same order of checks, same counts and the same stored samples as ``push``
        one message at a time (the stamp check against the running maximum of the stamps
        before: accepted stamps strictly increase, so that maximum is the last accepted one).

        Parameters
        ----------
        stamps_ns, recv_ns : array_like of int, shape (N,)
            Header stamps (device clock) and receive times, ns.
        position : array_like of float, shape (N, 3)
            Positions in ``frame_id``, m.
        quat_wxyz : array_like of float, shape (N, 4)
            Orientations (w, x, y, z).
        frame_id : str
            ``header.frame_id`` of all N messages.

        Returns
        -------
        rejected : dict
            Reason -> number of messages rejected for it (only reasons that occurred).

        """
        stamps = np.asarray(stamps_ns, dtype=np.int64)
        n = len(stamps)
        if n == 0:
            return {}
        vals = np.empty((n, 7))
        vals[:, :3] = position
        vals[:, 3:] = quat_wxyz
        with np.errstate(all='ignore'):  # inf * inf overflows to inf, as in push
            finite = np.isfinite(vals).all(axis=1)
            q = vals[:, 3:]
            # summed left to right like push, so the tolerance bites on the same messages
            norm = np.sqrt(q[:, 0] * q[:, 0] + q[:, 1] * q[:, 1] + q[:, 2] * q[:, 2]
                           + q[:, 3] * q[:, 3])
            unit = np.abs(norm - 1.0) <= UNIT_NORM_TOLERANCE
        counts = {}
        with self._lock:
            self.received += n
            ok = finite & unit
            counts['non_finite'] = n - int(finite.sum())
            counts['non_unit_quaternion'] = int(finite.sum()) - int(ok.sum())
            if self.frame_id is not None and frame_id != self.frame_id:
                counts['frame_id_changed'] = int(ok.sum())
                ok[:] = False
            cand = np.flatnonzero(ok)
            if len(cand):
                s = stamps[cand]
                fresh = self._last_stamp is None  # the first sample has nothing to follow
                prev = s[:-1] if fresh else np.concatenate(([self._last_stamp], s[:-1]))
                last = np.maximum.accumulate(prev)  # the last accepted stamp before each
                checked = s[1:] if fresh else s
                counts['stamp_backwards'] = int(np.sum(checked < last))
                counts['duplicate_stamp'] = int(np.sum(checked == last))
                keep = checked > last
                if fresh:
                    keep = np.concatenate(([True], keep))
                cand = cand[keep]
            counts = {r: c for r, c in counts.items() if c}
            for r, c in counts.items():
                self.rejected[r] += c
            k = len(cand)
            if k == 0:
                return counts
            if self.frame_id is None:
                self.frame_id = frame_id
            self._last_stamp = int(stamps[cand[-1]])
            keep_n = min(k, self.capacity)  # a batch longer than the ring keeps its newest
            src = cand[k - keep_n:]
            idx = (self._next + (k - keep_n) + np.arange(keep_n)) % self.capacity
            self._stamps[idx] = stamps[src]
            self._recv[idx] = np.asarray(recv_ns, dtype=np.int64)[src]
            self._vals[idx] = vals[src]
            self._next = (self._next + k) % self.capacity
            size = min(self.capacity, self._size + k)
            self.dropped += self._size + k - size
            self._size = size
            self.accepted += k
            return counts

    def snapshot(self) -> PoseStream:
        """Return a copy of the held samples, oldest first, as a PoseStream."""
        return self.tail(self.capacity)

    def tail(self, n: int) -> PoseStream:
        """Return a copy of the newest ``n`` samples (O(n), not O(capacity)), oldest first."""
        with self._lock:
            k = min(int(n), self._size)
            idx = np.arange(self._next - k, self._next) % self.capacity
            vals = self._vals[idx]  # fancy indexing copies
            return PoseStream(stamps=self._stamps[idx], position=vals[:, :3],
                              quat_wxyz=vals[:, 3:], frame_id=self.frame_id or '',
                              receive_stamps=self._recv[idx])

    def since(self, mark: int, until: int | None = None) -> tuple[int, PoseStream, bool]:
        """
        Return the accepted samples numbered ``mark + 1 .. until`` that are still held.

        Samples are numbered by the ``accepted`` counter (1 = the first ever accepted), which
        ``clear`` does not reset, so a caller can take "what is new since I last looked".

        Parameters
        ----------
        mark : int
            ``accepted`` at the caller's last look.
        until : int, optional
            Last sample number wanted (default: the newest).

        Returns
        -------
        end : int
            The number of the last sample asked for (the next ``mark``).
        stream : PoseStream
            Copies of those samples, oldest first.
        complete : bool
            False if some of them were overwritten (buffer full) or forgotten (``clear``).

        """
        with self._lock:
            end = self.accepted if until is None else min(int(until), self.accepted)
            oldest_held = self.accepted - self._size  # number of the sample before the oldest
            first = max(int(mark), oldest_held)
            k = max(0, end - first)
            stop = self._next - (self.accepted - end)
            idx = np.arange(stop - k, stop) % self.capacity
            vals = self._vals[idx]
            stream = PoseStream(stamps=self._stamps[idx], position=vals[:, :3],
                                quat_wxyz=vals[:, 3:], frame_id=self.frame_id or '',
                                receive_stamps=self._recv[idx])
            return end, stream, first == int(mark) or end <= int(mark)

    def clear(self) -> None:
        """Forget the samples, the reference frame id and the last stamp (not the counters)."""
        with self._lock:
            self._clear_locked()


class GapCounter:
    """
    Count messages missing from a stream from the gaps in its header stamps.

    Messages lost before the subscription callback runs (a full middleware history, a
    best-effort transport dropping under load) leave holes in the stamps of a stream sent at a
    steady rate. The stream's own period is estimated robustly (the median of the intervals
    not above 1.5 times their 10th percentile, so heavy loss does not inflate it), and an
    interval of ``k`` periods counts ``k - 1`` missing messages.
    """

    #: Intervals needed before a period estimate is trusted.
    MIN_INTERVALS = 20
    #: Single intervals the period is the median of (the newest).
    KEEP = 2000

    def __init__(self):
        self.missing = 0
        self.period_ns: float | None = None
        self._last: int | None = None
        self._early = np.zeros(0, np.int64)  # stamps seen before the period is known
        self._single = np.zeros(0)  # recent intervals of one period, ns

    def update(self, stamps: np.ndarray) -> int:
        """Take the next accepted stamps (increasing, ns); return the newly missing count."""
        if len(stamps) == 0:
            return 0
        if self.period_ns is None:  # too few stamps yet: keep them until there are enough
            stamps = np.concatenate((self._early, stamps))
            if len(stamps) <= self.MIN_INTERVALS:
                self._early = stamps
                return 0
            self._early = np.zeros(0, np.int64)
        joined = stamps if self._last is None else np.concatenate(([self._last], stamps))
        self._last = int(stamps[-1])
        d = np.diff(joined).astype(float)
        if len(d) >= self.MIN_INTERVALS:  # the newest single intervals give the period
            low = np.percentile(d, 10)
            self._single = np.concatenate((self._single, d[d <= 1.5 * low]))[-self.KEEP:]
            self.period_ns = float(np.median(self._single))
        if not self.period_ns or self.period_ns <= 0 or not len(d):
            return 0
        big = d[d > 1.5 * self.period_ns]
        new = int(np.sum(np.rint(big / self.period_ns) - 1)) if len(big) else 0
        self.missing += new
        return new

    def restart(self) -> None:
        """Forget the last stamp (after a reset: the next stamps start afresh)."""
        self._last = None
        self._early = np.zeros(0, np.int64)


class SequenceCounter:
    """
    Count the messages a publisher sent that the node never took, from their sequence numbers.

    The middleware numbers each publisher's messages 1, 2, 3, ... (the message info's
    ``publication_sequence_number``), so a hole between two messages taken is exactly what was
    lost on the way: in the transport (best effort under load) or overwritten in the
    subscription's history before the node took it (a node still starting up, a stream thread
    held). Unlike the stamps, this also sees the messages lost *before the first one taken*
    (``head``): they are counted when the publisher began after this counter was made, which
    is told from its publishing rate (the first message taken, numbered ``s``, was sent
    ``(s - 1) / rate`` after the publisher's first); a publisher that was already running sent
    its earlier messages to nobody here. Nothing can count messages lost after the last one
    taken.

    Sequence numbers are per publisher and the message info does not say which publisher
    sent a message: a number that does not increase (two publishers on the topic, or one
    restarted) makes the count unusable, and ``why_not`` says so (the stamps count instead).

    Parameters
    ----------
    created_ns : int
        When the subscription was made (system clock, ns: the clock of ``source_timestamp``).

    Attributes
    ----------
    between : int
        Messages missing between two messages taken.
    head : int
        Messages sent after ``created_ns`` but before the first one taken.
    why_not : str
        Empty while the count is usable; else why it is not.

    """

    #: Messages taken before the publishing rate (and so ``head``) is trusted.
    RATE_AFTER = 10
    #: Why the count cannot be used.
    NO_NUMBERS = 'the middleware gives no publication sequence numbers'
    INTERLEAVED = ('sequence numbers do not increase: several publishers on the topic (or one '
                   'restarted)')

    def __init__(self, created_ns: int):
        self.created_ns = int(created_ns)
        self.between = 0
        self.head = 0
        self.why_not = ''
        self._first: tuple | None = None  # (number, source ns) of the first message taken
        self._last: int | None = None
        self._head_decided = False

    @property
    def counting(self) -> bool:
        """Tell whether the count is usable and a message was taken."""
        return not self.why_not and self._first is not None

    @property
    def lost(self) -> int:
        """Return the messages lost: between those taken and before the first (int)."""
        return self.between + self.head

    def update(self, infos: list) -> None:
        """Take the message infos (rclpy dicts) of the next messages taken, in order."""
        if self.why_not or not infos:
            return
        numbers = [i.get('publication_sequence_number') if i else None for i in infos]
        if None in numbers:
            self.why_not = self.NO_NUMBERS
            return
        seq = np.asarray(numbers, dtype=np.int64)
        joined = seq if self._last is None else np.concatenate(([self._last], seq))
        steps = np.diff(joined)
        if np.any(steps <= 0):
            self.why_not = self.INTERLEAVED
            return
        if self._first is None:
            self._first = (int(seq[0]), infos[0].get('source_timestamp'))
        self.between += int(np.sum(steps - 1))
        self._last = int(seq[-1])
        if not self._head_decided:
            self._decide_head(infos[-1].get('source_timestamp'))

    def update_one(self, info: dict) -> None:
        """Take one message's info (the plain intake: plain Python, no numpy per message)."""
        if self.why_not:
            return
        number = info.get('publication_sequence_number') if info else None
        if number is None:
            self.why_not = self.NO_NUMBERS
            return
        if self._last is None:
            self._first = (number, info.get('source_timestamp'))
        elif number <= self._last:
            self.why_not = self.INTERLEAVED
            return
        else:
            self.between += number - self._last - 1
        self._last = number
        if not self._head_decided:
            self._decide_head(info.get('source_timestamp'))

    def _decide_head(self, last_source_ns) -> None:
        """Count the messages before the first taken if the publisher began after us."""
        first, first_source_ns = self._first
        if first == 1:
            self._head_decided = True
            return
        if (self._last - first < self.RATE_AFTER or not first_source_ns or not last_source_ns
                or last_source_ns <= first_source_ns):
            return  # not enough messages yet to tell the publisher's rate
        per_ns = (self._last - first) / (last_source_ns - first_source_ns)
        began_ns = first_source_ns - (first - 1) / per_ns
        self.head = first - 1 if began_ns >= self.created_ns else 0
        self._head_decided = True
