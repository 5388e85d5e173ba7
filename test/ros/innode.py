"""
coreg_node in the test's own process, for the tests of what needs no process of its own.

The node gets an rclpy context of its own on the test's reserved domain (no signal handlers:
the test process keeps its own), and both its executors spin in threads (``NodeExecutors``,
as in ``main``); the test drives it as it drives a node process, through the real publishers,
service clients and subscriptions of a ``RosSession`` (another context, the same domain).
What only a process shows (signals, discovery between processes, QoS across processes, the
journal after SIGKILL) stays with ``rosproc.NodeProcess``. The fixture is in conftest.py.
"""

import os
from pathlib import Path

os.environ['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'LOCALHOST'

from coreg_ros.ros.lifecycle import shutdown_quietly  # noqa: E402
from coreg_ros.ros.node import CoregNode, NodeExecutors  # noqa: E402
import rclpy  # noqa: E402
from rclpy.context import Context  # noqa: E402
from rclpy.signals import SignalHandlerOptions  # noqa: E402
import yaml  # noqa: E402


class Output:
    """What this process writes to stdout and stderr (the nodes' log lines), kept as it comes."""

    def __init__(self, capfd):
        self._capfd = capfd
        self.text = ''

    def read(self) -> str:
        """Return everything written since the test began."""
        out, err = self._capfd.readouterr()
        self.text += out + err
        return self.text


class InProcessNode:
    """
    coreg_node in this process, with the interface of ``rosproc.NodeProcess``.

    ``params`` go to a parameter file that the node reads as the executable does
    (``--params-file``); ``storage_dir`` defaults to a folder of the test. With
    ``spin=False`` the node is made (subscribed) but takes nothing until ``spin()``: a node
    still starting up.
    """

    def __init__(self, domain, folder: Path, params: dict, output: Output, name: str = 'node',
                 spin: bool = True):
        self.folder = Path(folder)
        self.folder.mkdir(parents=True, exist_ok=True)
        self.storage = Path(params.setdefault('storage_dir', str(self.folder / 'store')))
        self.params_file = self.folder / f'{name}_params.yaml'
        self.params_file.write_text(yaml.safe_dump({'coreg_node': {'ros__parameters': params}}))
        self._output = output
        self._start = len(output.read())
        self._end = None
        self.code = None
        self.context = Context()
        rclpy.init(context=self.context, domain_id=domain.domain_id,
                   signal_handler_options=SignalHandlerOptions.NO)
        try:
            self.node = CoregNode(context=self.context,
                                  cli_args=['--ros-args', '--params-file', str(self.params_file)])
            self.executors = NodeExecutors(self.node)
            if spin:
                self.spin()
        except BaseException:
            shutdown_quietly(self.context)
            raise

    def spin(self) -> None:
        """Start both executors' threads (once)."""
        self.executors.start(streams=True)

    def alive(self) -> bool:
        """Tell whether the node still runs (its context is up and both threads spin)."""
        return self.code is None and self.context.ok() and self.executors.alive()

    def stop(self) -> int:
        """
        Stop the node as ``main`` does on SIGINT or SIGTERM; return its exit code.

        The context is shut down, the executors end, the samples not yet saved go to a bag
        and the nodes are destroyed: 0, or 1 if the samples could not be saved.
        """
        if self.code is None:
            shutdown_quietly(self.context)
            self.executors.join(10.0)
            self.code = 0 if self.node.close() else 1
            for executor in (self.executors.streams, self.executors.services):
                executor.shutdown(timeout_sec=1.0)
            self.context.destroy()
            self._end = len(self._output.read())
        return self.code

    def log(self) -> str:
        """Return what was written while the node ran (its log lines among them)."""
        return self._output.read()[self._start:self._end]
