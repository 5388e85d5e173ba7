"""
Fingerprint of the package's numbers: a hash per output, to prove that a move changed nothing.

Every output is reached through the public names (``coreg_ros.calibrate_pairs``,
``coreg_ros.calibrate_streams``, ``coreg_ros.diagnose_streams``, the uncertainty functions, the
simulator, ``coreg plan --json``), so the same script runs before and after modules move. Each
output is hashed bit for bit (every float's bytes, every string, every dataclass field), so a
result that differs in its last bit is a different hash.

Usage::

    python bench/fingerprint.py --out /tmp/before.json
    python bench/fingerprint.py --compare /tmp/before.json   # exit 1 and the names that differ

Not a test: the hashes depend on the BLAS and the machine, so they are compared only between
two runs on one machine.
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import hashlib
import io
import json
import sys
import time

import numpy as np


def _feed(h, obj) -> None:
    """Feed ``obj`` into the hash ``h`` exactly (types, shapes and bytes)."""
    if obj is None or isinstance(obj, (bool, int, str)):
        h.update(repr((type(obj).__name__, obj)).encode())
    elif isinstance(obj, float):
        h.update(b'f' + np.float64(obj).tobytes())
    elif isinstance(obj, np.generic):
        _feed(h, obj.item())
    elif isinstance(obj, np.ndarray):
        a = np.ascontiguousarray(obj)
        h.update(repr(('nd', a.dtype.str, a.shape)).encode())
        h.update(a.tobytes())
    elif dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        # a field left at None or empty is skipped: adding an optional field changes no hash
        h.update(type(obj).__name__.encode())
        for f in dataclasses.fields(obj):
            value = getattr(obj, f.name)
            if value is not None and not (isinstance(value, tuple) and not value):
                h.update(f.name.encode())
                _feed(h, getattr(obj, f.name))
    elif isinstance(obj, dict):
        h.update(b'{')
        for k in sorted(obj, key=repr):
            _feed(h, k)
            _feed(h, obj[k])
        h.update(b'}')
    elif isinstance(obj, (list, tuple)):
        h.update(b'[' + str(len(obj)).encode())
        for v in obj:
            _feed(h, v)
    elif hasattr(obj, 'as_dict'):
        _feed(h, obj.as_dict())
    else:
        h.update(repr(obj).encode())


def digest(obj) -> str:
    """Return the hash of one output."""
    h = hashlib.sha256()
    _feed(h, obj)
    return h.hexdigest()[:16]


def _outcome(fn, *args, **kwargs):
    """Return fn's result, or its error's type and message (a refusal is an output too)."""
    try:
        return fn(*args, **kwargs)
    except Exception as e:  # noqa: BLE001 - the error is what is fingerprinted
        return ('error', type(e).__name__, str(e))


def _calibration_outputs(out: dict) -> None:
    import coreg_ros as cr
    from coreg_ros.sim import simulate_pairs

    for model in ('full_pose', 'position_only', 'three_marker'):
        for method in ('ols', 'tls'):
            for robust in (False, True):
                for prior in ('none', 'partial'):
                    for seed in range(6):
                        rng = np.random.default_rng(1000 + seed)
                        noisy, _, truth = simulate_pairs(rng, 400 + 300 * seed, model,
                                                         sigma_a=(2e-4, 1e-3),
                                                         sigma_b=(5e-4, 2e-3))
                        if robust and seed % 2:
                            bad = rng.choice(len(noisy), size=len(noisy) // 50, replace=False)
                            noisy.pos_b[bad] += 0.02
                        pr = None
                        if prior == 'partial':
                            cov = np.diag([1e-6, 1e-6, 1e-6, np.inf, np.inf, np.inf])
                            pr = cr.Prior(base_to_base=cr.UncertainPose(
                                truth.p0 + 1e-4, truth.q0,
                                cov))
                        settings = cr.Settings(model=model, method=method, robust=robust,
                                               sigma_a=(2e-4, 1e-3), sigma_b=(5e-4, 2e-3))
                        key = f'calibrate_pairs/{model}/{method}/robust={robust}/{prior}/{seed}'
                        out[key] = digest(_outcome(cr.calibrate_pairs, noisy, settings, pr))


def _calibrate_without(pairs, settings, prior=None, off=('start', 'refit', 'squares', 'screen')):
    """
    ``calibrate`` with the fast paths ``off`` switched off (the plain paths they are tested on).

    By ``calibrate``'s argument ``paths`` where there is one, else by the module flags
    ``FAST_*`` of before.
    """
    cal = _module('coreg_ros.core.calibration.calibrate')
    if hasattr(cal, 'FastPaths'):
        paths = cal.FastPaths(**dict.fromkeys(off, False))
        return cal.calibrate(pairs, settings, prior, paths=paths)
    flags = [f'FAST_{name.upper()}' for name in off]
    saved = {flag: getattr(cal, flag) for flag in flags}
    try:
        for flag in flags:
            setattr(cal, flag, False)
        return cal.calibrate(pairs, settings, prior)
    finally:
        for flag, value in saved.items():
            setattr(cal, flag, value)


def _large_robust_outputs(out: dict) -> None:
    """
    Robust fits of many pairs: the fast paths of calibrate at the sizes where they engage.

    The start from a subsample, the paused first TLS fit, and the refits from the last fit's
    sums (TLS) or normal equations (OLS).

    0.5° rotation noise on A, and gross errors of 2-5 cm in B's positions on 1 % of the pairs
    (or none: the paused fit then goes on with few or no pairs removed).
    """
    import coreg_ros as cr
    from coreg_ros.sim import simulate_pairs

    sigma_a, sigma_b = (2e-4, np.radians(0.5)), (5e-4, 2e-3)
    cases = [(model, method, n) for model in ('full_pose', 'position_only')
             for method, n in (('ols', 220_000), ('tls', 60_000), ('tls', 200_000))]
    cases += [('three_marker', 'tls', 30_000), ('three_marker', 'ols', 30_000)]
    for model, method, n in cases:
        for outliers in (False, True):
            rng = np.random.default_rng([8000, n, outliers])
            noisy, _, truth = simulate_pairs(rng, n, model, sigma_a=sigma_a, sigma_b=sigma_b)
            if outliers:
                bad = rng.choice(n, size=n // 100, replace=False)
                shift = (rng.uniform(0.02, 0.05, size=(len(bad), 3))
                         * rng.choice([-1, 1], (len(bad), 3)))
                # three markers: the whole marker set moves
                noisy.pos_b[bad] += shift if noisy.pos_b.ndim == 2 else shift[:, None]
            settings = cr.Settings(model=model, method=method, robust=True,
                                   sigma_a=sigma_a, sigma_b=sigma_b)
            key = f'large_robust/{model}/{method}/{n}/outliers={outliers}'
            out[key] = digest(_outcome(cr.calibrate_pairs, noisy, settings))
            prior = None
            if model == 'full_pose' and outliers and n == 60_000:  # the refit with a prior
                prior = cr.Prior(base_to_base=cr.UncertainPose(
                    truth.p0 + 1e-4, truth.q0, np.diag([1e-6] * 3 + [np.inf] * 3)))
                out[key + '/prior'] = digest(_outcome(cr.calibrate_pairs, noisy, settings,
                                                      prior))
            if n == 200_000:
                continue
            # the plain paths the fast ones are compared with, and the fit not screened early
            out[key + '/plain'] = digest(_outcome(_calibrate_without, noisy, settings, prior))
            if method == 'tls':
                out[key + '/unscreened'] = digest(_outcome(_calibrate_without, noisy, settings,
                                                           prior, off=('screen',)))


def _stream_outputs(out: dict) -> None:
    import coreg_ros as cr
    from coreg_ros.sim import simulate_recording

    for model in ('full_pose', 'position_only', 'three_marker'):
        for method in ('ols', 'tls'):
            for offset in ('fixed', 'auto', 'drift'):
                for seed in range(4):
                    rec = simulate_recording(2000 + seed, 30.0, model)
                    s = cr.Settings(model=model, method=method,
                                    estimate_time_offset=offset != 'fixed',
                                    estimate_clock_drift=offset == 'drift')
                    key = f'calibrate_streams/{model}/{method}/{offset}/{seed}'
                    out[key] = digest(_outcome(cr.calibrate_streams, rec.stream_a,
                                               list(rec.streams_b), s))
    # the front door on arrays
    for seed in range(6):
        rng = np.random.default_rng(3000 + seed)
        from coreg_ros.sim import simulate_pairs
        noisy, _, _ = simulate_pairs(rng, 500, 'full_pose')
        out[f'api.calibrate/{seed}'] = digest(_outcome(
            cr.calibrate, noisy.pos_a, noisy.quat_a, noisy.pos_b, noisy.quat_b,
            method='tls' if seed % 2 else 'ols'))


def _diagnosis_outputs(out: dict, quick: bool) -> None:
    import coreg_ros as cr
    from coreg_ros.sim import parse_effect, simulate_recording
    from coreg_ros.sim.injected import ALL_EFFECT_NAMES
    from coreg_ros.sim.injected.registry import _EXAMPLES

    values = {'time_offset': '0.02', 'clock_drift': '300', 'timestamp_jitter': '0.005',
              'field_distortion': '5', 'distance_noise': '2', 'scale': '0.01',
              'link_flex': '2', 'outliers': '0.03', 'backlash': '0.5', 'noise_scale': '2',
              'non_stationary': '4', 'shared_clock': '0.02'}
    values = {**_EXAMPLES, **values}  # effects added since: their --effect examples
    names = ['none'] + list(ALL_EFFECT_NAMES)
    models = ('full_pose',) if quick else ('full_pose', 'position_only', 'three_marker')
    for model in models:
        for i, name in enumerate(names):
            effects = () if name == 'none' else (parse_effect(f'{name}={values[name]}'),)
            rec = _outcome(simulate_recording, 4000 + i, 40.0, model, effects=effects)
            if isinstance(rec, tuple):
                out[f'diagnose/{model}/{name}'] = digest(rec)
                continue
            settings = cr.Settings(model=model)
            diag = _outcome(cr.diagnose_streams, rec.stream_a, list(rec.streams_b), settings)
            report = getattr(diag, 'report', diag)
            # the JSON document: a typed report gives it by as_dict() (the same keys)
            out[f'diagnose/{model}/{name}'] = digest(
                report.as_dict() if hasattr(report, 'as_dict') else report)


def _uncertainty_outputs(out: dict) -> None:
    import coreg_ros as cr
    from coreg_ros.sim import random_rotation

    rng = np.random.default_rng(5000)
    for i in range(40):
        def pose():
            a = rng.normal(size=(6, 6)) * 1e-3
            return cr.UncertainPose(rng.normal(size=3), random_rotation(rng), a @ a.T)
        p, q = pose(), pose()
        out[f'uncertainty/{i}'] = digest([
            _outcome(cr.compose, p, q), _outcome(cr.invert, p), _outcome(cr.fuse, p, q),
            _outcome(cr.ellipsoid_axes, p.covariance[0:3, 0:3]), _outcome(cr.axis_cones, p),
            _outcome(cr.pose_error, p.position, p.quat_wxyz, q.position, q.quat_wxyz),
            _outcome(cr.chain, [p, q, p]), _outcome(cr.propagate_point, p, rng.normal(size=3))])


def _cli_outputs(out: dict) -> None:
    import tempfile

    from coreg_ros.cli.main import main

    with tempfile.TemporaryDirectory() as tmp:
        for motion in ('diverse', 'single_axis', 'no_rotation'):
            for model in ('full_pose', 'position_only'):
                path = f'{tmp}/{model}_{motion}.json'
                buf = io.StringIO()
                with contextlib.redirect_stdout(buf), contextlib.redirect_stderr(buf):
                    code = _outcome(main, ['plan', '--model', model, '--motion', motion,
                                           '--duration', '20', '--sigma-a', '2e-4', '1e-3',
                                           '--sigma-b', '5e-4', '2e-3', '--seed', '3',
                                           '--json', path])
                try:
                    with open(path) as f:
                        text = f.read()
                except OSError:
                    text = ''
                printed = buf.getvalue().replace(path, 'OUT')
                out[f'plan/{model}/{motion}'] = digest((code, printed, text))


def _module(*names):
    """Import the first of ``names`` that exists (a module's home before or after a move)."""
    import importlib
    for name in names:
        try:
            return importlib.import_module(name)
        except ModuleNotFoundError:
            continue
    raise ModuleNotFoundError(names[-1])


def _live_outputs(out: dict) -> None:
    """Guidance and the watchdog fed as the node feeds them, on recordings with a change."""
    from dataclasses import replace

    import coreg_ros as cr
    from coreg_ros.sim import simulate_recording
    guidance = _module('coreg_ros.core.live.guidance', 'coreg_ros.core.live.guidance')
    watchdog = _module('coreg_ros.core.live.watchdog', 'coreg_ros.core.live.watchdog')
    changes = _module('coreg_ros.sim.changes')
    sa, sb = (2e-4, 5e-4), (5e-4, 2e-3)
    for model in ('full_pose', 'position_only', 'three_marker'):
        rec = simulate_recording(6000, 30.0, model, rate_a=100.0, rate_b=100.0,
                                 sigma_a=sa, sigma_b=sb)
        settings = cr.Settings(model=model, sigma_a=sa, sigma_b=sb)
        result, _ = cr.calibrate_streams(rec.stream_a, list(rec.streams_b), settings)
        for change in ('none', 't0_step=2mm@15', 'clock_step=0.01@15'):
            r = rec if change == 'none' else changes.apply_changes(rec, [change], seed=1)
            pairs, _ = cr.pair_streams(r.stream_a, list(r.streams_b),
                                       max_gap_ns=settings.max_gap_ns,
                                       offset_ns=result.time_offset.offset_ns(),
                                       with_orientation_b=model == 'full_pose')
            acc = guidance.GuidanceAccumulator(model, sa, sb, 1e-4, 1e-3,
                                               estimate_time_offset=True)
            wd = watchdog.Watchdog(result, sa, sb)
            feed = guidance.PairFeed()
            states = []
            for k in range(0, len(pairs), 100):
                sl = slice(k, k + 100)
                part = replace(pairs, **{f: None if getattr(pairs, f) is None
                                         else getattr(pairs, f)[sl]
                                         for f in ('stamps', 'pos_a', 'quat_a', 'pos_b',
                                                   'quat_b', 'a_var_scale')})
                batch = feed.push(part)
                if batch is not None and acc.estimate is None and len(batch) > 50:
                    acc.set_estimate(guidance.Estimate.from_pairs(model, batch))
                acc.add(batch)
                states.append(wd.update(batch))
            states.append(wd.update(feed.push(None, final=True)))
            g = _outcome(acc.guidance)
            out[f'live/{model}/{change}'] = digest(
                [[(s.level, s.statistic, s.message) for s in states],
                 g if isinstance(g, tuple) else (g.sigma, g.diagnostic_values())])


def fingerprint(quick: bool = False) -> dict:
    """Return {output name: hash} over every part (``quick``: fewer diagnoses)."""
    out: dict = {}
    for part in (_calibration_outputs, _large_robust_outputs, _stream_outputs,
                 _uncertainty_outputs, _cli_outputs, _live_outputs):
        t = time.perf_counter()
        part(out)
        print(f'{part.__name__}: {time.perf_counter() - t:.1f} s', file=sys.stderr)
    t = time.perf_counter()
    _diagnosis_outputs(out, quick)
    print(f'_diagnosis_outputs: {time.perf_counter() - t:.1f} s', file=sys.stderr)
    return out


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.strip().splitlines()[0])
    parser.add_argument('--out', help='write the hashes to this JSON file')
    parser.add_argument('--compare', help='compare with the hashes in this JSON file')
    parser.add_argument('--quick', action='store_true', help='fewer diagnoses')
    args = parser.parse_args(argv)
    from threadpoolctl import threadpool_limits
    with threadpool_limits(1):
        hashes = fingerprint(args.quick)
    print(f'{len(hashes)} outputs')
    if args.out:
        with open(args.out, 'w') as f:
            json.dump(hashes, f, indent=1, sort_keys=True)
    if args.compare:
        with open(args.compare) as f:
            before = json.load(f)
        differ = sorted(k for k in before.keys() | hashes.keys()
                        if before.get(k) != hashes.get(k))
        print(f'{len(differ)} of {len(before)} differ' + ''.join(f'\n  {k}' for k in differ))
        return 1 if differ else 0
    return 0


if __name__ == '__main__':
    sys.exit(main())
