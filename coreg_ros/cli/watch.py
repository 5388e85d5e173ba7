"""
``coreg watch``: a live terminal dashboard of a running coreg_node.

Subscribes to ``/diagnostics`` (``diagnostic_msgs/DiagnosticArray``, volatile QoS) and shows,
updating in place (``rich.live``), the dashboard of ``coreg_ros.cli.dashboard``: the live
sample counts, the σ each parameter would have now against the targets, the suggested next
motion, and the calibration and watchdog states. rclpy and rich are imported only inside the
command.
"""

from __future__ import annotations

from collections.abc import Sequence
import sys
import time
from typing import Optional

from coreg_ros.cli.argtypes import positive
from coreg_ros.cli.dashboard import DashboardState, render, Status
from coreg_ros.cli.policy import fail, interrupted, run_command


def register(subparsers) -> None:
    """Add the ``watch`` subcommand to the ``coreg`` subparsers."""
    p = subparsers.add_parser(
        'watch', help='live dashboard of a running coreg_node (counts, σ against targets, next '
                      'motion, calibration and watchdog state)',
        description="Subscribe to /diagnostics and show the node's counts, the σ each "
                    'parameter would have now against the targets, the suggested next motion '
                    'and the calibration and watchdog states, updating in place.')
    p.add_argument('--node', default='coreg_node', help='node name (default coreg_node)')
    p.add_argument('--topic', default='/diagnostics', help='default /diagnostics')
    p.add_argument('--once', action='store_true',
                   help='print one frame after the first update from the node and exit')
    p.add_argument('--timeout', type=positive,
                   help='seconds to wait for the node (default: 10 with --once, else forever)')
    p.add_argument('--refresh', type=positive, default=4.0,
                   help='screen refreshes per second (default 4)')
    p.set_defaults(func=cmd_watch)


def cmd_watch(args) -> int:
    """Run the dashboard until Ctrl-C (or one frame with ``--once``)."""
    # a missing rich or ROS 2 is one line by the error policy (coreg_ros.cli.policy)
    from coreg_ros.ros.session import RosSession
    from diagnostic_msgs.msg import DiagnosticArray
    from rich.console import Console
    from rich.live import Live

    state = DashboardState(node=args.node.lstrip('/'))
    timeout = args.timeout if args.timeout is not None else (10.0 if args.once else None)
    started = time.monotonic()

    def received(msg) -> None:
        state.update(Status.from_msg(s) for s in msg.status)

    console = Console()
    with RosSession('coreg_watch') as session:
        # depth 10, reliable, volatile (rclpy's default for a depth), as wait_for_diagnostics
        session.node.create_subscription(DiagnosticArray, args.topic, received, 10)
        if args.once or not console.is_terminal:
            got = session.spin_until(lambda: state.received_at is not None, timeout)
            if not got and not session.ok():  # Ctrl-C before any status
                return interrupted('watch')
            if not got:
                return fail('watch', f'no status of {state.node} on {args.topic} within '
                            f'{timeout:g} s; is the node running (and on this ROS domain)?')
            console.print(render(state))
            return 0
        period = 1.0 / args.refresh
        with Live(render(state), console=console, refresh_per_second=args.refresh,
                  transient=False) as live:
            while session.ok():
                session.spin_until(lambda: False, period)
                live.update(render(state))
                if (timeout is not None and state.received_at is None
                        and time.monotonic() - started > timeout):
                    return fail('watch', f'no status of {state.node} on {args.topic} within '
                                f'{timeout:g} s')
    # the dashboard runs until Ctrl-C (or SIGTERM): 130, as play and echo say it
    return interrupted('watch')


def main(argv: Optional[Sequence[str]] = None) -> int:
    """Run ``coreg watch`` alone (``python -m coreg_ros.cli.watch``)."""
    import argparse
    parser = argparse.ArgumentParser(prog='coreg')
    register(parser.add_subparsers(dest='command', required=True))
    args = parser.parse_args(['watch', *(sys.argv[1:] if argv is None else argv)])
    return run_command('watch', args.func, args)


if __name__ == '__main__':
    sys.exit(main())
