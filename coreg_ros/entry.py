"""
Console-script entry points (``coreg``, ``coreg_node``) that stay quiet under a signal.

Importing numpy, scipy and rclpy takes about a second; a Ctrl-C in that second would end in a
``KeyboardInterrupt`` traceback from deep inside an import (or, inside rclpy's extension, an
``ImportError``). The entry points import the real ``main`` with SIGINT only remembered, then
exit with one line and code 130 if it came; a Ctrl-C after that is the command's own business,
and anything that still escapes it as ``KeyboardInterrupt`` is one line too. Only the
standard library is imported here.
"""

from __future__ import annotations

from collections.abc import Callable
import signal
import sys


def _run(name: str, load: Callable[[], Callable[[], int]]) -> int:
    interrupted = []
    previous = signal.signal(signal.SIGINT, lambda signum, frame: interrupted.append(signum))
    try:
        main = load()
    finally:
        signal.signal(signal.SIGINT, previous)
    if interrupted:
        print(f'{name}: interrupted while starting', file=sys.stderr)
        return 130
    try:
        return int(main() or 0)
    except KeyboardInterrupt:
        print(f'{name}: interrupted', file=sys.stderr)
        return 130


def _load_coreg():
    from coreg_ros.cli import main as cli
    cli.build_parser()  # imports every subcommand's module now, while SIGINT is held
    return cli.main


def _load_node():
    from coreg_ros.ros.node import main as node_main
    return node_main


def coreg() -> int:
    """Run the ``coreg`` command."""
    return _run('coreg', _load_coreg)


def coreg_node() -> int:
    """Run ``coreg_node``."""
    return _run('coreg_node', _load_node)
