"""
Pairing of two pose streams by timestamp: the one pairing rule of the package.

Device A (the input) is interpolated at device B's stamps: linearly in position, by slerp in
rotation, and only between two A samples that are each close enough to the B stamp. The
function is pure and deterministic, vectorised with ``np.searchsorted``, and shared by the
offline bag tools and the live node (which calls it on its whole buffer every time).

Stamps are int64 nanoseconds (docs/design.md §3); no float seconds are used to decide what pairs
with what. Quaternions are (w, x, y, z).
"""

from __future__ import annotations

from collections.abc import Sequence
from concurrent.futures import ThreadPoolExecutor
import numbers
from typing import Optional, Union

from coreg_ros.core.errors import InputError
from coreg_ros.core.estimator.problem import chunk_slices
from coreg_ros.core.quaternion import normalised, slerp, validate_quaternions
from coreg_ros.core.settings import Settings
from coreg_ros.core.types import PairingReport, Pairs, PoseStream, TimeOffset
import numpy as np

#: Largest position (m) a tracker reading may have: beyond it the unit or the value is wrong.
MAX_POSITION_M = 1e6
#: Reasons a B sample is not paired, in the order they are tested (one reason per sample).
UNPAIRED_REASONS = ('before_first_a', 'after_last_a', 'gap_too_large', 'marker_missing')


def _as_int(value: object, name: str) -> int:
    """Return a Python int, refusing floats (pairing never uses float seconds)."""
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, numbers.Integral):
        raise InputError(f'{name} must be an integer number of nanoseconds, got {value!r}; '
                         f'convert seconds with int(round(s * 1e9))')
    return int(value)


def _stamps(values: object, name: str) -> np.ndarray:
    """Return stamps as a 1-D int64 array, refusing anything that is not integer ns."""
    try:
        arr = np.asarray(values)
    except Exception as err:  # ragged or exotic input: the message below names the fix
        raise InputError(f'{name}: stamps are not an array of integers ({err}); give int64 '
                         f'nanoseconds (sec * 10**9 + nanosec)') from err
    if arr.ndim != 1:
        raise InputError(f'{name}: stamps must have shape (N,), got {arr.shape}')
    if arr.dtype.kind == 'u' and arr.size and int(arr.max()) > np.iinfo(np.int64).max:
        raise InputError(f'{name}: a stamp exceeds the int64 range; give int64 nanoseconds '
                         f'(sec * 10**9 + nanosec)')
    if arr.dtype.kind not in 'iu':
        raise InputError(
            f'{name}: stamps must be integer nanoseconds, got dtype {arr.dtype}; convert with '
            f'sec * 10**9 + nanosec in integers (float seconds lose sub-microsecond precision)')
    return arr.astype(np.int64, copy=False)


#: Attribute of a stream ``validate_stream`` returned: the ``orientation`` it was checked with.
VALIDATED = '_validated_orientation'
#: Attribute of the pairs ``pair_streams`` made (True): their quaternions are unit and
#: canonical already (validated samples, slerps normalised here), so ``calibrate`` takes them
#: as they are instead of normalising a copy (122 MB at 2M pairs).
UNIT_QUATERNIONS = '_unit_quaternions'
#: ``validated_streams`` checks A in a second thread from this many samples on: below, the
#: thread costs more than it saves (1000 samples: 0.98 against 0.19 ms one after the other;
#: 20000: 3.3 against 4.6 ms).
VALIDATE_IN_THREAD = 1 << 14


