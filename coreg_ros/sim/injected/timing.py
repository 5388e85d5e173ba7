"""
Clock and stamp effects: an offset, a drift, jitter with drops and gaps, one host clock.

They act on the recorded stamps (stage ``'measured'``); the poses stay as measured.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Optional

from coreg_ros.sim.changes import step_stamps
from coreg_ros.sim.injected.common import EFFECT_UNITS
from coreg_ros.sim.injection import EffectContext
import numpy as np

#: Share of B's samples a ``timestamp_jitter`` drops.
JITTER_DROP_FRACTION = 0.02


@dataclass(frozen=True)
class TimeOffset:
    """
    Device B stamped τ late: B's header stamps are the true time plus ``tau_s``.

    Calibrating with ``time_offset = tau_s`` (``Settings.time_offset``, B's clock minus A's)
    undoes it exactly.
    """

    tau_s: float
    stage = 'measured'

    def __call__(self, streams: dict, context: EffectContext, rng) -> dict:
        """Shift the stamps of every B topic by τ (rounded to ns)."""
        shift = np.int64(round(self.tau_s * 1e9))
        out = dict(streams)
        for t in context.topics_b:
            out[t] = replace(streams[t], stamps=streams[t].stamps + shift)
        return out

    def as_dict(self) -> dict:
        """Describe the effect: ``tau_s``."""
        return {'name': 'time_offset', 'value': self.tau_s, 'unit': EFFECT_UNITS['time_offset'],
                'stage': self.stage, 'tau_s': self.tau_s}


@dataclass(frozen=True)
class ClockDrift:
    """
    B's clock runs fast by ``ppm``: stamps + κ (t - t_start), κ = ppm · 1e-6.

    The offset is zero at the recording's start (``EffectContext.start_ns``) and grows
    linearly: 100 ppm give 6 ms after a minute.
    """

    ppm: float
    stage = 'measured'
    _found: dict = field(default_factory=dict, init=False, repr=False, compare=False)

    def __call__(self, streams: dict, context: EffectContext, rng) -> dict:
        """Add κ (t - t_start) to the stamps of every B topic."""
        kappa = self.ppm * 1e-6
        out = dict(streams)
        last = 0
        for t in context.topics_b:
            s = streams[t]
            elapsed = (s.stamps - np.int64(context.start_ns)).astype(float)
            shift = np.round(kappa * elapsed).astype(np.int64)
            out[t] = replace(s, stamps=s.stamps + shift)
            last = int(shift[-1]) if len(s) else 0
        self._found['offset_at_end_s'] = last * 1e-9
        return out

    def as_dict(self) -> dict:
        """Describe the effect: ``ppm``, ``kappa`` and the offset reached at the end, s."""
        return {'name': 'clock_drift', 'value': self.ppm, 'unit': EFFECT_UNITS['clock_drift'],
                'stage': self.stage, 'ppm': self.ppm, 'kappa': self.ppm * 1e-6, **self._found}


@dataclass(frozen=True)
class TimestampJitter:
    """
    Random stamp errors on B, N(0, ``sigma_s``²) each, and ``drop_fraction`` of B's samples lost.

    The three marker topics of a three-marker tracker share their stamp errors and drops (one
    device). Jittered stamps that come out of order are sorted (a sample keeps its pose and
    wrong stamp); a stamp that repeats another is dropped too.
    """

    sigma_s: float
    drop_fraction: float = JITTER_DROP_FRACTION
    gaps: int = 0
    gap_s: float = 2.0
    stage = 'measured'
    _found: dict = field(default_factory=dict, init=False, repr=False, compare=False)

    def __call__(self, streams: dict, context: EffectContext, rng) -> dict:
        """Jitter, drop, cut gaps, sort and de-duplicate B's samples."""
        first = streams[context.topics_b[0]]
        n = len(first)
        error = np.round(rng.standard_normal(n) * self.sigma_s * 1e9).astype(np.int64)
        n_drop = int(round(self.drop_fraction * n))
        dropped = rng.choice(n, size=n_drop, replace=False) if n_drop else np.array([], int)
        keep = np.ones(n, dtype=bool)
        keep[dropped] = False
        t = (first.stamps - first.stamps[0]).astype(float) * 1e-9
        gap_list = []
        for _ in range(self.gaps):
            # a stretch of gap_s seconds with no sample at all (a lost connection)
            start = rng.uniform(0.1, 0.9) * max(float(t[-1]) - self.gap_s, 0.0) if n else 0.0
            keep[(t >= start) & (t < start + self.gap_s)] = False
            gap_list.append([float(start), float(self.gap_s)])
        stamps = first.stamps + error
        idx = np.flatnonzero(keep)
        idx = idx[np.argsort(stamps[idx], kind='stable')]
        unique = np.ones(idx.size, dtype=bool)
        unique[1:] = np.diff(stamps[idx]) > 0
        idx = idx[unique]
        out = dict(streams)
        for t in context.topics_b:
            s = streams[t]
            out[t] = replace(s, stamps=s.stamps + error).take(idx)
        self._found.update(n_dropped=int(n - idx.size), gaps_s=gap_list,
                           empirical_sigma_s=float(np.std(error[idx]) * 1e-9) if idx.size else 0.0)
        return out

    def as_dict(self) -> dict:
        """Describe the effect: ``sigma_s``, ``drop_fraction`` and the samples dropped."""
        return {'name': 'timestamp_jitter', 'value': self.sigma_s,
                'unit': EFFECT_UNITS['timestamp_jitter'], 'stage': self.stage,
                'sigma_s': self.sigma_s, 'drop_fraction': self.drop_fraction, **self._found}


