"""The guidance status in /diagnostics: its name, keys and parameter groups (no numpy)."""

from __future__ import annotations

#: Name of the guidance status in /diagnostics (``<node>: guidance``).
STATUS_NAME = 'guidance'
#: /diagnostics keys of the guidance status (the node publishes exactly
#: ``Guidance.diagnostic_values()``; ``coreg watch`` reads these).
KEY_PAIRS = 'pairs'
KEY_DURATION = 'duration s'
KEY_READY = 'ready'
KEY_TARGET_POSITION = 'target sigma position m'
KEY_TARGET_ROTATION = 'target sigma rotation rad'
KEY_TARGET_TIME = 'target sigma time s'
KEY_SIGMA_PREFIX = 'sigma '  # + group name (p0, theta0, p1, theta1, p2, p3, time_offset)
KEY_WORST = 'worst'
KEY_WORST_RATIO = 'worst ratio'
KEY_NEXT = 'next motion'
KEY_NEXT_TEXT = 'next motion text'
KEY_NEXT_RATIO = 'next motion worst ratio'
KEY_SUMMARY = 'summary'

#: Parameter groups of ψ per model (3 axes each), in the order of ``crlb``.
GROUPS = {'full_pose': ('p0', 'theta0', 'p1', 'theta1'),
          'position_only': ('p0', 'theta0', 'p1'),
          'three_marker': ('p0', 'theta0', 'p1', 'p2', 'p3')}
#: Group names for people.
GROUP_TITLES = {'p0': 'T0 position', 'theta0': 'T0 rotation', 'p1': 'T1 position',
                'theta1': 'T1 rotation', 'p2': 'marker 2', 'p3': 'marker 3',
                'time_offset': 'clock offset'}
AXES = 'xyz'


def is_rotation_group(name: str) -> bool:
    """Whether a group of ψ is a rotation (rad) rather than a position (m)."""
    return name.startswith('theta')