def validate_stream(stream: PoseStream, name: str, *, orientation: bool = True) -> PoseStream:
    """
    Check one device's stream before pairing and return it with normalised quaternions.

    Parameters
    ----------
    stream : PoseStream
        ``stamps`` (N,) int64 ns, ``position`` (N, 3) m, ``quat_wxyz`` (N, 4) (w, x, y, z),
        all in the device's base frame.
    name : str
        What the stream is (e.g. ``'stream_a'``), used in the error messages.
    orientation : bool
        Whether the quaternions are used. If False (a 3-DOF tracker, or B in the position-only
        and three-marker models) they are neither checked nor normalised.

    Returns
    -------
    stream : PoseStream
        The same samples with int64 stamps, float positions and unit quaternions of sign
        w >= 0 (when ``orientation``). A stream this function returned is returned as it is
        (checked once, normalised once).

    Raises
    ------
    InputError
        One line naming the problem, the first offending index and the fix: an empty stream,
        stamps that are not integers, wrong shapes, duplicate stamps, stamps going backwards
        (out-of-order messages or a clock jump, with the size of the jump), NaN or infinite
        positions, NaN, zero or non-unit quaternions.

    """
    if getattr(stream, VALIDATED, None) in (True, orientation):
        return stream  # this function's own result (with its quaternions, if asked)
    n = len(np.asarray(stream.stamps).reshape(-1))
    if n == 0:
        raise InputError(f'{name}: the stream is empty; record or select samples of this '
                         f'device (check the topic name and the time range)')
    stamps = _stamps(stream.stamps, name)
    position = np.asarray(stream.position, dtype=float)
    if position.shape != (n, 3):
        raise InputError(f'{name}: position must have shape ({n}, 3), got {position.shape}; '
                         f'give one position per stamp')
    quat = np.asarray(stream.quat_wxyz, dtype=float)
    if quat.shape != (n, 4):
        raise InputError(f'{name}: quat_wxyz must have shape ({n}, 4), got {quat.shape}; give '
                         f'one (w, x, y, z) quaternion per stamp')
    receive = stream.receive_stamps
    if receive is not None:
        receive = _stamps(receive, f'{name} receive_stamps')
        if receive.shape != (n,):
            raise InputError(f'{name}: receive_stamps must have shape ({n},), got '
                             f'{receive.shape}; give one receive stamp per sample or None')

    step = np.diff(stamps)
    bad = np.flatnonzero(step <= 0)
    if bad.size:
        i = int(bad[0]) + 1
        if step[i - 1] == 0:
            raise InputError(
                f'{name}: duplicate stamp {int(stamps[i])} ns at index {i} (same as index '
                f'{i - 1}; {int((step == 0).sum())} duplicate(s) in all); drop them with '
                f'`coreg fix-bag BAG NEW_BAG --drop-duplicates`')
        jump = -int(step[i - 1])
        raise InputError(
            f'{name}: stamps go backwards at index {i} by {jump} ns ({jump / 1e6:.3f} ms), '
            f'from {int(stamps[i - 1])} to {int(stamps[i])} ({int((step < 0).sum())} '
            f'backward step(s) in all): out-of-order messages or a clock jump; sort them with '
            f'`coreg fix-bag BAG NEW_BAG --sort`, or split at the jump with '
            f'`--split-at-jump S`')

    finite = np.isfinite(position).all(axis=1)
    if not finite.all():
        i = int(np.flatnonzero(~finite)[0])
        raise InputError(
            f'{name}: position contains NaN or inf at index {i} ({int((~finite).sum())} '
            f'sample(s) in all); drop those samples (tracking lost) before pairing')
    huge = np.abs(position).max(axis=1) > MAX_POSITION_M
    if huge.any():
        i = int(np.flatnonzero(huge)[0])
        raise InputError(
            f'{name}: position {np.abs(position[i]).max():.3g} m from the base at index {i} '
            f'({int(huge.sum())} sample(s) in all) is beyond {MAX_POSITION_M:g} m, no tracker '
            f'reading in metres; check the units (coreg convert --units-a/-b) or drop those '
            f'samples')
    if orientation:
        quat = validate_quaternions(quat, f'{name} quat_wxyz')
    out = PoseStream(stamps=stamps, position=position, quat_wxyz=quat,
                     frame_id=stream.frame_id, receive_stamps=receive)
    # marked (not a field: equality and the fingerprint ignore it), so that a caller can
    # validate once and let the samples as recorded go (a long recording's quaternions)
    object.__setattr__(out, VALIDATED, orientation)
    return out


def _bracket(t_src: np.ndarray, t: np.ndarray,
             max_gap_ns: int) -> tuple[np.ndarray, ...]:
    """
    Locate each time t among the source stamps t_src and decide whether it can be interpolated.

    Parameters
    ----------
    t_src : ndarray of int64, shape (M,)
        Strictly increasing source stamps, ns.
    t : ndarray of int64, shape (K,)
        Query times in the same clock, ns.
    max_gap_ns : int
        Largest distance of either bracketing sample from t, ns.

    Returns
    -------
    lo, hi : ndarray of int, shape (K,)
        Indices of the bracketing samples (lo == hi on an exact match); only meaningful where
        ``ok``.
    alpha : ndarray, shape (K,)
        Interpolation fraction from lo (0) to hi (1); 0 on an exact match.
    ok : ndarray of bool, shape (K,)
    before, after : ndarray of bool, shape (K,)
        t lies before the first or after the last source stamp.

    """
    m = t_src.shape[0]
    j = np.searchsorted(t_src, t, side='right')  # t_src[j-1] <= t < t_src[j]
    lo = np.clip(j - 1, 0, m - 1)
    exact = (j >= 1) & (t_src[lo] == t)
    before = j == 0
    after = (j == m) & ~exact
    inside = ~before & ~after & ~exact
    hi = np.where(inside, np.minimum(j, m - 1), lo)
    # Integer differences: exact in int64, converted to float only for the fraction.
    d_lo = t - t_src[lo]
    d_hi = t_src[hi] - t
    ok = exact | (inside & (d_lo <= max_gap_ns) & (d_hi <= max_gap_ns))
    span = (t_src[hi] - t_src[lo]).astype(float)
    alpha = np.where(inside, d_lo.astype(float) / np.where(inside, span, 1.0), 0.0)
    return lo, hi, alpha, ok, before, after


