"""
Fixtures of the node tests: a private ROS domain per test, coreg_node in a subprocess.

Import into a test module with ``from ros_fixtures import *  # noqa: F401,F403``.
Every test gets its own ROS_DOMAIN_ID (reserved with a file lock, so concurrent test runs
never share one) and discovery on localhost only.
"""

import os
from pathlib import Path
import signal
import subprocess
import sys
import time

os.environ['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'LOCALHOST'

from coreg_ros.ros.domain import reserve_domain_id  # noqa: E402
from coreg_ros.ros.tools import (  # noqa: E402
    diagnostics_values,
    RosSession,
    wait_for_diagnostics,
)
import pytest  # noqa: E402
import yaml  # noqa: E402

__all__ = ['ros_domain', 'ros_session', 'start_node', 'NodeProcess', 'run_cli', 'wait_counts',
           'diag_int']

PY = sys.executable


class NodeProcess:
    """coreg_node running in a subprocess on a given domain, logging to a file."""

    def __init__(self, domain, folder: Path, params: dict, name: str = 'node'):
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
            env=domain.env(), stdout=self._log, stderr=subprocess.STDOUT)

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


@pytest.fixture
def ros_domain():
    reservation = reserve_domain_id()
    yield reservation
    reservation.release()


@pytest.fixture
def ros_session(ros_domain):
    session = RosSession('coreg_test', domain_id=ros_domain.domain_id, signals=False)
    yield session
    session.close()


@pytest.fixture
def start_node(ros_domain, tmp_path):
    """Start coreg_node subprocesses (params dict) in the test's domain; stopped at teardown."""
    nodes = []

    def start(params=None, name='node') -> NodeProcess:
        node = NodeProcess(ros_domain, tmp_path, dict(params or {}), name=f'{name}{len(nodes)}')
        nodes.append(node)
        return node

    yield start
    for node in nodes:
        node.stop(signal.SIGKILL if node.alive() else signal.SIGINT, timeout=5)


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
