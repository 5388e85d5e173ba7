"""
Numbers a person reads: the gap on held-out data, each effect's size with its uncertainty.

All gaps are measured on held-out blocks (each block predicted by the fit on the others).
"""

from __future__ import annotations

from typing import Optional

from coreg_ros.core import quaternion as quat
from coreg_ros.core.diagnosis import variance as vm
from coreg_ros.core.rigid import rigid_part
import numpy as np


def _inflation(fit) -> float:
    """Factor (>= 1) on parameter variances: the chi-square per dof left under the fit."""
    quad, _, _, _ = vm.components(fit.state.var, fit.stats)
    if fit.state.var.eps > 0:
        _, p_in, _ = vm.loglik(fit.state.var, fit.stats, with_parts=True)
        quad = quad[p_in > 0.5]
    m = fit.stats.z.shape[1]
    return float(max(1.0, np.mean(quad) / m)) if len(quad) else 1.0


def gap_measures(data, fit, heldout) -> dict:
    """
    Measure the gap of a fitted model on held-out blocks.

    Returns
    -------
    dict
        ``chi2_per_dof`` (under the fitted noise model, inliers), ``chi2_per_dof_stated_noise``,
        ``position_rms_m`` (per axis, inliers), ``rotation_rms_rad`` (full pose),
        ``noise_floor_position_m`` / ``noise_floor_rotation_rad`` (RMS expected from the noise
        model), their ratios, ``log_likelihood_per_residual``, ``outlier_pairs``.

    """
    m = data.m
    inl = heldout.p_in > 0.5
    if not inl.any():
        inl = np.ones_like(inl)
    model = fit.model
    idx = np.arange(data.n)
    sd = np.concatenate([model._decorrelation(ch, None)[2] if _cached(model, ch)
                         else model.evaluate(fit.state, ch, jac=False).sd
                         for ch in model.chunks(idx)])
    var = fit.state.var
    st = fit.stats if len(fit.stats.z) == data.n else None
    if st is not None:
        _, _, D, _ = vm.components(var, st)
        ez = D + var.beta * st.u ** 2
        ratio = float(np.mean(np.sum(ez / (1.0 + st.lam), axis=1)) / m)
    else:
        ratio = float(np.exp(var.log_s2 + var.log_c))
    k = data.spec.n_markers
    pos_rows = list(range(3 * k)) if not data.spec.has_q1 else [0, 1, 2]
    e = heldout.e[inl]
    pos_rms = float(np.sqrt(np.mean(e[:, pos_rows] ** 2)))
    floor_pos_stated = float(np.sqrt(np.mean(sd[:, pos_rows] ** 2)))
    out = {
        'chi2_per_dof': float(np.mean(heldout.quad[inl]) / m),
        'chi2_per_dof_stated_noise': float(np.mean(heldout.quad_stated[inl]) / m),
        'position_rms_m': pos_rms,
        'noise_floor_position_m': floor_pos_stated * np.sqrt(ratio),
        'stated_noise_floor_position_m': floor_pos_stated,
        'position_rms_to_floor': pos_rms / (floor_pos_stated * np.sqrt(ratio)),
        'log_likelihood_per_residual': float(np.mean(heldout.ll) / m),
        'outlier_pairs': int(np.sum(~inl)),
        'n_pairs': int(len(heldout.ll)),
    }
    if data.spec.has_q1:
        rot_rms = float(2.0 * np.sqrt(np.mean(e[:, 3:6] ** 2)))
        floor_rot = float(2.0 * np.sqrt(np.mean(sd[:, 3:6] ** 2)))
        out.update({'rotation_rms_rad': rot_rms,
                    'noise_floor_rotation_rad': floor_rot * np.sqrt(ratio),
                    'stated_noise_floor_rotation_rad': floor_rot,
                    'rotation_rms_to_floor': rot_rms / (floor_rot * np.sqrt(ratio))})
    return out


def _cached(model, ch) -> bool:
    key = (int(ch[0]), int(ch[-1]), len(ch))
    return key in model.data.cache.get('decorrelation', {})


def transforms(fit) -> dict:
    """
    T0 and T1 of a fit: positions (m) with standard deviations, quaternions (w, x, y, z).

    The standard deviations are of the fit with its effects modelled (φ's posterior, inflated
    by any chi-square per dof left above one).
    """
    p = fit.state.params
    cov = fit.mean_cov()
    sd0 = sd1 = [float('nan')] * 3
    if cov is not None:
        infl = _inflation(fit)
        sd0 = np.sqrt(np.clip(np.diag(cov)[0:3], 0, None) * infl).tolist()
        sd1 = np.sqrt(np.clip(np.diag(cov)[6:9], 0, None) * infl).tolist()
    out = {'base_to_base': {'position': p.p0.tolist(), 'sigma_position': sd0,
                            'quat_wxyz': quat.canonical(p.q0).tolist()},
           'tool_to_marker': {'position': p.markers[0].tolist(), 'sigma_position': sd1,
                              'quat_wxyz': quat.canonical(p.q1).tolist()}}
    if p.spec.n_markers > 1:
        out['markers'] = p.markers.tolist()
    return out