def _lerp(values: np.ndarray, lo: np.ndarray, hi: np.ndarray, alpha: np.ndarray) -> np.ndarray:
    """Linear interpolation values[lo] + α (values[hi] - values[lo]), rows (K, d)."""
    v_lo = values[lo]
    out = values[hi]
    out -= v_lo
    out *= alpha[:, None]
    out += v_lo
    return out


def _slerp_rows(quats: np.ndarray, lo: np.ndarray, hi: np.ndarray,
                alpha: np.ndarray) -> np.ndarray:
    """
    Slerp from quats[lo] towards quats[hi] by α, rows (K, 4); α = 0 keeps the sample as it is.

    The slerps are normalised (``quaternion.normalised``), so that every row is a unit
    quaternion as validation leaves the samples (``UNIT_QUATERNIONS``). Chunk by chunk
    (``CHUNK`` rows): the temporaries of a million slerps stay in cache instead of a dozen
    (K,) and (K, 4) arrays being made afresh.
    """
    out = quats[lo]
    for sl in chunk_slices(len(lo)):
        rows = np.flatnonzero(alpha[sl] > 0.0) + sl.start
        if rows.size:
            out[rows] = normalised(slerp(out[rows], quats[hi[rows]], alpha[rows]))
    return out


def _paired_rows(values: np.ndarray, idx: np.ndarray) -> np.ndarray:
    """
    ``values[idx]`` for increasing indices: a view when they are one run of C-contiguous rows.

    B's samples are mostly all paired: at 2M samples this spares copies of B. Otherwise (or
    for rows not C-contiguous) a C-contiguous copy, as indexing gives it, so that what is
    computed on the pairs does not depend on how they are stored.
    """
    if idx.size and int(idx[-1]) - int(idx[0]) + 1 == idx.size:
        view = values[int(idx[0]):int(idx[-1]) + 1]
        if view.flags['C_CONTIGUOUS']:
            return view
    return values[idx]


def validated_streams(stream_a: PoseStream, markers: list, with_orientation_b: bool):
    """
    Validate A and the B stream(s) as pairing needs them: (A, [B or markers 1-3]).

    A long A not yet validated is validated in a second thread while B is here: the checks
    are whole-array NumPy calls, which run outside Python's lock (two 2M-sample streams:
    0.26 -> 0.18 s on two cores). A's error, if any, is the one raised, as when validated
    first. Shorter streams are validated one after the other (``VALIDATE_IN_THREAD``).
    """
    if (getattr(stream_a, VALIDATED, None) is not None
            or len(np.asarray(stream_a.stamps).reshape(-1)) < VALIDATE_IN_THREAD):
        a = validate_stream(stream_a, 'stream_a')
        return a, _validated_b(markers, with_orientation_b)
    with ThreadPoolExecutor(max_workers=1, thread_name_prefix='coreg-validate') as pool:
        a = pool.submit(validate_stream, stream_a, 'stream_a')
        try:
            bs = _validated_b(markers, with_orientation_b)
        except Exception:
            a.result()  # A's own error first
            raise
        return a.result(), bs


def _validated_b(markers: list, with_orientation_b: bool) -> list:
    """``validated_streams``' B: [B], or the three markers (positions only)."""
    if len(markers) == 3:
        return [validate_stream(s, f'streams_b[{k}]', orientation=False)
                for k, s in enumerate(markers)]
    return [validate_stream(markers[0], 'stream_b', orientation=with_orientation_b)]


