"""
Console-script entry points (``coreg``, ``coreg_node``) that stay quiet under a signal.

Importing numpy, scipy and rclpy takes about a second; a Ctrl-C in that second would end in a
``KeyboardInterrupt`` traceback from deep inside an import (or, inside rclpy's extension, an
``ImportError``). The entry points import the real ``main`` with SIGINT and SIGTERM only
remembered, then exit with one line and code 128 + the signal if one came (130 for SIGINT,
143 for SIGTERM); a signal after that is the command's own business,
and anything that still escapes it as ``KeyboardInterrupt`` is one line too. Only the
standard library is imported here.
"""

from __future__ import annotations

from collections.abc import Callable
import signal
import sys


def _run(name: str, load: Callable[[], Callable[[], int]]) -> int:
    interrupted = []
    held = (signal.SIGINT, signal.SIGTERM)
    previous = {s: signal.signal(s, lambda signum, frame: interrupted.append(signum))
                for s in held}
    try:
        main = load()
    finally:
        for s, handler in previous.items():
            signal.signal(s, handler)
    if interrupted:
        print(f'{name}: {signal.Signals(interrupted[0]).name} while starting; stopped',
              file=sys.stderr)
        return 128 + int(interrupted[0])
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
