"""
The blind validation of the gap diagnosis (``coreg validate-diagnosis``).

It simulates recordings with one random effect (or none, or two at once) of a random size drawn
from the realistic ranges of docs/design.md §5, hides the truth, diagnoses them and scores the
answers (confusion matrix, false alarms on clean recordings, the size from which each effect is
found, estimate / truth of each named effect's size).
"""

from __future__ import annotations

from dataclasses import replace
import time
from typing import Optional

from coreg_ros.core.memory import check_memory
import numpy as np

#: Realistic sizes per effect (docs/design.md §5) split into small / medium / large ranges, in the
#: unit of the simulator's ``NAME=VALUE`` (coreg_ros.sim.injected).
SIZE_RANGES = {
    'time_offset': ((0.001, 0.003), (0.003, 0.015), (0.015, 0.050)),
    'clock_drift': ((1.0, 10.0), (10.0, 100.0), (100.0, 500.0)),
    'timestamp_jitter': ((0.001, 0.003), (0.003, 0.010), (0.010, 0.025)),
    'field_distortion': ((1.0, 2.0), (2.0, 5.0), (5.0, 10.0)),
    'distance_noise': ((1.0, 2.0), (2.0, 4.0), (4.0, 8.0)),
    'scale': ((0.0005, 0.002), (0.002, 0.007), (0.007, 0.02)),
    'link_flex': ((0.1, 0.5), (0.5, 1.5), (1.5, 3.0)),
    'outliers': ((0.005, 0.01), (0.01, 0.025), (0.025, 0.05)),
    'backlash': ((0.05, 0.2), (0.2, 0.5), (0.5, 1.0)),
    'noise_scale': ((1.1, 1.3), (1.3, 2.0), (2.0, 3.0)),
    'non_stationary': ((1.0, 2.0), (2.0, 5.0), (5.0, 10.0)),
    'shared_clock': ((0.001, 0.003), (0.003, 0.015), (0.015, 0.050)),
}
#: The answer that names each simulated effect right (one host clock: a constant offset).
EXPECTED = {'shared_clock': 'time_offset'}
#: Effects that change only the noise model.
NOISE_TRUTHS = ('noise_scale', 'distance_noise', 'timestamp_jitter')
#: Bytes a validation holds per case (its drawn case and its result, Python objects):
#: measured 11 kB (``validate(4, 0)``, the results copied under tracemalloc), about twice
#: that at the peak while the JSON is written.
BYTES_PER_CASE = 25_000
#: Share of cases with a second effect at once, and of large offsets (0.1-2 s).
TWO_SHARE = 0.15
LARGE_OFFSET_SHARE = 0.25
#: The estimate's key compared with the truth's value, per effect (None: no size).
SIZE_KEYS = {'time_offset': 'tau_s', 'clock_drift': 'ppm', 'timestamp_jitter': 'sigma_s',
             'field_distortion': 'max_mm', 'distance_noise': 'exponent', 'scale': 'scale',
             'link_flex': 'sag_mm', 'outliers': 'fraction', 'backlash': 'width_mm',
             'noise_scale': 'factor', 'shared_clock': 'tau_s', 'non_stationary': 'max_mm'}
SIZES = ('small', 'medium', 'large')
#: Share of clean recordings among the validation cases.
CLEAN_SHARE = 0.25
#: Range of the recordings' durations, s (B at 50 Hz: 2000-6000 pairs).
DURATION = (40.0, 120.0)


