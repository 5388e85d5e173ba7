"""
The measured noise for a person (``coreg noise``'s text) and as JSON (``--json``).

σ in mm and mrad for reading; the JSON keeps SI units (m, m², rad, rad²) in each device's
base frame.
"""

from __future__ import annotations

from coreg_ros.core.noise.measure import ChannelNoise, DeviceMeasurement
from coreg_ros.core.noise.recording import NoiseReport
import numpy as np

#: Display factor and unit of each channel.
SHOWN = {'position': (1e3, 'mm'), 'rotation': (1e3, 'mrad')}
#: An axis direction whose standard error exceeds this (rad) is not stated (two σ too close).
AXIS_UNDEFINED_RAD = np.radians(15.0)


def _vec(v) -> str:
    return '[' + ', '.join(f'{x:+.2f}' for x in v) + ']'


def _allan_line(ch: ChannelNoise, k: float, unit: str) -> str:
    a = ch.allan
    white = ', '.join(f'{v * k:.3g}' for v in a.white)
    line = f'Allan: white {white} {unit} per sample'
    if np.isfinite(a.tau_limit):
        takes = 'drift' if np.max(a.drift) > 0 and not np.max(a.random_walk) > 0 else \
            'random walk' if not np.max(a.drift) > 0 else 'random walk and drift'
        line += f'; {takes} takes over beyond {a.tau_limit:.3g} s (average at most that long)'
    else:
        line += (f'; no random walk or drift within {a.tau[-1] * 2:.3g} s (averaging helps '
                 f'all the way)')
    return line


def channel_lines(ch: ChannelNoise) -> list:
    """Return the lines of one channel: σ per base axis, principal σ and axes, Allan, distance."""
    k, unit = SHOWN[ch.name]
    pairs = zip(ch.sigma_axes, ch.sigma_axes_se, strict=True)
    axes = ', '.join(f'{s * k:.3g} ± {e * k:.2g}' for s, e in pairs)
    out = [f'{ch.name:<8} σ along x y z: {axes} {unit}']
    parts = []
    defined = ch.axis_angle_se < AXIS_UNDEFINED_RAD
    for s, e, a, da, ok in zip(ch.principal_sigma, ch.principal_sigma_se, ch.principal_axes,
                               ch.axis_angle_se, defined, strict=True):
        parts.append(f'{s * k:.3g} ± {e * k:.2g}'
                     + (f' along {_vec(a)} (± {np.degrees(da):.1f}°)' if ok else ''))
    note = ('' if defined.all() else '; no axis stands out: isotropic within the uncertainty'
            if not defined.any() else '; the others equal within the uncertainty')
    out.append('         principal: ' + '; '.join(parts) + note)
    out.append('         ' + _allan_line(ch, k, unit))
    if ch.distance is not None:
        d = ch.distance
        r = d.distances_m
        out.append(f'         grows with distance: σ ∝ r^{d.exponent:.2f} ± {d.exponent_se:.2f} '
                   f'({r.min():.2f}-{r.max():.2f} m from the base; {d.sigma_ref * k:.3g} {unit} '
                   f'at {d.reference_m:.2f} m)')
    return out


def device_lines(m: DeviceMeasurement) -> list:
    """Return the lines of one device."""
    s = m.sampling
    spans = ', '.join(f'{a:.1f}-{b:.1f} s' for a, b, _ in m.segment_times())
    name = f'device {m.device.upper()}' + (f' ({m.topic}' if m.topic else '') + (
        f', frame {m.frame_id})' if m.frame_id else (')' if m.topic else ''))
    out = [f'{name}: {len(m.segments)} still segment(s), {s.duration_s:.1f} s ({spans}); '
           f'{s.n_samples} samples at {s.rate_hz:.1f} Hz (nominal {s.nominal_hz:.1f} Hz), '
           f'{s.dropped} dropped, {s.repeated_stamps} repeated stamps, {s.repeated_samples} '
           f'repeated samples']
    for ch in m.channels.values():
        out += ['  ' + line for line in channel_lines(ch)]
    out += [f'  warning: {w}' for w in m.warnings]
    return out


def format_noise_report(report: NoiseReport) -> str:
    """Render the measured noise of both devices for a person."""
    out = []
    for m in report.devices():
        out += device_lines(m)
    out.append("σ are 1-sigma per sample about each device's base axes (± their standard "
               'error); the rotation is the rotation vector of R = Exp(δθ)·R_mean.')
    return '\n'.join(out)


def device_dict(m: DeviceMeasurement) -> dict:
    """JSON of one device: the covariances, principal σ, segments, Allan, sampling."""
    out = {'topic': m.topic, 'frame_id': m.frame_id}
    for name, ch in m.channels.items():
        unit = 'm' if name == 'position' else 'rad'
        out[f'{name}_covariance'] = ch.covariance.tolist()
        out[f'{name}_sigma_{unit}'] = ch.principal_sigma.tolist()
        out[f'{name}_axes'] = ch.principal_axes.tolist()
    out.update({name: ch.as_dict() for name, ch in m.channels.items()})
    out['allan'] = {name: ch.allan.as_dict() for name, ch in m.channels.items()}
    out['segments'] = [{'start_s': a, 'end_s': b, 'samples': n} for a, b, n in
                       m.segment_times()]
    out['frozen_segments'] = [{'start_s': a, 'end_s': b, 'samples': n} for a, b, n in
                              m.segment_times(m.frozen)]
    s = m.sampling
    out['sampling'] = {'rate_hz': s.rate_hz, 'nominal_hz': s.nominal_hz,
                       'samples': s.n_samples, 'duration_s': s.duration_s,
                       'dropped': s.dropped, 'repeated_stamps': s.repeated_stamps,
                       'repeated_samples': s.repeated_samples}
    out['warnings'] = list(m.warnings)
    return out


def noise_report_dict(report: NoiseReport) -> dict:
    """JSON of the measured noise: ``model``, ``window``, ``device_a``, ``device_b``."""
    return {'model': report.model,
            'window': None if report.window is None else list(report.window),
            'device_a': device_dict(report.device_a), 'device_b': device_dict(report.device_b)}
