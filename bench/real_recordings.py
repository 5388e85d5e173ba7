"""
The real recordings, as a user meets them: CSV exports converted, calibrated and diagnosed.

The ETH ASL hand-eye data sets (BSD-3-Clause, not shipped with the package) live in the
project's shared data folder: ``COREG_REAL_DATA`` or ``../shared/data/real`` next to the
repository. Each two-device recording is converted with ``coreg convert`` (``--sort`` where the
export repeats or reorders stamps), calibrated with ``coreg calibrate --json`` and diagnosed
with ``coreg diagnose --json`` at the noise a user would guess for a camera (5 mm, 20 mrad), all
through the command line's own ``main`` in this process. ``table()`` renders the results for
docs/validation.md.

Usage: ``python bench/real_recordings.py [--data DIR] [--json OUT]``.
"""

from __future__ import annotations

import argparse
import contextlib
import io
import json
import os
from pathlib import Path
import sys
import tempfile
import time

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

#: Camera noise a user would state without a datasheet: 5 mm, 20 mrad.
SIGMA_B = ('0.005', '0.02')

#: (name, folder, device A's CSV, device B's CSV, convert flags)
RECORDINGS = (
    ('robot arm / SR300 IR camera', 'robot_arm_camera_real',
     'robot_arm_complete_bag_color_and_ir_base_link_sr300_hinge.csv',
     'robot_arm_complete_bag_color_and_ir_target_ir.csv', ()),
    ('Vicon / checkerboard RGB camera', 'prime_sense_vicon_2',
     '2017-04-09-18-14-38_vicon_prime_sense.csv',
     '2017-04-09-18-14-38_W_camera_rgb_image_raw.csv', ('--sort',)),
    ('simulated hand / camera (control)', 'robot_arm_camera_sim', 'robot_arm_sim_hand.csv',
     'robot_arm_sim_camera.csv', ('--sort',)),
)


def data_folder(given: str | None = None) -> Path | None:
    """Return the folder holding ``eth_hand_eye`` (None when it is not on this machine)."""
    for candidate in (given, os.environ.get('COREG_REAL_DATA'),
                      ROOT.parent / 'shared' / 'data' / 'real'):
        if candidate and (Path(candidate) / 'eth_hand_eye').is_dir():
            return Path(candidate)
    return None


def _coreg(*args) -> tuple[int, str]:
    """Run ``coreg ARGS`` in this process; return its exit code and what it printed."""
    from coreg_ros.cli.main import main
    buf = io.StringIO()
    with contextlib.redirect_stdout(buf), contextlib.redirect_stderr(buf):
        try:
            code = main([str(a) for a in args])
        except SystemExit as e:
            code = int(e.code or 0)
    return code, buf.getvalue()


def run_recording(root: Path, work: Path, name: str, folder: str, csv_a: str, csv_b: str,
                  flags: tuple) -> dict:
    """Convert, calibrate and diagnose one recording; return what the table needs."""
    src = root / 'eth_hand_eye' / folder
    bag = work / folder
    out = {'name': name, 'folder': folder}
    code, text = _coreg('convert', *flags, src / csv_a, src / csv_b, bag)
    if code != 0:
        return {**out, 'error': f'convert: {text.strip().splitlines()[-1]}'}
    t = time.perf_counter()
    code, text = _coreg('calibrate', bag, '--sigma-b', *SIGMA_B, '--json', work / 'cal.json')
    out['calibrate'] = {'exit_code': code, 'seconds': time.perf_counter() - t}
    if (work / 'cal.json').exists():
        out['calibrate']['result'] = json.loads((work / 'cal.json').read_text())
        (work / 'cal.json').unlink()
    else:
        out['calibrate']['error'] = text.strip().splitlines()[-1]
    t = time.perf_counter()
    code, text = _coreg('diagnose', bag, '--sigma-b', *SIGMA_B, '--json', work / 'diag.json')
    out['diagnose'] = {'exit_code': code, 'seconds': time.perf_counter() - t}
    if (work / 'diag.json').exists():
        out['diagnose']['report'] = json.loads((work / 'diag.json').read_text())
        (work / 'diag.json').unlink()
    else:
        out['diagnose']['error'] = text.strip().splitlines()[-1]
    return out