def _draw_effect(rng: np.random.Generator, names: tuple) -> dict:
    """One effect: name, size class, value, constructor arguments, spec text."""
    name = names[int(rng.integers(len(names)))]
    size = SIZES[int(rng.integers(3))]
    lo, hi = SIZE_RANGES[name][SIZES.index(size)]
    value = float(np.exp(rng.uniform(np.log(lo), np.log(hi))))
    kwargs = {}
    if name == 'noise_scale' and rng.random() < 0.4:
        value = 1.0 / value if value < 2.0 else 0.5 + 0.1 * rng.random()
    if name == 'time_offset' and size == 'large' and rng.random() < LARGE_OFFSET_SHARE:
        value = float(np.exp(rng.uniform(np.log(0.1), np.log(2.0))))
    if name in ('time_offset', 'clock_drift', 'shared_clock') and rng.random() < 0.3:
        value = -value
    if name == 'timestamp_jitter':
        # drops of 1-25 % and, in a third of the cases, gaps of seconds
        kwargs = {'drop_fraction': float(rng.uniform(0.01, 0.25)),
                  'gaps': int(rng.integers(1, 3)) if rng.random() < 0.33 else 0,
                  'gap_s': float(rng.uniform(1.0, 4.0))}
    if name == 'scale':
        signs = rng.choice([-1.0, 1.0], size=3)
        mags = value * rng.uniform(0.5, 1.0, size=3)
        mags[int(rng.integers(3))] = value
        value = (signs * mags).tolist()
        spec = f'scale={",".join(f"{v:.6g}" for v in value)}'
    else:
        spec = f'{name}={value:.6g}'
    return {'effect': name, 'size': size, 'value': value, 'spec': spec, 'kwargs': kwargs}


def draw_case(rng: np.random.Generator, clean_share: float = CLEAN_SHARE,
              duration: Optional[tuple] = None) -> dict:
    """
    Draw one validation case: effect(s) (or none), size class, value, recording settings.

    Returns
    -------
    dict
        ``effect`` (name or None), ``size`` ('small', 'medium', 'large' or None), ``value``
        (float or list), ``spec`` (the ``NAME=VALUE`` text), ``kwargs`` (further arguments of
        the simulator's effect), ``second`` (a second effect at once, or None), ``model``,
        ``duration``, ``sigma_a``, ``sigma_b``, ``seed``.

    """
    from coreg_ros.sim.injected import ALL_EFFECT_NAMES

    case = {'seed': int(rng.integers(0, 2 ** 31 - 1)),
            'model': 'full_pose' if rng.random() < 0.75 else 'position_only',
            'duration': float(rng.uniform(*(duration or DURATION))),
            'sigma_a': [float(rng.uniform(0.05, 0.3) * 1e-3), float(rng.uniform(0.2, 1.0) * 1e-3)],
            'sigma_b': [float(rng.uniform(0.2, 1.0) * 1e-3), float(rng.uniform(1.0, 4.0) * 1e-3)],
            'second': None}
    if rng.random() < clean_share:
        case.update(effect=None, size=None, value=None, spec=None, kwargs={})
        return case
    case.update(_draw_effect(rng, ALL_EFFECT_NAMES))
    if rng.random() < TWO_SHARE:
        # two effects at once: a structured one beside a different kind of error
        others = tuple(n for n in ('time_offset', 'scale', 'outliers', 'noise_scale',
                                   'non_stationary', 'field_distortion', 'link_flex')
                       if n != case['effect'] and EXPECTED.get(case['effect']) != n)
        second = _draw_effect(rng, others)
        second['size'] = 'large' if second['size'] == 'small' else second['size']
        lo, hi = SIZE_RANGES[second['effect']][SIZES.index(second['size'])]
        if second['effect'] != 'scale':
            v = float(np.sign(second['value']) * np.exp(rng.uniform(np.log(lo), np.log(hi))))
            if second['effect'] == 'noise_scale':
                v = abs(v)
            second.update(value=v, spec=f'{second["effect"]}={v:.6g}')
        case['second'] = second
    return case