def _sd(cov: Optional[np.ndarray], sl: slice, infl: float) -> np.ndarray:
    if cov is None:
        return np.full(sl.stop - sl.start, np.nan)
    return np.sqrt(np.clip(np.diag(cov)[sl], 0.0, None) * infl)


def effect_estimate(name: str, fit, cov: Optional[np.ndarray],
                    var_cov: Optional[np.ndarray]) -> dict:
    """
    Size of an accepted effect with its standard uncertainty, JSON-friendly.

    Parameters
    ----------
    name : str
        The effect (``candidates.EFFECT_NAMES``).
    fit : Fit
        The final fit (all accepted effects).
    cov : ndarray or None
        Covariance of the mean parameters (φ, θ).
    var_cov : ndarray or None
        Covariance of the variance parameters (order of ``fit.model.var_names``).

    Returns
    -------
    dict
        Effect-specific keys plus ``text``, e.g. ``'12.1 ± 0.3 ms'``.

    """
    model, state = fit.model, fit.state
    infl = _inflation(fit)
    var = state.var
    vnames = list(model.var_names)

    def vsd(p):
        if var_cov is None or p not in vnames:
            return float('nan')
        i = vnames.index(p)
        return float(np.sqrt(max(var_cov[i, i], 0.0) * infl))

    if name in model.slices:
        sl = model.slices[name]
        theta = state.theta[name]
        sd = _sd(cov, sl, infl)
    if name == 'time_offset':
        tau, s = float(theta[0]), float(sd[0])
        return {'tau_s': tau, 'sigma_s': s, 'text': f'{tau * 1e3:.2f} ± {s * 1e3:.2f} ms'}
    if name == 'clock_drift':
        T = model.duration
        kappa, s_k = theta[1] / T, sd[1] / T
        return {'ppm': float(kappa * 1e6), 'sigma_ppm': float(s_k * 1e6),
                'offset_at_start_s': float(theta[0]), 'sigma_offset_at_start_s': float(sd[0]),
                'offset_at_end_s': float(theta[0] + theta[1]),
                'text': f'{kappa * 1e6:.1f} ± {s_k * 1e6:.1f} ppm'}
    if name == 'scale':
        return {'scale': theta.tolist(), 'sigma': sd.tolist(),
                'text': 'per axis ' + ', '.join(f'{v * 100:+.3f}' for v in theta)
                        + f' % (± {np.max(sd) * 100:.3f} %)'}
    if name == 'link_flex':
        C = (cov[sl, sl] * infl) if cov is not None else np.full((len(theta),) * 2, np.nan)
        u = theta[0:3]
        b = float(np.linalg.norm(u))
        g = u / b if b > 0 else np.array([0.0, 0.0, -1.0])
        s = float(np.sqrt(max(g @ C[0:3, 0:3] @ g, 0.0)))
        # the length of a noisy vector is biased up: E|û|² = |u|² + tr C. Taken off (the
        # across-gravity variance), small sags are not overstated
        tr = float(np.trace(C[0:3, 0:3])) if np.all(np.isfinite(C[0:3, 0:3])) else 0.0
        b = float(np.sqrt(max(b * b - max(tr - s * s, 0.0), 0.25 * b * b)))
        out = {'sag_mm': b * 1e3, 'sigma_mm': s * 1e3}
        text = f'{b * 1e3:.2f} ± {s * 1e3:.2f} mm sag'
        if len(theta) == 6:
            w = theta[3:6]
            tilt = float(np.linalg.norm(w))
            gw = w / tilt if tilt > 0 else g
            st = float(np.sqrt(max(gw @ C[3:6, 3:6] @ gw, 0.0)))
            # gravity's direction from the better determined of the two vectors
            if tilt / max(st, 1e-30) > b / max(s, 1e-30):
                g = gw * np.sign(float(gw @ u)) if b > 0 else gw
                # sag and tilt are one pivot's turn under one gravity (u = lever · w): with
                # the direction fixed by the tilt, the sag is u's component along it (one
                # noisy component instead of a vector length, which the two across-gravity
                # components inflate)
                # best linear unbiased: u = b ĝ + noise (covariance Cu), so b is read with
                # all three components weighted, not along ĝ alone (the motion may fix
                # another direction far better than ĝ's)
                Cu = C[0:3, 0:3]
                try:
                    Wg = np.linalg.solve(Cu, g)
                    info = float(g @ Wg)
                    b = abs(float(Wg @ u) / info)
                    s = float(np.sqrt(1.0 / info))
                except (np.linalg.LinAlgError, ZeroDivisionError, FloatingPointError):
                    b = abs(float(g @ u))
                    s = float(np.sqrt(max(g @ Cu @ g, 0.0)))
                if not (np.isfinite(b) and np.isfinite(s)):
                    b = abs(float(g @ u))
                    s = float(np.sqrt(max(g @ Cu @ g, 0.0))) if np.all(np.isfinite(Cu)) else s
                out.update(sag_mm=b * 1e3, sigma_mm=s * 1e3)
                text = f'{b * 1e3:.2f} ± {s * 1e3:.2f} mm sag'
            out.update(tilt_deg=float(np.degrees(tilt)), sigma_tilt_deg=float(np.degrees(st)))
            text += f', {np.degrees(tilt):.3f} ± {np.degrees(st):.3f} deg tilt'
        out['gravity_in_a_base'] = g.tolist()
        out['text'] = text + ' (gravity in A base ' + ', '.join(f'{v:+.2f}' for v in g) + ')'
        return out
    if name == 'backlash':
        w = 2.0 * theta * 1e3
        ws = 2.0 * sd * 1e3
        mean = float(np.mean(w))
        mean_sd = float(np.sqrt(np.sum(ws ** 2)) / 3.0)
        return {'width_mm': mean, 'sigma_mm': mean_sd, 'width_per_axis_mm': w.tolist(),
                'sigma_per_axis_mm': ws.tolist(),
                'text': f'{mean:.3f} ± {mean_sd:.3f} mm play'}
    if name == 'field_distortion':
        eff = next(e for e in model.mean if e.name == name)
        # over every recorded sample of every marker, as the truth is defined (a subsample
        # misses the steep edge of a near-source field); the bootstrap draws use a subsample
        all_pts = model.data.b_points.reshape(-1, 3)
        pts = model.data.b_points
        pts = pts[:: max(1, len(pts) // 2000)].reshape(-1, 3)
        size = _field_size(eff, all_pts, theta)
        whole = _field_size(eff, all_pts, theta, rigid=False)
        sub = _field_size(eff, pts, theta)[0]
        draws = []
        if cov is not None:
            rng = np.random.default_rng(0)
            C = cov[sl, sl] * infl
            try:
                Ls = np.linalg.cholesky(C + 1e-30 * np.eye(len(C)))
                for _ in range(40):
                    draws.append(_field_size(eff, pts, theta + Ls @ rng.standard_normal(len(C))))
            except np.linalg.LinAlgError:
                pass
        s = float(np.std([d[0] for d in draws])) if draws else float('nan')
        if draws:
            # the largest value of a noisy field is biased up (its noise adds where the field
            # is largest, and the cubic terms overshoot where samples are few): the bias is
            # read from the draws (parametric bootstrap) and taken off
            bias = float(np.mean([d[0] for d in draws])) - sub
            size = (max(size[0] - max(bias, 0.0), 0.5 * size[0]), size[1])
        return {'max_mm': size[0], 'sigma_max_mm': s, 'rms_mm': size[1],
                'whole_field_max_mm': whole[0],
                'text': f'{size[0]:.2f} ± {s:.2f} mm at most beyond what a rigid registration '
                        f'absorbs (whole field {whole[0]:.2f} mm)'}
    if name == 'noise_scale':
        f = float(np.exp(0.5 * var.log_s2))
        s = 0.5 * f * vsd('log_s2')
        return {'factor': f, 'sigma': s, 'text': f'× {f:.3f} ± {s:.3f}'}
    if name == 'distance_noise':
        r = np.exp(model.log_g)
        edge = float((r.max()) ** var.k)
        return {'exponent': float(var.k), 'sigma': vsd('k'),
                'edge_to_centre': edge, 'level': float(np.exp(0.5 * var.log_c)),
                'source_m': [float(v) for v in model.source],
                'text': f'exponent {var.k:.2f} ± {vsd("k"):.2f} (edge/centre σ × {edge:.2f})'}
    if name == 'timestamp_jitter':
        sig = float(np.sqrt(var.beta))
        s = 0.5 * sig * vsd('log_beta')
        return {'sigma_s': sig, 'sigma_sigma_s': s,
                'text': f'{sig * 1e3:.2f} ± {s * 1e3:.2f} ms'}
    if name == 'outliers':
        eps = var.eps
        n = len(fit.stats.z)
        _, p_in, _ = vm.loglik(var, fit.stats, with_parts=True)
        s = float(np.sqrt(max(eps * (1 - eps), 1e-12) / n))
        return {'fraction': eps, 'sigma': s, 'count': int(np.sum(p_in < 0.5)),
                'scale': float(np.exp(var.log_lam)),
                'text': f'{eps * 100:.2f} ± {s * 100:.2f} % of the pairs'}
    return {'text': ''}


def _field_size(eff, pts: np.ndarray, theta: np.ndarray, rigid: bool = True) -> tuple:
    """Largest and RMS size (mm) of the field, without its rigid part unless ``rigid``."""
    d = eff.field(pts, theta[:eff.n_pos])
    if rigid:
        d = d - rigid_part(pts, d)
    norm = np.linalg.norm(d, axis=1) * 1e3
    return float(norm.max()), float(np.sqrt(np.mean(norm ** 2)))
