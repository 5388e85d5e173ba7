"""
Monte Carlo of ``noise: auto``: stated noise off by a factor, the estimate and the verdict scored.

A scenario states one device's noise (both channels, or one) ``factor`` times its truth and
calibrates simulated full-pose pairs with ``noise='auto'``. Scored per trial (issue 24):

- every *identifiable* component against its truth: with TLS, A's and B's rotation noise each,
  and A's and B's position noise together (no motion separates them: they reach the pairs as
  one sum); with OLS, B's position and rotation noise as OLS holds them (A's carried in);
- the NEES of (T0, T1) with the covariance of the fit at the estimated noise (12 dimensions;
  the mean over trials against its 99 % band);
- whether the verdict names exactly the channels whose noise was misstated (and only those).

``test/core/test_noise_auto.py`` runs it at a reduced size, ``bench/noise_auto_bench.py`` at
full size (``make bench``).
"""

from __future__ import annotations

from dataclasses import dataclass, replace

from coreg_ros.core import quaternion as quat
from coreg_ros.core.calibration.auto_noise import calibrate_pairs
from coreg_ros.core.calibration.noise_components import (
    linearised_pairs,
    ols_stated,
    stated_channels,
)
from coreg_ros.core.distributions import chi2_ppf
from coreg_ros.core.models import Parameters, SPECS
from coreg_ros.core.noise_model import DeviceNoise
from coreg_ros.core.settings import Settings
from coreg_ros.sim.device_noise import add_device_noise
from coreg_ros.sim.devices import simulate_pairs
import numpy as np

#: The true noise of the scenarios: (position m, rotation rad) of A and B.
TRUE_A = (2e-4, 1e-3)
TRUE_B = (5e-4, 2e-3)
#: Largest relative error of an identifiable component's σ (the issue's target).
TOLERANCE = 0.15


@dataclass(frozen=True)
class Scenario:
    """
    What is misstated, and how.

    Attributes
    ----------
    method : {'tls', 'ols'}
    device : {'a', 'b'}
        The device whose stated noise is off.
    factor : float
        Stated σ over the true σ.
    channels : tuple of str
        The channels misstated (``position``, ``rotation``).
    anisotropic : bool
        B's true position noise 3× larger along B's z than stated (the stated is the lateral).

    """

    method: str
    device: str
    factor: float
    channels: tuple = ('position', 'rotation')
    anisotropic: bool = False

    @property
    def name(self) -> str:
        """Return a short name, e.g. ``tls/b×3/position``."""
        what = '+'.join(self.channels) + ('/depth' if self.anisotropic else '')
        return f'{self.method}/{self.device}×{self.factor:g}/{what}'

    def stated(self) -> tuple:
        """Return the noise stated to the fit: (σ_A, σ_B)."""
        out = {'a': list(TRUE_A), 'b': list(TRUE_B)}
        for k, kind in enumerate(('position', 'rotation')):
            if kind in self.channels:
                out[self.device][k] *= self.factor
        return tuple(out['a']), tuple(out['b'])


def _true_b() -> DeviceNoise:
    return DeviceNoise.from_covariances(np.diag([1.0, 1.0, 9.0]) * TRUE_B[0] ** 2,
                                        np.eye(3) * TRUE_B[1] ** 2)


def pose_errors(result, truth) -> np.ndarray:
    """Return (T0, T1) true minus estimated, ROS layout, shape (12,)."""
    t0, t1 = result.base_to_base, result.tool_to_marker
    return np.concatenate([
        truth.p0 - t0.position, quat.log(quat.multiply(truth.q0, quat.conjugate(t0.quat_wxyz))),
        truth.p1 - t1.position, quat.log(quat.multiply(truth.q1, quat.conjugate(t1.quat_wxyz)))])


def _expected_misstated(sc: Scenario, cov_a_true, cov_b_true, cov_a, cov_b) -> set:
    """Return the statements the verdict should flag: off by more than 20 % in size."""
    def off(true, stated):
        return abs(np.sqrt(np.trace(true) / np.trace(stated)) - 1.0) > 0.2 + 0.05

    out = set()
    if sc.method == 'tls':
        for d, t, s in (('a', cov_a_true, cov_a), ('b', cov_b_true, cov_b)):
            if off(t[3:6, 3:6], s[3:6, 3:6]):
                out.add(((d, 'rotation'),))
        if off(cov_a_true[0:3, 0:3] + cov_b_true[0:3, 0:3], cov_a[0:3, 0:3] + cov_b[0:3, 0:3]):
            out.add('position group')
    return out


