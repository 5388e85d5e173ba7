"""The watchdog status in /diagnostics: levels, change kinds and keys (no numpy)."""

from __future__ import annotations

OK, WARN, ERROR = 0, 1, 2
LEVEL_NAMES = ('OK', 'WARN', 'ERROR')
#: The alternatives of the attribution.
KINDS = ('none', 't0', 't1', 't0_or_t1', 'clock', 'noise')
KIND_TEXT = {'none': 'no change', 't0': 'T0 moved (base bumped)',
             't1': 'T1 moved (marker slipped on the tool)',
             't0_or_t1': 'T0 or T1 moved (this motion cannot tell which: it never turns the '
                         'tool in a way that separates them)',
             'clock': 'clock offset changed', 'noise': 'noise or field changed'}

#: Name of the watchdog status in /diagnostics (``<node>: watchdog``).
STATUS_NAME = 'watchdog'
#: /diagnostics keys of the watchdog status (the node publishes exactly
#: ``WatchState.diagnostic_values()``; ``coreg watch`` reads these).
KEY_STATE = 'state'
KEY_MESSAGE = 'message'
KEY_STALE = 'calibration stale'
KEY_CHECKED = 'pairs checked'
KEY_STATISTIC = 'cusum'
KEY_THRESHOLD = 'cusum threshold'
KEY_MEAN_D2 = 'mean normalised residual'
KEY_CHANGE = 'change'
KEY_CHANGE_STAMP = 'change stamp ns'
KEY_ALARM_STAMP = 'alarm stamp ns'
KEY_TRANSLATION = 'translation mm'
KEY_ROTATION = 'rotation deg'
KEY_CLOCK = 'clock step ms'
KEY_NOISE = 'noise factor'
