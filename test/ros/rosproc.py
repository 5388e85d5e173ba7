"""
Node processes and ROS command-line runs for the node tests (the fixtures are in conftest.py).

Each runs on a reserved ROS domain (``ros_domain`` fixture) with discovery on localhost only.
"""

import os
from pathlib import Path
import signal
import subprocess
import sys
import time

os.environ['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'LOCALHOST'

from coreg_ros.ros.interface import PLAY_QOS  # noqa: E402
from coreg_ros.ros.tools import (  # noqa: E402
    diagnostics_values,
    wait_for_diagnostics,
    wait_for_subscribers,
)
from geometry_msgs.msg import PoseStamped  # noqa: E402
import yaml  # noqa: E402

PY = sys.executable


class NodeProcess:
    """coreg_node running in a subprocess on a given domain, logging to a file."""

    def __init__(self, domain, folder: Path, params: dict, name: str = 'node',
                 env: dict | None = None):
        self.folder = Path(folder)
        self.folder.mkdir(parents=True, exist_ok=True)
        self.storage = Path(params.setdefault('storage_dir', str(self.folder / 'store')))
        self.params_file = self.folder / f'{name}_params.yaml'
        self.params_file.write_text(yaml.safe_dump({'coreg_node': {'ros__parameters': params}}))
        self.log_path = self.folder / f'{name}.log'
        self._log = open(self.log_path, 'w')  # noqa: SIM115 - closed in stop()
        self.proc = subprocess.Popen(
            [PY, '-m', 'coreg_ros.ros.node', '--ros-args', '--params-file',
             str(self.params_file)],
            env={**domain.env(), **(env or {})}, stdout=self._log, stderr=subprocess.STDOUT)

    def alive(self) -> bool:
        return self.proc.poll() is None

    def stop(self, sig=signal.SIGINT, timeout: float = 15.0) -> int:
        if self.proc.poll() is None:
            self.proc.send_signal(sig)
            try:
                self.proc.wait(timeout)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()
        self._log.close()
        return self.proc.returncode

    def log(self) -> str:
        return self.log_path.read_text()


def run_cli(domain, *args, timeout=60.0) -> subprocess.CompletedProcess:
    """Run ``coreg <args>`` (the ROS subcommands) in a subprocess on ``domain``."""
    return subprocess.run([PY, '-m', 'coreg_ros.cli.ros_commands', *map(str, args)],
                          env=domain.env(), capture_output=True, text=True, timeout=timeout)


def diag_int(values: dict, key: str) -> int:
    return int(values[key])


def wait_counts(session, expect: dict, timeout: float = 20.0) -> dict:
    """Wait until the node's diagnostics show ``key >= value`` for all of ``expect``."""
    end = time.monotonic() + timeout
    values = {}
    while time.monotonic() < end:
        status = wait_for_diagnostics(session, timeout=min(3.0, end - time.monotonic()))
        if status is not None:
            values = diagnostics_values(status)
            if all(int(values.get(k, -1)) >= v for k, v in expect.items()):
                return values
    raise AssertionError(f'diagnostics never reached {expect}; last: {values}')


def publishers(session, topics, msg_type=PoseStamped, qos=PLAY_QOS) -> dict:
    """Create a publisher per topic; for PoseStamped, wait until the node has subscribed."""
    pubs = {t: session.node.create_publisher(msg_type, t, qos) for t in topics}
    if msg_type is PoseStamped:
        assert not wait_for_subscribers(session, pubs, 20.0), 'node did not subscribe'
    return pubs