def draw_effect_cases(rng: np.random.Generator, name: str, n: int,
                      sizes: tuple = ('medium', 'large'),
                      duration: Optional[tuple] = None) -> list:
    """
    Draw ``n`` cases of the one effect ``name`` (alone) at the given size classes.

    The recordings' settings are drawn as in ``draw_case``; for studying one effect's size
    accuracy on fresh random draws (never on the fixed cases of a validation seed).
    """
    out = []
    for _ in range(n):
        case = draw_case(rng, clean_share=0.0, duration=duration)
        eff = _draw_effect(rng, (name,))
        size = sizes[int(rng.integers(len(sizes)))]
        lo, hi = SIZE_RANGES[name][SIZES.index(size)]
        value = float(np.exp(rng.uniform(np.log(lo), np.log(hi))))
        if name in ('time_offset', 'clock_drift', 'shared_clock') and eff['value'] < 0:
            value = -value
        eff.update(size=size, value=value, spec=f'{name}={value:.6g}')
        case.update(eff)
        case['second'] = None
        out.append(case)
    return out


def _make_effects(case: dict) -> list:
    from coreg_ros.sim.injected import make_effect

    out = []
    for e in (case, case.get('second')):
        if not e or not e.get('spec'):
            continue
        eff = make_effect(e['effect'], e['value'])
        if e.get('kwargs'):
            eff = type(eff)(eff.sigma_s, **e['kwargs'])
        out.append(eff)
    return out


def _size_ratio(name: str, estimate: Optional[dict], value) -> Optional[float]:
    """Estimate / truth of the effect's size (None when not comparable)."""
    key = SIZE_KEYS.get(name)
    if key is None or not estimate or key not in estimate or value is None:
        return None
    est = estimate[key]
    if name == 'scale':
        t = np.asarray(value if isinstance(value, list) else [value] * 3, dtype=float)
        return float(np.linalg.norm(est) / max(np.linalg.norm(t), 1e-12))
    v = float(value)
    if name == 'noise_scale':
        # the size of a wrong noise model is how far the factor is from one, in log
        return float(np.log(est) / np.log(v)) if abs(np.log(v)) > 1e-9 else None
    return float(est / v) if v != 0 else None


def run_case(case: dict, options=None) -> dict:
    """Simulate the case's recording, diagnose it blind, and return the outcome."""
    from coreg_ros.core.diagnosis import diagnose_streams
    from coreg_ros.core.noise_model import DeviceNoise
    from coreg_ros.core.settings import Settings
    from coreg_ros.sim import simulate_recording
    from coreg_ros.threads import one_blas_thread

    effects = _make_effects(case)
    full = {d: None if case.get(f'noise_{d}') is None else DeviceNoise.from_covariances(
        *case[f'noise_{d}']) for d in 'ab'}
    rec = simulate_recording(case['seed'], case['duration'], case['model'],
                             sigma_a=tuple(case['sigma_a']), sigma_b=tuple(case['sigma_b']),
                             effects=effects, noise_a=full['a'], noise_b=full['b'])
    # the diagnosis sees the recording and the stated noise only, never the truth
    settings = Settings(model=case['model'], sigma_a=tuple(case['sigma_a']),
                        sigma_b=tuple(case['sigma_b']), noise_a=full['a'], noise_b=full['b'])
    t0 = time.perf_counter()
    with one_blas_thread():
        diag = diagnose_streams(rec.stream_a, list(rec.streams_b), settings, options=options)
    elapsed = time.perf_counter() - t0
    r = diag.report.as_dict()  # the JSON document: the outcome keeps parts of it
    named = [e['name'] for e in r['effects']]
    kinds = [e.get('kind') for e in r['effects']]
    truth = case['effect']
    expected = EXPECTED.get(truth, truth)
    accepted = {expected}
    if case.get('second'):
        s = case['second']['effect']
        accepted.add(EXPECTED.get(s, s))
    in_not_sep = truth is not None and any(expected in p for p in r['not_separable'])
    first = named[0] if named else 'none'
    outcome = 'not_separable' if in_not_sep and first not in accepted else first
    ratio = None
    if truth is not None and expected in named:
        row = r['effects'][named.index(expected)]
        ratio = _size_ratio(truth, row['estimate'], case['value'])
    out = dict(case)
    out.update(named=named, kinds=kinds, first=first, outcome=outcome,
               correct=bool(truth is not None and first in accepted),
               both_named=bool(case.get('second') and accepted <= set(named)),
               expected=expected, size_ratio=ratio,
               not_separable=r['not_separable'], gap_detected=r['gap_detected'],
               seconds=elapsed, n_pairs=r['n_pairs'], gap_before=r['gap_before'],
               gap_after=r['gap_after'],
               estimate=r['effects'][0]['estimate'] if r['effects'] else None,
               truth_description=[dict(e) for e in rec.truth.effects])
    return out


