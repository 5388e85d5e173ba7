"""
The numerical core imports nothing from ROS, rosbags or YAML (docs/design.md §2).

A fresh interpreter installs a ``sys.meta_path`` finder that refuses rclpy, rosbags, message and
service packages and yaml, imports every module under ``coreg_ros.core`` and runs a tiny
calibration with data made from numpy alone.
"""

import os
from pathlib import Path
import subprocess
import sys
import textwrap

import coreg_ros

ROOT = Path(coreg_ros.__file__).resolve().parent.parent

SCRIPT = textwrap.dedent("""
    import importlib
    import importlib.abc
    import pkgutil
    import sys

    BLOCKED = {'rclpy', 'rosbags', 'std_srvs', 'yaml', 'rcl_interfaces', 'builtin_interfaces',
               'rosidl_runtime_py', 'message_filters', 'launch', 'launch_ros',
               'ament_index_python', 'tf2_ros', 'mcap', 'ruamel'}


    def blocked(name):
        top = name.split('.')[0]
        return top in BLOCKED or top.endswith(('_msgs', '_srvs', '_interfaces'))


    class Refuse(importlib.abc.MetaPathFinder):
        def find_spec(self, name, path=None, target=None):
            if blocked(name):
                raise ImportError(f'core purity: import of {name!r} is not allowed')
            return None


    for name in list(sys.modules):
        if blocked(name):
            del sys.modules[name]
    sys.meta_path.insert(0, Refuse())

    # the blocker works
    for probe in ('yaml', 'rclpy', 'geometry_msgs.msg', 'std_srvs.srv', 'rosbags.rosbag2'):
        try:
            importlib.import_module(probe)
        except ImportError:
            pass
        else:
            raise SystemExit(f'blocker failed for {probe}')

    import coreg_ros.core as core
    names = [m.name for m in pkgutil.walk_packages(core.__path__, 'coreg_ros.core.')]
    assert len(names) >= 12, names
    for name in names:
        importlib.import_module(name)
    leaked = sorted(n for n in sys.modules if blocked(n))
    assert not leaked, leaked

    import numpy as np
    from coreg_ros.core import quaternion as quat
    from coreg_ros.core.calibration.calibrate import calibrate
    from coreg_ros.core.settings import Settings
    from coreg_ros.core.types import Pairs

    rng = np.random.default_rng(0)
    n = 60
    q0 = quat.exp(np.array([0.3, -2.0, 0.5]))
    q1 = quat.exp(np.array([-1.0, 0.2, 2.5]))
    p0, p1 = np.array([0.5, -0.2, 1.0]), np.array([0.05, 0.1, -0.08])
    pos_a = rng.uniform(-0.2, 0.2, (n, 3))
    quat_a = quat.exp(rng.uniform(-1.0, 1.0, (n, 3)))
    pos_b = p0 + (pos_a + p1 @ quat.to_matrix(quat_a).transpose(0, 2, 1)) @ quat.to_matrix(q0).T
    quat_b = quat.multiply(q0, quat.multiply(quat_a, q1))
    pairs = Pairs(np.arange(n, dtype=np.int64), pos_a, quat_a, pos_b, quat_b)
    r = calibrate(pairs, Settings(method='tls'))
    assert r.success, r.message
    assert np.abs(r.base_to_base.position - p0).max() < 1e-6
    assert quat.angle_between(r.base_to_base.quat_wxyz, q0) < 1e-6
    assert np.abs(r.markers[0] - p1).max() < 1e-6
    leaked = sorted(n for n in sys.modules if blocked(n))
    assert not leaked, leaked
    print('PURE', len(names))
""")


def test_core_imports_no_ros_and_calibrates():
    env = dict(os.environ)
    env['PYTHONPATH'] = os.pathsep.join([str(ROOT), env.get('PYTHONPATH', '')])
    proc = subprocess.run([sys.executable, '-c', SCRIPT], capture_output=True, text=True,
                          env=env, timeout=120, cwd=str(ROOT))
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert proc.stdout.strip().startswith('PURE')


def test_sim_is_pure_too():
    """The simulator is core-side as well (it is used in notebooks and Monte Carlo)."""
    script = SCRIPT.split('# the blocker works')[0] + textwrap.dedent("""
        import coreg_ros.sim as sim
        import numpy as np
        rec = sim.simulate_recording(1, 2.0, 'three_marker')
        assert len(rec.streams_b) == 3
        leaked = sorted(n for n in sys.modules if blocked(n))
        assert not leaked, leaked
        print('PURE')
    """)
    env = dict(os.environ)
    env['PYTHONPATH'] = os.pathsep.join([str(ROOT), env.get('PYTHONPATH', '')])
    proc = subprocess.run([sys.executable, '-c', script], capture_output=True, text=True,
                          env=env, timeout=120, cwd=str(ROOT))
    assert proc.returncode == 0, proc.stderr[-3000:]
