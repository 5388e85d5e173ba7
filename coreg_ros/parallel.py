"""
Run many independent cases (validation cases, Monte Carlo trials, recordings) in parallel.

The one engine behind every ``--workers`` / ``--scheduler`` option: local processes by default,
or an existing Dask distributed cluster when a scheduler address is given (dask is an optional
extra, ``pip install coreg_ros[dask]``, imported only then). Results come back in the order of
the cases, so they are the same whatever the number of workers, as long as every case carries
its own seed. A case that raises becomes a :class:`CaseFailure` record in its place (seed and
one-line error) and the others go on; the caller reports the failures.

Local workers are *spawned* (fresh interpreters): forking a process that already runs threads
(rich's refresh thread, a ROS executor, BLAS pools) can deadlock the child. BLAS / OpenMP pools
are pinned to one thread in the workers, so N workers use N cores and do not oversubscribe.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator, Sequence
import contextlib
from dataclasses import asdict, dataclass
import os
import signal
import sys
from typing import Any, Optional

from coreg_ros.core.errors import ConfigError

#: Thread-pool variables of the numerical libraries, set to 1 in the workers.
BLAS_THREAD_VARS = ('OMP_NUM_THREADS', 'OPENBLAS_NUM_THREADS', 'MKL_NUM_THREADS',
                    'VECLIB_MAXIMUM_THREADS', 'NUMEXPR_NUM_THREADS')
#: How long to wait for a Dask scheduler to answer, s.
CONNECT_TIMEOUT_S = 10.0
#: The longest error text kept per failed case (one line).
MAX_ERROR_CHARS = 600

Progress = Callable[[float, str], None]


class SchedulerError(ConfigError):
    """The Dask scheduler cannot be used (dask missing, address unreachable)."""


class Terminated(KeyboardInterrupt):
    """
    SIGTERM while cases run: stops them as a Ctrl-C does (the workers ended, the tasks cancelled).

    A ``KeyboardInterrupt`` so that every handler of Ctrl-C cleans up alike; ``signum`` tells
    the front end which signal came (exit code 128 + ``signum``).
    """

    signum = int(signal.SIGTERM)


@contextlib.contextmanager
def _terminate_as_interrupt() -> Iterator[None]:
    """
    Turn SIGTERM into ``Terminated`` while cases run (main thread, default handler only).

    Python's default SIGTERM ends the process at once: no ``finally`` runs, so the local
    workers and the resource tracker they share would go on, orphaned, and a cluster would
    keep computing the cancelled run. A handler someone else installed is left alone.
    """
    import threading

    if (threading.current_thread() is not threading.main_thread()
            or signal.getsignal(signal.SIGTERM) is not signal.SIG_DFL):
        yield
        return

    def stop(signum, frame):
        if _SPAWNING.depth:  # raised when the workers have started (_spawning_workers)
            _SPAWNING.pending = True
            return
        raise Terminated()

    signal.signal(signal.SIGTERM, stop)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, signal.SIG_DFL)


class _Spawning:
    """Whether workers are being spawned, and a SIGTERM held back meanwhile."""

    depth = 0
    pending = False


_SPAWNING = _Spawning()


@contextlib.contextmanager
def _spawning_workers() -> Iterator[None]:
    """
    Hold a SIGTERM back while worker processes are spawned; raise it (``Terminated``) after.

    A spawned worker reads its start-up data from a pipe the parent is still writing: a
    ``Terminated`` raised in the middle cuts it off, and the worker dies printing an EOFError
    traceback instead of being stopped cleanly with the others.
    """
    _SPAWNING.depth += 1
    try:
        yield
    finally:
        _SPAWNING.depth -= 1
    if not _SPAWNING.depth and _SPAWNING.pending:
        _SPAWNING.pending = False
        raise Terminated()


@dataclass(frozen=True)
class CaseFailure:
    """
    A case that raised: where it was, which seed, and the error in one line.

    Attributes
    ----------
    index : int
        Position of the case in the ``cases`` given to :func:`run_cases`.
    seed : int or None
        The case's seed (``case['seed']``, ``case.seed`` or the case itself when it is an int).
    label : str
        What the case is, for a person (a bag path, ``seed 123``, ``case 7``).
    error : str
        ``ExceptionType: message``, one line.

    """

    index: int
    seed: Optional[int]
    label: str
    error: str

    def as_dict(self) -> dict:
        """Return the record as a JSON-ready dict (with ``failed: True``)."""
        return {'failed': True, **asdict(self)}

    def __str__(self) -> str:
        seed = '' if self.seed is None or self.label == f'seed {self.seed}' \
            else f' (seed {self.seed})'
        return f'{self.label}{seed}: {self.error}'


def failures(results: Sequence) -> list[CaseFailure]:
    """Return the :class:`CaseFailure` records among ``results``."""
    return [r for r in results if isinstance(r, CaseFailure)]


def default_workers() -> int:
    """Local workers when none are asked for: the machine's cores."""
    return max(1, os.cpu_count() or 1)