def run(data: str | None = None) -> dict:
    """Run every recording (``RECORDINGS``); ``{'available': False}`` without the data."""
    root = data_folder(data)
    if root is None:
        return {'available': False}
    with tempfile.TemporaryDirectory(prefix='coreg_real_') as tmp:
        rows = [run_recording(root, Path(tmp), *rec) for rec in RECORDINGS]
    return {'available': True, 'sigma_b': SIGMA_B, 'recordings': rows}


def _calibration_cells(cal: dict) -> list:
    res = cal.get('result')
    if res is None:
        return [cal.get('error', '–')] * 3
    tau = res.get('time_offset') or {}
    tau_text = (f'{tau["value_s"] * 1e3:+.1f} ± {tau["sigma_s"] * 1e3:.1f} ms'
                if tau.get('estimated') else f'{tau.get("value_s", 0) * 1e3:g} ms (kept)')
    rej = res.get('rejected_pairs') or {}
    verdict = 'consistent' if res.get('fit_consistent') else '**inconsistent**'
    chi = res['chi2'] / res['dof'] if res.get('dof') else float('nan')
    return [tau_text, f'{rej.get("count", 0)} of {res["n_pairs"]} ({rej.get("share", 0):.1%})',
            f'{chi:.2f}, {verdict}, exit {cal["exit_code"]}']


def _diagnosis_cells(diag: dict) -> list:
    rep = diag.get('report')
    if rep is None:
        return [diag.get('error', '–'), '–']
    named = [f'{e["name"]} {e["estimate"].get("text", "")} ({e["kind"]})'.strip()
             for e in rep.get('effects', [])]
    b, a = rep['gap_before'], rep['gap_after']
    gap = (f'{b["chi2_per_dof_at_stated_noise"]:.2f} → {a["chi2_per_dof_at_stated_noise"]:.2f}; '
           f'{b["rms_position_mm"]:.2f} → {a["rms_position_mm"]:.2f} mm (floor '
           f'{b["stated_floor_position_mm"]:.2f}); {b["rms_rotation_deg"]:.3f} → '
           f'{a["rms_rotation_deg"]:.3f}° (floor {b["stated_floor_rotation_deg"]:.3f}); '
           f'{a.get("share_of_excess_explained", 0):.0%} of the excess explained')
    return ['; '.join(named) or 'no effect', gap]


def table(result: dict) -> str:
    """Markdown tables of the real recordings (calibrate, diagnose)."""
    if not result.get('available'):
        return 'not measured: the real recordings are not on this machine'
    lines = [f'Camera noise stated as {SIGMA_B[0]} m, {SIGMA_B[1]} rad (`--sigma-b`); clock '
             'offset estimated (the default).', '',
             '| recording (A / B) | τ by `coreg calibrate` | rejected pairs | χ²/dof, verdict, '
             'exit code | `coreg diagnose`: effects | held out at the stated noise: χ²/dof, '
             'position RMS, rotation RMS (before → after) |', '|---|---|---|---|---|---|']
    for rec in result['recordings']:
        if 'error' in rec:
            lines.append(f'| {rec["name"]} | {rec["error"]} | | | | |')
            continue
        cells = _calibration_cells(rec['calibrate']) + _diagnosis_cells(rec['diagnose'])
        lines.append(f'| {rec["name"]} | ' + ' | '.join(cells) + ' |')
    return '\n'.join(lines)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.strip().splitlines()[0])
    parser.add_argument('--data', help='folder holding eth_hand_eye (default: COREG_REAL_DATA '
                                       'or ../shared/data/real)')
    parser.add_argument('--json', help='also write the results here')
    args = parser.parse_args(argv)
    result = run(args.data)
    print(table(result))
    if args.json:
        Path(args.json).write_text(json.dumps(result, indent=1, default=str) + '\n')
    return 0


if __name__ == '__main__':
    sys.exit(main())
