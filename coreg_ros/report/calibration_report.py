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

The figures are drawn by ``coreg_ros.report.figures``; this module assembles the page.
"""

from __future__ import annotations

import base64
from collections.abc import Sequence
import html
from pathlib import Path
from typing import Optional

from coreg_ros.core import uncertainty as unc
from coreg_ros.core.types import CalibrationResult, PairingReport, UncertainPose
from coreg_ros.report.figures import (
    png,
    pose_uncertainty_figure,
    position_known,
    residuals_figure,
    rotation_known,
)
import numpy as np

#: Frames user points may be given in.
POINT_FRAMES = ('a_base', 'a_tool')


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
    if position_known(pose):
        ell = unc.ellipsoid_axes(pose.covariance[0:3, 0:3], n_sigma)
        rows.append(f'<tr><th>{n_sigma:g}σ position ellipsoid semi-axes</th>'
                    f'<td>{_vec(ell.semi_axes, 1e3)} mm '
                    f'(holds {100 * ell.probability:.1f} %)</td></tr>')
        for k in range(3):
            rows.append(f'<tr><th>&nbsp;&nbsp;axis {k + 1} direction</th>'
                        f'<td>{_vec(ell.axes[:, k], 1.0, "{:+.3f}")}</td></tr>')
    if rotation_known(pose):
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
    figures = {'pose_uncertainty': png(fig), 'residuals': png(residuals_figure(result))}
    for name, image in figures.items():
        (out / f'{name}.png').write_bytes(image)
    pts = None if points is None else point_errors(result, points, points_frame, n_sigma)
    page = render_html(result, figures, captions, pts, points_frame, report, title, n_sigma)
    path = out / 'index.html'
    tmp = out / '.index.html.tmp'
    tmp.write_text(page, encoding='utf-8')
    tmp.replace(path)
    return path
