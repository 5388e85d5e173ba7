"""
HTML report of a calibration: uncertainty ellipsoids and axis cones, residuals, point errors.

``write_calibration_report(result, out_dir)`` writes ``out_dir/index.html`` (self-contained,
the figures embedded as PNG) and the figures as separate PNG files beside it:

- ``pose_uncertainty.png``: T0 and T1 drawn as in Hoff & Vincent's Fig. 1, the 3σ position
  ellipsoid at the frame origin and a 3σ cone about each axis (magnified, factors printed);
- ``residuals.png``: whitened output residuals per channel against the pair index, their
  histogram against N(0, 1), and (TLS) the whitened input residuals;
- tables: the ellipsoid semi-axes and directions, the cone half-angles, and the registration
  error expected at user-given points.

Matplotlib is used through its object API with the Agg canvas (no global backend, no display).
"""

from __future__ import annotations

import base64
from collections.abc import Sequence
import html
import io
from pathlib import Path
from typing import Optional

from coreg_ros.core import quaternion as quat
from coreg_ros.core import uncertainty as unc
from coreg_ros.core.types import CalibrationResult, PairingReport, UncertainPose
import numpy as np

#: Frames user points may be given in.
POINT_FRAMES = ('a_base', 'a_tool')
_AXIS_COLOURS = ('#d62728', '#2ca02c', '#1f77b4')
#: Displayed size of the largest ellipsoid semi-axis and cone half-angle after magnification.
_SHOW_ELLIPSOID = 0.3
_SHOW_CONE_DEG = 14.0


def _figure(width: float, height: float):
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(width, height), dpi=110)
    FigureCanvasAgg(fig)
    return fig


def _png(fig) -> bytes:
    buf = io.BytesIO()
    fig.savefig(buf, format='png', bbox_inches='tight')
    return buf.getvalue()


def _rotation_known(pose: UncertainPose) -> bool:
    return pose.covariance is not None and bool(np.all(np.diag(pose.covariance)[3:6] > 0))


def _position_known(pose: UncertainPose) -> bool:
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
        ax.plot([0, a[0]], [0, a[1]], [0, a[2]], color=_AXIS_COLOURS[i], lw=2.5)
        ax.text(*(1.12 * a), 'xyz'[i], color=_AXIS_COLOURS[i], fontsize=11, weight='bold')
    if _position_known(pose):
        ell = unc.ellipsoid_axes(pose.covariance[0:3, 0:3], n_sigma)
        gain = _SHOW_ELLIPSOID / max(float(ell.semi_axes[0]), 1e-300)
        shown = unc.Ellipsoid(ell.semi_axes * gain, ell.axes, ell.n_sigma, ell.probability)
        X, Y, Z = shown.surface(n=28)
        ax.plot_surface(X, Y, Z, color='#9467bd', alpha=0.35, linewidth=0, shade=True)
        ax.plot_wireframe(X, Y, Z, color='#5b3a8c', linewidth=0.3, alpha=0.5, rstride=3,
                          cstride=3)
        gains['ellipsoid_gain'] = gain
    if _rotation_known(pose):
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
            ax.plot_surface(X, Y, Z, color=_AXIS_COLOURS[c.index], alpha=0.25, linewidth=0)
            ax.plot(rim[0], rim[1], rim[2], color=_AXIS_COLOURS[c.index], lw=1.2)
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
    fig = _figure(11.0, 5.6)
    captions = []
    for k, (pose, title) in enumerate((
            (result.base_to_base, "T0 base_to_base: A's base in B's base"),
            (result.tool_to_marker, "T1 tool_to_marker: B's marker in A's tool"))):
        ax = fig.add_subplot(1, 2, k + 1, projection='3d')
        g = draw_pose_uncertainty(ax, pose, title, n_sigma)
        ax.view_init(elev=22, azim=-55)
        lines, shown = [], []
        if _position_known(pose):
            ell = unc.ellipsoid_axes(pose.covariance[0:3, 0:3], n_sigma)
            lines.append(f'ellipsoid {n_sigma:g}σ semi-axes '
                         f'{", ".join(f"{v * 1e3:.3f}" for v in ell.semi_axes)} mm')
            shown.append(f'1 mm as {g["ellipsoid_gain"] * 1e-3:.3g} axis lengths')
        if _rotation_known(pose):
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
    fig = _figure(11.0, 6.8)
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


