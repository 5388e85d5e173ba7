"""
After a bad fit: is it the clock? A wrong fixed offset, a drift left out, or a clock step.

A clock offset that is not what the fit assumed makes every pair a little wrong, in proportion
to the speed of the motion, and the fit cannot match the stated noise. Which clock story fits
is seen by estimating the offset τ on its own in consecutive time blocks of the recording
(each block a joint fit of τ, T0 and T1, ``offset_search``): the same τ in every block, away
from a fixed one, is a wrong ``--time-offset``; a τ that grows in proportion to time is a
drift (``--clock-drift auto``); two levels is a clock step (``coreg fix-bag --split-at-jump``).
Each block's σ of τ is inflated by its own √(χ²/dof), so a misfit that is not the clock (noise
understated, an effect the model lacks) does not make the blocks disagree. It runs only after
a fit the data contradict, and speaks only when one story explains the blocks, the
assumption of the fit does not, and the data fit the stated noise once the story is modelled.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Optional

from coreg_ros.core.calibration.offset_search import fit_with_offset_search
from coreg_ros.core.calibration.verdict import CONSISTENT_P
from coreg_ros.core.distributions import chi2_sf
from coreg_ros.core.errors import CoregError
from coreg_ros.core.settings import Settings
from coreg_ros.core.types import PoseStream
import numpy as np

#: Consecutive blocks of B's samples in which τ is estimated on its own.
N_BLOCKS = 6
#: B samples per block at most (evenly thinned): τ's σ needs no more, long recordings stay fast.
MAX_BLOCK_SAMPLES = 2000
#: A story (one τ, a line, one step) explains the blocks when its χ² has p above this.
EXPLAINS_P = 1e-3
#: Iterations a block fit may take: a check, not the answer. A block of a good recording
#: converges in 2-10; one that needs more says nothing about the clock, and on data that fit
#: nothing (a fuzzed stream) 6 blocks x every candidate lag x 100 iterations made the answer
#: wait for tens of seconds.
BLOCK_ITERATIONS = 30
#: A fixed offset is wrong when the blocks' common τ is this many σ away from it.
WRONG_OFFSET_SIGMAS = 5.0


@dataclass(frozen=True)
class _Block:
    start_s: float
    end_s: float
    tau: float
    sigma: float
    reduced_chi2: float

    @property
    def mid(self) -> float:
        return 0.5 * (self.start_s + self.end_s)


def block_offsets(stream_a: PoseStream, streams_b: Sequence[PoseStream], settings: Settings,
                  n_blocks: int = N_BLOCKS) -> list:
    """
    Estimate τ on its own in each of ``n_blocks`` consecutive blocks of B's samples.

    Parameters
    ----------
    stream_a : PoseStream
        Device A, whole.
    streams_b : sequence of PoseStream
        Device B (three streams for ``three_marker``), cut into blocks by B's first stream's
        stamps.
    settings : Settings
        The calibration's; τ is estimated (no drift) from ``time_offset``.
    n_blocks : int
        Blocks of equal time span.

    Returns
    -------
    list of _Block
        (start s, end s from B's first stamp, τ s, σ s inflated by the block's √(χ²/dof)) of
        the blocks whose fit determined τ.

    """
    first = streams_b[0]
    if len(first) < 2:
        return []
    use = settings.updated(estimate_time_offset=True, estimate_clock_drift=False,
                           max_iterations=min(settings.max_iterations, BLOCK_ITERATIONS))
    t0 = int(first.stamps[0])
    edges = np.linspace(first.stamps[0], first.stamps[-1] + 1, n_blocks + 1)
    out = []
    for lo, hi in zip(edges[:-1], edges[1:], strict=True):
        block = []
        for s in streams_b:
            keep = np.flatnonzero((s.stamps >= lo) & (s.stamps < hi))
            keep = keep[::max(1, int(np.ceil(len(keep) / MAX_BLOCK_SAMPLES)))]
            block.append(PoseStream(s.stamps[keep], s.position[keep], s.quat_wxyz[keep],
                                    s.frame_id))
        if len(block[0]) < use.min_pairs:
            continue
        try:
            result, _ = fit_with_offset_search(stream_a, block, use, None)
        except CoregError:
            continue
        timing = result.time_offset
        if result.status not in (1, 2):  # not converged (BLOCK_ITERATIONS): no witness
            continue
        if timing is None or not timing.estimated or not timing.sigma_s:
            continue
        inflate = np.sqrt(max(1.0, result.reduced_chi2)) if np.isfinite(
            result.reduced_chi2) else 1.0
        out.append(_Block(float(lo - t0) * 1e-9, float(hi - t0) * 1e-9, timing.value_s,
                          timing.sigma_s * inflate, float(result.reduced_chi2)))
    return out


def _weighted_fit(x: np.ndarray, y: np.ndarray, s: np.ndarray, degree: int) -> tuple:
    """(coefficients highest first, χ², dof) of a weighted polynomial fit."""
    X = np.vander(x, degree + 1)
    w = 1.0 / s
    coef, *_ = np.linalg.lstsq(X * w[:, None], y * w, rcond=None)
    chi2 = float(np.sum(((X @ coef - y) * w) ** 2))
    return coef, chi2, len(y) - degree - 1


def _explains(chi2: float, dof: int) -> bool:
    return dof > 0 and float(chi2_sf(chi2, dof)) >= EXPLAINS_P


def _best_step(blocks: list) -> Optional[tuple]:
    """(χ², dof, k, skipped) of the best two-level fit: blocks before k, after (one skipped)."""
    tau = np.array([b.tau for b in blocks])
    sig = np.array([b.sigma for b in blocks])
    best = None
    for k in range(1, len(blocks)):
        for skip in (None, k - 1, k):  # the step may fall inside the block at the split
            use = np.array([i for i in range(len(blocks)) if i != skip])
            before, after = use[use < k], use[use >= k]
            if skip == k:
                after = after[after > k]
            if not len(before) or not len(after):
                continue
            chi2 = 0.0
            for part in (before, after):
                _, c, _ = _weighted_fit(np.zeros(len(part)), tau[part], sig[part], 0)
                chi2 += c
            dof = len(before) + len(after) - 2
            if best is None or chi2 < best[0]:
                best = (chi2, dof, k, skip, before, after)
    return best


def _consistent(stream_a: PoseStream, streams_b: Sequence[PoseStream], settings: Settings,
                lo_s: float = -np.inf, hi_s: float = np.inf) -> bool:
    """Tell whether B's samples between ``lo_s`` and ``hi_s`` (s from its start) fit the noise."""
    t0 = int(streams_b[0].stamps[0])
    part = []
    for s in streams_b:
        t = (s.stamps - t0).astype(float) * 1e-9
        keep = np.flatnonzero((t >= lo_s) & (t < hi_s))
        part.append(PoseStream(s.stamps[keep], s.position[keep], s.quat_wxyz[keep], s.frame_id))
    try:
        result, _ = fit_with_offset_search(stream_a, part, settings, None)
    except CoregError:
        return False
    return bool(result.p_value >= CONSISTENT_P)