def pair_streams(stream_a: PoseStream,
                 streams_b: Union[PoseStream, Sequence[PoseStream]], *,
                 max_gap_ns: int, offset_ns: int = 0, drift: float = 0.0,
                 drift_ref_ns: int = 0, with_orientation_b: bool = True,
                 validated: bool = False) -> tuple[Pairs, PairingReport]:
    """
    Pair device A (input) with device B (output) by interpolating A at B's stamps.

    For each B sample at stamp ``t_B`` (B's clock), A is evaluated at ``t = t_B - offset_ns``
    (A's clock): linearly in position and by slerp in rotation between the two A samples that
    bracket t, provided each of them is at most ``max_gap_ns`` from t. An A sample stamped
    exactly t is used alone. Each B sample gives at most one pair.

    Parameters
    ----------
    stream_a : PoseStream
        Device A: tool pose in A's base frame, stamps in A's clock (int64 ns).
    streams_b : PoseStream or sequence of PoseStream
        Device B: marker pose in B's base frame, stamps in B's clock. A sequence of three
        streams is the three-marker model (Ikits eq. 19): markers 2 and 3 are interpolated
        linearly at marker 1's stamps by the same gap rule (all three in B's clock), and
        their orientations are ignored. A sequence of one stream is the same as the stream.
    max_gap_ns : int
        Largest distance (ns) of each bracketing sample from the interpolation time.
    offset_ns : int
        B's clock minus A's clock (ns), e.g. a known latency of B.
    drift : float
        Clock drift κ (dimensionless, ppm × 1e-6): the offset at B stamp t is
        ``offset_ns + κ (t - drift_ref_ns)``, rounded to whole nanoseconds.
    drift_ref_ns : int
        B stamp at which the offset equals ``offset_ns``.
    with_orientation_b : bool
        False for the position-only model: B's orientations are ignored (neither checked nor
        returned) and ``Pairs.quat_b`` is None.
    validated : bool
        The streams were returned by ``validate_stream`` already (pairing them again at
        another offset need not check them again).

    Returns
    -------
    pairs : Pairs
        ``stamps`` (N,) the paired B stamps (B's clock, ns); ``pos_a`` (N, 3) m and ``quat_a``
        (N, 4) (w, x, y, z), A's tool pose in A's base frame interpolated at those stamps;
        ``pos_b`` (N, 3) m, or (N, 3, 3) for three markers (axis 1 = marker 1..3), in B's base
        frame; ``quat_b`` (N, 4) or None; ``a_var_scale`` (N,) = α² + (1 - α)² for the
        interpolation fraction α (1 on an exact stamp match), the factor on A's noise variance.
    report : PairingReport
        ``n_a``, ``n_b`` (samples offered; for three markers ``n_b`` counts marker 1),
        ``n_paired``, ``unpaired`` with the keys of ``UNPAIRED_REASONS`` (one reason per B
        sample, the first that applies in that order), ``n_a_unused`` (A samples that bracket
        no pair). ``n_paired + sum(unpaired.values()) == n_b``.

    Raises
    ------
    InputError
        If a stream fails ``validate_stream`` (the message names the stream and the index),
        ``max_gap_ns`` is negative or not an integer, or the number of B streams is not 1 or 3.

    Notes
    -----
    The function is pure and deterministic: the live node may call it on its whole buffer
    each time, and gets the same pairs the offline tools get from the same samples.

    """
    max_gap_ns = _as_int(max_gap_ns, 'max_gap_ns')
    offset_ns = _as_int(offset_ns, 'offset_ns')
    if max_gap_ns < 0:
        raise InputError(f'max_gap_ns must be >= 0, got {max_gap_ns}; give the largest '
                         f'allowed distance to a bracketing sample in nanoseconds')
    if isinstance(streams_b, PoseStream):
        markers = [streams_b]
    else:
        markers = list(streams_b)
        if len(markers) not in (1, 3):
            raise InputError(f'streams_b: expected one stream or three marker streams, got '
                             f'{len(markers)}; pass a PoseStream or [marker1, marker2, '
                             f'marker3]')
    three = len(markers) == 3
    if validated:
        a, bs = stream_a, markers
    else:
        a, bs = validated_streams(stream_a, markers, with_orientation_b)
    b = bs[0]
    n_a, n_b = len(a), len(b)

    t_query = b.stamps - np.int64(offset_ns)
    if drift:
        since = (b.stamps - np.int64(_as_int(drift_ref_ns, 'drift_ref_ns'))).astype(float)
        t_query = t_query - np.round(float(drift) * since).astype(np.int64)
    lo, hi, alpha, ok, before, after = _bracket(a.stamps, t_query, max_gap_ns)
    gap = ~ok & ~before & ~after
    # Marker 2 and 3 at marker 1's stamps (same clock, same gap rule).
    marker_ok = np.ones(n_b, dtype=bool)
    marker_pos = []
    for m in bs[1:]:
        m_lo, m_hi, m_alpha, m_ok, _, _ = _bracket(m.stamps, b.stamps, max_gap_ns)
        marker_ok &= m_ok
        marker_pos.append((m, m_lo, m_hi, m_alpha))
    missing = ok & ~marker_ok
    keep = ok & marker_ok

    idx = np.flatnonzero(keep)
    lo_k, hi_k, alpha_k = lo[idx], hi[idx], alpha[idx]
    pos_a = _lerp(a.position, lo_k, hi_k, alpha_k)
    quat_a = _slerp_rows(a.quat_wxyz, lo_k, hi_k, alpha_k)
    a_var_scale = alpha_k ** 2 + (1.0 - alpha_k) ** 2

    if three:
        pos_b = np.empty((idx.size, 3, 3))
        pos_b[:, 0, :] = b.position[idx]
        for k, (m, m_lo, m_hi, m_alpha) in enumerate(marker_pos, start=1):
            pos_b[:, k, :] = _lerp(m.position, m_lo[idx], m_hi[idx], m_alpha[idx])
        quat_b = None
    else:
        pos_b = _paired_rows(b.position, idx)
        quat_b = _paired_rows(b.quat_wxyz, idx) if with_orientation_b else None

    used = np.zeros(n_a, dtype=bool)
    used[lo_k] = True
    used[hi_k] = True
    report = PairingReport(
        n_a=n_a, n_b=n_b, n_paired=int(idx.size),
        unpaired={'before_first_a': int(before.sum()), 'after_last_a': int(after.sum()),
                  'gap_too_large': int(gap.sum()), 'marker_missing': int(missing.sum())},
        n_a_unused=int(n_a - used.sum()))
    pairs = Pairs(stamps=_paired_rows(b.stamps, idx), pos_a=pos_a, quat_a=quat_a, pos_b=pos_b,
                  quat_b=quat_b, a_var_scale=a_var_scale)
    object.__setattr__(pairs, UNIT_QUATERNIONS, True)  # a mark, not a field (as VALIDATED)
    return pairs, report


