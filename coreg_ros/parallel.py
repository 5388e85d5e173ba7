"""
Run many independent cases (validation cases, Monte Carlo trials, recordings) in parallel.

The one engine behind every ``--workers`` / ``--scheduler`` option: local processes by default,
or an existing Dask distributed cluster when a scheduler address is given (dask is an optional
extra, imported only then). Results come back in the order of the cases, so they are the same
whatever the number of workers, as long as every case carries its own seed.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any, Optional


def run_cases(fn: Callable, cases: Sequence, args: tuple = (), workers: int = 1,
              scheduler: Optional[str] = None, progress: Optional[Callable] = None) -> list:
    """
    ``[fn(case, *args) for case in cases]``, in ``workers`` processes.

    Parameters
    ----------
    fn : callable
        A module-level function (picklable).
    cases : sequence
        One item per case.
    args : tuple
        Further arguments, the same for every case.
    workers : int
        Local processes (1: in this process).
    scheduler : str, optional
        Address of a Dask distributed scheduler (not implemented yet).
    progress : callable, optional
        ``progress(fraction, text)`` after each case.

    Returns
    -------
    list
        The results in the order of ``cases``.

    """
    if scheduler is not None:
        raise NotImplementedError('--scheduler is not available yet')
    n = len(cases)
    results: list[Any] = []
    if workers > 1:
        from concurrent.futures import ProcessPoolExecutor
        with ProcessPoolExecutor(max_workers=workers) as ex:
            for i, res in enumerate(ex.map(fn, cases, *[[a] * n for a in args])):
                results.append(res)
                if progress:
                    progress((i + 1) / n, f'case {i + 1}/{n}')
        return results
    for i, case in enumerate(cases):
        if progress:
            progress(i / n, f'case {i + 1}/{n}')
        results.append(fn(case, *args))
    if progress:
        progress(1.0, 'done')
    return results
