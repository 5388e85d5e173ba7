"""
Errors no stationary candidate explains: structure or non-stationarity found where it acts.

``non_stationary`` is not fitted as an extension of the model: it is named from what the
fitted effects leave (``findings.structure_checks``): pairs an outlier model sets aside that
cluster in time or in the workspace, or an excess left in some time blocks only.
"""

from __future__ import annotations

from coreg_ros.core.diagnosis.effects.base import CandidateEffect


class NonStationaryCandidate(CandidateEffect):
    """A structured error that acts at some times or places only (a disturbance brought near)."""

    name = 'non_stationary'
