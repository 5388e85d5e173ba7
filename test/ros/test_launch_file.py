"""
launch/coreg.launch.py: what it starts, with which parameter file, and that the node runs so.

``launch`` and ``launch_ros`` are not installable here (no wheels): the file is parsed with
ast and checked against setup.py and the parameter file; the command line launch_ros makes of
its Node action runs the real node; where launch_ros is importable, the description is built.
"""

import ast
import importlib.util
import os
from pathlib import Path
import signal
import subprocess
import sys
import time

from coreg_ros.ros.interface import NODE_NAME
import pytest
import yaml

ROOT = Path(__file__).resolve().parents[2]
LAUNCH = ROOT / 'launch' / 'coreg.launch.py'


def _default_params(launch_file: Path) -> Path:
    """Evaluate the launch file's DEFAULT_PARAMS as if the file were at ``launch_file``."""
    tree = ast.parse(LAUNCH.read_text())
    (assign,) = [n for n in tree.body if isinstance(n, ast.Assign)
                 and [t.id for t in n.targets] == ['DEFAULT_PARAMS']]
    expression = ast.Expression(assign.value)
    return Path(os.path.normpath(eval(compile(expression, str(LAUNCH), 'eval'),
                                      {'os': os, '__file__': str(launch_file)})))


def _calls(name: str) -> list:
    tree = ast.parse(LAUNCH.read_text())
    return [n for n in ast.walk(tree) if isinstance(n, ast.Call)
            and getattr(n.func, 'id', '') == name]


def test_launch_file_names_the_installed_node_and_its_parameter_file(tmp_path):
    tree = ast.parse(LAUNCH.read_text())
    assert any(isinstance(n, ast.FunctionDef) and n.name == 'generate_launch_description'
               for n in tree.body)
    (node,) = _calls('Node')
    kw = {k.arg: k.value for k in node.keywords}
    literal = {k: ast.literal_eval(v) for k, v in kw.items()
               if k in ('package', 'executable', 'name')}
    assert literal == {'package': 'coreg_ros', 'executable': 'coreg_node', 'name': NODE_NAME}
    declared = {ast.literal_eval(c.args[0]) for c in _calls('DeclareLaunchArgument')}
    used = {ast.literal_eval(c.args[0]) for c in _calls('LaunchConfiguration')}
    assert used == declared == {'params_file', 'log_level'}
    # setup.py installs the executable and both files where the launch file looks
    setup = (ROOT / 'setup.py').read_text()
    assert "'coreg_node = coreg_ros.entry:coreg_node'" in setup
    assert "'/launch', glob('launch/*.launch.py')" in setup
    assert "'/config', glob('config/*.yaml')" in setup
    # the parameter file: in the source tree and in an installed share/coreg_ros alike
    params = _default_params(LAUNCH)
    assert params == ROOT / 'config' / 'coreg.yaml'
    assert list(yaml.safe_load(params.read_text())) == [NODE_NAME]
    share = tmp_path / 'install' / 'share' / 'coreg_ros'
    assert _default_params(share / 'launch' / 'coreg.launch.py') == share / 'config/coreg.yaml'


@pytest.mark.ros
def test_the_command_line_of_the_launch_runs_the_node(ros_domain, tmp_path):
    """Run the node as launch_ros runs the Node action: name remap, parameter file, log level."""
    params = _default_params(LAUNCH)
    env = {**ros_domain.env(), 'HOME': str(tmp_path)}  # storage_dir: ~/.ros/coreg
    proc = subprocess.Popen(
        [sys.executable, '-m', 'coreg_ros.ros.node', '--ros-args', '-r',
         f'__node:={NODE_NAME}', '--params-file', str(params), '--log-level', 'info'],
        env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, cwd=ROOT)
    try:
        end, log = time.monotonic() + 30, ''
        while time.monotonic() < end and 'listening to A' not in log:
            line = proc.stdout.readline()
            if not line:
                break
            log += line
        assert 'listening to A /device_a/pose' in log, log
        assert 'WARN' not in log and 'ERROR' not in log, log
    finally:
        proc.send_signal(signal.SIGINT)
        log += proc.communicate(timeout=20)[0]
    assert proc.returncode == 0, log
    assert (tmp_path / '.ros' / 'coreg').is_dir()  # the file's storage_dir, under HOME


def test_launch_description_builds():
    pytest.importorskip('launch_ros')
    spec = importlib.util.spec_from_file_location('coreg_launch', LAUNCH)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    description = module.generate_launch_description()
    from launch_ros.actions import Node

    (node,) = [e for e in description.entities if isinstance(e, Node)]
    assert node.node_package == 'coreg_ros' and node.node_executable == 'coreg_node'
