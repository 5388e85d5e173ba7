"""
A calibration as text to paste into a ROS system: tf2 static publishers, a launch file, URDF.

Each takes the document of ``files.export`` and gives T0 and T1 in tf2's direction (the
parent's frame id, the child's, the child's pose in the parent): T0 ``base_b`` -> ``base_a``
(``base_parent='a'``: its inverse, ``base_a`` -> ``base_b``), T1 ``tool`` -> ``marker``.
Numbers are written as Python's shortest text that reads back to the same float, so nothing
is lost on the way (tests: 1e-12). Comments say where the numbers come from, whether the fit
was a success, which directions a restricted rig's fit held (not measured), and which
rotation a position-only model does not estimate.

- ``static_tf``: ``ros2 run tf2_ros static_transform_publisher --x .. --frame-id ..
  --child-frame-id ..``, one line per transform;
- ``launch``: a ``launch.py`` starting those publishers (launch_ros ``Node``);
- ``urdf``: ``<link>`` and fixed ``<joint>`` elements to paste into a robot description (the
  links of device B's frames, which A's description lacks).
"""

from __future__ import annotations

from collections.abc import Mapping
import shlex
from typing import Any, NamedTuple
from xml.sax.saxutils import quoteattr

from coreg_ros.core.so3 import invert_poses
from coreg_ros.files.export import held_directions, TRANSFORMS
import numpy as np

#: Which base is T0's parent: B's (the node's /tf_static, the default) or A's.
BASE_PARENTS = ('b', 'a')


class Transform(NamedTuple):
    """One tf2 transform: the child's pose in the parent (m; (w, x, y, z))."""

    name: str
    what: str
    parent: str
    child: str
    position: np.ndarray
    quat_wxyz: np.ndarray


def number(value: float) -> str:
    """Return a float as the shortest text that reads back to the same float."""
    return repr(float(value))


def transforms(doc: Mapping[str, Any], base_parent: str = 'b') -> list[Transform]:
    """
    Return T0 and T1 of an export document as tf2 transforms.

    Parameters
    ----------
    doc : mapping
        The export document (``files.export``).
    base_parent : str
        ``'b'``: T0 as ``base_b`` -> ``base_a`` (the node's /tf_static); ``'a'``: its inverse,
        ``base_a`` -> ``base_b`` (a robot description rooted at A's base).

    """
    out = []
    for key, parent, child, what in TRANSFORMS:
        pose = doc[key]
        o = pose['orientation']
        p = np.array(pose['position'], dtype=float)
        q = np.array([o['w'], o['x'], o['y'], o['z']], dtype=float)
        frames = (doc['frames'][parent], doc['frames'][child])
        if key == 'base_to_base' and base_parent == 'a':
            p, q = invert_poses(p, q)
            frames = frames[::-1]
            what = "T0⁻¹: pose of B's base in A's base"
        out.append(Transform(key, what, *frames, p, q))
    return out


def notes(doc: Mapping[str, Any]) -> list[str]:
    """Return the comment lines of every format: source, verdict, held directions."""
    fit = doc.get('fit', {})
    chi2, dof = fit.get('chi2'), fit.get('dof') or 0
    lines = [f'coreg_ros calibration of {doc.get("source", "?")} ({doc.get("date", "?")})',
             f'{fit.get("model", "?")}, {str(fit.get("method", "?")).upper()}: '
             + ('success' if fit.get('success') else 'NOT A SUCCESS: '
                + str(fit.get('verdict') or fit.get('message') or 'the fit failed'))
             + (f'; chi2/dof {chi2 / dof:.3f}, p {fit.get("p_value", float("nan")):.3g}'
                if chi2 is not None and dof else '')
             + f'; {fit.get("n_pairs", "?")} pairs']
    offset = doc.get('time_offset')
    if isinstance(offset, Mapping) and offset.get('value_s') is not None:
        sigma = offset.get('sigma_s')
        lines.append(f'time offset (B minus A) {offset["value_s"] * 1e3:.4g} ms'
                     + (f' ± {sigma * 1e3:.2g} ms' if sigma else ' (given)'))
    for text in held_directions(doc):
        lines.append(f'held, not measured (the motion cannot show it): {text}')
    cov = doc['tool_to_marker'].get('covariance')
    if cov is not None and min(cov[21], cov[28], cov[35]) < 0:
        lines.append(f"T1's rotation is not estimated by model {fit.get('model', '?')}: "
                     f"identity (the marker frame's axes taken as the tool's)")
    return [' '.join(line.split()) for line in lines]  # one line each, whatever the text