def one_line(error: BaseException) -> str:
    """``Type: message`` on one line, cut at MAX_ERROR_CHARS."""
    text = ' '.join(f'{type(error).__name__}: {error}'.split())
    return text if len(text) <= MAX_ERROR_CHARS else text[:MAX_ERROR_CHARS - 1] + '…'


def seed_of(case: Any) -> Optional[int]:
    """Return the seed a case carries, if any (dict key, attribute, or the int itself)."""
    if isinstance(case, bool):
        return None
    if isinstance(case, int):
        return int(case)
    seed = case.get('seed') if isinstance(case, dict) else getattr(case, 'seed', None)
    return int(seed) if isinstance(seed, int) else None


@dataclass(frozen=True)
class _Failed:
    """What a worker sends back for a case that raised (the parent adds seed and label)."""

    error: str


def _run_chunk(fn: Callable, chunk: list, args: tuple) -> list:
    """Run ``fn(case, *args)`` for each case of a chunk; an exception becomes ``_Failed``."""
    out = []
    for case in chunk:
        try:
            out.append(fn(case, *args))
        except Exception as e:  # noqa: BLE001 - one case's failure must not stop the others
            out.append(_Failed(one_line(e)))
    return out


def _init_worker() -> None:
    # Ctrl-C at a terminal reaches the whole process group: the parent alone handles it and
    # stops the workers, so no worker prints a traceback of its own.
    signal.signal(signal.SIGINT, signal.SIG_IGN)


@contextlib.contextmanager
def _single_threaded_blas() -> Iterator[None]:
    """Set the BLAS thread variables to 1 while workers are spawned (they inherit them)."""
    saved = {k: os.environ.get(k) for k in BLAS_THREAD_VARS}
    os.environ.update(dict.fromkeys(BLAS_THREAD_VARS, '1'))
    try:
        yield
    finally:
        for k, v in saved.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v


class _Tally:
    """Counts finished cases; drives the rich bar and/or the plain callback."""

    def __init__(self, total: int, progress: Optional[Progress], bar: bool, title: str):
        self.total, self.done, self.failed = total, 0, 0
        self.progress = progress
        self._bar = None
        if bar:
            from rich import progress as rp
            from rich.console import Console

            self._bar = rp.Progress(
                rp.TextColumn('{task.description}'), rp.BarColumn(), rp.MofNCompleteColumn(),
                rp.TextColumn('cases, {task.fields[failed]} failed'), rp.TimeElapsedColumn(),
                rp.TextColumn('left'), rp.TimeRemainingColumn(),
                console=Console(stderr=True), transient=False)
            self._task = self._bar.add_task(title, total=total, failed=0)
            self._bar.start()
        if progress is not None:
            progress(0.0, f'0/{total} cases')

    def add(self, results: list) -> None:
        self.done += len(results)
        self.failed += sum(isinstance(r, _Failed) for r in results)
        if self._bar is not None:
            self._bar.update(self._task, completed=self.done, failed=self.failed)
        if self.progress is not None:
            self.progress(self.done / max(self.total, 1),
                          f'{self.done}/{self.total} cases, {self.failed} failed')

    def close(self) -> None:
        if self._bar is not None:
            self._bar.stop()
            self._bar = None


