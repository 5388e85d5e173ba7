"""
The figure of ``coreg noise --plot``: each device's Allan deviation and its σ per axis.

One row per device: the Allan deviation of the position and of the rotation per base axis
with the fitted white noise (slope -1/2) and the averaging limit, and the σ along the base
axes with their standard errors.
"""

from __future__ import annotations

from coreg_ros.core.noise.recording import NoiseReport
from coreg_ros.report.figures import AXIS_COLOURS, new_figure, png
import numpy as np

_SHOWN = {'position': (1e3, 'mm'), 'rotation': (1e3, 'mrad')}


def _allan_axes(ax, ch, title: str) -> None:
    k, unit = _SHOWN[ch.name]
    a = ch.allan
    for i, axis in enumerate('xyz'):
        ax.loglog(a.tau, a.adev[:, i] * k, 'o-', ms=3, color=AXIS_COLOURS[i],
                  label=f'{axis}: white {a.white[i] * k:.3g} {unit}')
        fit = np.sqrt(a.white[i] ** 2 * a.tau0 / a.tau + a.random_walk[i] ** 2 * a.tau / 3.0
                      + a.drift[i] ** 2 * a.tau ** 2 / 2.0)
        ax.loglog(a.tau, fit * k, '--', lw=0.8, color=AXIS_COLOURS[i])
    if np.isfinite(a.tau_limit):
        ax.axvline(a.tau_limit, color='grey', lw=0.8, ls=':')
    ax.set_xlabel('averaging time τ [s]')
    ax.set_ylabel(f'Allan deviation [{unit}]')
    ax.set_title(title, fontsize=9)
    ax.legend(fontsize=7)
    ax.grid(True, which='both', alpha=0.3)


def _sigma_axes(ax, channels: dict, title: str) -> None:
    names = list(channels)
    width = 0.8 / max(len(names), 1)
    for j, name in enumerate(names):
        ch = channels[name]
        k, unit = _SHOWN[name]
        ax.bar(np.arange(3) + j * width, ch.sigma_axes * k, width,
               yerr=2.0 * ch.sigma_axes_se * k, capsize=3, color=AXIS_COLOURS,
               alpha=0.9 if j == 0 else 0.5, label=f'{name} [{unit}]')
    ax.set_xticks(np.arange(3) + 0.4 - width / 2)
    ax.set_xticklabels(['x', 'y', 'z'])
    ax.set_ylabel('σ along the base axes (±2 SE)')
    ax.set_title(title, fontsize=9)
    ax.legend(fontsize=7)


def noise_figure(report: NoiseReport):
    """Return the figure: per device, Allan deviation of each channel and σ per axis."""
    fig = new_figure(13.0, 3.6 * 2)
    for row, m in enumerate(report.devices()):
        name = f'device {m.device.upper()}' + (f' ({m.topic})' if m.topic else '')
        col = 1
        for ch in m.channels.values():
            _allan_axes(fig.add_subplot(2, 3, row * 3 + col), ch, f'{name}: {ch.name}')
            col += 1
        _sigma_axes(fig.add_subplot(2, 3, row * 3 + 3), m.channels, f'{name}: σ per axis')
    fig.tight_layout()
    return fig


def write_noise_plot(report: NoiseReport, path) -> None:
    """Write ``noise_figure(report)`` as a PNG file."""
    from coreg_ros.files.atomic import write_bytes

    write_bytes(path, png(noise_figure(report)))
