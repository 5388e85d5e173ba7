"""
The stream-level entry: read the stamps, find the clock offset coarsely, pair, diagnose.

``diagnose_streams`` is what ``coreg diagnose`` runs on a recording: the stamps are read
for jitter, drops and gaps before pairing (``stamps.py``), and a clock offset too large for
the fine fit to walk to is found first by cross-correlating the devices' speeds.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import replace
from typing import Optional, Union

from coreg_ros.core.calibration.calibrate import calibrate
from coreg_ros.core.calibration.pairing import pair_for
from coreg_ros.core.clock.timing import coarse_offsets
from coreg_ros.core.diagnosis.engine import diagnose, Diagnosis
from coreg_ros.core.diagnosis.options import Options, Progress
from coreg_ros.core.diagnosis.report import Pairing
from coreg_ros.core.diagnosis.stamps import stamps_report
from coreg_ros.core.settings import check_settings, Settings
from coreg_ros.core.types import Pairs, PoseStream
import numpy as np

#: A coarse offset this far from the given one (s) is tried as the pairing offset.
COARSE_MIN_S = 0.05
#: ... and kept when the fit there has at most this share of the χ² at the given offset.
COARSE_GAIN = 0.5


def diagnose_streams(stream_a: PoseStream, streams_b: Union[PoseStream, Sequence[PoseStream]],
                     settings: Settings, options: Optional[Options] = None,
                     progress: Optional[Progress] = None) -> Diagnosis:
    """
    Read the stamps, search the clock offset coarsely, pair as ``coreg calibrate``, diagnose.

    The coarse search (``timing.coarse_offsets``, the devices' speeds cross-correlated) finds
    offsets of any size even when another error dominates the residuals; when its best
    candidate is more than ``COARSE_MIN_S`` from the given offset and pairing there fits
    clearly better, the diagnosis pairs there, names the offset and measures the gap before
    at the given offset.
    """
    bs = list(streams_b) if isinstance(streams_b, (list, tuple)) else [streams_b]
    context = {'stamps': stamps_report(stream_a, bs)}
    check_settings(settings)
    pairs, paired = pair_for(stream_a, bs, settings)
    use_settings = settings
    shift = coarse_shift(stream_a, bs, settings, pairs)
    if shift:
        moved = settings.updated(time_offset=settings.time_offset + shift)
        context['before'] = (pairs, settings)
        context['coarse_shift_s'] = shift
        pairs, paired = pair_for(stream_a, bs, moved)
        use_settings = moved
    diag = diagnose(pairs, use_settings, stream_a, options, progress, context=context)
    diag.report = replace(diag.report, pairing=Pairing(
        n_a=paired.n_a, n_b=paired.n_b, n_paired=paired.n_paired,
        unpaired=dict(paired.unpaired)))
    return diag


def coarse_shift(stream_a: PoseStream, streams_b: list, settings: Settings,
                 pairs: Pairs) -> float:
    """
    Shift (s) of the pairing offset found by the coarse search, or 0.

    The best two offsets of ``timing.coarse_offsets`` more than ``COARSE_MIN_S`` from the
    given one are tried: pairing there must fit with at most ``COARSE_GAIN`` of the χ²/dof
    at the given offset (on a few thousand pairs, without the robust weights).
    """
    angular = settings.model == 'full_pose' or len(streams_b) == 3
    try:
        cands = coarse_offsets(stream_a, streams_b, angular=angular)
    except (ValueError, np.linalg.LinAlgError):
        return 0.0
    if not cands or abs(cands[0][0] - settings.time_offset) <= COARSE_MIN_S or len(pairs) < 50:
        # the speeds correlate best near the given offset: the fine fit takes it from there
        return 0.0
    far = [tau for tau, _ in cands[:2] if abs(tau - settings.time_offset) > COARSE_MIN_S]

    def thin(p):
        # the comparison needs a few thousand pairs, not all
        step = max(1, len(p) // 4000)
        if step == 1:
            return p
        return Pairs(stamps=p.stamps[::step], pos_a=p.pos_a[::step], quat_a=p.quat_a[::step],
                     pos_b=p.pos_b[::step],
                     quat_b=None if p.quat_b is None else p.quat_b[::step],
                     a_var_scale=None if p.a_var_scale is None else p.a_var_scale[::step])

    try:
        here = calibrate(thin(pairs), settings.updated(robust=False))
    except Exception:  # noqa: BLE001 - a refusal at the given offset: try the other
        here = None
    best, best_chi = 0.0, here.chi2 / max(here.dof, 1) if here is not None else np.inf
    for tau in far:
        moved = settings.updated(time_offset=tau)
        p2, _ = pair_for(stream_a, streams_b, moved)
        if len(p2) < max(50, 0.5 * len(pairs)):
            continue
        try:
            res = calibrate(thin(p2), moved.updated(robust=False))
        except Exception:  # noqa: BLE001 - unobservable or too few: not this one
            continue
        chi = res.chi2 / max(res.dof, 1)
        if chi < COARSE_GAIN * best_chi:
            best, best_chi = tau - settings.time_offset, chi
    return float(best)
