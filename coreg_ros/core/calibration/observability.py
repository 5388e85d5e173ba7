"""
Observability of φ from the whitened Jacobian, and a plain-language account of what is missing.

The information matrix (JᵀJ for OLS, the Schur complement for TLS) is scaled to unit diagonal;
eigenvalues below ``RANK_TOLERANCE`` of the largest mark directions the data cannot determine
at all, and a posterior standard deviation above ``WEAK_POSITION_M`` / ``WEAK_ROTATION_RAD``
marks directions determined too poorly to be of use. Either way the calibration is refused with
the parameter direction named and the motion that would fix it.
"""

from __future__ import annotations

from coreg_ros.core import quaternion as quat
from coreg_ros.core.errors import UnobservableError
from coreg_ros.core.models import Parameters, tangent_of_chart
import numpy as np

RANK_TOLERANCE = 1e-10
WEAK_POSITION_M = 0.1
WEAK_ROTATION_RAD = 0.1
#: Rotation spread (rad, RMS about a principal axis) below which the tool counts as not turning.
STILL_RAD = 0.02
#: Orientations the motion check reads at most (every k-th, so the whole recording is seen):
#: an RMS spread from 100k of them is within ~0.2 % (1/√(2n)) of that of all, far inside the
#: margins of the limits, and a million-pair recording is checked in a tenth of the time.
MOTION_SAMPLE = 100_000

_BLOCK_NAMES = {
    'p0': 'base-to-base translation',
    's0': 'base-to-base rotation',
    's1': 'tool-to-marker rotation',
}


def _blocks(params: Parameters) -> dict:
    spec = params.spec
    out = {'p0': slice(0, 3), 's0': slice(3, 6)}
    for j in range(spec.n_markers):
        out[f'p{j + 1}'] = spec.marker_slice(j)
    if spec.has_q1:
        out['s1'] = slice(9, 12)
    return out


def _block_name(key: str, n_markers: int) -> str:
    if key in _BLOCK_NAMES:
        return _BLOCK_NAMES[key]
    if n_markers == 1:
        return 'tool-to-marker translation'
    return f'marker {key[1]} position'


