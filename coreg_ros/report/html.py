# noqa: A005 (coreg_ros.report.html: imported as a package module, never as `html`)
"""
HTML report of a gap diagnosis: ``index.html`` and one PNG per plot (matplotlib, Agg).

The plots are the ones a person reads at a glance: normalized residuals over time with ±3σ
bands, a QQ plot, the residual-velocity cross-correlation, the excess against speed and
against distance from B's base, a workspace map of the excess, the candidate ranking, and the
gap before and after.
"""

from __future__ import annotations

import html
import json
from pathlib import Path

import numpy as np


def _plt():
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt
    return plt


def _standardized(diag):
    """Raw standardized errors (n, m) before (base fit) and after (held-out final)."""
    from coreg_ros.core.diagnosis.residuals import base_errors

    e, sd, z, lam, _ = base_errors(diag.data, diag.base)
    before = e / sd
    after = diag.after.e / sd
    quad_before = np.sum(z ** 2 / (1.0 + lam), axis=1)
    return before, after, quad_before


def _save(fig, path: Path) -> str:
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    _plt().close(fig)
    return path.name


def _plot_time(plt, d, before, after, out, window=None):
    fig, axes = plt.subplots(2, 1, figsize=(10, 5), sharex=True)
    if window is not None:
        # the window in time whose held-out errors stand out (structure.time_window)
        for ax in axes:
            ax.axvspan(window.from_s, window.to_s, color='orange', alpha=0.2, lw=0)
    step = max(1, d.n // 4000)
    names = ['x', 'y', 'z', 'rot x', 'rot y', 'rot z']
    for ax, r, label in ((axes[0], before, 'before (base model)'),
                         (axes[1], after, 'after (effects modelled, held out)')):
        for j in range(min(r.shape[1], 6)):
            ax.plot(d.t[::step], r[::step, j], '.', ms=1.5,
                    label=names[j] if d.spec.has_q1 else f'ch {j}')
        ax.axhline(3, color='k', lw=0.8, ls='--')
        ax.axhline(-3, color='k', lw=0.8, ls='--')
        ax.set_ylabel('error / σ')
        ax.set_title(label, fontsize=9)
        lim = max(6.0, float(np.percentile(np.abs(r), 99.5)) * 1.1)
        ax.set_ylim(-lim, lim)
    axes[0].legend(fontsize=7, ncol=6, markerscale=5, loc='upper right')
    axes[1].set_xlabel('time (s)')
    return _save(fig, out / 'residuals_time.png')


def _plot_qq(plt, before, after, out):
    from scipy import stats
    fig, ax = plt.subplots(figsize=(4.5, 4.5))
    for r, label in ((before, 'before'), (after, 'after')):
        x = np.sort(r.reshape(-1))
        x = x[:: max(1, len(x) // 5000)]
        q = stats.norm.ppf((np.arange(len(x)) + 0.5) / len(x))
        ax.plot(q, x, '.', ms=2, label=label)
    lim = 5
    ax.plot([-lim, lim], [-lim, lim], 'k--', lw=0.8)
    ax.set_xlim(-lim, lim)
    ax.set_ylim(-2 * lim, 2 * lim)
    ax.set_xlabel('normal quantile')
    ax.set_ylabel('standardized error')
    ax.set_title('QQ plot', fontsize=9)
    ax.legend(fontsize=8)
    return _save(fig, out / 'qq.png')


def _plot_xcorr(plt, loc, out):
    xc = loc.velocity_xcorr
    fig, ax = plt.subplots(figsize=(5, 3.5))
    ax.plot(np.array(xc.lag_s) * 1e3, xc.linear, label='linear velocity')
    ax.plot(np.array(xc.lag_s) * 1e3, xc.angular, label='angular velocity')
    ax.axhline(0, color='k', lw=0.6)
    ax.set_xlabel('lag (ms)')
    ax.set_ylabel('correlation with the residual')
    ax.set_title('residual-velocity cross-correlation', fontsize=9)
    ax.legend(fontsize=8)
    return _save(fig, out / 'xcorr.png')


def _binned(x, y, bins=12):
    edges = np.unique(np.quantile(x, np.linspace(0, 1, bins + 1)))
    if len(edges) < 2:
        return np.array([]), np.array([]), np.array([])
    k = np.clip(np.searchsorted(edges, x, side='right') - 1, 0, len(edges) - 2)
    centres, means, errs = [], [], []
    for i in range(len(edges) - 1):
        sel = k == i
        if sel.sum() > 2:
            centres.append(x[sel].mean())
            means.append(y[sel].mean())
            errs.append(y[sel].std() / np.sqrt(sel.sum()))
    return np.array(centres), np.array(means), np.array(errs)


def _plot_speed_range(plt, d, quad_before, diag, out):
    m = d.m
    ex_b = quad_before / m - 1.0
    ex_a = diag.after.quad / m - 1.0
    fig, axes = plt.subplots(1, 2, figsize=(10, 3.5))
    for ax, x, label in ((axes[0], d.speed * 1e3, 'A speed (mm/s)'),
                         (axes[1], np.linalg.norm(d.b_points[:, 0, :], axis=1),
                          'distance from B base (m)')):
        for ex, name in ((ex_b, 'before'), (ex_a, 'after')):
            c, mu, err = _binned(x, ex)
            if len(c):
                ax.errorbar(c, mu, yerr=err, marker='o', ms=3, label=name)
        ax.axhline(0, color='k', lw=0.6)
        ax.set_xlabel(label)
        ax.set_ylabel('excess of normalized squared error')
        ax.legend(fontsize=8)
    axes[0].set_title('residual against speed', fontsize=9)
    axes[1].set_title('residual against distance', fontsize=9)
    return _save(fig, out / 'speed_distance.png')


def _plot_map(plt, d, quad_before, out):
    p = d.b_points[:, 0, :]
    ex = quad_before / d.m - 1.0
    step = max(1, d.n // 6000)
    fig, axes = plt.subplots(1, 3, figsize=(13, 4.2), layout='constrained')
    vmax = max(1.0, float(np.percentile(ex, 95)))
    for ax, (i, j) in zip(axes, ((0, 1), (0, 2), (1, 2)), strict=True):
        sc = ax.scatter(p[::step, i], p[::step, j], c=np.clip(ex[::step], -1, vmax), s=3,
                        cmap='viridis', vmin=-1, vmax=vmax)
        ax.set_xlabel('xyz'[i] + ' (m, B base)')
        ax.set_ylabel('xyz'[j] + ' (m, B base)')
        ax.set_aspect('equal', adjustable='datalim')
    fig.colorbar(sc, ax=list(axes), shrink=0.8, label='excess (before)')
    fig.suptitle('workspace map of the excess', fontsize=9)
    fig.savefig(out / 'workspace.png', dpi=90)
    _plt().close(fig)
    return 'workspace.png'


def _plot_candidates(plt, report, out):
    rounds = report.candidates
    if not rounds:
        return None
    rows = rounds[0]
    accepted = {e.name for e in report.effects}
    fig, ax = plt.subplots(figsize=(6, 0.35 * len(rows) + 1.2))
    # a screened candidate was not refitted (its predicted gain was too small): drawn at 0
    names = [r.name + (' (screened)' if r.screened else '') for r in rows][::-1]
    gains = [r.held_out_gain_per_residual or 0.0 for r in rows][::-1]
    colors = ['tab:green' if n.split(' ')[0] in accepted
              else ('tab:blue' if r.accepted_test else 'tab:gray')
              for n, r in zip(names, rows[::-1], strict=True)]
    ax.barh(names, gains, color=colors)
    ax.axvline(0, color='k', lw=0.6)
    ax.set_xlabel('held-out gain (nats per residual), round 1')
    ax.set_title('candidate ranking (green: accepted, blue: passes the tests)', fontsize=9)
    return _save(fig, out / 'candidates.png')


def _plot_before_after(plt, report, out):
    """
    Held-out gap before and after at the stated noise (a noise model cannot move these).

    The "after" bar is green only where the measure fell by more than 2 %; otherwise it is
    grey and labelled unchanged, so a relabelled noise never looks like an explanation.
    """
    b, a = report.gap_before.stated.counted, report.gap_after.stated.counted
    items = [('chi2/dof at the stated noise', b.chi2_per_dof_at_stated_noise,
              a.chi2_per_dof_at_stated_noise, 1.0),
             ('position RMS (mm)', b.rms_position_mm, a.rms_position_mm,
              a.stated_floor_position_mm)]
    if a.rms_rotation_deg is not None:
        items.append(('rotation RMS (deg)', b.rms_rotation_deg, a.rms_rotation_deg,
                      a.stated_floor_rotation_deg))
    fig, axes = plt.subplots(1, len(items), figsize=(3.2 * len(items), 3.2))
    for ax, (label, vb, va, floor) in zip(np.atleast_1d(axes), items, strict=True):
        moved = va < 0.98 * vb
        ax.bar(['before', 'after' if moved else 'after (unchanged)'], [vb, va],
               color=['tab:red', 'tab:green' if moved else 'tab:gray'])
        ax.axhline(floor, color='k', ls='--', lw=0.8, label='stated noise floor')
        ax.set_title(label, fontsize=9)
        ax.legend(fontsize=7)
    share = report.gap_after.share_of_excess_explained
    excl = report.gap_after.stated.excluded_pairs.count
    fig.suptitle(f'gap on held-out blocks at the stated noise: {share * 100:.0f} % of the '
                 f'excess explained' + (f' ({excl} pairs set aside, counted as unexplained)'
                                        if excl else ''), fontsize=9)
    return _save(fig, out / 'before_after.png')


def _what_else(report) -> list:
    """HTML of what is not an effect found: a cheap cause, small effects, unexplained structure."""
    parts = []
    if report.cause is not None:
        parts.append(f'<h2>Cause: {html.escape(report.cause.check.replace("_", " "))}</h2>'
                     f'<p>{html.escape(report.cause.text)}</p>')
    if report.not_significant:
        parts.append('<h2>Not significant (supported by the held-out data, too small to matter '
                     'at the stated noise)</h2><ul>')
        parts += [f'<li>{html.escape(s.name)}: {html.escape(s.text)}</li>'
                  for s in report.not_significant]
        parts.append('</ul>')
    u = report.unexplained
    if u is not None:
        items = [('excess left at the stated noise', f'{u.excess:.2f}'),
                 ('channel', u.channel),
                 ('when', u.when.text if u.when is not None else None),
                 ('where', u.where),
                 ('tied to', ', '.join(f'{k} (ρ {v:+.2f})' for k, v in u.tied_to.items())
                  if u.tied_to else None),
                 ('not white', f'autocorrelation up to {u.not_white:.2f}'
                  if u.not_white is not None else None)]
        parts.append('<h2>Unexplained structure (no effect of the library explains it)</h2>'
                     '<table border="1" cellpadding="4" style="border-collapse:collapse">')
        parts += [f'<tr><th>{html.escape(k)}</th><td>{html.escape(v)}</td></tr>'
                  for k, v in items if v]
        parts.append('</table>')
    return parts


def write_report(diag, out_dir, title: str = 'coreg diagnosis') -> Path:
    """
    Write ``index.html`` and its PNGs into ``out_dir`` (created if needed).

    Parameters
    ----------
    diag : coreg_ros.core.diagnosis.Diagnosis
        The diagnosis to draw.
    out_dir : str or Path
        Directory of the report.
    title : str
        Title of the page.

    Returns
    -------
    Path
        The ``index.html`` written.

    """
    plt = _plt()
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    d = diag.data
    report = diag.report
    before, after, quad_before = _standardized(diag)
    figures = [
        ('Normalized residuals over time (±3σ; shaded: the window that stands out)',
         _plot_time(plt, d, before, after, out, report.excess_left.window)),
        ('QQ plot of the standardized residuals', _plot_qq(plt, before, after, out)),
        ('Residual-velocity cross-correlation', _plot_xcorr(plt, report.location, out)),
        ('Residual against speed and against distance',
         _plot_speed_range(plt, d, quad_before, diag, out)),
        ('Workspace map of the excess', _plot_map(plt, d, quad_before, out)),
        ('Candidate ranking', _plot_candidates(plt, report, out)),
        ('Before and after', _plot_before_after(plt, report, out)),
    ]
    from coreg_ros.core.diagnosis.text import format_diagnosis
    summary = html.escape(format_diagnosis(report))
    parts = [f'<!DOCTYPE html><html><head><meta charset="utf-8"><title>{html.escape(title)}'
             '</title><style>body{font-family:sans-serif;max-width:1100px;margin:auto}'
             'pre{background:#f4f4f4;padding:8px;white-space:pre-wrap}img{max-width:100%}'
             'h2{font-size:1.1em;margin-top:1.5em}</style></head><body>',
             f'<h1>{html.escape(title)}</h1>',
             f'<p><b>{html.escape(report.verdict)}</b></p>',
             f'<pre>{summary}</pre>']
    if report.effects:
        parts.append('<table border="1" cellpadding="4" style="border-collapse:collapse">'
                     '<tr><th>effect</th><th>kind</th><th>estimate</th>'
                     '<th>held-out gain (nats)</th>'
                     '<th>blocks improved</th></tr>')
        for e in report.effects:
            parts.append(f'<tr><td>{html.escape(e.name)}</td>'
                         f'<td>{html.escape(e.kind)}</td>'
                         f'<td>{html.escape(e.estimate.text)}</td>'
                         f'<td>{e.held_out_gain:.1f}</td>'
                         f'<td>{e.blocks_improved}/{e.blocks}</td></tr>')
        parts.append('</table>')
    parts += _what_else(report)
    for caption, name in figures:
        if name:
            parts.append(f'<h2>{html.escape(caption)}</h2><img src="{name}" alt="{caption}">')
    document = report.as_dict()
    parts.append('<h2>JSON</h2><pre>'
                 + html.escape(json.dumps({k: document[k] for k in (
                     'gap_detected', 'cause', 'effects', 'not_significant', 'unexplained',
                     'not_separable', 'gap_before', 'gap_after', 'noise_excess', 'verdict')
                     if k in document}, indent=1))
                 + '</pre></body></html>')
    path = out / 'index.html'
    path.write_text('\n'.join(parts), encoding='utf-8')
    return path
