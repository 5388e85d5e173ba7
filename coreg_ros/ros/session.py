"""
``RosSession``: an rclpy context, one node and an executor, for the tools and the tests.

Every tool (``coreg_ros.ros.tools``, ``coreg_ros.ros.echo``), ``coreg watch`` and the live
demo work on a session, so the same code serves the ``coreg`` subcommands and the tests (which
give every session its own ROS domain). A shutdown (Ctrl-C, SIGTERM) ends a session's waits
quietly (``coreg_ros.ros.lifecycle``) and shows as ``not session.ok()``.

A tool's session takes SIGINT and SIGTERM itself and only marks itself interrupted: every wait
spins in steps of at most 0.1 s and checks ``ok()``, so the tool stops within a step, and the
context is shut down by the main thread in ``close()``. rclpy's own handlers would shut the
context down from their thread while the main thread may be inside rmw (a graph query, a wait
set): a ``coreg echo`` interrupted while looking for publishers once ended in SIGSEGV.
"""

from __future__ import annotations

from collections.abc import Callable
import math
import signal
import time
from typing import Optional

from coreg_ros.core.errors import CoregError
from coreg_ros.ros.lifecycle import ended_by_shutdown, shutdown_quietly
import rclpy
from rclpy.context import Context
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from rclpy.signals import SignalHandlerOptions


class ToolError(CoregError):
    """A tool cannot do what was asked (no subscriber, no service, timeout)."""


class RosSession:
    """
    An rclpy context, one node and a single-threaded executor, as a context manager.

    Parameters
    ----------
    name : str
        Node name.
    domain_id : int, optional
        ROS domain; default ``ROS_DOMAIN_ID`` of the environment.
    signals : bool
        Take SIGINT and SIGTERM while the session is open: they mark it interrupted
        (command-line tools, from the main thread: yes; tests: no). The previous handlers
        are restored by ``close()``.

    """

    def __init__(self, name: str, domain_id: Optional[int] = None, signals: bool = True):
        self.context = Context()
        #: Set once a Ctrl-C, a SIGTERM or an external shutdown was seen.
        self.interrupted = False
        self._previous_handlers = {}
        if signals:
            for sig in (signal.SIGINT, signal.SIGTERM):
                self._previous_handlers[sig] = signal.signal(sig, self._on_signal)
        try:
            rclpy.init(context=self.context, domain_id=domain_id,
                       signal_handler_options=SignalHandlerOptions.NO)
            self.node = Node(name, context=self.context)
            self.executor = SingleThreadedExecutor(context=self.context)
            self.executor.add_node(self.node)
        except BaseException:  # an RCLError; a Ctrl-C if signals=False: do not leave it running
            shutdown_quietly(self.context)
            self._restore_handlers()
            raise

    def _on_signal(self, signum: int, frame) -> None:
        """Python's handler for SIGINT/SIGTERM (main thread): mark the session interrupted."""
        self.interrupted = True

    def _restore_handlers(self) -> None:
        for sig, handler in self._previous_handlers.items():
            signal.signal(sig, handler)
        self._previous_handlers = {}

    def ok(self) -> bool:
        """Return False once interrupted (SIGINT) or the context is shut down."""
        return not self.interrupted and self.context.ok()

    def interrupt(self) -> None:
        """Mark the session as interrupted: ``ok()`` is False from now on."""
        self.interrupted = True

    def stoppable(self):
        """
        Return a context manager that a shutdown of this session ends quietly.

        ``with session.stoppable(): ...`` leaves the block on a Ctrl-C or a shutdown of the
        context (``coreg_ros.ros.lifecycle.ended_by_shutdown``) and marks the session
        interrupted, so the code after it sees ``not session.ok()``.
        """
        return ended_by_shutdown(self.context, self.interrupt)

    def spin_until(self, done: Callable[[], bool], timeout: Optional[float]) -> bool:
        """
        Spin until ``done()``, the timeout or a shutdown; return ``done()``.

        Parameters
        ----------
        done : callable
            Checked before each spin; an ``RCLError`` of a shut-down context counts as False.
        timeout : float, optional
            Seconds; None: until ``done()`` or shutdown.

        """
        end = math.inf if timeout is None else time.monotonic() + timeout
        while not self._check(done):
            left = end - time.monotonic()
            if left <= 0 or not self.ok():
                break
            # rclpy shuts the context down from another thread: it may still look ok
            with self.stoppable():
                self.executor.spin_once(timeout_sec=min(0.1, left))
        return self._check(done)

    def _check(self, done: Callable[[], bool]) -> bool:
        """Return ``done()``; False when a shutdown (Ctrl-C) made it fail."""
        with self.stoppable():
            return done()
        return False

    def close(self) -> None:
        """Destroy the node, shut the context down and give the signals back."""
        try:
            self.executor.shutdown()
            self.node.destroy_node()
            shutdown_quietly(self.context)
        finally:
            self._restore_handlers()

    def __enter__(self) -> RosSession:
        return self

    def __exit__(self, *exc) -> None:
        self.close()
