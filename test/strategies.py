"""
Random draws shared by the tests: poses, covariances, outliers, CSV exports, hypothesis strategies.

One home for each: test modules import what they need (``from strategies import random_quat``);
pytest puts this folder on the path through its conftest.py.
"""

from dataclasses import replace
from pathlib import Path

from coreg_ros.core import quaternion as quat
from coreg_ros.core.so3 import invert_poses
from coreg_ros.core.types import PoseStream
import hypothesis.extra.numpy as hnp
import hypothesis.strategies as st
import numpy as np

#: Index of scipy's ``as_quat()`` (x, y, z, w) that gives (w, x, y, z): ``r.as_quat()[..., WXYZ]``.
WXYZ = [3, 0, 1, 2]


def scipy_rotation(q_wxyz):
    """
    Return scipy's Rotation of quaternions (w, x, y, z).

    scipy's ``scalar_first`` keyword needs scipy 1.14; the package supports scipy 1.11 (what
    ROS 2 Jazzy's Ubuntu 24.04 ships), so the tests reorder to scipy's (x, y, z, w) themselves.
    """
    from scipy.spatial.transform import Rotation
    q = np.asarray(q_wxyz, dtype=float)
    return Rotation.from_quat(q[..., [1, 2, 3, 0]])


def unit(v) -> np.ndarray:
    """Return ``v`` scaled to unit length."""
    v = np.asarray(v, dtype=float)
    return v / np.linalg.norm(v)


def random_quat(rng, n=None, *, canonical=False) -> np.ndarray:
    """Draw uniform unit quaternions (w, x, y, z), shape (4,) or (n, 4); canonical if asked."""
    q = rng.normal(size=(4,) if n is None else (n, 4))
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    return quat.canonical(q) if canonical else q


def random_rotation(rng, n=None) -> np.ndarray:
    """Draw uniform rotations as canonical unit quaternions (w ≥ 0), shape (4,) or (n, 4)."""
    return random_quat(rng, n, canonical=True)


def random_cov(rng, sig_pos, sig_rot, corr=0.5) -> np.ndarray:
    """Draw a random SPD 6×6: per-block scales sig_pos (m), sig_rot (rad), random correlations."""
    A = rng.normal(size=(6, 6))
    C = A @ A.T + corr * 6 * np.eye(6)
    d = np.sqrt(np.diag(C))
    C = C / np.outer(d, d)
    s = np.array([sig_pos] * 3 + [sig_rot] * 3) * rng.uniform(0.5, 1.5, 6)
    return C * np.outer(s, s)


def with_outliers(stream: PoseStream, share: float, rng, burst: bool = False) -> PoseStream:
    """Replace ``share`` of the samples by outliers (5-50 mm, 2-20°), scattered or in bursts."""
    n = len(stream)
    k = int(round(share * n))
    if burst:
        starts = rng.choice(n - 20, size=max(1, k // 20), replace=False)
        idx = np.unique(np.concatenate([np.arange(s, s + 20) for s in starts]))[:k]
    else:
        idx = rng.choice(n, size=k, replace=False)
    pos = stream.position.copy()
    q = stream.quat_wxyz.copy()
    direction = rng.normal(size=(idx.size, 3))
    direction /= np.linalg.norm(direction, axis=1, keepdims=True)
    pos[idx] += direction * rng.uniform(0.005, 0.05, size=(idx.size, 1))
    axis = rng.normal(size=(idx.size, 3))
    axis /= np.linalg.norm(axis, axis=1, keepdims=True)
    q[idx] = quat.multiply(quat.exp(axis * np.radians(rng.uniform(2, 20, size=(idx.size, 1)))),
                           q[idx])
    return replace(stream, position=pos, quat_wxyz=q)


def seconds(ns: int) -> str:
    """Format an int64 nanosecond stamp as exact decimal seconds."""
    return f'{ns // 10 ** 9}.{ns % 10 ** 9:09d}'


def write_csv(path, stream, *, order='xyzw', scale=1.0, header=None, sep=', ', invert=False):
    """Write ``stream`` as a CSV export (t, x, y, z, quaternion in ``order``); return the path."""
    p, q = stream.position, stream.quat_wxyz
    if invert:
        p, q = invert_poses(p, q)
    cols = q[:, [1, 2, 3, 0]] if order == 'xyzw' else q
    lines = [header] if header else []
    for t, pos, qq in zip(stream.stamps, p * scale, cols, strict=True):
        lines.append(sep.join([seconds(int(t))] + [repr(float(v)) for v in (*pos, *qq)]))
    Path(path).write_text('\n'.join(lines) + '\n')
    return str(path)


@st.composite
def axes(draw):
    """Draw unit rotation axes."""
    v = draw(hnp.arrays(np.float64, 3, elements=st.floats(-1.0, 1.0)))
    if np.linalg.norm(v) < 1e-3:
        v = np.array([0.3, -0.5, 0.8])
    return unit(v)


@st.composite
def quaternions(draw):
    """Draw unit quaternions: generic, near the identity, near 180°, exactly 180°, random sign."""
    kind = draw(st.sampled_from(['generic', 'identity', 'near_pi', 'pi']))
    if kind == 'generic':
        v = draw(hnp.arrays(np.float64, 4, elements=st.floats(-1.0, 1.0)))
        if np.linalg.norm(v) < 1e-3:
            v = np.array([0.1, 0.7, -0.2, 0.4])
        q = unit(v)
    else:
        axis = draw(axes())
        if kind == 'identity':
            angle = draw(st.floats(0.0, 1e-3))
        elif kind == 'near_pi':
            angle = np.pi - draw(st.floats(0.0, 1e-3))
        else:
            angle = np.pi
        q = np.concatenate([[np.cos(angle / 2)], np.sin(angle / 2) * axis])
    return q if draw(st.booleans()) else -q


@st.composite
def rotvecs(draw, max_angle=np.pi):
    """Draw rotation vectors: tiny, small, generic and near ``max_angle``."""
    axis = draw(axes())
    kind = draw(st.sampled_from(['tiny', 'small', 'generic', 'near_pi']))
    angle = {
        'tiny': lambda: draw(st.floats(0.0, 1e-7)),
        'small': lambda: draw(st.floats(1e-7, 1e-2)),
        'generic': lambda: draw(st.floats(1e-2, max_angle - 1e-2)),
        'near_pi': lambda: max_angle - draw(st.floats(1e-9, 1e-4)),
    }[kind]()
    return angle * axis
