"""
Gap measures that a noise model cannot game: the held-out gap at the stated noise.

Every number here is taken at the **stated** noise (docs/design.md §5): an effect that only
widens the noise model (noise scale, distance noise, jitter as a variance) changes none of
them, so it can never look as if it closed the gap. Pairs an outlier model sets aside are
counted, shown and taken as unexplained.

- ``stated_measures``: held-out χ²/dof at the stated noise, position RMS (mm) and rotation
  RMS (deg) against the stated floor, over the counted pairs and over all pairs.
- ``share_explained``: the share of the excess explained, with excluded pairs unexplained.

Where the excess that is left lies is ``excess.py``.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

from coreg_ros.core.diagnosis.record import inline, optional, Record
from coreg_ros.core.diagnosis.summary import HeldOutGap
import numpy as np

#: An RMS that moved by less than this share did not move.
RMS_MOVED = 0.02


@dataclass(frozen=True, kw_only=True)
class StatedBlock(Record):
    """
    The held-out gap at the stated noise over some pairs.

    Attributes
    ----------
    chi2_per_dof_at_stated_noise : float
        Mean squared normalised error per residual (one if the model and the noise hold).
    rms_position_mm, stated_floor_position_mm : float
        RMS position error and what the stated noise alone gives, mm.
    rms_rotation_deg, stated_floor_rotation_deg : float, optional
        The same for rotation, deg (full pose).

    """

    chi2_per_dof_at_stated_noise: float
    rms_position_mm: float
    stated_floor_position_mm: float
    rms_rotation_deg: Optional[float] = optional()
    stated_floor_rotation_deg: Optional[float] = optional()


@dataclass(frozen=True, kw_only=True)
class ExcludedPairs(Record):
    """
    Pairs an outlier model set aside: counted as unexplained.

    Attributes
    ----------
    count : int
    share : float
        Of all pairs.
    counted_as : str
        ``'unexplained'``.
    stamps_ns : list of int
        The first 200 of their stamps, ns.

    """

    count: int
    share: float
    counted_as: str
    stamps_ns: list


@dataclass(frozen=True, kw_only=True)
class StatedGap(Record):
    """
    The held-out gap at the stated noise: over the counted pairs, over all, the excluded.

    Attributes
    ----------
    counted : StatedBlock
        Over the pairs counted (keys as they are).
    all_pairs : StatedBlock
        Over all pairs (keys with the suffix ``_all_pairs``).
    excluded_pairs : ExcludedPairs

    """

    counted: StatedBlock = inline()
    all_pairs: StatedBlock = inline('_all_pairs')
    excluded_pairs: ExcludedPairs


@dataclass(frozen=True, kw_only=True)
class GapBefore(Record):
    """
    The gap before the effects: the base model on held-out blocks.

    Attributes
    ----------
    held_out : HeldOutGap
        Under the base model's noise (keys as they are).
    stated : StatedGap
        At the stated noise, all pairs counted (keys as they are).
    held_out_on : str
        ``'time blocks'`` or ``'workspace cells'``.
    share_of_excess_explained : float
        Nothing before the effects: 0.

    """

    held_out: HeldOutGap = inline()
    stated: StatedGap = inline()
    held_out_on: str
    share_of_excess_explained: float = 0.0


@dataclass(frozen=True, kw_only=True)
class GapAfter(Record):
    """
    The gap after the accepted effects: the final model on the same held-out blocks.

    Attributes
    ----------
    held_out : HeldOutGap
        Under the final model's noise (keys as they are).
    stated : StatedGap
        At the stated noise, over the pairs counted (keys as they are).
    share_of_excess_explained : float
        ``share_explained``.
    held_out_on : str
    rms_moved : bool
        ``rms_moved``: whether the effects moved the RMS at all.

    """

    held_out: HeldOutGap = inline()
    stated: StatedGap = inline()
    share_of_excess_explained: float
    held_out_on: str
    rms_moved: bool


def position_rotation_rows(data) -> tuple[list, Optional[list]]:
    """Return the rows of the output error that are positions (m), and rotation (None if none)."""
    k = data.spec.n_markers
    if data.spec.has_q1:
        return [0, 1, 2], [3, 4, 5]
    return list(range(3 * k)), None


def stated_measures(data, quad_stated: np.ndarray, e: np.ndarray, sd: np.ndarray,
                    counted: np.ndarray) -> StatedGap:
    """
    Held-out gap at the stated noise.

    Parameters
    ----------
    data : DiagData
        The pairs.
    quad_stated : ndarray, shape (N,)
        Held-out squared normalised error per pair at the stated noise.
    e : ndarray, shape (N, m)
        Held-out raw output errors (m; half-angle for rotation rows).
    sd : ndarray, shape (N, m)
        Standard deviation of each raw error under the stated noise.
    counted : ndarray of bool, shape (N,)
        Pairs counted (False: set aside by an outlier model).

    Returns
    -------
    StatedGap

    """
    m = data.m
    pos, rot = position_rotation_rows(data)
    if not counted.any():
        counted = np.ones_like(counted)

    def block(sel):
        rotation = {}
        if rot is not None:
            # rows 3:6 are half-angle errors: the angle is twice their size
            rotation = {'rms_rotation_deg': float(np.degrees(
                            2.0 * np.sqrt(np.mean(e[sel][:, rot] ** 2)))),
                        'stated_floor_rotation_deg': float(np.degrees(
                            2.0 * np.sqrt(np.mean(sd[sel][:, rot] ** 2))))}
        return StatedBlock(
            chi2_per_dof_at_stated_noise=float(np.mean(quad_stated[sel]) / m),
            rms_position_mm=float(np.sqrt(np.mean(e[sel][:, pos] ** 2)) * 1e3),
            stated_floor_position_mm=float(np.sqrt(np.mean(sd[sel][:, pos] ** 2)) * 1e3),
            **rotation)

    excluded = np.flatnonzero(~counted)
    return StatedGap(counted=block(counted), all_pairs=block(np.ones_like(counted)),
                     excluded_pairs=ExcludedPairs(
                         count=int(excluded.size),
                         share=float(excluded.size / max(len(counted), 1)),
                         counted_as='unexplained',
                         stamps_ns=[int(s) for s in data.stamps[excluded[:200]]]))


def share_explained(before: StatedBlock, after: StatedBlock, excluded_share: float) -> float:
    """
    Share of the excess explained, at the stated noise, excluded pairs unexplained.

    ``(1 - excluded share) · (1 - excess after / excess before)``, the excess being χ²/dof at
    the stated noise minus one (before over all pairs, after over the counted ones), clipped
    to [0, 1]; zero when both RMS (position and rotation) moved by less than ``RMS_MOVED``.

    Parameters
    ----------
    before, after : StatedBlock
        The gap at the stated noise before (all pairs) and after (the counted pairs).
    excluded_share : float
        Share of the pairs set aside after.

    """
    ex_b = before.chi2_per_dof_at_stated_noise - 1.0
    ex_a = after.chi2_per_dof_at_stated_noise - 1.0
    if ex_b <= 1e-9:
        return 0.0
    if not rms_moved(before, after):
        return 0.0
    share = float(np.clip(1.0 - max(ex_a, 0.0) / ex_b, 0.0, 1.0))
    return share * (1.0 - excluded_share)


def rms_moved(before: StatedBlock, after: StatedBlock) -> bool:
    """Tell whether the position or the rotation RMS fell by at least ``RMS_MOVED``."""
    for b, a in ((before.rms_position_mm, after.rms_position_mm),
                 (before.rms_rotation_deg, after.rms_rotation_deg)):
        if b is not None and a is not None and a < (1.0 - RMS_MOVED) * b:
            return True
    return False
