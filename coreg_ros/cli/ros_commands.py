"""
The ``coreg`` subcommands that need ROS: ``play``, ``record``, ``call``, ``echo``.

``register(subparsers)`` adds them to the ``coreg`` command; rclpy is imported only inside the
commands, so ``coreg calibrate`` works without ROS. Every command returns an exit code and
reports a failure in one line (what is wrong and what to do), never with a traceback.
Also runnable alone: ``python -m coreg_ros.cli.ros_commands play BAG``.
"""

from __future__ import annotations

import argparse
import functools
from pathlib import Path
import sys

from coreg_ros.cli.argtypes import add_storage_option, positive, positive_or_inf
from coreg_ros.cli.policy import fail, run_command

SERVICES = ('calibrate', 'reset', 'save_samples')


def cmd_play(args) -> int:
    """Publish a bag on live topics with its original timing."""
    from coreg_ros.files.bag.posebag import list_topics, POSE_STAMPED, read_pose_bag
    from coreg_ros.ros.session import RosSession
    from coreg_ros.ros.tools import play_streams

    topics = args.topics or [t for t, ty in list_topics(args.bag).items() if POSE_STAMPED in ty]
    if not topics:
        return fail('play', f'bag {args.bag} has no {POSE_STAMPED} topic; pass --topics')
    streams = read_pose_bag(args.bag, topics)
    total = sum(len(s) for s in streams.values())
    with RosSession('coreg_play') as session:
        sent = play_streams(session, streams, rate=args.rate, wait_subscribers=args.wait)
        interrupted = not session.ok()
    if interrupted:
        print(f'coreg play: interrupted after {sent} of {total} messages', file=sys.stderr)
        return 130
    return 0


def cmd_record(args) -> int:
    """Record live PoseStamped topics to a new bag."""
    from coreg_ros.core.errors import BagError
    from coreg_ros.files.bag.posebag import write_pose_bag
    from coreg_ros.files.output_paths import check_new_bag
    from coreg_ros.ros.lifecycle import record_stop_signals
    from coreg_ros.ros.persistence import read_journal, SampleJournal
    from coreg_ros.ros.session import RosSession
    from coreg_ros.ros.tools import record_streams

    out = Path(args.out_bag)
    partial = out.with_name(out.name + '.partial')
    if args.recover:
        if not partial.is_dir():
            raise BagError(f'no interrupted recording at {partial}; nothing to recover')
        streams = read_journal(partial, args.topics)
    else:
        check_new_bag(out, 'OUT_BAG')
        if partial.exists():
            raise BagError(f'{partial} holds an interrupted recording; recover it with coreg '
                           f'record {out} --topics ... --recover, or delete it')
        # written as it goes (a killed recorder loses at most a second), merged at the end
        journal = SampleJournal(partial, storage='mcap')
        print(f'recording to {out} (written as it goes to {partial})')
        # Ctrl-C stops the recording without a KeyboardInterrupt, which could reach the main
        # thread after the block that expects the stop, and the samples would not be
        # written: before the session, the signal is recorded (lifecycle.record_stop_signals);
        # during it, the session takes it and ends its waits
        stops = record_stop_signals()
        try:
            with RosSession('coreg_record') as session:
                if stops:  # a signal before the session took the signals: it did not see it
                    session.interrupt()
                streams = record_streams(session, args.topics, duration=args.duration,
                                         on_flush=journal.append, flush_period=1.0)
        except KeyboardInterrupt:
            if journal.n_chunks == 0:  # stopped before any sample: leave nothing behind
                journal.remove()
            raise
    n = {t: len(s) for t, s in streams.items()}
    write_pose_bag(out, streams, storage=args.storage)
    SampleJournal(partial).remove()
    print(f'wrote {out}: ' + ', '.join(f'{t} {k}' for t, k in n.items()))
    return 0


