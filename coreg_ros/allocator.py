"""
How a command that holds a long recording gets its memory, set at the edge, never by the core.

A 4M-message ``coreg calibrate`` makes and frees arrays of tens to hundreds of MB again and
again (pairs, input states, velocities). With the C library's defaults each is a fresh
``mmap`` that the kernel zeroes page by page when first touched and takes back at ``free``,
and NumPy asks for transparent huge pages on each (``madvise``), which under the common
``defrag=madvise`` setting has the kernel compact memory inside the page fault. That was
1.4-1.9 s of system time in a 7.6-8.2 s run. Served from the heap and kept there for the
next array instead, the same run spends 0.7-0.9 s in the kernel, and its peak stays where it
was (the memory is reused, not added; ``bench/bag_bench.py``).

One heap (arena) for all threads: the bag reader fetches pages in a second thread
(``files.bag.bulk_read``), and the blobs it allocates would otherwise stay in that thread's
own arena, where the main thread cannot reuse them once freed.

This suits a process that runs one command and exits (``coreg calibrate``, ``diagnose``,
``batch``); a long-lived process (the node) keeps the defaults, which give memory back.
Elsewhere than glibc on Linux only NumPy's setting applies.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import sys

#: glibc's ``mallopt`` parameters (malloc.h).
_M_TRIM_THRESHOLD, _M_TOP_PAD, _M_MMAP_THRESHOLD, _M_ARENA_MAX = -1, -2, -3, -8
#: Allocations below this come from the heap (above it, a fresh mmap each time): above any
#: array of a 4M-message recording.
MMAP_THRESHOLD_BYTES = 1 << 30
#: Free memory at the top of the heap is given back to the system only above this.
TRIM_THRESHOLD_BYTES = (1 << 31) - 1
#: Extra heap asked for at each growth, so that a growing run of arrays is not a system call
#: each.
TOP_PAD_BYTES = 64 << 20

_done = False


def keep_memory_for_reuse() -> bool:
    """
    Have this process reuse the memory of freed arrays instead of asking the system again.

    NumPy's huge page advice is turned off; with glibc, large blocks come from one heap
    shared by all threads and freed memory stays there (the module docstring says why).
    Idempotent; call it once at a command's start, before any thread is started (a thread
    started before keeps an arena of its own, which later threads may be given: memory
    that the main thread cannot reuse, 1.3 instead of 1.05 GiB at the 4M-message peak).

    Returns
    -------
    bool
        Whether glibc's allocator was set (False elsewhere: only NumPy's advice then).

    """
    global _done
    if _done:
        return True
    try:
        from numpy._core import multiarray  # noqa: PLC0415 - NumPy >= 2
    except ImportError:  # pragma: no cover - NumPy 1.x
        from numpy.core import multiarray  # noqa: PLC0415
    setter = getattr(multiarray, '_set_madvise_hugepage', None)
    if setter is not None:
        setter(False)
    if not sys.platform.startswith('linux'):
        return False
    try:
        libc = ctypes.CDLL(ctypes.util.find_library('c') or 'libc.so.6')
        mallopt = libc.mallopt
    except (OSError, AttributeError):
        return False
    mallopt.argtypes = (ctypes.c_int, ctypes.c_int)
    mallopt.restype = ctypes.c_int
    ok = all(mallopt(param, value) == 1 for param, value in (
        (_M_MMAP_THRESHOLD, MMAP_THRESHOLD_BYTES), (_M_TRIM_THRESHOLD, TRIM_THRESHOLD_BYTES),
        (_M_TOP_PAD, TOP_PAD_BYTES), (_M_ARENA_MAX, 1)))
    _done = ok
    return ok
