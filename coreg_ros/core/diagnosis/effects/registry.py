"""
The effects the diagnosis can name, by name: one class each (``CANDIDATES``).

Adding an effect is adding its class (``effects.base.CandidateEffect``: what it is, its model
term or noise parameters, its size) to ``CANDIDATES``; the selection, the fit and the report
read everything else from the class.
"""

from __future__ import annotations

from coreg_ros.core.diagnosis.effects.change import NoiseStepCandidate, PoseStepCandidate
from coreg_ros.core.diagnosis.effects.clock import (
    ClockDriftCandidate,
    ClockStepCandidate,
    TimeOffsetCandidate,
)
from coreg_ros.core.diagnosis.effects.link import BacklashCandidate, LinkFlexCandidate
from coreg_ros.core.diagnosis.effects.local import NonStationaryCandidate
from coreg_ros.core.diagnosis.effects.noise import (
    AnisotropicNoiseCandidate,
    DistanceNoiseCandidate,
    NoiseScaleCandidate,
    OutliersCandidate,
    TimestampJitterCandidate,
)
from coreg_ros.core.diagnosis.effects.spatial import FieldDistortionCandidate, ScaleCandidate

#: Every effect the report can name, in the order of docs/design.md §5 (the candidates of the
#: selection first, in the order they are tried).
CANDIDATES = {c.name: c for c in (
    TimeOffsetCandidate, ClockDriftCandidate, ClockStepCandidate, TimestampJitterCandidate,
    FieldDistortionCandidate, DistanceNoiseCandidate, ScaleCandidate, LinkFlexCandidate,
    OutliersCandidate, BacklashCandidate, NoiseScaleCandidate, AnisotropicNoiseCandidate,
    PoseStepCandidate, NoiseStepCandidate, NonStationaryCandidate)}

#: The candidates of the selection: effects fitted as extensions of the model (the names of
#: ``coreg_ros.sim.injected.EFFECT_NAMES``).
EFFECT_NAMES = tuple(name for name, c in CANDIDATES.items() if c.acts_on is not None)
