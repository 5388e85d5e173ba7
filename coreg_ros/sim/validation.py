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
from coreg_ros.sim.draws import (  # noqa: F401 - the validation's draws, importable from here
    draw_case,
    draw_effect_cases,
    DURATION,
    SIZE_RANGES,
    SIZES,
)
import numpy as np

#: The answer that names each simulated effect right (one host clock: a constant offset;
#: outliers in bursts are outliers, their runs said).
EXPECTED = {'shared_clock': 'time_offset', 'outlier_bursts': 'outliers',
            't0_step': 'pose_step', 't1_step': 'pose_step'}
#: Effects that change only the noise model.
NOISE_TRUTHS = ('noise_scale', 'distance_noise', 'timestamp_jitter', 'anisotropic_noise',
                'noise_step')
#: Bytes a validation holds per case (its drawn case and its result, Python objects):
#: measured 11 kB (``validate(4, 0)``, the results copied under tracemalloc), about twice
#: that at the peak while the JSON is written.
BYTES_PER_CASE = 25_000
#: The estimate's key compared with the truth's value, per effect (None: no size).
SIZE_KEYS = {'time_offset': 'tau_s', 'clock_drift': 'ppm', 'timestamp_jitter': 'sigma_s',
             'field_distortion': 'max_mm', 'distance_noise': 'exponent', 'scale': 'scale',
             'link_flex': 'sag_mm', 'outliers': 'fraction', 'backlash': 'width_mm',
             'noise_scale': 'factor', 'shared_clock': 'tau_s', 'non_stationary': 'max_mm',
             'outlier_bursts': 'fraction', 'clock_step': 'step_s',
             'anisotropic_noise': 'factors', 't0_step': 't0_mm', 't1_step': 't1_mm',
             'noise_step': 'factor'}
#: Answers beside the effects: no effect but structure by its signature, or a cheap cause.
UNEXPLAINED, CAUSE = 'unexplained', 'cause'


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
    if name == 'anisotropic_noise':
        est = est[0]  # the factor along the axis it grew along: the largest
    if name in ('noise_scale', 'anisotropic_noise', 'noise_step'):
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
                             effects=effects, motion=case.get('motion', 'diverse'),
                             noise_a=full['a'], noise_b=full['b'])
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
    first = named[0] if named else ('unexplained' if r.get('unexplained')
                                    else 'cause' if r.get('cause') else 'none')
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
               unexplained=(r['unexplained']['text'] if r.get('unexplained') else None),
               cause=r['cause']['text'] if r.get('cause') else None,
               not_significant=[e['name'] for e in r.get('not_significant', [])],
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
    cols = ['none', *EFFECT_NAMES, 'non_stationary', 'not_separable', UNEXPLAINED, CAUSE]
    matrix = {r: dict.fromkeys(cols, 0) for r in rows}
    for res in results:
        truth = res['effect'] or 'none'
        outcome = res['outcome'] if res['outcome'] in cols else 'none'
        matrix[truth][outcome] += 1
    # rigs that cannot move in every direction are scored apart: an effect the motion cannot
    # show is not expected there
    n_cases = len(results)
    rigs = [r for r in results if r.get('motion', 'diverse') != 'diverse']
    results = [r for r in results if r.get('motion', 'diverse') == 'diverse']
    clean = [r for r in results if r['effect'] is None]

    def alarm(r):
        return bool(r['named'] or r.get('unexplained') or r.get('cause'))

    false_alarm = (float(np.mean([alarm(r) for r in clean])) if clean else None)
    gap_flag = (float(np.mean([bool(r['gap_detected']) for r in clean])) if clean else None)
    rig_clean = [r for r in rigs if r['effect'] is None]
    rig_effects = [r for r in rigs if r['effect'] is not None]
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
        'cases': n_cases,
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
        'restricted_rigs': {'clean_cases': len(rig_clean),
                            'false_alarms': int(sum(alarm(r) for r in rig_clean)),
                            'effect_cases': len(rig_effects),
                            'named_correctly': int(sum(bool(r['correct'])
                                                       for r in rig_effects))},
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
             'shared_clock': 'shclk', 'clock_step': 'cstep', 'anisotropic_noise': 'aniso',
             'outlier_bursts': 'burst', UNEXPLAINED: 'unexp', CAUSE: 'cause',
             'pose_step': 'pstep', 'noise_step': 'nstep', 't0_step': 't0st',
             't1_step': 't1st'}
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
    two = max(summary['two_effect_cases'], 1)
    lines.append(f'noise effects answered with a structured effect: '
                 f'{summary["noise_reported_as_structured"]} of {summary["noise_cases"]}; two '
                 f'effects at once: first correct {summary["two_effects_first_correct"]} '
                 f'({summary["two_effects_first_correct"] / two * 100:.1f} %), both named '
                 f'{summary["two_effects_both_named"]} '
                 f'({summary["two_effects_both_named"] / two * 100:.1f} %) of '
                 f'{summary["two_effect_cases"]}')
    rig = summary.get('restricted_rigs')
    if rig:
        lines.append(f'restricted rigs (scored apart): false alarms {rig["false_alarms"]} of '
                     f'{rig["clean_cases"]} clean; effects named first {rig["named_correctly"]}'
                     f' of {rig["effect_cases"]} (some cannot show in the motion)')
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
