"""
Sim-to-real gap diagnosis (docs/design.md §5): detect, locate, explain with ten effects, quantify.

Pure: numpy and scipy only. ``diagnose(pairs, settings)`` returns a ``Diagnosis`` whose
``report`` is a ``DiagnosisReport``; ``report.as_dict()`` is the JSON document of
``coreg diagnose``. The effects it can name are one class each (``effects.CANDIDATES``).
"""

from coreg_ros.core.diagnosis.effects.registry import EFFECT_NAMES
from coreg_ros.core.diagnosis.engine import diagnose, Diagnosis
from coreg_ros.core.diagnosis.options import Options
from coreg_ros.core.diagnosis.report import DiagnosisReport
from coreg_ros.core.diagnosis.streams import diagnose_streams

__all__ = ['EFFECT_NAMES', 'Diagnosis', 'DiagnosisReport', 'Options', 'diagnose',
           'diagnose_streams']
