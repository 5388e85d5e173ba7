"""
The end of a ROS process: one home for the shutdown race, shared by the node and the tools.

rclpy's signal handlers (SIGINT, SIGTERM) shut the context down from their own thread, so
whatever the main thread was doing at that moment can end in one of three ways, all of them a
normal stop and none worth a traceback:

- ``KeyboardInterrupt`` (a SIGINT that reached Python first),
- ``ExternalShutdownException`` (an executor noticed the shut-down context), or
- ``RCLError`` from rcl itself when the context went down between a check of ``ok()`` and
  the call (a wait set refused, a publish on a dead context, "rcl_shutdown already called";
  see ros2/ros2cli#854). Only then: an ``RCLError`` while the context is still up is a bug.

The Jazzy idiom of ros2/demos and ros2/examples (ros2/demos#581, ros2/examples#379) is
``try: spin except (KeyboardInterrupt, ExternalShutdownException): pass finally:
rclpy.try_shutdown()``; ``ended_by_shutdown`` is that ``except`` with the ``RCLError`` race
added, and ``shutdown_quietly`` is that ``finally``. ``coreg_ros.ros.node.main``, its services
thread, and ``coreg_ros.ros.session.RosSession`` (hence every tool, ``coreg play/record/call/
echo/watch`` and the demo) use them. Neither installs rclpy's handlers any more (a shutdown
from their thread while the main thread was inside rmw ended in SIGSEGV, in ``coreg echo``
and in a node stopped just after it started): a tool's session and the node
(``record_stop_signals``) take SIGINT and SIGTERM in Python, which only records them; the
main thread sees that between short spins and shuts the context down itself, so only an
external shutdown of the context is left for the races above, and what the node collected is
saved after its spin.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from contextlib import contextmanager
import signal
from typing import Optional

import rclpy
from rclpy.context import Context
from rclpy.executors import ExternalShutdownException
from rclpy.impl.implementation_singleton import rclpy_implementation as _rclpy

#: The exception rcl raises (``rclpy._rclpy_pybind11.RCLError``).
RCLError = _rclpy.RCLError


@contextmanager
def ended_by_shutdown(context: Optional[Context] = None,
                      on_stop: Optional[Callable[[], None]] = None) -> Iterator[None]:
    """
    Run a block that a ROS shutdown (Ctrl-C, SIGTERM) may end: such an end is quiet.

    A ``KeyboardInterrupt``, an ``ExternalShutdownException``, or an ``RCLError`` raised
    once ``context`` is no longer ok leaves the block without an exception (after
    ``on_stop()``, if given); every other exception, an ``RCLError`` of a live context
    included, propagates. Code after the ``with`` runs in both cases, so it checks ``ok()``.

    Parameters
    ----------
    context : rclpy.context.Context, optional
        The context whose shutdown is normal (default: rclpy's default context).
    on_stop : callable, optional
        Called without arguments when a shutdown ended the block (e.g. to mark a session
        interrupted: rclpy may not have shut the context down yet on a ``KeyboardInterrupt``).

    """
    try:
        yield
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except RCLError:
        if rclpy.ok(context=context):
            raise
    else:
        return
    if on_stop is not None:
        on_stop()


def shutdown_quietly(context: Optional[Context] = None) -> None:
    """
    Shut ``context`` down unless it is already (``rclpy.try_shutdown``), tolerating the race.

    ``try_shutdown`` checks ``ok()`` and then shuts down, so rclpy's signal handler can win in
    between and rcl raises "rcl_shutdown already called". The context is shut down either way.

    Parameters
    ----------
    context : rclpy.context.Context, optional
        Default: rclpy's default context.

    """
    try:
        rclpy.try_shutdown(context=context)
    except RCLError:
        if rclpy.ok(context=context):
            raise


def record_stop_signals() -> list:
    """
    Let SIGINT and SIGTERM be recorded, never raised as a KeyboardInterrupt.

    Call in the main thread before ``rclpy.init(signal_handler_options=NO)``. A
    KeyboardInterrupt would arrive at the main thread's next bytecode, possibly in the middle
    of saving what was collected; recorded, the signal is seen by the main thread's loop
    between spins, which then shuts the context down and saves.

    Returns
    -------
    list
        The signals received, in order (the caller stops once it is not empty).

    """
    received: list = []
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda signum, frame: received.append(signum))
    return received