def clock_problem(stream_a: PoseStream, streams_b: Sequence[PoseStream],
                  settings: Settings) -> Optional[str]:
    """
    Name the clock story that explains a bad fit, with the option that models it, or None.

    The blocks' offsets (``block_offsets``) propose a story; it is named only when modelling
    it makes the data match the stated noise: the offset estimated (a wrong fixed one), the
    drift estimated, or each side of a step calibrated on its own. So an effect that only
    looks like the clock in the blocks (a distorted field seen in other places at other
    times) is not taken for it.

    Parameters
    ----------
    stream_a, streams_b :
        The streams the fit was made of.
    settings : Settings
        The fit's: a fixed offset (``estimate_time_offset`` false) is checked against the
        blocks' common τ; a drift is named only when it was not estimated.

    Returns
    -------
    str or None
        One phrase naming ``--time-offset auto``, ``--clock-drift auto`` or ``coreg fix-bag
        --split-at-jump`` (and the sizes seen); None when no clock story explains the blocks
        and the data, or too few blocks determine τ.

    """
    blocks = block_offsets(stream_a, streams_b, settings)
    if len(blocks) < 3:
        return None
    tau = np.array([b.tau for b in blocks])
    sig = np.array([b.sigma for b in blocks])
    mid = np.array([b.mid for b in blocks])
    (mean,), chi2_const, dof_const = _weighted_fit(np.zeros(len(tau)), tau, sig, 0)
    fixed = not settings.estimate_time_offset
    estimated = settings.updated(estimate_time_offset=True)
    if _explains(chi2_const, dof_const):
        sigma_mean = float(1.0 / np.sqrt(np.sum(sig ** -2)))
        if not fixed or abs(mean - settings.time_offset) < WRONG_OFFSET_SIGMAS * sigma_mean:
            return None
        if not _consistent(stream_a, streams_b, estimated):
            return None
        return (f'the clock offset is {mean * 1e3:.3f} ± {sigma_mean * 1e3:.3f} ms in every '
                f'part of the recording, not the given {settings.time_offset * 1e3:.3f} ms: '
                f'estimate it (--time-offset auto)')
    (slope, _), chi2_line, dof_line = _weighted_fit(mid - mid.mean(), tau, sig, 1)
    step = _best_step(blocks)
    line_ok = _explains(chi2_line, dof_line) and not settings.estimate_clock_drift
    step_ok = step is not None and _explains(step[0], step[1])
    if line_ok and (not step_ok or chi2_line <= step[0]):
        if not _consistent(stream_a, streams_b,
                           estimated.updated(estimate_clock_drift=True)):
            return None
        also = ' with --time-offset auto' if fixed else ''
        return (f'the clock offset drifts by {slope * 1e6:.0f} ppm ({tau[0] * 1e3:.2f} ms at '
                f'{mid[0]:.0f} s, {tau[-1] * 1e3:.2f} ms at {mid[-1]:.0f} s): estimate the '
                f'drift (--clock-drift auto{also})')
    if step_ok:
        _, _, _, _, before, after = step
        end, start = blocks[before[-1]].end_s, blocks[after[0]].start_s
        if not (_consistent(stream_a, streams_b, estimated, hi_s=end)
                and _consistent(stream_a, streams_b, estimated, lo_s=start)):
            return None
        t_before = float(np.average(tau[before], weights=sig[before] ** -2))
        t_after = float(np.average(tau[after], weights=sig[after] ** -2))
        return (f'the clock offset steps from {t_before * 1e3:.2f} ms to {t_after * 1e3:.2f} ms '
                f'between {end:.0f} s and {start:.0f} s into the recording (a clock step): '
                f'split the recording there and calibrate each part '
                f'({_split_advice(t_after - t_before, streams_b[0])})')
    return None


def _split_advice(jump: float, stream_b: PoseStream) -> str:
    """Name the ``coreg fix-bag --split-at-jump S`` that finds a step of B's clock by ``jump``."""
    period = float(np.median(np.diff(stream_b.stamps))) * 1e-9
    # B's stamps step by period + jump where its clock jumps: S between that and the period
    if jump > 0:
        threshold = period + 0.5 * jump
    elif -jump > 2.0 * period:
        threshold = -0.5 * jump
    else:  # a step back by less than two periods leaves no jump in the stamps to find
        return ('its stamps do not jump there by more than two sample periods: cut it at that '
                'time')
    return f'coreg fix-bag BAG NEW_BAG --split-at-jump {threshold:.3g}'
