"""
``Throttle``: at most one log line per key and period, so a failing timer cannot flood the log.

The node, its uncertainty outputs and its live checks log a repeated problem (a rejected
message, a failing tick, a storage error) once, then again only after ``WARN_PERIOD`` s; the
counts in /diagnostics say how often it happened meanwhile.
"""

from __future__ import annotations

from collections.abc import Hashable
import math
import time
from typing import Optional

#: Seconds between two log lines about the same problem.
WARN_PERIOD = 5.0


class Throttle:
    """
    Allow an action (a log line) at most once every ``period`` seconds per key.

    Parameters
    ----------
    period : float
        Seconds between two allowed actions of one key (monotonic clock).

    """

    def __init__(self, period: float = WARN_PERIOD):
        self.period = period
        self._last: dict = {}

    def ready(self, key: Hashable = None, period: Optional[float] = None) -> bool:
        """
        Return True (and start a new period) if ``key`` may act now.

        Parameters
        ----------
        key : hashable
            What the line is about (e.g. ``(topic, reason)``); None for a single concern.
        period : float, optional
            This key's period instead of the default (s).

        """
        now = time.monotonic()
        if now - self._last.get(key, -math.inf) < (self.period if period is None else period):
            return False
        self._last[key] = now
        return True
