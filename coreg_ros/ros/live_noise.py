"""
The node's noise: stated, measured while a device stands still, or estimated; one for all.

Stated: ``sigma_a``/``sigma_b`` or the ``noise_file``; measured while still by the monitors;
estimated with the last calibration.

``NoiseSources`` is the one place the node's noise comes from: ``apply(settings)`` (through
``ParameterView.settings``) gives every collaborator (the calibration, guidance, watchdog,
fusion) the same noise. It is the stated one (the ``noise_file``'s full covariances, else the
σ) unless the parameter ``noise`` is ``auto``: then a device's noise is the one the last
calibration estimated (``CalibrationResult.noise``), else the one measured while it stood
still (``core.live.still_noise``, once ``MIN_STILL_S`` of still time), else the stated; a
calibration with ``auto`` estimates the noise again, holding what the motion cannot separate
at that noise.

Once a second (the diagnostics timer) ``tick`` feeds the new samples of A and B (B's first
topic) to the still monitors and returns the status ``<node>: noise``: per device the noise
measured while still and the still time, the stated noise, what is used and where it comes
from; WARN when a device measured while still is far from its stated noise (with ``noise:
stated``) or its still parts are a frozen stream.
"""

from __future__ import annotations

from dataclasses import replace
from typing import Optional

from coreg_ros.core.live.still_noise import LiveNoise, StillNoiseMonitor
from coreg_ros.core.noise_model import DeviceNoise
from coreg_ros.core.settings import Settings
from coreg_ros.core.types import CalibrationResult
from diagnostic_msgs.msg import DiagnosticStatus, KeyValue
import numpy as np

#: Name suffix of the status.
STATUS_NAME = 'noise'
#: A device measured while still this many times off its stated σ (or its inverse) warns.
WARN_RATIO = 1.5


def _sigmas(noise: DeviceNoise, kind: str) -> str:
    return ' '.join(f'{v:.3g}' for v in noise.principal(kind)[0])


def _stated(settings: Settings, device: str) -> DeviceNoise:
    given = settings.device_noise(device)
    return given if isinstance(given, DeviceNoise) else DeviceNoise.isotropic(given)


