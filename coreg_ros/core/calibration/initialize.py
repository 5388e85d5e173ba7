"""
Closed-form initial estimates, so that no initial guess is ever needed.

All solves are O(N) accumulations into small matrices followed by an SVD:

- full pose: rotations from ``R0 R_Ai = R_Bi R1ᵀ``, a bilinear problem whose relaxed solution
  is the top singular pair of a 9×9 matrix (the Kronecker form of the rotation equations),
  each factor projected onto SO(3); then p0, p1 by linear least squares. When the tool turns
  about one axis or not at all (a SCARA arm, a turntable, a gantry), the rotations alone
  leave R0 open along a family (the top singular value is not unique). About one axis a (A's
  base frame), B's rotations turn about b = R0 a: R0 is the rotation taking a to b, then
  about b by the angle whose linear least squares of the positions fit best (a search over
  the circle); without rotation R0 comes from the positions, as for position only; R1 from
  the rotations given R0;
- position only: a linear lifting ``p_B = p0 + R0 p_A + G vec(R_A)`` with G = R0 ⊗ p1ᵀ
  (13 regressors per axis), R0 projected onto SO(3), then p0, p1 by linear least squares;
- three markers: the lifting per marker, the R0 estimates averaged on SO(3), then p0 and the
  three marker positions jointly.
"""

from __future__ import annotations

from coreg_ros.core import quaternion as quat
from coreg_ros.core.models import ModelSpec, Parameters
from coreg_ros.core.so3 import skew
import numpy as np


def project_to_so3(M: np.ndarray) -> np.ndarray:
    """Nearest rotation matrix (Frobenius norm) to a 3×3 matrix, via its SVD."""
    U, _, Vt = np.linalg.svd(M)
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt)) or 1.0])
    return U @ D @ Vt


#: The rotations alone determine R0 and R1 unless the second singular value of the Kronecker
#: matrix is this close to the first (1 within rounding for rotation about one axis or none;
#: 0.84-0.92 for motion about every axis).
DEGENERATE_RATIO = 0.995


def rotations_from_pairs(Ra: np.ndarray, Rb: np.ndarray
                         ) -> tuple[np.ndarray, np.ndarray, float]:
    """
    R0, R1 minimising Σ ‖R0 R_Ai - R_Bi R1ᵀ‖², relaxed to a rank-one problem.

    With X = R0 and Z = R1ᵀ, ``Σ tr(R_Aiᵀ Xᵀ R_Bi Z) = vec(X)ᵀ K vec(Z)``, so the relaxed
    optimum is the top singular pair of K (9×9), accumulated as one BLAS product over the pairs.

    Parameters
    ----------
    Ra, Rb : ndarray, shape (N, 3, 3)
        Rotation matrices of A's tool and B's marker poses.

    Returns
    -------
    R0, R1 : ndarray, shape (3, 3)
    ratio : float
        Second over first singular value: near 1 the rotations do not determine the pair.

    """
    P = rotation_moments(Ra, Rb)
    K = P.transpose(2, 0, 3, 1).reshape(9, 9)  # K[(l, k), (m, j)] = P[k, j, l, m]
    U, sv, Vt = np.linalg.svd(K)
    X, Z = U[:, 0].reshape(3, 3), Vt[0].reshape(3, 3)
    if np.linalg.det(X) < 0:  # the singular pair's joint sign is arbitrary
        X, Z = -X, -Z
    ratio = float(sv[1] / sv[0]) if sv[0] > 0 else 1.0
    return project_to_so3(X), project_to_so3(Z).T, ratio


def rotation_moments(Ra: np.ndarray, Rb: np.ndarray) -> np.ndarray:
    """
    Return ``P[k, j, l, m] = Σ_i Ra[i, k, j] Rb[i, l, m]``, shape (3, 3, 3, 3): one BLAS product.

    Every sum over the pairs of products of an A and a B rotation entry is a contraction of P.
    """
    n = len(Ra)
    return (Ra.reshape(n, 9).T @ Rb.reshape(n, 9)).reshape(3, 3, 3, 3)