@dataclass(frozen=True)
class SharedClock:
    """
    Both devices stamped on receipt by one host clock: a constant offset, never a drift.

    Header stamps = true sample time + the device's transport latency + a small positive
    host scheduling delay (exponential, mean ``host_jitter_s``); the recorder's receive stamps
    follow by an exponential 0.3 ms on average. ``latency_s`` is B's latency minus A's (A's
    is drawn in 1-5 ms): the offset the diagnosis should find (B stamped late by it), with no
    drift at all.
    """

    latency_s: float
    host_jitter_s: float = 3e-5
    stage = 'measured'
    _found: dict = field(default_factory=dict, init=False, repr=False, compare=False)

    def __call__(self, streams: dict, context: EffectContext, rng) -> dict:
        """Restamp A and B with host receive times."""
        lat_a = rng.uniform(0.001, 0.005)
        out = dict(streams)
        first = streams[context.topics_b[0]]
        delay_b = rng.exponential(self.host_jitter_s, len(first))
        for topic, lat, delay in (
                [(context.topic_a, lat_a, rng.exponential(self.host_jitter_s,
                                                          len(streams[context.topic_a])))]
                + [(t, lat_a + self.latency_s, delay_b) for t in context.topics_b]):
            s = streams[topic]
            stamps = s.stamps + np.round((lat + delay) * 1e9).astype(np.int64)
            order = np.argsort(stamps, kind='stable')
            keep = np.ones(len(order), dtype=bool)
            keep[1:] = np.diff(stamps[order]) > 0
            idx = order[keep]
            # the recorder receives each message a little after the driver stamped it
            receive = stamps + np.round(rng.exponential(3e-4, len(stamps)) * 1e9).astype(
                np.int64)
            out[topic] = replace(s, stamps=stamps, receive_stamps=receive).take(idx)
        self._found.update(latency_a_s=float(lat_a))
        return out

    def as_dict(self) -> dict:
        """Describe the effect: ``latency_s`` (B's minus A's) and A's latency."""
        return {'name': 'shared_clock', 'value': self.latency_s,
                'unit': EFFECT_UNITS['shared_clock'], 'stage': self.stage,
                'latency_s': self.latency_s, 'host_jitter_s': self.host_jitter_s,
                **self._found}


@dataclass(frozen=True)
class ClockStep:
    """
    B's clock jumps by ``step_s`` once: stamps at or after the instant grow by it.

    The instant is ``at`` (a share of the recording, drawn in 0.25-0.75 when None). A clock
    set back makes some stamps repeat earlier ones: B's samples are then sorted by stamp (a
    sample keeps its pose and its wrong stamp) and a repeated stamp is dropped, as
    ``TimestampJitter`` does. B's offset is ``step_s`` larger after the instant.
    """

    step_s: float
    at: Optional[float] = None
    stage = 'measured'
    _found: dict = field(default_factory=dict, init=False, repr=False, compare=False)

    def __call__(self, streams: dict, context: EffectContext, rng) -> dict:
        """Step the stamps of every B topic at the instant."""
        first = streams[context.topics_b[0]]
        share = rng.uniform(0.25, 0.75) if self.at is None else float(self.at)
        t0, t1 = int(first.stamps[0]), int(first.stamps[-1])
        at = t0 + int(round(share * (t1 - t0)))
        stamps = step_stamps(first.stamps, at, int(round(self.step_s * 1e9)))
        idx = np.argsort(stamps, kind='stable')
        unique = np.ones(idx.size, dtype=bool)
        unique[1:] = np.diff(stamps[idx]) > 0
        idx = idx[unique]
        out = dict(streams)
        for t in context.topics_b:
            s = streams[t]
            out[t] = replace(s, stamps=step_stamps(s.stamps, at, int(round(self.step_s * 1e9)))
                             ).take(idx)
        self._found.update(at_s=(at - t0) * 1e-9, at_ns=at)
        return out

    def as_dict(self) -> dict:
        """Describe the effect: ``step_s`` and the instant (s from B's first sample)."""
        return {'name': 'clock_step', 'value': self.step_s, 'unit': EFFECT_UNITS['clock_step'],
                'stage': self.stage, 'step_s': self.step_s, **self._found}
