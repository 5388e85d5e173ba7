"""
What went wrong in coreg_node: one log line per problem and period, and the errors it shows.

``Alerts`` is shared by the node's collaborators (``ros.sample_store``, ``ros.calibrator``,
``ros.status_publisher``): a repeated problem (a rejected message, a failing timer, a storage
error) is logged once, then again only after ``WARN_PERIOD`` s (``ros.throttle``); a failure of
``storage_dir`` and a failed service or timer are held for /diagnostics, which goes ERROR with
them. The guards wrap the node's service and timer callbacks, so an exception is answered or
logged and never ends the services thread.
"""

from __future__ import annotations

from collections.abc import Callable
import inspect
import traceback
from typing import Optional

from coreg_ros.ros.lifecycle import ended_by_shutdown
from coreg_ros.ros.throttle import Throttle, WARN_PERIOD


def os_reason(error: BaseException) -> str:
    """
    Return an OSError as 'strerror: file' (other errors as their text).

    Parameters
    ----------
    error : BaseException
        The failure to describe in one line.

    """
    if isinstance(error, OSError) and error.strerror:
        return f'{error.strerror}: {error.filename}' if error.filename else error.strerror
    return str(error) or type(error).__name__


class Alerts:
    """
    Throttled log lines and the node's standing errors (``storage_dir``, a failed callback).

    Parameters
    ----------
    logger : rclpy.impl.rcutils_logger.RcutilsLogger
        The node's logger.
    storage_dir : str
        The configured ``storage_dir`` (named in the storage error).
    context : rclpy.context.Context, optional
        The node's context: a timer that fails because it was shut down meanwhile (the
        shutdown race of ``ros.lifecycle``) is a normal stop, not an error.

    Attributes
    ----------
    storage_error : str or None
        One line: ``storage_dir`` failed (/diagnostics goes ERROR).
    internal_error : str or None
        One line: a service or timer failed (/diagnostics goes ERROR).

    """

    def __init__(self, logger, storage_dir: str, context=None):
        self.logger = logger
        self.context = context
        self.storage_dir = storage_dir
        self.storage_error: Optional[str] = None
        self.internal_error: Optional[str] = None
        self._throttle = Throttle()  # one line per problem and WARN_PERIOD

    def ready(self, key, period: Optional[float] = None) -> bool:
        """Return True (and start a new period) if a line about ``key`` may be logged now."""
        return self._throttle.ready(key, period)

    def throttled(self, key, line: str, level: str = 'warning',
                  period: float = WARN_PERIOD) -> None:
        """Log ``line`` at most once every ``period`` seconds per ``key``."""
        if self._throttle.ready(key, period):
            getattr(self.logger, level)(line)

    def storage_failed(self, what: str, error: BaseException) -> str:
        """Record that ``storage_dir`` failed (diagnostics ERROR); return the one line."""
        self.storage_error = (f'cannot {what} in storage_dir {self.storage_dir} '
                              f'({os_reason(error)}); fix storage_dir (a directory on a '
                              f'mounted disk with free space) and restart')
        self.throttled(('storage', what), self.storage_error, level='error')
        return self.storage_error

    def guard_service(self, name: str, handler: Callable) -> Callable:
        """
        Wrap a service handler: any exception is answered (success=false), never raised.

        A coroutine handler (one that awaits work done in another thread) gets a coroutine
        wrapper, so the executor still runs it as a task.
        """
        if inspect.iscoroutinefunction(handler):
            async def call_async(request, response):
                try:
                    return await handler(request, response)
                except Exception as e:  # a bug or an OS failure must not end the services
                    return self._service_failed(name, e, response)
            return call_async

        def call(request, response):
            try:
                return handler(request, response)
            except Exception as e:  # a bug or an OS failure must not end the services thread
                return self._service_failed(name, e, response)
        return call

    def _service_failed(self, name: str, error: Exception, response):
        self.logger.error(f'~/{name} failed: {traceback.format_exc()}')
        response.success = False
        response.message = (f'~/{name} failed: {type(error).__name__}: {os_reason(error)}; '
                            f'the node keeps its samples and runs on (see its log)')
        self.internal_error = response.message
        return response

    def guard_timer(self, name: str, callback: Callable[[], None]) -> Callable[[], None]:
        """Wrap a timer callback: an exception is logged (throttled) and shown in diagnostics."""
        def tick():
            try:
                if self.context is None:
                    callback()
                else:
                    with ended_by_shutdown(self.context):
                        callback()
            except Exception as e:
                self.internal_error = f'{name} failed: {type(e).__name__}: {os_reason(e)}'
                self.throttled(('timer', name), f'{self.internal_error}\n'
                               f'{traceback.format_exc()}', level='error')
        return tick
