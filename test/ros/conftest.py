"""
Fixtures of the node tests: a private ROS domain per test, coreg_node in a subprocess or here.

Every test gets its own ROS_DOMAIN_ID (reserved with a file lock, so concurrent test runs
never share one) and discovery on localhost only. ``start_node_here`` runs coreg_node in the
test's process (``innode``); ``start_node`` in a subprocess (``rosproc``), for what only a
process shows: signals, discovery between processes, QoS across processes, SIGKILL.
"""

import os
import signal
import sys

os.environ['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'LOCALHOST'

from coreg_ros.ros.domain import reserve_domain_id  # noqa: E402
from coreg_ros.ros.session import RosSession  # noqa: E402
from innode import InProcessNode, Output  # noqa: E402
import pytest  # noqa: E402
from rosproc import NodeProcess  # noqa: E402


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

    def start(params=None, name='node', env=None) -> NodeProcess:
        node = NodeProcess(ros_domain, tmp_path, dict(params or {}), name=f'{name}{len(nodes)}',
                           env=env)
        nodes.append(node)
        return node

    yield start
    for node in nodes:
        node.stop(signal.SIGKILL if node.alive() else signal.SIGINT, timeout=5)


@pytest.fixture
def start_node_here(ros_domain, tmp_path, capfd):
    """Start coreg_node in this process (params dict) in the test's domain; stopped at teardown."""
    output = Output(capfd)
    nodes = []

    def start(params=None, name='node', spin=True) -> InProcessNode:
        node = InProcessNode(ros_domain, tmp_path, dict(params or {}), output,
                             name=f'{name}{len(nodes)}', spin=spin)
        nodes.append(node)
        return node

    yield start
    for node in nodes:
        node.stop()
    sys.stderr.write(output.read())  # shown with a failure, as a node process's log would be
