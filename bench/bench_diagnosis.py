"""
Benchmark and full-size validation of the sim-to-real gap diagnosis (issues 11 and 15).

1. Runtime: a 60k-pair recording (1200 s, A at 100 Hz, B at 50 Hz) with a time offset is
   diagnosed end to end by ``diagnose_streams`` (stamps, coarse offset search, pairing,
   calibration, detect, locate, every candidate effect of the diagnosis, held-out gap); goal
   under 10 s on the 2-core development machine (issue 15; issue 11 asked for 30 s). Beside it,
   measured in the same run on the same recording: the calibration alone (``calibrate`` on the
   same pairs) and the diagnosis at a baseline commit (a git worktree under /tmp, run in a
   subprocess), so the ratio holds however loaded the shared machine is.
2. Validation (``coreg validate-diagnosis`` at full size): recordings with one hidden random
   effect (or none) at a random size; the confusion matrix, the false-alarm rate on clean
   recordings, the share named correctly at medium and large sizes, the gap left after the
   named effect and the size at which each effect is found half and nine tenths of the time.

Run alone: ``python bench/bench_diagnosis.py [--cases 0] [--seed 2024] [--jobs 2]
[--baseline-commit COMMIT | --no-baseline] [--json bench/results/bench_diagnosis.json]``;
prints the table and writes bench/results/bench_diagnosis.json.
"""

from __future__ import annotations

import argparse
import json
import os
from pathlib import Path
import subprocess
import sys
import time

N_PAIRS = 60_000
GOAL_SECONDS = 10.0
#: The commit before the diagnosis was made faster (the baseline of the speed-up).
BASELINE_COMMIT = '9bf8d64'
ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / 'bench' / 'results'


def _recording(n_pairs: int, seed: int, effect: str):
    from coreg_ros.sim import simulate_recording
    from coreg_ros.sim.injected import parse_effect

    return simulate_recording(seed, n_pairs / 50.0,
                              effects=[parse_effect(effect)] if effect else [])


def time_large(n_pairs: int = N_PAIRS, seed: int = 7, effect: str = 'time_offset=0.012') -> dict:
    """Diagnose one large simulated recording; wall-clock seconds and the answer."""
    from coreg_ros.core.diagnosis import diagnose_streams
    from coreg_ros.core.settings import Settings

    rec = _recording(n_pairs, seed, effect)
    settings = Settings()
    t0 = time.perf_counter()
    diag = diagnose_streams(rec.stream_a, list(rec.streams_b), settings)
    seconds = time.perf_counter() - t0
    r = diag.report.as_dict()  # the JSON document
    return {'n_pairs': r['n_pairs'], 'effect': effect, 'seconds': seconds,
            'goal_seconds': GOAL_SECONDS, 'within_goal': seconds <= GOAL_SECONDS,
            'named': [e['name'] for e in r['effects']],
            'estimate': r['effects'][0]['estimate'] if r['effects'] else None,
            'verdict': r['verdict'],
            'candidates_screened': sum(bool(c.get('screened'))
                                       for rnd in r['candidates'] for c in rnd),
            'candidates_refitted': sum(not c.get('screened')
                                       for rnd in r['candidates'] for c in rnd)}


def time_calibration(n_pairs: int = N_PAIRS, seed: int = 7,
                     effect: str = 'time_offset=0.012') -> float:
    """Seconds of the calibration alone (``pair_for`` + ``calibrate``) on the same recording."""
    from coreg_ros.core.calibration.calibrate import calibrate
    from coreg_ros.core.calibration.pairing import pair_for
    from coreg_ros.core.settings import Settings

    rec = _recording(n_pairs, seed, effect)
    settings = Settings()
    t0 = time.perf_counter()
    pairs, _ = pair_for(rec.stream_a, list(rec.streams_b), settings)
    calibrate(pairs, settings)
    return time.perf_counter() - t0


def _worktree(commit: str) -> Path:
    """Return a git worktree of ``commit`` under /tmp (made once, reused)."""
    path = Path('/tmp') / f'coreg-bench-diag-{commit}'
    if not (path / 'coreg_ros').is_dir():
        subprocess.run(['git', '-C', str(ROOT), 'worktree', 'add', '--detach', str(path),
                        commit], check=True, capture_output=True)
    return path


def time_baseline(commit: str, n_pairs: int = N_PAIRS, seed: int = 7,
                  effect: str = 'time_offset=0.012') -> dict:
    """Time the same with the code of ``commit`` (a subprocess importing its worktree)."""
    path = _worktree(commit)
    code = ('import json, sys; sys.path.insert(0, "bench"); import bench_diagnosis as b; '
            f'print(json.dumps(b.time_large({n_pairs}, {seed}, {effect!r}), default=str))')
    env = dict(os.environ, PYTHONPATH=str(path))
    out = subprocess.run([sys.executable, '-c', code], cwd=path, env=env, check=True,
                         capture_output=True, text=True)
    res = json.loads(out.stdout.strip().splitlines()[-1])
    return {'commit': commit, 'seconds': res['seconds'], 'named': res['named']}