def point_errors(result: CalibrationResult, points, frame: str = 'a_base',
                 n_sigma: float = 3.0) -> list[dict]:
    """
    Registration error expected at user points from the calibration's uncertainty (§3.3).

    Parameters
    ----------
    result : CalibrationResult
        The calibration.
    points : array_like, shape (M, 3)
        Points, m: in A's base frame (``frame='a_base'``: mapped into B's base frame by T0, the
        registration of A's workspace in B's) or in A's tool frame (``'a_tool'``: located in
        B's marker frame by T1⁻¹, e.g. a stylus tip on the tool as B's tracking sees it).
    frame : str
        ``a_base`` or ``a_tool``.
    n_sigma : float
        Size of the ellipsoids, in standard deviations.

    Returns
    -------
    list of dict
        Per point: ``point`` (given), ``mapped`` (m, in the target frame), ``rms`` (m,
        √trace C), ``semi_axes`` (m, n_sigma ellipsoid), ``axes`` (3×3 columns), or
        ``unknown`` True where the model does not determine it.

    """
    if frame not in POINT_FRAMES:
        raise ValueError(f'frame must be one of {POINT_FRAMES}, got {frame!r}')
    pts = np.atleast_2d(np.asarray(points, dtype=float))
    pose = result.base_to_base if frame == 'a_base' else unc.invert(result.tool_to_marker)
    out = []
    for x in pts:
        y, cov = unc.propagate_point(pose, x)
        entry = {'point': x, 'mapped': y}
        if (np.diag(cov) < 0).any():
            entry['unknown'] = True
        else:
            ell = unc.ellipsoid_axes(cov, n_sigma)
            entry.update(unknown=False, rms=float(np.sqrt(np.trace(cov))),
                         semi_axes=ell.semi_axes, axes=ell.axes)
        out.append(entry)
    return out


def _b64(png: bytes) -> str:
    return base64.b64encode(png).decode('ascii')


def _vec(v, scale=1.0, fmt='{:.3f}') -> str:
    return '[' + ', '.join(fmt.format(x * scale) for x in v) + ']'


def _pose_table(name: str, pose: UncertainPose, n_sigma: float) -> str:
    rows = [f'<h3>{html.escape(name)}</h3>', '<table>']
    rows.append(f'<tr><th>position</th><td>{_vec(pose.position, 1.0, "{:.6f}")} m</td></tr>')
    w, x, y, z = pose.quat_wxyz
    rows.append(f'<tr><th>orientation (w, x, y, z)</th><td>[{w:.6f}, {x:.6f}, {y:.6f}, '
                f'{z:.6f}]</td></tr>')
    if _position_known(pose):
        ell = unc.ellipsoid_axes(pose.covariance[0:3, 0:3], n_sigma)
        rows.append(f'<tr><th>{n_sigma:g}σ position ellipsoid semi-axes</th>'
                    f'<td>{_vec(ell.semi_axes, 1e3)} mm '
                    f'(holds {100 * ell.probability:.1f} %)</td></tr>')
        for k in range(3):
            rows.append(f'<tr><th>&nbsp;&nbsp;axis {k + 1} direction</th>'
                        f'<td>{_vec(ell.axes[:, k], 1.0, "{:+.3f}")}</td></tr>')
    if _rotation_known(pose):
        for c in unc.axis_cones(pose, n_sigma):
            rows.append(f'<tr><th>{"xyz"[c.index]} axis cone ({n_sigma:g}σ half-angles)</th>'
                        f'<td>{np.degrees(c.half_angles[0]):.4f}° × '
                        f'{np.degrees(c.half_angles[1]):.4f}°</td></tr>')
    else:
        rows.append('<tr><th>orientation uncertainty</th><td>not estimated by this model'
                    '</td></tr>')
    rows.append('</table>')
    return '\n'.join(rows)


_CSS = """
body { font-family: sans-serif; max-width: 1150px; margin: 1.5em auto; color: #222; }
table { border-collapse: collapse; margin: 0.5em 0 1em 0; }
th, td { border: 1px solid #ccc; padding: 3px 8px; text-align: left; font-size: 0.92em; }
th { background: #f4f4f4; font-weight: normal; }
.ok { color: #2a7d2a; } .bad { color: #b22222; }
figure { margin: 0.5em 0; } figcaption { font-size: 0.85em; color: #555; }
img { max-width: 100%; }
"""