def run_cases(fn: Callable, cases: Sequence, args: tuple = (), workers: Optional[int] = 1,
              scheduler: Optional[str] = None, progress: Optional[Progress] = None,
              bar: Optional[bool] = None, chunksize: int = 1,
              label: Optional[Callable[[Any], str]] = None, title: str = 'cases') -> list:
    """
    ``[fn(case, *args) for case in cases]`` in local processes or on a Dask cluster.

    Parameters
    ----------
    fn : callable
        A module-level function (pickled by reference to the workers).
    cases : sequence
        One item per case, each carrying its own seed, so the results do not depend on which
        worker runs it or when.
    args : tuple
        Further arguments, the same for every case (sent once per chunk).
    workers : int, optional
        Local processes; 1 runs in this process, None uses every core (:func:`default_workers`).
        Ignored when ``scheduler`` is given (the cluster has its own workers).
    scheduler : str, optional
        Address of a running Dask distributed scheduler, e.g. ``tcp://10.0.0.5:8786``.
    progress : callable, optional
        ``progress(fraction, text)`` after each finished chunk (0..1, e.g. ``'12/40 cases, 1
        failed'``).
    bar : bool, optional
        Draw a rich progress bar on stderr (cases done / total, failures, time left). Default:
        when no ``progress`` callback is given and stderr is a terminal.
    chunksize : int
        Cases per task: raise it for many short cases (ms each) so the per-task overhead
        (pickling, ~1 ms locally, more on a cluster) stays small.
    label : callable, optional
        ``label(case) -> str`` naming a case in its failure record (default ``seed N`` or
        ``case I``).
    title : str
        The progress bar's caption.

    Returns
    -------
    list
        One entry per case, in the order of ``cases``: ``fn``'s result, or a
        :class:`CaseFailure` where the case raised.

    Raises
    ------
    SchedulerError
        ``scheduler`` given but dask is not installed or the scheduler cannot be reached.
    KeyboardInterrupt
        After stopping the workers (local) or cancelling the tasks (Dask); ``Terminated`` (a
        KeyboardInterrupt) on SIGTERM, where the process had Python's default handler.

    """
    cases = list(cases)
    n = len(cases)
    size = max(1, int(chunksize))
    chunks = [cases[i:i + size] for i in range(0, n, size)]
    if bar is None:
        bar = progress is None and sys.stderr.isatty()
    nworkers = default_workers() if workers is None else max(1, int(workers))
    client = _connect(scheduler) if scheduler is not None else None
    tally = _Tally(n, progress, bool(bar) and n > 0, title)
    with _terminate_as_interrupt():
        parts = _run_all(fn, chunks, args, client, nworkers, tally)
    results = [r for part in parts for r in part]
    for i, r in enumerate(results):
        if isinstance(r, _Failed):
            results[i] = CaseFailure(i, seed_of(cases[i]), _label(cases[i], i, label), r.error)
    return results


def _run_all(fn: Callable, chunks: list, args: tuple, client, nworkers: int,
             tally: _Tally) -> list:
    """Run the chunks on the cluster, on local processes or here; return parts in order."""
    try:
        if client is not None:
            parts = _run_dask(client, fn, chunks, args, tally)
        elif nworkers > 1 and len(chunks) > 1:
            parts = _run_local(fn, chunks, args, min(nworkers, len(chunks)), tally)
        else:
            parts = []
            for chunk in chunks:
                parts.append(_run_chunk(fn, chunk, args))
                tally.add(parts[-1])
    finally:
        tally.close()
        if client is not None:
            client.close()
    return parts


def _label(case: Any, index: int, label: Optional[Callable]) -> str:
    if label is not None:
        return str(label(case))
    seed = seed_of(case)
    return f'case {index}' if seed is None else f'seed {seed}'


def _run_local(fn: Callable, chunks: list, args: tuple, workers: int, tally: _Tally) -> list:
    """Chunks in ``workers`` spawned processes; parts in chunk order."""
    from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait
    from concurrent.futures.process import BrokenProcessPool
    import multiprocessing

    parts: list = [None] * len(chunks)
    pool = ProcessPoolExecutor(workers, mp_context=multiprocessing.get_context('spawn'),
                               initializer=_init_worker)
    try:
        with _single_threaded_blas(), _spawning_workers():
            pending = {pool.submit(_run_chunk, fn, chunk, args): k
                       for k, chunk in enumerate(chunks)}
        while pending:
            finished, _ = wait(pending, return_when=FIRST_COMPLETED)
            for fut in finished:
                k = pending.pop(fut)
                try:
                    parts[k] = fut.result()
                except BrokenProcessPool as e:
                    # a worker died (killed, out of memory): its cases and the unstarted ones
                    parts[k] = [_Failed(f'worker process died: {one_line(e)}')] * len(chunks[k])
                except Exception as e:  # noqa: BLE001 - e.g. a result that cannot be pickled
                    parts[k] = [_Failed(one_line(e))] * len(chunks[k])
                tally.add(parts[k])
    except BaseException:
        # Ctrl-C (or any error of ours): drop the queue and stop the workers now (the pool
        # forgets its processes on shutdown, so take them first)
        procs = list((getattr(pool, '_processes', None) or {}).values())
        pool.shutdown(wait=False, cancel_futures=True)
        for proc in procs:
            proc.terminate()
        for proc in procs:
            proc.join(timeout=5.0)
        raise
    pool.shutdown(wait=True)
    return parts


def _connect(scheduler: str):
    """Connect to ``scheduler``; SchedulerError in one line if impossible."""
    try:
        from distributed import Client
    except ImportError:
        raise SchedulerError(f'--scheduler {scheduler} needs dask: pip install '
                             "'coreg_ros[dask]' (or drop --scheduler to run on local "
                             'processes)') from None
    import logging
    _probe(scheduler)
    log = logging.getLogger('distributed')
    level = log.level
    log.setLevel(logging.CRITICAL)  # the failure is said once, below, not as a log trace
    try:
        return Client(scheduler, timeout=CONNECT_TIMEOUT_S, set_as_default=False)
    except Exception as e:  # noqa: BLE001 - OSError, TimeoutError, ValueError of the address
        raise SchedulerError(f'cannot reach the Dask scheduler at {scheduler} '
                             f'({one_line(e)}); {_START_ONE}') from None
    finally:
        log.setLevel(level)