def _translations(R0: np.ndarray, Ra: np.ndarray, pos_a: np.ndarray, pos_b: np.ndarray):
    """
    p0 and marker positions p_j by linear least squares given R0.

    ``p_Bj - R0 p_A = p0 + (R0 R_A) p_j`` for every marker j; normal equations of size 3(k+1).

    Parameters
    ----------
    R0 : ndarray, shape (3, 3)
        The base-to-base rotation.
    Ra : ndarray, shape (N, 3, 3)
        A's tool orientations.
    pos_a : ndarray, shape (N, 3)
        A's tool positions, m.
    pos_b : ndarray, shape (N, k, 3)
        B's positions of the k markers, m.

    """
    n, k = pos_b.shape[0], pos_b.shape[1]
    M = R0 @ Ra  # (N, 3, 3)
    d = pos_b - (pos_a @ R0.T)[:, None, :]  # (N, k, 3)
    dim = 3 * (k + 1)
    A = np.zeros((dim, dim))
    rhs = np.zeros(dim)
    A[0:3, 0:3] = k * n * np.eye(3)
    rhs[0:3] = d.sum(axis=(0, 1))
    sum_m = M.sum(axis=0)
    for j in range(k):
        sl = slice(3 + 3 * j, 6 + 3 * j)
        A[0:3, sl] = sum_m
        A[sl, 0:3] = sum_m.T
        A[sl, sl] = n * np.eye(3)  # Σ MᵢᵀMᵢ = N·I for rotations
        rhs[sl] = np.einsum('nab,na->b', M, d[:, j, :])
    sol = np.linalg.lstsq(A, rhs, rcond=1e-12)[0]
    return sol[0:3], sol[3:].reshape(k, 3)


#: A direction of A's positions counts as moving apart from A's rotations when its RMS, after
#: what the rotations (and a constant) explain is taken out, is at least this share of the
#: positions' largest RMS spread.
LIFT_SHARE = 1e-2


def _lifted_rotation(Ra: np.ndarray, pos_a: np.ndarray, pos_b: np.ndarray) -> np.ndarray:
    """
    R0 from the linear lifting of the position-only model (13 regressors per axis).

    When the tool turns about one axis a (a SCARA arm, a mobile robot, a turntable), the
    lifting gives R0 only along the directions in which A's positions move apart from what
    A's rotations explain (its other columns are noise: a mobile robot's constant height is
    the intercept's); R0 then also takes a to the normal b of the circle B's marker
    describes (``_axis_correspondence``). On a turntable (the tool's positions turn with its
    rotations) the rotation about b is what the data leave open, and the fit holds it.
    """
    n = len(Ra)
    Phi = np.concatenate([np.ones((n, 1)), pos_a, Ra.reshape(n, 9)], axis=1)
    scale = np.maximum(np.abs(Phi).max(axis=0), 1e-12)  # column scaling for conditioning
    theta = np.linalg.lstsq(Phi / scale, pos_b, rcond=1e-12)[0] / scale[:, None]
    M = theta[1:4].T
    if not turns_about_one_axis(Ra):
        return project_to_so3(M)
    others = np.concatenate([np.ones((n, 1)), Ra.reshape(n, 9)], axis=1)
    apart = pos_a - others @ np.linalg.lstsq(others, pos_a, rcond=1e-9)[0]
    _, sv, vt = np.linalg.svd(apart, full_matrices=False)
    spread = np.linalg.svd(pos_a - pos_a.mean(axis=0), compute_uv=False)[0]
    moving = sv > LIFT_SHARE * max(float(spread), 1e-300)
    if moving.all():
        return project_to_so3(M)
    M = M @ (vt[moving].T @ vt[moving])  # the lifting's R0 along these directions only
    pair = _axis_correspondence(Ra, pos_b)
    if pair is not None:
        a, b = pair
        M = M + np.outer(b, a)
    return project_to_so3(M)  # two directions fix R0 (the third by the determinant)


def _axis_correspondence(Ra: np.ndarray, pos_b: np.ndarray):
    """
    Return (a, b): A's rotation axis a (A's base frame) and b = R0 a, or None.

    For a tool that turns about one axis a (``turns_about_one_axis``), the marker's positions
    in B describe ``c + cos θ U + sin θ V`` (θ the angle about a) with ``U × V`` along
    ``R0 a``: the marker's offset from the axis turns about it. None when the tool does not
    turn, or the marker does not go round (it sits on the axis).
    """
    a, angle = principal_axis(Ra)
    if float(np.sqrt(np.mean(angle ** 2))) < TURNING_RAD:
        return None
    Z = np.stack([np.ones_like(angle), np.cos(angle), np.sin(angle)], axis=1)
    coef = np.linalg.lstsq(Z, pos_b[::axis_stride(len(Ra))], rcond=1e-9)[0]
    b = np.cross(coef[1], coef[2])
    norm = float(np.linalg.norm(b))
    if norm <= 1e-12:
        return None
    return a, b / norm


