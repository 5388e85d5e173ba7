"""
Timing read from the stamps themselves, per device (docs/design.md §5: jitter, drops, gaps).

A device's header stamps tell a lot before any residual is computed: the nominal rate (the
median interval), the scatter of the intervals about whole multiples of it (stamp jitter:
independent stamp errors of σ give intervals scattered by √2 σ), dropped samples (intervals
of two or more periods), gaps (intervals far longer than a few periods), stamps going
backwards or repeating, and, when the recording kept the receive time, the latency from the
header stamp to the receive stamp. Jitter the residuals cannot show (slow motion, noisy
devices) is still named from the stamps.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Optional

from coreg_ros.core.diagnosis.effects.finding import Finding, STAMPS
from coreg_ros.core.diagnosis.effects.noise import TimestampJitterCandidate
from coreg_ros.core.diagnosis.record import optional, Record
from coreg_ros.core.types import PoseStream
import numpy as np

#: Interval scatter (per-stamp σ, s) from which the stamps count as jittered: clean clocks
#: scatter by well under a microsecond, host stamps of a busy computer by 0.1-1 ms and more.
JITTER_MIN_S = 1e-4
#: ... and the scatter must also be this share of the nominal interval.
JITTER_MIN_SHARE = 0.005
#: An interval longer than this many nominal intervals (and GAP_MIN_S) is a gap, not drops.
GAP_PERIODS = 10
GAP_MIN_S = 0.25


@dataclass(frozen=True, kw_only=True)
class Latency(Record):
    """
    Receive stamp minus header stamp of a device's samples, s.

    Attributes
    ----------
    median_s, sigma_s : float
        Median and robust σ.
    min_s, max_s : float
    negative : int
        Samples received before their header stamp.

    """

    median_s: float
    sigma_s: float
    min_s: float
    max_s: float
    negative: int


@dataclass(frozen=True, kw_only=True)
class DeviceTiming(Record):
    """
    What a device's stamps say (the defaults: too few samples to say anything).

    Attributes
    ----------
    device : str
        ``'A'`` or ``'B'``.
    n : int
        Samples.
    nominal_interval_s, nominal_rate_hz : float or None
        The median interval and its rate.
    interval_scatter_s : float
        Robust σ of the intervals about whole multiples of the nominal one.
    stamp_jitter_s : float
        That over √2: the per-stamp σ.
    jittered : bool
        The stamps scatter beyond clean clocks and rounding.
    dropped : int
        Samples missing inside regular stretches.
    drop_share : float
    gaps : list of [float, float]
        Intervals far longer than a few periods: start and length, s.
    backward, duplicate : int
        Stamps going backwards, repeated.
    latency : Latency or None
        None without receive stamps.
    text : str
    irregular : bool, optional
        Stamp errors of a sizeable share of the period (read from the stamps' phases).
    quantum_s : float, optional
        The power of ten all stamps are multiples of, s (0: none above 1 ns).
    bunched : int, optional
        Intervals under half a period.

    """

    device: str
    n: int
    nominal_interval_s: Optional[float] = None
    nominal_rate_hz: Optional[float] = None
    interval_scatter_s: float = 0.0
    stamp_jitter_s: float = 0.0
    jittered: bool = False
    dropped: int = 0
    drop_share: float = 0.0
    gaps: list = field(default_factory=list)
    backward: int = 0
    duplicate: int = 0
    latency: Optional[Latency] = None
    text: str = 'too few samples'
    irregular: Optional[bool] = optional()
    quantum_s: Optional[float] = optional()
    bunched: Optional[int] = optional()

    @property
    def issues(self) -> bool:
        """Whether the stamps show jitter, drops, gaps, backward or duplicate stamps."""
        return bool(self.jittered or self.dropped or self.gaps or self.backward
                    or self.duplicate)


@dataclass(frozen=True, kw_only=True)
class StampReport(Record):
    """
    Stamp timing of both devices.

    Attributes
    ----------
    devices : list of DeviceTiming
        A's and B's.
    jittered : list of str
        The devices whose stamps scatter.
    issues : bool
        Some device shows jitter, drops, gaps, backward or duplicate stamps.

    """

    devices: list
    jittered: list
    issues: bool


def _robust_sd(x: np.ndarray) -> float:
    if x.size < 2:
        return 0.0
    return float(1.4826 * np.median(np.abs(x - np.median(x))))


def _phase_period(stamps: np.ndarray, guess: float) -> tuple[float, float]:
    """
    Period (s) and per-stamp σ (s) from the phases of stamps on a regular grid.

    With stamps ``t_i = t0 + k_i P + e_i`` (some k missing: drops), the mean resultant length
    ``R(P) = |mean exp(2πi t/P)|`` peaks at the true period and equals ``exp(-(2π σ/P)²/2)``
    for Gaussian errors of σ. The peak is searched on the first thousand stamps over ±10 %
    of the guess, then refined on all of them.
    """
    t = (np.sort(stamps) - stamps.min()).astype(float) * 1e-9

    def best(ts, lo, hi, n):
        grid = np.linspace(lo, hi, n)
        r = np.array([abs(np.mean(np.exp(2j * np.pi * ts / p))) for p in grid])
        i = int(np.argmax(r))
        return float(grid[i]), float(r[i]), float(grid[1] - grid[0])

    head = t[:1000]
    n1 = int(np.clip(0.8 * head.size * 4, 200, 4000))
    p1, _, step = best(head, 0.9 * guess, 1.1 * guess, n1)
    n2 = int(np.clip(8 * t.size / max(head.size, 1), 20, 400))
    p2, r2, _ = best(t, p1 - 2 * step, p1 + 2 * step, n2)
    if r2 < 4.0 / np.sqrt(t.size):
        # no phase left to read: errors of a third of the period or more
        return guess, float('inf')
    sigma = p2 / (2 * np.pi) * np.sqrt(max(-2.0 * np.log(max(r2, 1e-12)), 0.0))
    return p2, float(sigma)


def _quantum(stamps: np.ndarray) -> float:
    """Largest power of ten (s, 1 ns to 1 s) all stamps are multiples of, from the first."""
    rel = stamps - stamps[0]
    q = 0.0
    for k in range(1, 10):
        if np.all(rel % (10 ** k) == 0):
            q = 10.0 ** k * 1e-9
        else:
            break
    return q


def stamp_timing(stream: PoseStream, device: str) -> DeviceTiming:
    """
    Interval statistics, drops, gaps, backward and duplicate stamps of one device.

    Parameters
    ----------
    stream : PoseStream
        The device's samples in recorded order (stamps int64 ns; receive stamps optional).
    device : str
        Name for the text (``'A'``, ``'B'``).

    Returns
    -------
    DeviceTiming

    """
    stamps = np.asarray(stream.stamps, dtype=np.int64)
    n = int(stamps.size)
    timing = DeviceTiming(device=device, n=n)
    if n < 3:
        return timing
    d = np.diff(stamps)
    timing = replace(timing, backward=int(np.sum(d < 0)), duplicate=int(np.sum(d == 0)))
    pos = d[d > 0].astype(float) * 1e-9
    if pos.size < 2:
        return timing
    nominal = float(np.median(pos))
    k = np.maximum(np.rint(pos / nominal), 1.0)
    gap = (k > GAP_PERIODS) & (pos > GAP_MIN_S)
    regular = ~gap
    scatter = _robust_sd(pos[regular] - k[regular] * nominal)
    irregular = bool(scatter > 0.25 * nominal)
    if irregular:
        # stamp errors of a sizeable share of the period reorder and merge intervals: read
        # the period and the errors from the stamps' phases instead (drops keep the phase)
        nominal, sigma_phase = _phase_period(stamps, nominal)
        if not np.isfinite(sigma_phase):
            sigma_phase = nominal / 3.0
        k = np.maximum(np.rint(pos / nominal), 1.0)
        gap = (k > GAP_PERIODS) & (pos > GAP_MIN_S)
        regular = ~gap
        scatter = np.sqrt(2.0) * sigma_phase
        expected = float(np.sum(pos[regular])) / nominal + 1.0
        dropped = int(max(round(expected - 1.0 - regular.sum()), 0))
    else:
        dropped = int(np.sum(k[regular] - 1.0))
    t_rel = (stamps[1:][d > 0] - stamps[0]).astype(float) * 1e-9
    gaps = [[float(t_rel[i] - pos[i]), float(pos[i])] for i in np.flatnonzero(gap)]
    quantum = _quantum(stamps)
    floor = max(JITTER_MIN_S, JITTER_MIN_SHARE * nominal)
    if quantum >= 1e-6 and not irregular:
        # stamps rounded to a quantum (CSV exports in ms): intervals take a few values and
        # the median absolute deviation says little; the rounding itself scatters each stamp
        # by q/√12, which is not jitter
        # intervals under half a period are bunched samples, counted apart, not scatter
        r = (pos - k * nominal)[regular & (pos >= 0.5 * nominal)]
        lo, hi = np.percentile(r, [1, 99])
        scatter = float(np.std(r[(r >= lo) & (r <= hi)]))
        floor = max(floor, 1.5 * quantum / np.sqrt(12.0))
    jitter = scatter / np.sqrt(2.0)
    jittered = bool(jitter > floor)
    timing = replace(timing, nominal_interval_s=nominal, nominal_rate_hz=1.0 / nominal,
                     interval_scatter_s=float(scatter), stamp_jitter_s=float(jitter),
                     jittered=jittered, irregular=bool(irregular), quantum_s=quantum,
                     bunched=int(np.sum(pos < 0.5 * nominal)) if not irregular else 0,
                     dropped=dropped, drop_share=float(dropped / max(n + dropped, 1)),
                     gaps=gaps, latency=_latency(stream, stamps))
    return replace(timing, text=_text(timing))


def _latency(stream: PoseStream, stamps: np.ndarray) -> Optional[Latency]:
    """Return the receive latency of the samples (None without receive stamps)."""
    rec = stream.receive_stamps
    if rec is None or len(rec) != len(stamps) or np.array_equal(rec, stamps):
        # (receive stamps equal to the header stamps carry no receive time)
        return None
    lat = (np.asarray(rec, dtype=np.int64) - stamps).astype(float) * 1e-9
    return Latency(median_s=float(np.median(lat)), sigma_s=_robust_sd(lat),
                   min_s=float(lat.min()), max_s=float(lat.max()),
                   negative=int(np.sum(lat < 0)))


def _text(t: DeviceTiming) -> str:
    parts = [f'{t.nominal_rate_hz:.2f} Hz nominal, interval scatter '
             f'{t.interval_scatter_s * 1e3:.4f} ms']
    if t.quantum_s >= 1e-6:
        parts.append(f'stamps rounded to {t.quantum_s * 1e3:g} ms')
    if t.jittered:
        parts.append(f'stamp jitter {t.stamp_jitter_s * 1e3:.3f} ms'
                     + (' or more (stamps reordered: read from the residuals)'
                        if t.irregular else ''))
    if t.dropped:
        parts.append(f'{t.dropped} samples dropped ({t.drop_share * 100:.1f} %)')
    if t.gaps:
        longest = max(g[1] for g in t.gaps)
        parts.append(f'{len(t.gaps)} gaps (longest {longest:.2f} s)')
    if t.bunched:
        parts.append(f'{t.bunched} intervals under half a period')
    if t.backward or t.duplicate:
        parts.append(f'{t.backward} backward and {t.duplicate} duplicate stamps')
    if t.latency is not None:
        parts.append(f'receive latency {t.latency.median_s * 1e3:.2f} ± '
                     f'{t.latency.sigma_s * 1e3:.2f} ms')
    return '; '.join(parts)


def stamps_report(stream_a: PoseStream, streams_b) -> StampReport:
    """Stamp timing of both devices (B's marker topics share stamps: the first is read)."""
    b = streams_b[0] if isinstance(streams_b, (list, tuple)) else streams_b
    devices = [stamp_timing(stream_a, 'A'), stamp_timing(b, 'B')]
    return StampReport(devices=devices, jittered=[d.device for d in devices if d.jittered],
                       issues=any(d.issues for d in devices))


@dataclass(frozen=True, kw_only=True)
class StampJitter(Record):
    """
    Stamp jitter read from the stamps of the device that scatters most.

    Attributes
    ----------
    sigma_s, sigma_sigma_s : float
        Per-stamp σ and its standard uncertainty, s.
    device : str
        ``'A'`` or ``'B'``.
    dropped : int
        Samples the device dropped.
    gaps : list of [float, float]
        Its gaps: start and length, s.
    text : str

    """

    sigma_s: float
    sigma_sigma_s: float
    device: str
    dropped: int
    gaps: list
    text: str


def jitter_finding(report: StampReport) -> Optional[Finding]:
    """Return the ``timestamp_jitter`` the stamps show (None: no device's stamps scatter)."""
    devs = [d for d in report.devices if d.jittered]
    if not devs:
        return None
    worst = max(devs, key=lambda d: d.stamp_jitter_s)
    sig = worst.stamp_jitter_s
    extra = [f'{d.device}: {d.text}' for d in report.devices if d.dropped or d.gaps]
    text = (f'{sig * 1e3:.2f} ms on device {worst.device} from the stamps (interval scatter '
            f'{worst.interval_scatter_s * 1e3:.3f} ms)')
    if extra:
        text += '; ' + '; '.join(extra)
    estimate = StampJitter(sigma_s=sig, sigma_sigma_s=sig / np.sqrt(2.0 * max(worst.n - 1, 1)),
                           device=worst.device, dropped=worst.dropped, gaps=worst.gaps,
                           text=text)
    return Finding(name=TimestampJitterCandidate.name, kind=TimestampJitterCandidate.kind,
                   device=worst.device, source=STAMPS, estimate=estimate)