class NoiseSources:
    """
    Where the node's noise comes from (module docstring).

    Parameters
    ----------
    noise_file : files.noise_file.NoiseFile or None
        The ``noise_file`` read at start-up.
    settings : Settings
        The start-up settings (topics, model, stated noise).

    """

    def __init__(self, noise_file, settings: Settings):
        self.noise_file = noise_file
        stated = self.stated(settings)
        self.topics = {'a': settings.topic_a, 'b': settings.topic_b[0]}
        self.monitors = {'a': StillNoiseMonitor(True, _stated(stated, 'a')),
                         'b': StillNoiseMonitor(settings.model == 'full_pose',
                                                _stated(stated, 'b'))}
        self._marks = dict.fromkeys(self.topics.values(), 0)
        self.estimated: Optional[dict] = None  # device -> DeviceNoise of the last calibration

    def stated(self, settings: Settings) -> Settings:
        """Return the settings with the noise file's noise (the stated noise)."""
        if self.noise_file is None:
            return settings
        from coreg_ros.files.noise_file import with_noise_file
        return with_noise_file(settings, self.noise_file)

    def measured(self) -> dict:
        """Return the noise measured while still, per device ({} before any)."""
        return {d: m.latest.noise for d, m in self.monitors.items()
                if m.latest.noise is not None}

    def apply(self, settings: Settings) -> Settings:
        """Return the settings with the noise the node uses now (module docstring)."""
        settings = self.stated(settings)
        if settings.noise != 'auto':
            return settings
        use = dict(self.measured())
        use.update(self.estimated or {})
        return replace(settings, **{f'noise_{d}': n for d, n in use.items()})

    def source(self, settings: Settings, device: str) -> str:
        """Say where a device's noise in use comes from."""
        if settings.noise == 'auto':
            if self.estimated and device in self.estimated:
                return 'estimated with the last calibration'
            if device in self.measured():
                return 'measured while still'
        return 'noise_file' if (self.noise_file is not None and getattr(
            self.noise_file, f'device_{device}') is not None) else 'sigma_' + device

    # --- listener of the calibrator ---------------------------------------------------------

    def set_result(self, result: CalibrationResult) -> None:
        """Keep the noise a calibration estimated (``noise: auto``)."""
        if result.noise is not None:
            self.estimated = dict(result.noise.estimated)

    def set_stored(self, doc: dict, *poses) -> None:
        """Keep nothing of a stored result at start-up: it says nothing of the noise now."""

    def forget(self) -> None:
        """Forget what was measured and estimated (``~/reset``)."""
        for d, m in self.monitors.items():
            self.monitors[d] = StillNoiseMonitor(m.rotation, m.fallback)
        self.estimated = None

    # --- the tick ---------------------------------------------------------------------------

    def feed(self, buffers: dict) -> None:
        """Give the monitors the samples accepted since the last tick."""
        for d, topic in self.topics.items():
            buffer = buffers.get(topic)
            if buffer is None:
                continue
            end, stream, _ = buffer.since(self._marks[topic])
            self._marks[topic] = end
            self.monitors[d].add(stream)

    def tick(self, node_name: str, settings: Settings, buffers: dict) -> DiagnosticStatus:
        """Feed the monitors and return the status ``<node>: noise``."""
        self.feed(buffers)
        stated = self.stated(settings)
        used = self.apply(settings)
        values, said, level = [KeyValue(key='noise', value=settings.noise)], [], 0
        for d in 'ab':
            live: LiveNoise = self.monitors[d].latest
            name = d.upper()
            st, us = _stated(stated, d), _stated(used, d)
            values += [
                KeyValue(key=f'{name} still seconds', value=f'{live.still_seconds:.1f}'),
                KeyValue(key=f'{name} still stretches', value=str(live.stretches)),
                KeyValue(key=f'{name} frozen seconds', value=f'{live.frozen_seconds:.1f}'),
                KeyValue(key=f'{name} stated position sigma m', value=_sigmas(st, 'position')),
                KeyValue(key=f'{name} stated rotation sigma rad', value=_sigmas(st, 'rotation')),
                KeyValue(key=f'{name} used position sigma m', value=_sigmas(us, 'position')),
                KeyValue(key=f'{name} used rotation sigma rad', value=_sigmas(us, 'rotation')),
                KeyValue(key=f'{name} source', value=self.source(settings, d))]
            if live.noise is not None:
                values += [KeyValue(key=f'{name} measured position sigma m',
                                    value=_sigmas(live.noise, 'position')),
                           KeyValue(key=f'{name} measured rotation sigma rad',
                                    value=_sigmas(live.noise, 'rotation'))]
                kinds = ('position', 'rotation') if self.monitors[d].rotation else ('position',)
                ratios = {k: float(np.sqrt(np.trace(live.noise.channel(k))
                                           / np.trace(st.channel(k)))) for k in kinds}
                text = ', '.join(f'{k} {r:.2g}× stated' for k, r in ratios.items())
                said.append(f'{name} measured still {live.still_seconds:.0f} s: {text}')
                off = [k for k, r in ratios.items() if max(r, 1.0 / r) > WARN_RATIO]
                if off and settings.noise != 'auto':
                    level = 1
                    said[-1] += ' (set noise: auto, or measure it: coreg noise)'
            else:
                said.append(f'{name} not still yet')
            if live.frozen_seconds > 0:
                level = 1
                said.append(f'{name} froze {live.frozen_seconds:.0f} s (identical samples: '
                            f'lost tracking?); not measured there')
        message = '; '.join(said) + f'; in use: {settings.noise}'
        return DiagnosticStatus(name=f'{node_name}: {STATUS_NAME}', level=bytes([level]),
                                message=message, hardware_id=' + '.join(self.topics.values()),
                                values=values)