#: Angles tried about the rotation axis when the rotations leave R0 open about it (0.1°; the
#: fit refines).
AXIS_ANGLES = 3600
#: Rotation (rad, RMS about the principal axis) below which the tool counts as not turning.
TURNING_RAD = 0.02


#: Rotations (every k-th) the axis of a tool that turns about one axis is read from: the
#: principal axis of 5k rotation vectors is as good as that of all, at a fraction of the cost.
AXIS_SAMPLE = 5_000


def axis_stride(n: int) -> int:
    """Return k: every k-th of n rotations is read for the axis (``AXIS_SAMPLE``)."""
    return max(1, n // AXIS_SAMPLE)


def _relative_rotation_vectors(R: np.ndarray) -> np.ndarray:
    """Rotation vectors of ``R_i R_refᵀ`` (base frame) of every ``axis_stride``-th rotation."""
    R = R[::axis_stride(len(R))]
    return quat.log(quat.from_matrix(R @ R[0].T))


def principal_axis(R: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """
    Return the axis (base frame) rotations R (N, 3, 3) turn about most, and the angles about it.

    From the rotation vectors of ``R_i R_refᵀ`` (ref: the first), centred; the angles are their
    projections on the axis, so two such series can be compared for sign. Both are read from
    every ``axis_stride(N)``-th rotation: the angles are those of ``R[::axis_stride(N)]``.
    """
    rel = _relative_rotation_vectors(R)
    rel = rel - rel.mean(axis=0)
    _, _, vt = np.linalg.svd(rel, full_matrices=False)
    return vt[0], rel @ vt[0]


#: The tool turns about one axis when the rotation vectors' second principal spread is below
#: this share of the first.
ONE_AXIS_SHARE = 1e-2


def turns_about_one_axis(R: np.ndarray) -> bool:
    """Tell whether rotations R (N, 3, 3) turn about one axis only (``ONE_AXIS_SHARE``)."""
    rel = _relative_rotation_vectors(R)
    sv = np.linalg.svd(rel - rel.mean(axis=0), compute_uv=False)
    return bool(sv[0] > 0 and sv[1] <= ONE_AXIS_SHARE * sv[0])


def _rotation_taking(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Return the smallest rotation taking unit vector a to unit vector b (Rodrigues)."""
    v, c = np.cross(a, b), float(np.dot(a, b))
    if c < -1.0 + 1e-12:  # opposite: half a turn about any axis orthogonal to a
        ortho = np.cross(a, [1.0, 0.0, 0.0] if abs(a[0]) < 0.9 else [0.0, 1.0, 0.0])
        ortho /= np.linalg.norm(ortho)
        return 2.0 * np.outer(ortho, ortho) - np.eye(3)
    vx = skew(v)
    return np.eye(3) + vx + vx @ vx / (1.0 + c)


def _axis_aligned_r0(Ra: np.ndarray, Rb: np.ndarray, pos_a: np.ndarray,
                     pos_b: np.ndarray) -> np.ndarray:
    """
    R0 when the tool turns about one axis only (the rotations determine R0 up to that axis).

    ``R_Bi R_Bjᵀ = R0 (R_Ai R_Ajᵀ) R0ᵀ``: B turns about b = R0 a, so R0 = Rot(b, φ) · R_ab
    (R_ab takes a to b). φ is the angle whose linear least squares of p0 and p1 leaves the
    smallest position residual. In A's base frame the residual of pair i is
    ``y_i(φ) - R0ᵀp0 - R_Ai p1`` with ``y_i(φ) = R0ᵀ p_Bi - p_Ai``: the regressors do not
    depend on φ, and ``y(φ) = u0 + cos φ u1 + sin φ u2`` (Rodrigues), so the least squares
    residual is the quadratic form ``vᵀ G v`` of v = (1, cos φ, sin φ) with the 3×3 G of
    the u's projected off the regressors: one pass over every ``axis_stride``-th pair, then
    ``AXIS_ANGLES`` angles for nothing. Where the positions do not determine φ either (a
    turntable), any angle is as good, and the fit holds that direction.
    """
    a, angle_a = principal_axis(Ra)
    b, angle_b = principal_axis(Rb)
    if np.dot(angle_a, angle_b) < 0:  # the two axes' signs must turn the same way
        b = -b
    base = _rotation_taking(a, b)
    k = axis_stride(len(Ra))  # the angle from as many pairs as the axis (the fit refines)
    Ra, pos_a, pos_b = Ra[::k], pos_a[::k], pos_b[::k]
    bx = skew(b)
    # y(φ) = baseᵀ Rot(b, -φ) p_B - p_A, Rot(b, -φ) = (I + B²) - cos φ B² - sin φ B
    u = np.stack([pos_b @ (base.T @ (np.eye(3) + bx @ bx)).T - pos_a,
                  -pos_b @ (base.T @ bx @ bx).T, -pos_b @ (base.T @ bx).T])  # (3, N, 3)
    n = len(Ra)
    xtx = np.block([[n * np.eye(3), Ra.sum(axis=0)], [Ra.sum(axis=0).T, n * np.eye(3)]])
    xtu = np.concatenate([u.sum(axis=1), np.einsum('nji,knj->ki', Ra, u)], axis=1)  # (3, 6)
    gram = np.einsum('kni,lni->kl', u, u) - xtu @ np.linalg.pinv(xtx) @ xtu.T
    phi = np.linspace(0.0, 2.0 * np.pi, AXIS_ANGLES, endpoint=False)
    v = np.stack([np.ones_like(phi), np.cos(phi), np.sin(phi)])
    best = phi[int(np.argmin(np.einsum('kp,kl,lp->p', v, gram, v)))]
    return (np.eye(3) + np.sin(best) * bx + (1.0 - np.cos(best)) * bx @ bx) @ base


def initialize(spec: ModelSpec, pos_a, quat_a, pos_b, quat_b=None) -> Parameters:
    """
    Closed-form estimate of φ from the pairs, for any T0, T1 over SO(3).

    Parameters
    ----------
    spec : ModelSpec
        The measurement model.
    pos_a : ndarray, shape (N, 3)
        A's tool positions, m.
    quat_a : ndarray, shape (N, 4)
        A's tool orientations.
    pos_b : ndarray, shape (N, 3) or (N, 3, 3)
        B's marker position(s), m.
    quat_b : ndarray, shape (N, 4), optional (full pose)
        B's marker orientations.

    Returns
    -------
    params : Parameters
        In the charts of the estimate's largest quaternion components.

    """
    Ra = quat.to_matrix(quat_a)
    pos_b3 = pos_b if pos_b.ndim == 3 else pos_b[:, None, :]
    q1 = None
    if spec.has_q1:
        Rb = quat.to_matrix(quat_b)
        R0, R1, ratio = rotations_from_pairs(Ra, Rb)
        if ratio > DEGENERATE_RATIO:  # rotation about one axis or none: R0 from the positions
            turning = _relative_rotation_vectors(Ra).std(axis=0).max() > TURNING_RAD
            k = axis_stride(len(Ra))  # no rotation: R0 from the positions of a sample
            R0 = (_axis_aligned_r0(Ra, Rb, pos_a, pos_b3[:, 0, :]) if turning else
                  _lifted_rotation(Ra[::k], pos_a[::k], pos_b3[::k, 0, :]))
            # R1 from Σ (R0 R_A)ᵀ R_B = Σ_ja R0[j, a] P[a, i, j, m]: no pass over the pairs
            R1 = project_to_so3(np.einsum('ja,aijm->im', R0, rotation_moments(Ra, Rb)))
        q1 = quat.from_matrix(R1)
    else:
        rotations = [_lifted_rotation(Ra, pos_a, pos_b3[:, j, :]) for j in range(pos_b3.shape[1])]
        R0 = project_to_so3(np.sum(rotations, axis=0))
    p0, markers = _translations(R0, Ra, pos_a, pos_b3)
    return Parameters.from_transforms(spec, p0, quat.from_matrix(R0), markers, q1)
