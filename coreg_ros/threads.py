"""
BLAS threads, set at the edge (threadpoolctl), never by the numerical core.

The gap diagnosis multiplies many small matrices (a few thousand rows by tens of columns), and
the calibration sums products of a chunk of pairs by a dozen columns. On a machine whose cores
are busy, OpenBLAS's threads then spin against each other and the same products take 20-70
times longer than on one thread (``coreg calibrate`` of 2M pairs: 2.5 times the CPU time). The
front ends that run them (``coreg calibrate``, ``coreg diagnose``, ``coreg batch``, the
validation harness) therefore hold BLAS at one thread for the call; a Python user decides for
their own process (``threadpoolctl.threadpool_limits``).
"""

from __future__ import annotations


def one_blas_thread():
    """
    Return a context manager that holds every loaded BLAS at one thread, then restores it.

    Returns
    -------
    threadpoolctl.threadpool_limits
        Use as ``with one_blas_thread(): ...``.

    """
    from threadpoolctl import threadpool_limits

    return threadpool_limits(limits=1, user_api='blas')
