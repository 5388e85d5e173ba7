"""
ROS_DOMAIN_ID reservation, so that concurrent tests and demos never hear each other.

A domain id is reserved by holding an exclusive ``flock`` on a file per id in a shared
directory; the lock dies with the process, so a crashed holder never leaks its id.
"""

from __future__ import annotations

import fcntl
import itertools
import os
from pathlib import Path
import tempfile

#: Ids handed out (inclusive); Fast DDS allows up to 232, the tests stay well inside.
DOMAIN_RANGE = (1, 100)
_LOCK_DIR = Path(tempfile.gettempdir()) / 'coreg_ros_domains'
_counter = itertools.count()


class DomainReservation:
    """
    A reserved ROS domain id; release it with ``release()`` or a ``with`` block.

    Attributes
    ----------
    domain_id : int

    """

    def __init__(self, domain_id: int, handle):
        self.domain_id = domain_id
        self._handle = handle

    def env(self, base: dict | None = None) -> dict:
        """Return an environment for a child process on this domain, discovery on localhost."""
        env = dict(os.environ if base is None else base)
        env['ROS_DOMAIN_ID'] = str(self.domain_id)
        env['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'LOCALHOST'
        env.pop('ROS_LOCALHOST_ONLY', None)  # deprecated in Jazzy; would warn
        return env

    def release(self) -> None:
        """Give the id back."""
        if self._handle is not None:
            self._handle.close()  # closing drops the flock
            self._handle = None

    def __enter__(self) -> DomainReservation:
        return self

    def __exit__(self, *exc) -> None:
        self.release()


def reserve_domain_id() -> DomainReservation:
    """
    Reserve a ROS domain id no other process of this machine holds through this function.

    The search starts at a point derived from the process id and a per-process counter, so
    concurrent processes rarely even try the same id.

    Raises
    ------
    RuntimeError
        If every id in ``DOMAIN_RANGE`` is held.

    """
    lo, hi = DOMAIN_RANGE
    span = hi - lo + 1
    _LOCK_DIR.mkdir(parents=True, exist_ok=True)
    start = (os.getpid() * 7 + next(_counter)) % span
    for k in range(span):
        domain = lo + (start + k) % span
        handle = open(_LOCK_DIR / f'{domain}.lock', 'a')  # noqa: SIM115 - held while reserved
        try:
            fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            handle.close()
            continue
        return DomainReservation(domain, handle)
    raise RuntimeError(f'all ROS domain ids {lo}..{hi} are reserved; wait for other runs to end')