_START_ONE = 'check the address, or start one with `dask scheduler` and `dask worker ADDRESS`'


def _probe(scheduler: str) -> None:
    """
    Refuse an address Dask cannot use, or a host:port nothing listens on, in one line, now.

    Why before ``Client``: a client that fails to connect retries until its timeout, and the
    half-made client then closes itself on garbage collection, waiting twice the timeout and
    printing a traceback after our one-line error. A plain socket answers at once when the
    port is closed, and within ``CONNECT_TIMEOUT_S`` when the host does not answer.
    """
    import asyncio
    import socket

    from distributed.comm.addressing import parse_address, parse_host_port
    from distributed.comm.registry import backends

    example = 'e.g. tcp://10.0.0.5:8786, as `dask scheduler` prints it'
    try:
        scheme, location = parse_address(scheduler)
    except ValueError as e:
        raise SchedulerError(f'--scheduler {scheduler!r} is not a Dask address '
                             f'({one_line(e)}); {example}') from None
    if scheme not in backends:
        raise SchedulerError(f'--scheduler {scheduler!r}: {scheme}:// is not a Dask protocol '
                             f'(known: {", ".join(sorted(backends))}); {example}')
    if scheme not in ('tcp', 'tls', 'ws', 'wss'):
        return  # no host and port to try (inproc, ucx): the client says what goes wrong
    try:
        host, port = parse_host_port(location)
    except ValueError as e:
        raise SchedulerError(f'--scheduler {scheduler!r} is not a Dask address '
                             f'({one_line(e)}); {example}') from None
    if not 0 < port < 65536:
        raise SchedulerError(f'--scheduler {scheduler!r}: port {port} is not a port number '
                             f'(1-65535); {example}')
    try:
        with socket.create_connection((host, port), timeout=CONNECT_TIMEOUT_S):
            pass
    except OSError as e:
        reason = 'no answer' if isinstance(e, TimeoutError) else one_line(e)
        raise SchedulerError(f'cannot reach the Dask scheduler at {scheduler} ({reason} '
                             f'from {host} port {port}); {_START_ONE}') from None
    # Something listens (a firewall or proxy may accept any port): is it a Dask scheduler?
    try:
        kind = asyncio.run(asyncio.wait_for(_identity(scheduler), CONNECT_TIMEOUT_S))
    except Exception as e:  # noqa: BLE001 - OSError, TimeoutError, a comm or protocol error
        reason = (f'no Dask answer in {CONNECT_TIMEOUT_S:g} s' if isinstance(e, TimeoutError)
                  else one_line(e) if isinstance(e, OSError)
                  else "what answers there does not speak Dask's protocol")
        raise SchedulerError(f'cannot reach the Dask scheduler at {scheduler} ({reason}); '
                             f'{_START_ONE}') from None
    if kind != 'Scheduler':
        raise SchedulerError(f'{scheduler} is a Dask {kind}, not a scheduler: give the address '
                             '`dask scheduler` prints (the workers connect to it too)')


async def _identity(address: str) -> str:
    """Ask the Dask server at ``address`` what it is (``'Scheduler'``, ``'Worker'``...)."""
    from distributed.comm import connect

    comm = await connect(address, timeout=CONNECT_TIMEOUT_S)
    try:
        await comm.write({'op': 'identity', 'reply': True})
        answer = await comm.read()
    finally:
        comm.abort()
    return str(answer.get('type', 'server of another kind')) if isinstance(answer, dict) \
        else 'server of another kind'


def _run_dask(client, fn: Callable, chunks: list, args: tuple, tally: _Tally) -> list:
    """Chunks as Dask tasks; parts in chunk order."""
    from distributed import as_completed

    parts: list = [None] * len(chunks)
    [shared] = client.scatter([args], broadcast=True)  # sent once, not with every task
    futures = client.map(_run_chunk, [fn] * len(chunks), chunks, [shared] * len(chunks),
                         pure=False)
    index = {f.key: k for k, f in enumerate(futures)}
    try:
        for fut in as_completed(futures, loop=client.loop):
            k = index[fut.key]
            try:
                parts[k] = fut.result()
            except Exception as e:  # noqa: BLE001 - a worker lost, a result not picklable
                parts[k] = [_Failed(one_line(e))] * len(chunks[k])
            fut.release()
            tally.add(parts[k])
    except BaseException:
        client.cancel(futures)
        raise
    return parts
