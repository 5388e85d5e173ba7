"""
Run BLAS single-threaded while diagnosing.

The diagnosis multiplies many small matrices (a few thousand rows by tens of columns). On a
machine whose cores are busy, OpenBLAS's threads then spin against each other and the same
products take 20-70 times longer than on one thread. ``single_blas_thread()`` sets the thread
count of every OpenBLAS loaded in the process to one for the duration of a ``with`` block (and
restores it), through the library's own ``*openblas_set_num_threads*`` entry point; where that
is not available it does nothing.
"""

from __future__ import annotations

from contextlib import contextmanager
import ctypes
import os


def _openblas_libraries() -> list:
    """(get, set) function pairs of the OpenBLAS libraries mapped into this process."""
    paths = set()
    try:
        with open('/proc/self/maps', encoding='utf-8', errors='replace') as f:
            for line in f:
                path = line.rsplit(' ', 1)[-1].strip()
                if 'openblas' in os.path.basename(path).lower() and path.startswith('/'):
                    paths.add(path)
    except OSError:
        return []
    pairs = []
    for path in sorted(paths):
        try:
            lib = ctypes.CDLL(path)
        except OSError:
            continue
        for get_name, set_name in (
                ('scipy_openblas_get_num_threads64_', 'scipy_openblas_set_num_threads64_'),
                ('scipy_openblas_get_num_threads', 'scipy_openblas_set_num_threads'),
                ('openblas_get_num_threads64_', 'openblas_set_num_threads64_'),
                ('openblas_get_num_threads', 'openblas_set_num_threads')):
            get = getattr(lib, get_name, None)
            put = getattr(lib, set_name, None)
            if get is not None and put is not None:
                get.restype = ctypes.c_int
                put.argtypes = [ctypes.c_int]
                pairs.append((get, put))
                break
    return pairs


@contextmanager
def single_blas_thread():
    """Limit OpenBLAS to one thread inside the block."""
    libs = _openblas_libraries()
    saved = []
    for get, put in libs:
        try:
            saved.append((put, int(get())))
            put(1)
        except Exception:  # pragma: no cover - a foreign build without the entry point
            continue
    try:
        yield
    finally:
        for put, n in saved:
            try:
                put(n)
            except Exception:  # pragma: no cover
                pass