def cmd_call(args) -> int:
    """Call one of coreg_node's Trigger services; exit 0 if it answered success."""
    from coreg_ros.ros.interface import service_name
    from coreg_ros.ros.session import RosSession
    from coreg_ros.ros.tools import call_trigger

    name = service_name(args.service, args.node)
    with RosSession('coreg_call') as session:
        success, message = call_trigger(session, name, timeout=args.timeout,
                                        wait_service=min(10.0, args.timeout))
    print(f'{name}: {"success" if success else "FAILED"}: {message}')
    return 0 if success else 1


def cmd_echo(args) -> int:
    """Print the messages of a topic with its publishers' type and QoS (latched ones too)."""
    from coreg_ros.ros.echo import echo_topic
    from coreg_ros.ros.interface import service_name
    from coreg_ros.ros.session import RosSession

    topic = service_name(args.topic, args.node)
    timeout = args.timeout
    if timeout is None and args.once:
        timeout = 10.0
    with RosSession('coreg_echo') as session:
        printed = echo_topic(session, topic, timeout=timeout, once=args.once,
                             out=functools.partial(print, flush=True))
        interrupted = not session.ok()
    if interrupted and printed == 0:
        print(f'coreg echo: interrupted before any message on {topic}', file=sys.stderr)
        return 130
    return 0


def register(subparsers) -> None:
    """Add the ``play``, ``record``, ``call`` and ``echo`` subcommands to ``subparsers``."""
    p = subparsers.add_parser('play', help='publish a bag on live topics with its timing')
    p.add_argument('bag', help='rosbag2 directory')
    p.add_argument('--rate', type=positive_or_inf, default=1.0,
                   help='speed factor (default 1: real time; inf: as fast as possible)')
    p.add_argument('--topics', nargs='+', help='topics to play (default: every PoseStamped)')
    p.add_argument('--wait', type=float, default=10.0,
                   help='seconds to wait for subscribers first (0: do not wait; default 10)')
    p.set_defaults(func=cmd_play)

    p = subparsers.add_parser('record', help='record live PoseStamped topics to a bag')
    p.add_argument('out_bag', help='rosbag2 directory to create')
    p.add_argument('--topics', nargs='+', required=True, help='PoseStamped topics')
    p.add_argument('--duration', type=positive, help='seconds (default: until Ctrl-C)')
    add_storage_option(p)
    p.add_argument('--recover', action='store_true',
                   help='write OUT_BAG from the samples an interrupted recording left in '
                        'OUT_BAG.partial')
    p.set_defaults(func=cmd_record)

    p = subparsers.add_parser('call', help='call a coreg_node service and print the answer')
    p.add_argument('service', choices=SERVICES, help="the node's Trigger service to call")
    p.add_argument('--node', default='coreg_node', help='node name (default coreg_node)')
    p.add_argument('--timeout', type=positive, default=60.0,
                   help='seconds to wait for the service and its answer (default 60)')
    p.set_defaults(func=cmd_call)

    p = subparsers.add_parser(
        'echo', help='print the messages of a topic (poses, diagnostics, markers)',
        description='Print the messages of a topic readably, with the type and QoS of its '
                    'publishers: PoseStamped, PoseWithCovarianceStamped, DiagnosticArray, '
                    'MarkerArray.')
    p.add_argument('topic', help='e.g. base_to_base, tool_to_marker, fused_pose, '
                                 'uncertainty_markers or a full name such as /diagnostics')
    p.add_argument('--node', default='coreg_node',
                   help='node whose private topic a relative name means (default coreg_node)')
    p.add_argument('--once', action='store_true', help='exit after the first message')
    p.add_argument('--timeout', type=positive,
                   help='seconds to wait for a publisher and for each message (default: 10 with '
                        '--once, else forever)')
    p.set_defaults(func=cmd_echo)


def main(argv=None) -> int:
    """Run one of these subcommands alone (``python -m coreg_ros.cli.ros_commands``)."""
    parser = argparse.ArgumentParser(prog='coreg')
    register(parser.add_subparsers(dest='command', required=True))
    args = parser.parse_args(argv)
    return run_command(args.command, args.func, args)


if __name__ == '__main__':
    sys.exit(main())