def _logistic_sizes(sizes: np.ndarray, hits: np.ndarray) -> dict:
    """Sizes at which the detection probability is 1/2 and 9/10 (logistic in log size)."""
    from scipy import optimize

    sizes = np.abs(np.asarray(sizes, dtype=float))
    hits = np.asarray(hits, dtype=float)
    out = {'n': int(len(sizes)), 'detected': int(hits.sum())}
    if len(sizes) < 4 or hits.all() or not hits.any():
        out.update(size_50=None, size_90=None,
                   note='all detected' if len(sizes) and hits.all() else
                   ('none detected' if len(sizes) else 'no cases'))
        if len(sizes) and hits.all():
            out['smallest_detected'] = float(sizes.min())
        return out
    x = np.log(sizes)

    def nll(p):
        z = p[0] + p[1] * x
        return float(np.sum(np.logaddexp(0, -z) * hits + np.logaddexp(0, z) * (1 - hits))
                     + 1e-3 * p[1] ** 2)

    res = optimize.minimize(nll, np.array([0.0, 1.0]), method='Nelder-Mead')
    a, b = res.x
    if b <= 1e-6:
        out.update(size_50=None, size_90=None, note='no increase with size')
        return out
    out.update(size_50=float(np.exp(-a / b)), size_90=float(np.exp((np.log(9.0) - a) / b)))
    return out


