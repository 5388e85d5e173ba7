"""
The coreg command: offline calibration, simulation, diagnosis, and the ROS stand-in tools.

Every subcommand returns an exit code; a failure is one line on stderr saying what is wrong and
what to do (``coreg_ros.cli.policy``), never a traceback.
"""

from __future__ import annotations

import argparse
from collections.abc import Sequence
import sys
from typing import Optional

from coreg_ros.cli.options import OneLineParser
from coreg_ros.cli.policy import PROG, run_command


def build_parser() -> argparse.ArgumentParser:
    """Build the ``coreg`` argument parser with every subcommand."""
    parser = OneLineParser(prog=PROG, description=__doc__.strip().splitlines()[0])
    sub = parser.add_subparsers(dest='command', required=True, parser_class=OneLineParser)
    # each front end adds its own subcommands (and imports its heavy parts lazily)
    from coreg_ros.cli import (
        batch,
        calibrate,
        convert,
        diagnose,
        export,
        noise,
        plan,
        ros_commands,
        simulate,
        watch,
    )
    for module in (calibrate, noise, simulate, diagnose, batch, convert, plan, export,
                   ros_commands, watch):
        module.register(sub)
    return parser


def main(argv: Optional[Sequence[str]] = None) -> int:
    """Entry point of the ``coreg`` console script."""
    args = build_parser().parse_args(argv)
    return run_command(args.command, args.func, args)


if __name__ == '__main__':
    sys.exit(main())