def _arguments(t: Transform) -> list[str]:
    w, x, y, z = t.quat_wxyz
    values = zip(('--x', '--y', '--z'), t.position, strict=True)
    return ([a for flag, v in values for a in (flag, number(v))]
            + [a for flag, v in zip(('--qx', '--qy', '--qz', '--qw'), (x, y, z, w),
                                    strict=True)
               for a in (flag, number(v))]
            + ['--frame-id', t.parent, '--child-frame-id', t.child])


def static_tf(doc: Mapping[str, Any], base_parent: str = 'b') -> str:
    """Return the ``ros2 run tf2_ros static_transform_publisher`` lines (shell, commented)."""
    lines = [f'# {note}' for note in notes(doc)]
    for t in transforms(doc, base_parent):
        lines.append(f'# {t.what} (tf2: {t.parent} -> {t.child})')
        lines.append(shlex.join(['ros2', 'run', 'tf2_ros', 'static_transform_publisher',
                                 *_arguments(t)]))
    return '\n'.join(lines) + '\n'


def launch(doc: Mapping[str, Any], base_parent: str = 'b') -> str:
    """Return a ``launch.py`` that starts one static transform publisher per transform."""
    nodes = []
    for t in transforms(doc, base_parent):
        args = ', '.join(repr(a) for a in _arguments(t))
        nodes.append(f'        # {t.what} (tf2: {t.parent} -> {t.child})\n'
                     f"        Node(package='tf2_ros', executable='static_transform_publisher',\n"
                     f"             name={('coreg_' + t.name)!r}, output='screen',\n"
                     f'             arguments=[{args}]),\n')
    comments = ''.join(f'# {note}\n' for note in notes(doc))
    return ('"""tf2 static transforms of a coreg_ros calibration (coreg export --format '
            'launch)."""\n\n' + comments +
            '\nfrom launch import LaunchDescription\nfrom launch_ros.actions import Node\n\n\n'
            'def generate_launch_description():\n'
            '    """Start a static_transform_publisher for each calibrated transform."""\n'
            '    return LaunchDescription([\n' + ''.join(nodes) + '    ])\n')


def rpy(quat_wxyz) -> np.ndarray:
    """
    Return URDF's roll, pitch, yaw (rad) of a rotation: R = Rz(yaw) Ry(pitch) Rx(roll).

    URDF's ``<origin rpy>`` are rotations about the parent's fixed x, y, z axes in that order
    (scipy's extrinsic ``'xyz'``).
    """
    from scipy.spatial.transform import Rotation

    w, x, y, z = (float(v) for v in quat_wxyz)
    return Rotation.from_quat([x, y, z, w]).as_euler('xyz')


def _xml_comment(text: str) -> str:
    return f'<!-- {text.replace("--", "- -")} -->'


def urdf(doc: Mapping[str, Any], base_parent: str = 'b') -> str:
    """Return ``<link>`` and fixed ``<joint>`` elements to paste inside a ``<robot>``."""
    lines = [_xml_comment(note) for note in notes(doc)]
    b_frames = {doc['frames']['base_b'], doc['frames']['marker']}  # the links A's URDF lacks
    for t in transforms(doc, base_parent):
        xyz = ' '.join(number(v) for v in t.position)
        angles = ' '.join(number(v) for v in rpy(t.quat_wxyz))
        new = t.child if t.child in b_frames else t.parent
        lines += [_xml_comment(f'{t.what} (tf2: {t.parent} -> {t.child})'),
                  f'<link name={quoteattr(new)}/>',
                  f'<joint name={quoteattr(t.parent + "_to_" + t.child)} type="fixed">',
                  f'  <parent link={quoteattr(t.parent)}/>',
                  f'  <child link={quoteattr(t.child)}/>',
                  f'  <origin xyz="{xyz}" rpy="{angles}"/>',
                  '</joint>']
    return '\n'.join(lines) + '\n'
