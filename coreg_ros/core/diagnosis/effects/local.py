"""
Errors no stationary candidate explains: structure or non-stationarity found where it acts.

``non_stationary`` is not fitted as an extension of the model: it is named from what the
fitted effects leave (``findings.structure_checks``), in one of two forms: pairs an outlier
model set aside that cluster in time or in the workspace (``ClusteredOutliers``), or an excess
left in some time blocks only (``LocalExcess``). Either is sized where it acts (``sized``).
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Optional

from coreg_ros.core.diagnosis.effects.base import CandidateEffect
from coreg_ros.core.diagnosis.excess import LocalSize
from coreg_ros.core.diagnosis.record import optional


class NonStationaryCandidate(CandidateEffect):
    """A structured error that acts at some times or places only (a disturbance brought near)."""

    name = 'non_stationary'

    def sized(self, size: LocalSize):
        """Return the estimate with the error's size where it acts (``excess.LocalSize``)."""
        return replace(self, max_mm=size.max_mm, rms_mm=size.rms_mm,
                       window_s=[size.from_s, size.to_s],
                       text=f'{self.text}; up to {size.max_mm:.2f} mm (RMS {size.rms_mm:.2f} '
                            f'mm) in {size.from_s:.0f}-{size.to_s:.0f} s')


@dataclass(frozen=True, kw_only=True)
class ClusteredOutliers(NonStationaryCandidate):
    """
    Pairs an outlier model set aside that cluster: a structured error there, not glitches.

    Attributes
    ----------
    flagged_pairs : int
        Pairs set aside.
    flagged_share : float
        Their share of all pairs.
    where : str
        Where they cluster (time blocks, workspace cells); empty if only ``at_cap``.
    at_cap : bool
        The outlier share is at the model's cap.
    text : str
    max_mm, rms_mm : float, optional
        The largest and the RMS held-out position error where it acts, noise taken off, mm.
    window_s : list of float, optional
        When it acts: from, to, s.

    """

    flagged_pairs: int
    flagged_share: float
    where: str
    at_cap: bool
    text: str
    max_mm: Optional[float] = optional()
    rms_mm: Optional[float] = optional()
    window_s: Optional[list] = optional()

    @classmethod
    def of(cls, count: int, share: float, where: str, at_cap: bool) -> ClusteredOutliers:
        """Name the clustered pairs (``count``, ``share`` of all) and where they cluster."""
        return cls(flagged_pairs=count, flagged_share=share, where=where, at_cap=bool(at_cap),
                   text=(f'structured/non-stationary error here: {where or "throughout"} '
                         f'({count} pairs, {share * 100:.1f} %, flagged in clusters, not at '
                         'random)'))


@dataclass(frozen=True, kw_only=True)
class LocalExcess(NonStationaryCandidate):
    """
    An excess left after the accepted effects in some time blocks or cells only.

    Attributes
    ----------
    where : str
        The blocks and cells (``excess.ExcessMap.text``).
    share_in_time_blocks, share_in_cells : float
        The share of the excess they hold.
    excess_after : float
        χ²/dof left under the fitted noise model, minus one.
    text : str
    max_mm, rms_mm : float, optional
        The largest and the RMS held-out position error where it acts, noise taken off, mm.
    window_s : list of float, optional
        When it acts: from, to, s.

    """

    where: str
    share_in_time_blocks: float
    share_in_cells: float
    excess_after: float
    text: str
    max_mm: Optional[float] = optional()
    rms_mm: Optional[float] = optional()
    window_s: Optional[list] = optional()

    @classmethod
    def of(cls, where: str, share_in_time_blocks: float, share_in_cells: float,
           excess_after: float) -> LocalExcess:
        """Name the excess left in ``where``."""
        return cls(where=where, share_in_time_blocks=share_in_time_blocks,
                   share_in_cells=share_in_cells, excess_after=excess_after,
                   text=f'excess left in {where} only: no stationary effect explains it')