def render_html(result: CalibrationResult, figures: dict, captions: Sequence[str],
                points: Optional[list], points_frame: str, report: Optional[PairingReport],
                title: str, n_sigma: float) -> str:
    """Assemble the report page (figures as {name: png bytes})."""
    status = ('<span class="ok">success</span>' if result.success
              else '<span class="bad">FAILED</span>')
    ratio = result.reduced_chi2
    parts = [
        '<!DOCTYPE html>', '<html><head><meta charset="utf-8">',
        f'<title>{html.escape(title)}</title><style>{_CSS}</style></head><body>',
        f'<h1>{html.escape(title)}</h1>',
        f'<p>model <b>{result.model}</b>, method <b>{result.method.upper()}</b>: {status} '
        f'({html.escape(result.message)}); {result.n_pairs} pairs; '
        f'χ² = {result.chi2:.1f}, dof = {result.dof}, χ²/dof = {ratio:.3f}, '
        f'p = {result.p_value:.3g}.</p>']
    if report is not None:
        parts.append(f'<p>pairing: {html.escape(report.summary())}</p>')
    parts += [
        '<h2>Uncertainty of the calibration</h2>',
        '<p>Covariances follow <code>geometry_msgs/PoseWithCovariance</code>: position, then the '
        'small rotation δθ with R_true = Exp(δθ)·R about the fixed axes of the parent frame. '
        f'The ellipsoid bounds the position error with {n_sigma:g}σ; each cone shows where the '
        f'tip of a unit axis may lie ({n_sigma:g}σ ellipse), as in Hoff &amp; Vincent (2000), '
        'Fig. 1.</p>',
        f'<figure><img src="data:image/png;base64,{_b64(figures["pose_uncertainty"])}" '
        'alt="pose uncertainty"><figcaption>' + '<br>'.join(html.escape(c) for c in captions)
        + '</figcaption></figure>',
        _pose_table("T0 = base_to_base (A's base frame in B's base frame)",
                    result.base_to_base, n_sigma),
        _pose_table("T1 = tool_to_marker (B's marker frame in A's tool frame)",
                    result.tool_to_marker, n_sigma),
        '<h2>Registration error at your points</h2>']
    if points is None:
        parts.append('<p>No points given: pass <code>--points X Y Z [X Y Z ...]</code> '
                     '(metres) to see the error expected at them.</p>')
    else:
        where = ("A's base frame, mapped into B's base frame by T0" if points_frame == 'a_base'
                 else "A's tool frame, located in B's marker frame by T1⁻¹")
        parts.append(f"<p>Points given in {where}; error from the calibration's uncertainty "
                     f'alone (Hoff §3.3: a rotation error Δθ moves a point at distance d by '
                     f'd·Δθ).</p><table><tr><th>point (m)</th><th>mapped (m)</th>'
                     f'<th>RMS error (mm)</th><th>{n_sigma:g}σ ellipsoid semi-axes (mm)</th>'
                     '</tr>')
        for e in points:
            if e.get('unknown'):
                cells = '<td colspan="2">not determined by this model</td>'
            else:
                cells = f'<td>{e["rms"] * 1e3:.3f}</td><td>{_vec(e["semi_axes"], 1e3)}</td>'
            parts.append(f'<tr><td>{_vec(e["point"])}</td><td>{_vec(e["mapped"], 1.0, "{:.4f}")}'
                         f'</td>{cells}</tr>')
        parts.append('</table>')
    parts += [
        '<h2>Residuals</h2>',
        '<p>If the model and the stated noise hold, the whitened residuals show no trend over '
        'the recording, the per-pair χ² histogram follows the red curve, and the '
        'autocorrelations stay inside the green band (white noise). '
        '<code>coreg diagnose</code> locates the gap when they do not.</p>',
        f'<figure><img src="data:image/png;base64,{_b64(figures["residuals"])}" '
        'alt="residuals"></figure>',
        '</body></html>']
    return '\n'.join(parts)


def write_calibration_report(result: CalibrationResult, out_dir, *,
                             report: Optional[PairingReport] = None, points=None,
                             points_frame: str = 'a_base', title: str = 'Calibration report',
                             n_sigma: float = 3.0) -> Path:
    """
    Write the calibration report to ``out_dir`` (created if needed).

    Parameters
    ----------
    result : CalibrationResult
        The calibration reported.
    out_dir : str or path-like
        Directory the report is written to.
    report : PairingReport, optional
        Shown as one line.
    points : array_like, shape (M, 3), optional
        User points, m, in ``points_frame``.
    points_frame : str
        ``a_base`` (A's base frame, mapped into B's by T0) or ``a_tool`` (A's tool frame,
        located in B's marker frame by T1⁻¹).
    title : str
        Title of the report.
    n_sigma : float
        Size of ellipsoids and cones (3 as in Hoff).

    Returns
    -------
    Path
        ``out_dir/index.html``; ``pose_uncertainty.png`` and ``residuals.png`` beside it.

    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    fig, captions = pose_uncertainty_figure(result, n_sigma)
    figures = {'pose_uncertainty': _png(fig), 'residuals': _png(residuals_figure(result))}
    for name, png in figures.items():
        (out / f'{name}.png').write_bytes(png)
    pts = None if points is None else point_errors(result, points, points_frame, n_sigma)
    page = render_html(result, figures, captions, pts, points_frame, report, title, n_sigma)
    path = out / 'index.html'
    tmp = out / '.index.html.tmp'
    tmp.write_text(page, encoding='utf-8')
    tmp.replace(path)
    return path


def points_from_flat(values, report_dir=None) -> Optional[np.ndarray]:
    """
    Turn ``--points X Y Z [X Y Z ...]`` into an (M, 3) array (None stays None).

    Parameters
    ----------
    values : sequence of float, optional
        The flat numbers, metres.
    report_dir : str, optional
        ``--report``; points without a report are refused rather than ignored.

    Raises
    ------
    ConfigError
        If the number of values is not a positive multiple of three, or no report is asked.

    """
    if values is None:
        return None
    from coreg_ros.core.errors import ConfigError

    if not report_dir:
        raise ConfigError('--points are shown in the report: add --report DIR')
    flat = np.asarray(values, dtype=float).ravel()
    if flat.size == 0 or flat.size % 3:
        raise ConfigError(f'--points takes X Y Z triples (metres), got {flat.size} number(s)')
    return flat.reshape(-1, 3)