def _timed(effect: str, repeats: int, baseline_commit) -> tuple:
    """Best of ``repeats`` alternated timings of the diagnosis, the calibration, the baseline."""
    runs, base, cal = [], [], []
    error = None
    for _ in range(max(repeats, 1)):
        runs.append(time_large(effect=effect))
        cal.append(time_calibration(effect=effect))
        if baseline_commit:
            try:
                base.append(time_baseline(baseline_commit, effect=effect))
            except (subprocess.CalledProcessError, OSError, ValueError) as e:
                error = f'{type(e).__name__}: {e}'
                baseline_commit = None
    best = min(runs, key=lambda r: r['seconds'])
    best['repeats'] = [r['seconds'] for r in runs]
    best['calibration_seconds'] = min(cal)
    best['ratio_to_calibration'] = best['seconds'] / max(min(cal), 1e-9)
    if base:
        b = min(base, key=lambda r: r['seconds'])
        best['baseline'] = b
        best['speedup'] = b['seconds'] / max(best['seconds'], 1e-9)
    return best, error


#: Recordings timed: a time offset and a field distortion (the largest
#: candidate model, 89 parameters, refitted on all pairs).
EFFECTS = ('time_offset=0.012', 'field_distortion=5')


def run(cases: int = 0, seed: int = 2024, jobs: int = 1, timing: bool = True,
        baseline_commit: str | None = BASELINE_COMMIT, repeats: int = 2) -> dict:
    """
    Run the timing (and the validation when ``cases`` > 0); returns a JSON-friendly dict.

    The diagnosis and its baselines are timed alternately ``repeats`` times (best of each),
    so a load change on the shared machine hits both alike. ``runtime`` is the first
    recording of ``EFFECTS``; ``runtimes`` holds them all.
    """
    from coreg_ros.sim.validation import validate

    out = {}
    if timing:
        out['runtimes'] = []
        for effect in EFFECTS:
            best, error = _timed(effect, repeats, baseline_commit)
            if error:
                out['baseline_error'] = error
                baseline_commit = None
            out['runtimes'].append(best)
        out['runtime'] = out['runtimes'][0]
    if cases > 0:
        t0 = time.perf_counter()
        val = validate(cases, seed, workers=jobs)
        out['validation'] = {'cases': cases, 'seed': seed, 'seconds': time.perf_counter() - t0,
                             'summary': val['summary'], 'results': val['results']}
    return out


def table(result: dict) -> str:
    """Markdown table of the timing."""
    rts = result.get('runtimes') or ([result['runtime']] if result.get('runtime') else [])
    if not rts:
        return ''
    lines = ['| what (same recording, same run) | pairs | seconds | note |',
             '|---|---|---|---|']
    for rt in rts:
        lines.append(f'| `diagnose_streams`, every candidate effect; {rt["effect"]} '
                     f'| {rt["n_pairs"]:,} | {rt["seconds"]:.2f} | goal < {rt["goal_seconds"]:g} '
                     f's: {"met" if rt["within_goal"] else "not met"}; named '
                     f'{", ".join(rt["named"]) or "none"}; {rt["candidates_refitted"]} '
                     f'candidate models refitted, {rt["candidates_screened"]} screened |')
        if 'baseline' in rt:
            b = rt['baseline']
            lines.append(f'| the same at {b["commit"]} (before) | {rt["n_pairs"]:,} '
                         f'| {b["seconds"]:.2f} | speed-up x{rt["speedup"]:.2f}; named '
                         f'{", ".join(b["named"]) or "none"} |')
        lines.append(f'| calibration alone (`pair_for` + `calibrate`) | {rt["n_pairs"]:,} '
                     f'| {rt["calibration_seconds"]:.2f} | the diagnosis costs '
                     f'x{rt["ratio_to_calibration"]:.1f} the calibration |')
    return '\n'.join(lines)


def main(argv=None) -> int:
    from coreg_ros.sim.validation import _jsonable, format_validation

    p = argparse.ArgumentParser(description=__doc__.strip().splitlines()[0])
    p.add_argument('--cases', type=int, default=0)
    p.add_argument('--seed', type=int, default=2024)
    p.add_argument('--jobs', type=int, default=1)
    p.add_argument('--repeats', type=int, default=2)
    p.add_argument('--no-timing', action='store_true')
    p.add_argument('--baseline-commit', default=BASELINE_COMMIT)
    p.add_argument('--no-baseline', action='store_true')
    p.add_argument('--json', default=str(RESULTS / 'bench_diagnosis.json'))
    args = p.parse_args(argv)
    out = run(args.cases, args.seed, args.jobs, timing=not args.no_timing,
              baseline_commit=None if args.no_baseline else args.baseline_commit,
              repeats=args.repeats)
    if 'runtime' in out:
        print(table(out))
        for rt in out['runtimes']:
            print(f'{rt["effect"]}: {rt["verdict"]}')
    if 'validation' in out:
        print(format_validation(out['validation']['summary']))
    if args.json:
        Path(args.json).parent.mkdir(parents=True, exist_ok=True)
        with open(args.json, 'w', encoding='utf-8') as f:
            json.dump(out, f, indent=1, default=_jsonable)
    return 0


if __name__ == '__main__':
    sys.exit(main())
