"""
Figures of the calibration report: Hoff & Vincent's Fig. 1 for T0 and T1, and the residuals.

- ``pose_uncertainty_figure``: each frame drawn with its 3σ position ellipsoid at the origin and a
  3σ cone about each axis (magnified, the factors printed in the captions);
- ``residuals_figure``: whitened output residuals per channel against the pair index, their
  histogram against N(0, 1), and (TLS) the whitened input residuals.

Matplotlib is used through its object API with the Agg canvas (no global backend, no display).
"""

from __future__ import annotations

import io

from coreg_ros.core import quaternion as quat
from coreg_ros.core import uncertainty as unc
from coreg_ros.core.types import CalibrationResult, UncertainPose
import numpy as np

AXIS_COLOURS = ('#d62728', '#2ca02c', '#1f77b4')
#: Displayed size of the largest ellipsoid semi-axis and cone half-angle after magnification.
_SHOW_ELLIPSOID = 0.3
_SHOW_CONE_DEG = 14.0


def new_figure(width: float, height: float):
    """Return an empty figure on the Agg canvas (inches; no global backend)."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(width, height), dpi=110)
    FigureCanvasAgg(fig)
    return fig


def png(fig) -> bytes:
    """Render a figure as PNG bytes."""
    buf = io.BytesIO()
    fig.savefig(buf, format='png', bbox_inches='tight')
    return buf.getvalue()


def rotation_known(pose: UncertainPose) -> bool:
    """Tell whether every rotation variance of the pose is known (positive)."""
    return pose.covariance is not None and bool(np.all(np.diag(pose.covariance)[3:6] > 0))


def position_known(pose: UncertainPose) -> bool:
    """Tell whether every position variance of the pose is known (positive)."""
    return pose.covariance is not None and bool(np.all(np.diag(pose.covariance)[0:3] > 0))


def draw_pose_uncertainty(ax, pose: UncertainPose, title: str, n_sigma: float = 3.0) -> dict:
    """
    Draw a frame with its position ellipsoid and axis cones (Hoff Fig. 1) on a 3-D axes.

    The frame is drawn at the origin with unit axes in the parent frame's orientation; the
    ellipsoid and the cones are magnified to be visible, by factors returned and printed.

    Parameters
    ----------
    ax : mpl_toolkits.mplot3d.Axes3D
        The axes drawn into.
    pose : UncertainPose
        With a ROS-layout covariance.
    title : str
        Title of the axes.
    n_sigma : float
        Size of the ellipsoid and cones, in standard deviations.

    Returns
    -------
    dict
        ``ellipsoid_gain`` (display units per metre) and ``cone_gain`` (factor on tan of the
        half-angle), None where not drawn.

    """
    R = quat.to_matrix(pose.quat_wxyz)
    gains = {'ellipsoid_gain': None, 'cone_gain': None}
    for i in range(3):
        a = R[:, i]
        ax.plot([0, a[0]], [0, a[1]], [0, a[2]], color=AXIS_COLOURS[i], lw=2.5)
        ax.text(*(1.12 * a), 'xyz'[i], color=AXIS_COLOURS[i], fontsize=11, weight='bold')
    if position_known(pose):
        ell = unc.ellipsoid_axes(pose.covariance[0:3, 0:3], n_sigma)
        gain = _SHOW_ELLIPSOID / max(float(ell.semi_axes[0]), 1e-300)
        shown = unc.Ellipsoid(ell.semi_axes * gain, ell.axes, ell.n_sigma, ell.probability)
        X, Y, Z = shown.surface(n=28)
        ax.plot_surface(X, Y, Z, color='#9467bd', alpha=0.35, linewidth=0, shade=True)
        ax.plot_wireframe(X, Y, Z, color='#5b3a8c', linewidth=0.3, alpha=0.5, rstride=3,
                          cstride=3)
        gains['ellipsoid_gain'] = gain
    if rotation_known(pose):
        cones = unc.axis_cones(pose, n_sigma)
        largest = max(float(np.max(c.half_angles)) for c in cones)
        gain = np.tan(np.radians(_SHOW_CONE_DEG)) / max(np.tan(largest), 1e-300)
        t = np.linspace(0.0, 2.0 * np.pi, 40)
        for c in cones:
            ext = gain * np.tan(c.half_angles)
            rim = (c.direction[:, None] + c.ellipse_axes[:, 0:1] * ext[0] * np.cos(t)
                   + c.ellipse_axes[:, 1:2] * ext[1] * np.sin(t))
            apex = np.zeros((3, t.size))
            X, Y, Z = (np.stack([apex[k], rim[k]]) for k in range(3))
            ax.plot_surface(X, Y, Z, color=AXIS_COLOURS[c.index], alpha=0.25, linewidth=0)
            ax.plot(rim[0], rim[1], rim[2], color=AXIS_COLOURS[c.index], lw=1.2)
        gains['cone_gain'] = gain
    ax.set_xlim(-1.1, 1.1)
    ax.set_ylim(-1.1, 1.1)
    ax.set_zlim(-1.1, 1.1)
    ax.set_box_aspect((1, 1, 1))
    ax.set_xticklabels([])
    ax.set_yticklabels([])
    ax.set_zticklabels([])
    ax.set_xlabel('X (parent)', labelpad=-10)
    ax.set_ylabel('Y (parent)', labelpad=-10)
    ax.set_zlabel('Z (parent)', labelpad=-10)
    ax.set_title(title, fontsize=11)
    return gains


def pose_uncertainty_figure(result: CalibrationResult, n_sigma: float = 3.0):
    """Figure with T0 and T1 drawn as in Hoff Fig. 1; returns (figure, captions)."""
    fig = new_figure(11.0, 5.6)
    captions = []
    for k, (pose, title) in enumerate((
            (result.base_to_base, "T0 base_to_base: A's base in B's base"),
            (result.tool_to_marker, "T1 tool_to_marker: B's marker in A's tool"))):
        ax = fig.add_subplot(1, 2, k + 1, projection='3d')
        g = draw_pose_uncertainty(ax, pose, title, n_sigma)
        ax.view_init(elev=22, azim=-55)
        lines, shown = [], []
        if position_known(pose):
            ell = unc.ellipsoid_axes(pose.covariance[0:3, 0:3], n_sigma)
            lines.append(f'ellipsoid {n_sigma:g}σ semi-axes '
                         f'{", ".join(f"{v * 1e3:.3f}" for v in ell.semi_axes)} mm')
            shown.append(f'1 mm as {g["ellipsoid_gain"] * 1e-3:.3g} axis lengths')
        if rotation_known(pose):
            cones = unc.axis_cones(pose, n_sigma)
            lines.append(f'cone {n_sigma:g}σ half-angles (largest) ' + ', '.join(
                f'{"xyz"[c.index]} {np.degrees(c.half_angles[0]):.4f}°' for c in cones))
            shown.append(f'cone widths ×{g["cone_gain"]:.0f}')
        else:
            lines.append('orientation not estimated: no cones')
        if shown:
            lines.append('shown magnified: ' + ', '.join(shown))
        ax.text2D(0.5, -0.02, '\n'.join(lines), transform=ax.transAxes, ha='center',
                  va='top', fontsize=9)
        if k == 0:
            captions.append(
                'Each panel shows the frame with unit-length axes, oriented as in its parent '
                "frame (T0 in B's base axes, T1 in A's tool axes). The ellipsoid and the cones "
                'are magnified to be visible (factors under each panel); the numbers give '
                'their true sizes.')
    fig.suptitle(f'Calibration uncertainty (Hoff & Vincent Fig. 1 style, {n_sigma:g}σ)',
                 fontsize=13)
    return fig, captions


def _autocorrelation(x: np.ndarray, max_lag: int) -> np.ndarray:
    """Autocorrelation of each column of x (N, m) at lags 0..max_lag, shape (max_lag + 1, m)."""
    x = x - x.mean(axis=0)
    n = len(x)
    f = np.fft.rfft(x, n=2 * n, axis=0)
    ac = np.fft.irfft(f * np.conj(f), axis=0)[:max_lag + 1]
    return ac / np.maximum(ac[0], 1e-300)


def residuals_figure(result: CalibrationResult):
    """
    Residual plots: whitened residuals against the pair index, per-pair χ², whiteness.

    For TLS the output and input residuals of a pair share its noise (the fitted input
    absorbs part of it), so neither alone is N(0, 1); their squared norm together follows
    χ² with m degrees of freedom (m residuals per pair), which is what the histogram shows.
    """
    from scipy import stats

    res = np.asarray(result.residuals, dtype=float)
    inp = None if result.input_residuals is None else np.asarray(result.input_residuals)
    has_inp = inp is not None and inp.size > 0
    n, m = res.shape
    fig = new_figure(11.0, 6.8)
    out_labels = (['x', 'y', 'z', 'rot x', 'rot y', 'rot z'] if m == 6
                  else [f'm{j // 3 + 1} {"xyz"[j % 3]}' for j in range(m)])
    step = max(1, n // 4000)  # at most ~4000 points per channel
    idx = np.arange(n)[::step]

    def scatter(ax, data, labels, title):
        for j in range(data.shape[1]):
            ax.plot(idx, data[::step, j], '.', ms=1.5, alpha=0.5, label=labels[j])
        for y in (-3, 3):
            ax.axhline(y, color='k', lw=0.8, ls='--')
        ax.set_xlabel('pair index')
        ax.set_ylabel('whitened residual')
        ax.set_title(title, fontsize=10)
        ax.legend(markerscale=6, fontsize=7, ncol=3, loc='upper right')

    scatter(fig.add_subplot(2, 2, 1), res, out_labels,
            'device B (output) residuals against time (±3 dashed)')
    chi = np.sum(res ** 2, axis=1) + (np.sum(inp ** 2, axis=1) if has_inp else 0.0)
    ax = fig.add_subplot(2, 2, 2)
    hi = max(float(np.percentile(chi, 99.5)), stats.chi2.ppf(0.999, m))
    ax.hist(chi, bins=np.linspace(0, hi, 60), density=True, color='#7f7f7f', alpha=0.7,
            label='pairs')
    xs = np.linspace(0, hi, 300)
    ax.plot(xs, stats.chi2.pdf(xs, m), 'r', lw=1.5, label=f'χ²({m})')
    ax.set_xlabel('squared whitened residual of a pair'
                  + (' (output + input)' if has_inp else ''))
    ax.set_title(f'per-pair χ²: mean {chi.mean():.2f} (expected ≈ {m})', fontsize=10)
    ax.legend(fontsize=8)
    ax = fig.add_subplot(2, 2, 3)
    if has_inp:
        scatter(ax, inp, ['x', 'y', 'z', 'rot x', 'rot y', 'rot z'],
                'device A (input) residuals against time (TLS adjustments)')
    else:
        ax.plot(idx, chi[::step], '.', ms=1.5, color='#444')
        ax.axhline(stats.chi2.ppf(0.999, m), color='r', lw=0.8, ls='--', label='99.9 %')
        ax.set_xlabel('pair index')
        ax.set_ylabel('per-pair χ²')
        ax.set_title('per-pair χ² against time', fontsize=10)
        ax.legend(fontsize=8)
    ax = fig.add_subplot(2, 2, 4)
    lags = min(60, n // 4)
    ac = _autocorrelation(res, lags)
    for j in range(m):
        ax.plot(np.arange(1, lags + 1), ac[1:, j], lw=1, label=out_labels[j])
    band = 2.0 / np.sqrt(n)
    ax.axhspan(-band, band, color='#2ca02c', alpha=0.15, label='±2/√N (white)')
    ax.set_xlabel('lag (pairs)')
    ax.set_ylabel('autocorrelation')
    ax.set_title('whiteness of the output residuals', fontsize=10)
    ax.legend(fontsize=7, ncol=3, loc='upper right')
    fig.tight_layout()
    return fig