def summarize_validation(results: list) -> dict:
    """Confusion matrix, rates, size accuracy and detection sizes from the case outcomes."""
    from coreg_ros.core.diagnosis import EFFECT_NAMES
    from coreg_ros.sim.injected import ALL_EFFECT_NAMES

    rows = ['none', *ALL_EFFECT_NAMES]
    cols = ['none', *EFFECT_NAMES, 'non_stationary', 'not_separable']
    matrix = {r: dict.fromkeys(cols, 0) for r in rows}
    for res in results:
        truth = res['effect'] or 'none'
        outcome = res['outcome'] if res['outcome'] in cols else 'none'
        matrix[truth][outcome] += 1
    clean = [r for r in results if r['effect'] is None]
    false_alarm = (float(np.mean([bool(r['named']) for r in clean])) if clean else None)
    gap_flag = (float(np.mean([bool(r['gap_detected']) for r in clean])) if clean else None)
    by_size = {}
    for size in SIZES:
        sel = [r for r in results if r['size'] == size]
        ns = [r for r in sel if r['outcome'] == 'not_separable']
        decided = [r for r in sel if r['outcome'] != 'not_separable']
        correct = [r for r in decided if r['correct']]
        by_size[size] = {
            'cases': len(sel), 'not_separable': len(ns), 'named_correctly': len(correct),
            'named_correctly_share': (len(correct) / len(decided)) if decided else None,
            'named_correctly_share_of_all': (len(correct) / len(sel)) if sel else None}
    medium_large = [r for r in results if r['size'] in ('medium', 'large')]
    ml_decided = [r for r in medium_large if r['outcome'] != 'not_separable']
    ml_correct = [r for r in ml_decided if r['correct']]
    gap_ok = [r for r in ml_correct if r['gap_after'].get('position_rms_to_floor', 9) <= 1.2]
    extra = [r for r in results if r['correct'] and len(r['named']) > 1 + bool(r.get('second'))]
    noise_cases = [r for r in results if r['effect'] in NOISE_TRUTHS and not r.get('second')]
    noise_structured = [r for r in noise_cases if 'structured' in (r.get('kinds') or [])]
    two = [r for r in results if r.get('second')]
    sizes = {}
    for name in ALL_EFFECT_NAMES:
        ratios = [r['size_ratio'] for r in results if r['effect'] == name
                  and r['size'] in ('medium', 'large') and r['size_ratio'] is not None]
        if ratios:
            a = np.array(ratios)
            sizes[name] = {'n': len(a), 'median_ratio': float(np.median(a)),
                           'within_20pct': float(np.mean(np.abs(a - 1.0) <= 0.2))}
    detection = {}
    for name in ALL_EFFECT_NAMES:
        sel = [r for r in results if r['effect'] == name]
        vals = [np.max(np.abs(r['value'])) if isinstance(r['value'], list)
                else (abs(np.log(r['value'])) if name == 'noise_scale' else abs(r['value']))
                for r in sel]
        hits = [r['correct'] or r['outcome'] == 'not_separable' for r in sel]
        d = _logistic_sizes(np.array(vals), np.array(hits))
        if name == 'noise_scale':
            d['size_unit'] = '|log factor|'
            for key in ('size_50', 'size_90'):
                if d.get(key) is not None:
                    d[key + '_factor_up'] = float(np.exp(d[key]))
        detection[name] = d
    return {
        'cases': len(results),
        'confusion_matrix': {'rows_truth': rows, 'columns_answer': cols,
                             'counts': [[matrix[r][c] for c in cols] for r in rows]},
        'false_alarm_rate_clean': false_alarm,
        'gap_flag_rate_clean': gap_flag,
        'clean_cases': len(clean),
        'by_size': by_size,
        'medium_large_named_correctly_share': (len(ml_correct) / len(ml_decided)
                                               if ml_decided else None),
        'medium_large_not_separable': len(medium_large) - len(ml_decided),
        'medium_large_gap_after_within_20pct_share': (len(gap_ok) / len(ml_correct)
                                                      if ml_correct else None),
        'correct_with_extra_effects': len(extra),
        'noise_cases': len(noise_cases),
        'noise_reported_as_structured': len(noise_structured),
        'two_effect_cases': len(two),
        'two_effects_both_named': int(sum(bool(r['both_named']) for r in two)),
        'two_effects_first_correct': int(sum(bool(r['correct']) for r in two)),
        'size_accuracy_medium_large': sizes,
        'detection_size': detection,
        'median_seconds_per_case': float(np.median([r['seconds'] for r in results]))
        if results else None,
    }


