"""
The live demo: coreg_node in a subprocess, a bag played into it, calibrate, print, shut down.

``run_live_demo(bag)`` runs the whole loop on its own ROS domain (so it never disturbs other
ROS processes of the machine) and returns an exit code; ``python -m coreg_ros.ros.demo BAG``
runs it from a shell.
"""

from __future__ import annotations

import argparse
from collections.abc import Callable
from pathlib import Path
import signal
import subprocess
import sys
import tempfile
import time
from typing import Optional

from coreg_ros.core.errors import CoregError
from coreg_ros.files.bag.posebag import list_topics, POSE_STAMPED, read_pose_bag
from coreg_ros.ros.domain import reserve_domain_id
from coreg_ros.ros.echo import format_pose_msg
from coreg_ros.ros.interface import service_name
from coreg_ros.ros.session import RosSession
from coreg_ros.ros.tools import (
    call_trigger,
    diagnostics_values,
    play_streams,
    wait_for_diagnostics,
    wait_for_result,
)

#: config/coreg.yaml of a source checkout (an installed package has it under share/).
DEFAULT_CONFIG = Path(__file__).resolve().parents[2] / 'config' / 'coreg.yaml'
#: Diagnostic keys worth showing in the demo (per topic keys are added).
_SHOWN = ('paired', 'pairing rate', 'last calibration n_pairs', 'last calibration chi2_dof',
          'last calibration p_value', 'last calibration seconds')


def _node_command(config: Optional[Path], storage_dir: str, topics_b: list[str],
                  topic_a: str) -> list[str]:
    cmd = [sys.executable, '-m', 'coreg_ros.ros.node', '--ros-args']
    if config is not None and config.is_file():
        cmd += ['--params-file', str(config)]
    # Reliable QoS: the demo's numbers must not depend on a dropped message.
    cmd += ['-p', f'storage_dir:={storage_dir}', '-p', 'qos_reliable:=true',
            '-p', f'topic_a:={topic_a}', '-p', f'topic_b:=[{",".join(topics_b)}]']
    if len(topics_b) == 3:
        cmd += ['-p', 'model:=three_marker']
    return cmd


def run_live_demo(bag_path, *, rate: float = 4.0, config: Optional[Path] = DEFAULT_CONFIG,
                  storage_dir: Optional[str] = None, timeout: float = 60.0,
                  out: Callable[[str], None] = print) -> int:
    """
    Start coreg_node, play ``bag_path`` into it, calibrate, print the result, stop the node.

    Parameters
    ----------
    bag_path : path-like
        rosbag2 recording; its first PoseStamped topic is device A, the others device B (three
        B topics select the three-marker model).
    rate : float
        Replay speed factor.
    config : Path, optional
        Parameter file of the node (default: the package's config/coreg.yaml).
    storage_dir : str, optional
        Where the node stores its result and samples (default: a fresh temporary directory).
    timeout : float
        Seconds allowed to each step (node start-up, calibration).
    out : callable
        Where the report lines go.

    Returns
    -------
    code : int
        0 if the node calibrated and published, 1 otherwise (the reason is printed).

    """
    try:
        topics = [t for t, ty in list_topics(bag_path).items() if POSE_STAMPED in ty]
        if len(topics) < 2:
            raise CoregError(f'bag {bag_path} needs a device A and a device B PoseStamped topic, '
                             f'has {topics}')
        topics = sorted(topics, key=lambda t: ('device_a' not in t, t))
        streams = read_pose_bag(bag_path, topics)
    except CoregError as e:
        out(f'demo: {e}')
        return 1
    storage_dir = storage_dir or tempfile.mkdtemp(prefix='coreg_demo_')
    with reserve_domain_id() as domain:
        out(f'demo: ROS_DOMAIN_ID={domain.domain_id}; starting coreg_node (storage {storage_dir})')
        log_path = Path(storage_dir) / 'coreg_node.log'
        Path(storage_dir).mkdir(parents=True, exist_ok=True)
        with open(log_path, 'w') as log:
            node = subprocess.Popen(_node_command(config, storage_dir, topics[1:], topics[0]),
                                    env=domain.env(), stdout=log, stderr=subprocess.STDOUT)
        try:
            return _drive(node, domain.domain_id, streams, rate, timeout, out, log_path)
        finally:
            if node.poll() is None:
                node.send_signal(signal.SIGINT)
                try:
                    node.wait(15)
                except subprocess.TimeoutExpired:
                    node.kill()
                    node.wait()
            out(f'demo: coreg_node exited with code {node.returncode}; its log: {log_path}')
            bags = sorted(Path(storage_dir).glob('samples_*'))
            if bags:
                out(f'demo: samples saved on shutdown to {bags[-1]}')


def _drive(node, domain_id, streams, rate, timeout, out, log_path) -> int:
    with RosSession('coreg_demo', domain_id=domain_id, signals=False) as session:
        try:
            t0 = time.monotonic()
            play_streams(session, streams, rate=rate, wait_subscribers=timeout,
                         log=lambda s: out(f'demo: {s}'))
            n = {t: len(s) for t, s in streams.items()}
            want = {f'{t} received': k for t, k in n.items()}
            status = wait_for_diagnostics(
                session, timeout=10.0,
                accept=lambda s: all(int(diagnostics_values(s).get(k, -1)) >= v
                                     for k, v in want.items()))
            if status is None:
                out('demo: the node did not report every message as received (continuing)')
            ok, message = call_trigger(session, service_name('calibrate'), timeout=timeout)
            out(f'demo: ~/calibrate -> {"success" if ok else "FAILED"}: {message}')
            if not ok:
                return 1
            for name in ('base_to_base', 'tool_to_marker'):
                msg = wait_for_result(session, service_name(name), timeout=5.0)
                if msg is None:
                    out(f'demo: nothing received on ~/{name}')
                    return 1
                out(format_pose_msg(msg, service_name(name)))
            status = wait_for_diagnostics(session, timeout=3.0)
            if status is not None:
                values = diagnostics_values(status)
                counters = ('received', 'accepted', 'rejected', 'dropped oldest')
                shown = [f'{t} {k}' for t in n for k in counters] + list(_SHOWN)
                out('/diagnostics:')
                out('\n'.join(f'  {k}: {values[k]}' for k in shown if k in values))
            out(f'demo: done in {time.monotonic() - t0:.1f} s')
            return 0
        except CoregError as e:
            out(f'demo: {e}')
            if node.poll() is not None:
                out(f'demo: coreg_node died; last lines of {log_path}:')
                out('\n'.join(Path(log_path).read_text().splitlines()[-10:]))
            return 1


def main(argv=None) -> int:
    """``python -m coreg_ros.ros.demo BAG [--rate R]``."""
    parser = argparse.ArgumentParser(prog='coreg demo', description=__doc__.splitlines()[1])
    parser.add_argument('bag', help='rosbag2 directory to play into the node')
    parser.add_argument('--rate', type=float, default=4.0, help='replay speed (default 4)')
    parser.add_argument('--storage-dir', help='node storage (default: a temporary directory)')
    args = parser.parse_args(argv)
    return run_live_demo(args.bag, rate=args.rate, storage_dir=args.storage_dir)


if __name__ == '__main__':
    sys.exit(main())