#: Rows moved at a time by ``own_rows`` (a 2 MB buffer of (N, 4) floats).
_COMPACT_ROWS = 65_536


def own_rows(x: np.ndarray, keep: np.ndarray) -> np.ndarray:
    """
    Return the rows ``keep`` (increasing indices) of ``x``, moved to its front when it owns them.

    For the pairs' arrays once the pairs are spent (the offset search keeps a round's inliers).
    An array that owns its C-contiguous data (``pair_streams`` allocated it) is
    compacted in place a block at a time (row j takes row keep[j] >= j, which no earlier block
    overwrote) and its first rows returned: the values ``np.take`` gives, without a second
    array of nearly all pairs. Anything else (a view of a stream) is copied by ``np.take``.
    """
    if not (x.flags.owndata and x.flags.c_contiguous):
        return np.take(x, keep, axis=0)  # np.take: ~6× a boolean index on (N, 4)
    if keep.size == len(x):
        return x
    for lo in range(0, keep.size, _COMPACT_ROWS):
        rows = keep[lo:lo + _COMPACT_ROWS]
        x[lo:lo + rows.size] = np.take(x, rows, axis=0)
    return x[:keep.size]


__all__ = ['UNPAIRED_REASONS', 'pair_streams', 'validate_stream', 'validated_streams']


def stream_list(streams_b: Union[PoseStream, Sequence[PoseStream]]) -> list:
    """Return device B's streams as a list (one stream, or one per marker)."""
    return [streams_b] if isinstance(streams_b, PoseStream) else list(streams_b)


def pair_for(stream_a: PoseStream, streams_b: Union[PoseStream, Sequence[PoseStream]],
             settings: Settings, timing: Optional[TimeOffset] = None,
             validated: bool = False):
    """
    Pair the streams with the settings' gap and model; returns (Pairs, report).

    At ``timing`` (offset and drift) when given, else at ``settings.time_offset``.
    """
    timing = timing or TimeOffset(settings.time_offset)
    return pair_streams(stream_a, streams_b, max_gap_ns=settings.max_gap_ns,
                        offset_ns=timing.offset_ns(), drift=timing.drift,
                        drift_ref_ns=timing.reference_ns,
                        with_orientation_b=settings.model == 'full_pose', validated=validated)