def format_validation(summary: dict) -> str:
    """Text tables of a validation summary."""
    cm = summary['confusion_matrix']
    short = {'none': 'none', 'time_offset': 'toff', 'clock_drift': 'drift',
             'timestamp_jitter': 'jitt', 'field_distortion': 'field', 'distance_noise': 'dist',
             'scale': 'scale', 'link_flex': 'flex', 'outliers': 'outl', 'backlash': 'blash',
             'noise_scale': 'nscl', 'not_separable': 'n.sep', 'non_stationary': 'nstat',
             'shared_clock': 'shclk'}
    head = 'truth \\ answer'.ljust(18) + ''.join(short[c].rjust(6) for c in cm['columns_answer'])
    lines = [head]
    for r, counts in zip(cm['rows_truth'], cm['counts'], strict=True):
        lines.append(r.ljust(18) + ''.join(str(v).rjust(6) for v in counts))

    def pct(v):
        return 'n/a' if v is None else f'{v * 100:.1f} %'

    lines.append('')
    lines.append(f'false alarms on clean recordings: {pct(summary["false_alarm_rate_clean"])} '
                 f'of {summary["clean_cases"]} (gap flag raised: '
                 f'{pct(summary["gap_flag_rate_clean"])})')
    for size, s in summary['by_size'].items():
        lines.append(f'{size:>6}: {s["named_correctly"]}/{s["cases"] - s["not_separable"]} named '
                     f'correctly ({pct(s["named_correctly_share"])}), {s["not_separable"]} not '
                     f'separable')
    lines.append(f'medium+large named correctly: '
                 f'{pct(summary["medium_large_named_correctly_share"])}; gap after within 20 % '
                 f'of the noise floor: {pct(summary["medium_large_gap_after_within_20pct_share"])}'
                 f'; correct but with extra effects: {summary["correct_with_extra_effects"]}')
    lines.append(f'noise effects answered with a structured effect: '
                 f'{summary["noise_reported_as_structured"]} of {summary["noise_cases"]}; two '
                 f'effects at once: first correct {summary["two_effects_first_correct"]}, both '
                 f'named {summary["two_effects_both_named"]} of {summary["two_effect_cases"]}')
    lines.append('size estimate / truth, medium and large (median, share within 20 %):')
    for name, d in summary['size_accuracy_medium_large'].items():
        lines.append(f'  {name:18s} {d["median_ratio"]:.3f}  {d["within_20pct"] * 100:5.1f} % '
                     f'of {d["n"]}')
    lines.append('detection size (50 % / 90 %):')
    for name, d in summary['detection_size'].items():
        if d.get('size_50') is not None:
            lines.append(f'  {name:18s} {d["size_50"]:.4g} / {d["size_90"]:.4g} '
                         f'({d["detected"]}/{d["n"]} found)')
        else:
            lines.append(f'  {name:18s} {d.get("note", "")} ({d["detected"]}/{d["n"]} found)')
    return '\n'.join(lines)


def validate(cases: int, seed: int, progress=None, options=None, workers: int = 1,
             duration: Optional[tuple] = None, scheduler: Optional[str] = None,
             noise: Optional[dict] = None) -> dict:
    """
    Run ``cases`` blind validation cases drawn from ``seed``; returns results and summary.

    A case that raises comes back as a ``CaseFailure`` in ``results`` (also listed under
    ``failed`` with its seed) and is not scored; the other cases go on.

    Every case carries its own seed (drawn up front from ``seed``), so the results are the same
    whatever the number of workers. ``noise`` (``{'a': DeviceNoise, 'b': DeviceNoise}``,
    either may be left out; ``--noise FILE``) replaces the drawn noise of those devices in
    every case, simulated and stated: the diagnosis scored at a user's trackers' noise.
    ``workers`` local processes, or the Dask cluster at ``scheduler``, run them
    (``coreg_ros.parallel.run_cases``).
    """
    from coreg_ros.parallel import CaseFailure, run_cases

    check_memory(cases, BYTES_PER_CASE, f'a validation of {cases} cases', '--cases',
                 unit='cases')
    rng = np.random.default_rng(seed)
    drawn = [draw_case(rng, duration=duration or DURATION) for _ in range(cases)]
    for d, full in (noise or {}).items():
        for case in drawn:
            case[f'noise_{d}'] = [full.position_cov.tolist(), full.rotation_cov.tolist()]
            case[f'sigma_{d}'] = list(full.largest_sigmas())
    # the longest recordings first, so that no worker is left with a long case at the end; the
    # results go back to the order drawn (each case has its own seed: nothing else changes)
    order = sorted(range(len(drawn)), key=lambda i: -drawn[i]['duration'])
    done = run_cases(run_case, [drawn[i] for i in order], args=(options,), workers=workers,
                     scheduler=scheduler, progress=progress)
    results = [None] * len(drawn)
    for k, i in enumerate(order):
        results[i] = replace(done[k], index=i) if isinstance(done[k], CaseFailure) else done[k]
    # a case that raised is reported with its seed (``failed``) and left out of the scores
    scored = [r for r in results if not isinstance(r, CaseFailure)]
    return {'seed': seed, 'results': results,
            'failed': [r.as_dict() for r in results if isinstance(r, CaseFailure)],
            'summary': summarize_validation(scored)}


def _jsonable(o):
    if isinstance(o, (np.floating, np.integer)):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    return str(o)
