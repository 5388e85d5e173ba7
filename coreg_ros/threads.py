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


def blas_threads_for(settings):
    """
    Return ``one_blas_thread()`` when ``settings`` estimate the noise, else a no-op context.

    The noise estimation (``noise: auto``) sums products of small per-pair matrices, which
    suffer as the diagnosis' do; for a caller whose plain calibration keeps BLAS as it is
    (``coreg calibrate`` holds one thread for every fit, ``one_blas_thread``).
    """
    import contextlib

    return one_blas_thread() if getattr(settings, 'noise', 'stated') == 'auto' else \
        contextlib.nullcontext()