def run_trial(sc: Scenario, k: int, n_pairs: int, seed: int = 24) -> dict:
    """
    One trial of a scenario: simulate, calibrate with ``noise='auto'``, score.

    Returns
    -------
    dict
        ``nees``, ``errors`` (identifiable component → relative error of σ), ``named``
        (misstated statements named as expected), ``flagged``, ``expected``.

    """
    rng = np.random.default_rng([seed, k])
    _, clean, truth = simulate_pairs(rng, n_pairs, sigma_a=(0.0, 0.0), sigma_b=(0.0, 0.0))
    noise_a = DeviceNoise.isotropic(TRUE_A)
    noise_b = _true_b() if sc.anisotropic else DeviceNoise.isotropic(TRUE_B)
    pos_a, q_a = add_device_noise(rng, clean.pos_a, clean.quat_a, noise_a)
    pos_b, q_b = add_device_noise(rng, clean.pos_b, clean.quat_b, noise_b)
    noisy = replace(clean, pos_a=pos_a, quat_a=q_a, pos_b=pos_b, quat_b=q_b)
    sigma_a, sigma_b = sc.stated()
    settings = Settings(method=sc.method, sigma_a=sigma_a, sigma_b=sigma_b, noise='auto')
    result = calibrate_pairs(noisy, settings)
    e = pose_errors(result, truth)
    nees = float(e @ np.linalg.solve(result.cov_joint, e))
    est = result.noise
    ca_t, cb_t = noise_a.covariance(), noise_b.covariance()
    errors = {}
    if sc.method == 'tls':
        for d, t in (('a', ca_t), ('b', cb_t)):
            ch = est.devices[d]['rotation']
            if ch.status == 'estimated':
                errors[f'{d} rotation'] = float(np.sqrt(np.trace(ch.covariance)
                                                        / np.trace(t[3:6, 3:6])) - 1.0)
        pos = est.devices['a']['position'].covariance + est.devices['b']['position'].covariance
        summed = ca_t[0:3, 0:3] + cb_t[0:3, 0:3]
        errors['a+b position'] = float(np.sqrt(np.trace(pos) / np.trace(summed)) - 1)
    else:
        # what OLS's B holds: B's noise and A's carried through the model, at the truth
        spec = SPECS['full_pose']
        params = Parameters.from_transforms(spec, truth.p0, truth.q0, truth.markers, truth.q1)
        sub, layout = linearised_pairs(params, clean.pos_a, clean.quat_a, clean.pos_b,
                                       clean.quat_b, None, False)
        held = ols_stated(sub, layout, stated_channels(spec, ca_t, cb_t, False), ca_t)
        said = ols_stated(sub, layout, stated_channels(spec, settings.cov_a, settings.cov_b,
                                                       False), settings.cov_a)
        for kind in ('position', 'rotation'):
            cov = est.devices['b'][kind].covariance
            metric = np.trace(cov) * (1.0 if kind == 'position' else 0.25)
            errors[f'b {kind} (OLS)'] = float(np.sqrt(metric / held[('b', kind)]) - 1.0)
    flagged = set()
    for s in est.misstated:
        flagged.add('position group' if len(s.channels) > 1 else
                    (tuple(s.channels) if sc.method == 'tls' else 'ols ' + s.channels[0][1]))
    undetermined = {(d, k) for d in 'ab' for k, ch in est.devices[d].items()
                    if ch.status == 'held' and 'not separable' not in ch.note}
    if sc.method == 'tls':
        # what this motion does not determine is held and said, not named: only the rest
        expected = {e for e in _expected_misstated(sc, ca_t, cb_t, settings.cov_a,
                                                   settings.cov_b)
                    if not (isinstance(e, tuple) and set(e) & undetermined)}
    else:
        expected = {f'ols {kind}' for kind in ('position', 'rotation')
                    if abs(np.sqrt(held[('b', kind)] / said[('b', kind)]) - 1.0) > 0.25}
    return {'nees': nees, 'errors': errors, 'flagged': flagged, 'expected': expected,
            'named': flagged == expected, 'verdict': est.verdict(),
            'held': sorted(undetermined)}


def run_scenario(sc: Scenario, trials: int, n_pairs: int, seed: int = 24) -> dict:
    """
    Run ``trials`` of a scenario and summarise them.

    Returns
    -------
    dict
        ``name``; ``max_error`` (component → largest relative error of σ over the trials);
        ``mean_nees`` with its 99 % band ``nees_band``; ``named_share`` (verdicts naming
        exactly the misstated channels); ``trials``, ``n_pairs``.

    """
    rows = [run_trial(sc, k, n_pairs, seed) for k in range(trials)]
    errors = {}
    for r in rows:
        for k, v in r['errors'].items():
            errors.setdefault(k, []).append(v)
    band = chi2_ppf([0.005, 0.995], 12 * trials) / trials
    return {'name': sc.name, 'trials': trials, 'n_pairs': n_pairs,
            'max_error': {k: float(np.max(np.abs(v))) for k, v in errors.items()},
            'mean_error': {k: float(np.mean(v)) for k, v in errors.items()},
            'mean_nees': float(np.mean([r['nees'] for r in rows])),
            'nees_band': [float(band[0]), float(band[1])],
            'named_share': float(np.mean([r['named'] for r in rows])),
            'held_share': {f'{d} {k}': float(np.mean([(d, k) in r['held'] for r in rows]))
                           for d in 'ab' for k in ('position', 'rotation')
                           if any((d, k) in r['held'] for r in rows)},
            'verdicts': sorted({r['verdict'] for r in rows})[:3]}


def scenarios() -> list:
    """Return the scenarios of the issue: each device ×0.5 and ×3, both methods, one depth."""
    out = [Scenario(m, d, f) for m in ('tls', 'ols') for d in 'ab' for f in (0.5, 3.0)]
    out.append(Scenario('tls', 'b', 1.0, ('position',), anisotropic=True))
    return out