def rotation_spread(quat_a: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """
    How the tool turned: RMS rotation (rad) about its principal axes, in A's tool frame.

    Rotation vectors are taken relative to the chordal mean orientation.

    Parameters
    ----------
    quat_a : ndarray, shape (N, 4)
        A's tool orientations.

    Returns
    -------
    spread : ndarray, shape (3,)
        Descending RMS angles about the principal axes.
    axes : ndarray, shape (3, 3)
        Rows are the principal axes (unit vectors in the tool frame).

    """
    q = np.asarray(quat_a, dtype=float)
    ref = quat.chordal_mean(q)
    # ref* ⊗ q for every pair as one matrix product, and its rotation vector as quat.log
    # (the same formula, written out to skip its copies): one pass instead of five
    r = q @ quat.left_matrix(quat.conjugate(ref)).T
    w = r[:, 0]
    r *= np.where(w < 0.0, -1.0, 1.0)[:, None]
    w = np.clip(r[:, 0], -1.0, 1.0)
    vec = r[:, 1:]
    s = np.sqrt(np.einsum('ij,ij->i', vec, vec))
    small = s < 1e-9
    k = np.where(small, 2.0 / np.maximum(w, 1e-300),
                 2.0 * np.arctan2(s, w) / np.where(small, 1.0, s))
    rotvecs = vec * k[:, None]  # tool-frame rotations
    rotvecs -= rotvecs.mean(axis=0)
    # principal axes from the 3×3 second moment (the right singular vectors of the N×3
    # matrix, without its SVD), each signed so that its largest component is positive; the
    # spread about each axis from the projections themselves, not the square root of an
    # eigenvalue, which would lift a spread of rounding size (1e-16) to 1e-8
    _, eigvec = np.linalg.eigh(rotvecs.T @ rotvecs)
    vt = eigvec[:, ::-1].T.copy()
    vt *= np.where(vt[np.arange(3), np.abs(vt).argmax(axis=1)] < 0.0, -1.0, 1.0)[:, None]
    proj = rotvecs @ vt.T
    sv = np.sqrt(np.einsum('ij,ij->j', proj, proj) / len(rotvecs))
    return sv, vt


def _still_limit(sigma_rot_a: float) -> float:
    """Rotation spread (rad) that is indistinguishable from no rotation at A's noise level."""
    return max(STILL_RAD, 5.0 * sigma_rot_a)


def describe_motion(quat_a: np.ndarray, sigma_rot_a: float = 0.0) -> str:
    """One phrase on what the rotation of device A's tool lacks."""
    spread, axes = rotation_spread(quat_a)
    still = _still_limit(sigma_rot_a)
    if spread[0] < still:
        return (f"device A's tool hardly rotated ({np.degrees(spread[0]):.1f}° RMS): rotate it "
                'about at least two different axes while recording')
    if spread[1] < max(still, 0.1 * spread[0]):
        a = axes[0]
        return (f'rotation about only one axis (tool axis [{a[0]:.2f}, {a[1]:.2f}, {a[2]:.2f}]): '
                f'rotate about a second axis')
    deg = np.degrees(spread)
    return (f'the recorded rotations (RMS {deg[0]:.1f}°, {deg[1]:.1f}°, {deg[2]:.1f}° about the '
            f'principal axes) are too small or too few: rotate the tool more widely about all '
            f'three axes')


def check_motion(quat_a: np.ndarray, spec, sigma_rot_a: float) -> None:
    """
    Refuse motion whose rotations leave parameters unobservable, before any fitting.

    Rotation about a single tool axis hides the marker offset(s) along that axis (their
    rotated image is constant, absorbed by p0); no rotation at all also hides the split of
    orientation between T0 and T1. Variation at the level of A's rotation noise is no
    rotation: under OLS it would lend spurious information to exactly those directions.

    Parameters
    ----------
    quat_a : ndarray, shape (N, 4)
        A's tool orientations.
    spec : ModelSpec
        The measurement model.
    sigma_rot_a : float
        Device A's rotation noise, rad.

    """
    spread, axes = rotation_spread(quat_a[::max(1, len(quat_a) // MOTION_SAMPLE)])
    still = _still_limit(sigma_rot_a)
    one = spec.n_markers == 1
    offsets = 'tool-to-marker translation' if one else 'the marker positions in the tool frame'
    verb = 'is' if one else 'are'
    if spread[0] < still:
        lost = [f'{offsets} {verb} unobservable']
        if spec.has_q1:
            lost.append('the rotation split between base-to-base and tool-to-marker is '
                        'unobservable')
        raise UnobservableError(
            f"device A's tool hardly rotated ({np.degrees(spread[0]):.2f}° RMS, noise-level "
            f"limit {np.degrees(still):.2f}°): {'; '.join(lost)}; rotate the tool about at "
            f'least two different axes while recording', directions=lost)
    if spread[1] < still:
        a = axes[0]
        lost = [f'{offsets} along that axis {verb} unobservable']
        raise UnobservableError(
            f'rotation about only one axis (tool axis [{a[0]:.2f}, {a[1]:.2f}, {a[2]:.2f}], '
            f'{np.degrees(spread[1]):.2f}° RMS about any other): {lost[0]}; rotate about a '
            f'second axis', directions=lost)


def check_observability(info: np.ndarray, params: Parameters, quat_a: np.ndarray) -> None:
    """
    Refuse (UnobservableError) when the data leave a direction of φ undetermined.

    Parameters
    ----------
    info : ndarray, shape (P, P)
        Information matrix of φ (whitened JᵀJ or the TLS Schur complement).
    params : Parameters
        The estimate (for the units of the rotation coordinates).
    quat_a : ndarray, shape (N, 4)
        Device A's tool orientations, to explain which motion is missing.

    """
    spec = params.spec
    blocks = _blocks(params)
    d = np.sqrt(np.clip(np.diag(info), 0.0, None))
    problems = []
    if (d == 0).any():
        scaled = np.eye(len(d))
    else:
        scaled = info / np.outer(d, d)
    w, V = np.linalg.eigh(scaled)
    for k in np.flatnonzero(w <= RANK_TOLERANCE * w[-1]):
        u = V[:, k] / np.where(d > 0, d, 1.0)
        problems.append(_direction_phrase(u, blocks, spec.n_markers, params, 'unobservable'))
    if not problems and (d > 0).all():
        cov = np.linalg.inv(info)
        sd = np.sqrt(np.clip(np.diag(cov), 0.0, None))
        for key, sl in blocks.items():
            if key.startswith('p'):
                worst = float(sd[sl].max())
                if worst > WEAK_POSITION_M:
                    problems.append(
                        f'{_block_name(key, spec.n_markers)} is barely observable '
                        f'(σ = {worst:.2g} m)')
            else:
                q, dq = (params.q0, params.dq0) if key == 's0' else (params.q1, params.dq1)
                G = tangent_of_chart(q, dq)
                c = G @ cov[sl, sl] @ G.T
                worst = float(np.sqrt(max(np.linalg.eigvalsh(c).max(), 0.0)))
                if worst > WEAK_ROTATION_RAD:
                    problems.append(
                        f'{_block_name(key, spec.n_markers)} is barely observable '
                        f'(σ = {np.degrees(worst):.2g}°)')
    if (d == 0).any():
        for key, sl in blocks.items():
            if (d[sl] == 0).any():
                problems.append(f'{_block_name(key, spec.n_markers)} is unobservable')
    if problems:
        unique = list(dict.fromkeys(problems))
        raise UnobservableError(
            f'{describe_motion(quat_a)}; {"; ".join(unique)}', directions=unique)


def _direction_phrase(u: np.ndarray, blocks: dict, n_markers: int, params: Parameters,
                      what: str) -> str:
    """Name the parameter block that dominates a null direction and the axis along it."""
    weights = {key: float(np.linalg.norm(u[sl])) for key, sl in blocks.items()}
    # a translation of T1 along the axis is what single-axis rotation cannot see; prefer
    # naming the tool-side block, whose direction is meaningful in the tool frame
    key = max(weights, key=lambda k: (weights[k] * (2.0 if k not in ('p0', 's0') else 1.0)))
    v = u[blocks[key]]
    v = v / (np.linalg.norm(v) or 1.0)
    if key.startswith('s'):
        q, dq = (params.q0, params.dq0) if key == 's0' else (params.q1, params.dq1)
        v = tangent_of_chart(q, dq) @ v
        v = v / (np.linalg.norm(v) or 1.0)
        frame = "B's base frame" if key == 's0' else 'the tool frame'
        return (f'{_block_name(key, n_markers)} about axis [{v[0]:.2f}, {v[1]:.2f}, {v[2]:.2f}] '
                f'({frame}) is {what}')
    frame = "B's base frame" if key == 'p0' else 'the tool frame'
    return (f'{_block_name(key, n_markers)} along [{v[0]:.2f}, {v[1]:.2f}, {v[2]:.2f}] '
            f'({frame}) is {what}')
