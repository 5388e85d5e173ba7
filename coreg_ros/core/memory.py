"""
One guard for every size a user types: refuse a job whose memory would not fit, before it starts.

A duration, a rate or a number of cases is a small number on the command line and can be an
allocation of terabytes (``coreg plan --duration 1e7``), which the kernel answers by killing
the process after minutes of swapping. Every command that allocates in proportion to such a
number estimates its peak from a measured cost per item and calls ``check_memory`` first: the
simulator (``sim.devices.BYTES_PER_SAMPLE``), the planner (``planning.plan.BYTES_PER_PAIR``)
and the blind validation (``sim.validation.BYTES_PER_CASE``).
"""

from __future__ import annotations

import os
from typing import Optional

from coreg_ros.core.errors import InputError

#: Largest allocation a job may plan, bytes: 4 GiB, or half the machine's memory if that is
#: less (``memory_limit``).
MAX_BYTES = 4 * 2**30


def memory_limit() -> int:
    """Return the largest allocation a job may plan: ``MAX_BYTES`` or half the RAM, bytes."""
    try:
        ram = os.sysconf('SC_PHYS_PAGES') * os.sysconf('SC_PAGE_SIZE')
    except (AttributeError, ValueError, OSError):  # not a POSIX system
        return MAX_BYTES
    return int(min(MAX_BYTES, ram // 2)) if ram > 0 else MAX_BYTES


def _gb(n_bytes: float) -> str:
    return f'{n_bytes / 1e9:.3g} GB'


def check_memory(n_items: float, bytes_per_item: float, what: str, fix: str,
                 max_bytes: Optional[int] = None, unit: str = 'samples') -> None:
    """
    Refuse a job that would allocate more than ``max_bytes``, before it allocates.

    Parameters
    ----------
    n_items : float
        Items the job holds at its peak (a float: the estimate may be astronomically large).
    bytes_per_item : float
        Measured peak bytes per item.
    what : str
        What is asked, for the message (e.g. ``'a recording of 1 s at 1e+09 Hz'``).
    fix : str
        The options to lower, for the message.
    max_bytes : int, optional
        The limit; default ``memory_limit()``.
    unit : str
        What an item is, for the message.

    Raises
    ------
    InputError
        One line with the estimate, the limit and the options to lower.

    """
    limit = memory_limit() if max_bytes is None else max_bytes
    need = float(n_items) * float(bytes_per_item)
    if not need <= limit:  # NaN too
        raise InputError(f'{what} has ~{float(n_items):.3g} {unit} and would need '
                         f'~{_gb(need)} of memory (limit {_gb(limit)}); lower {fix}')
