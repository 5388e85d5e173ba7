"""
Sim-to-real gap diagnosis (docs/design.md §5): detect, locate, explain with ten effects, quantify.

Pure: numpy and scipy only. ``diagnose(pairs, settings)`` returns a ``Diagnosis`` whose
``report`` is the JSON document of ``coreg diagnose``.
"""

from coreg_ros.core.diagnosis.effects.registry import EFFECT_NAMES
from coreg_ros.core.diagnosis.engine import diagnose, Diagnosis
from coreg_ros.core.diagnosis.options import Options
from coreg_ros.core.diagnosis.streams import diagnose_streams

__all__ = ['EFFECT_NAMES', 'Diagnosis', 'Options', 'diagnose', 'diagnose_streams']
