"""
The effects the diagnosis can name, one class each (``CANDIDATES``, name -> class).

Modules by kind: ``clock`` (offset, drift), ``noise`` (noise level, distance noise, stamp
jitter, outliers), ``spatial`` (scale, field distortion), ``link`` (link flex, backlash),
``local`` (non-stationary errors); ``base`` holds what they share, ``registry`` names them.
"""

from coreg_ros.core.diagnosis.effects.base import CandidateEffect, FitReading
from coreg_ros.core.diagnosis.effects.registry import CANDIDATES, EFFECT_NAMES

__all__ = ['CANDIDATES', 'CandidateEffect', 'EFFECT_NAMES', 'FitReading']
