"""
Unit quaternions in (w, x, y, z) order, rotation matrices and the reduced quaternion.

Every function is vectorised over leading axes: a quaternion argument has shape ``(..., 4)``
in (w, x, y, z) order (Hamilton convention, active rotation), a rotation matrix ``(..., 3, 3)``,
a rotation vector ``(..., 3)`` in radians. ROS messages carry (x, y, z, w); that order appears
only at the message boundary (``coreg_ros.files.bag`` and ``coreg_ros.ros``).

References
----------
Ikits, M. (2000). Coregistration of pose measurement devices using nonlinear least squares
parameter estimation. UUCS-00-018. Section 3.1 (reduced quaternion, eqs. 7-10), section 3.2
(error metric, eqs. 11-15), appendix A (rotation matrix, eq. 21).

"""

from __future__ import annotations

from coreg_ros.core.errors import InputError
import numpy as np

#: Largest accepted deviation of a measured quaternion's norm from 1 before it is refused.
UNIT_NORM_TOLERANCE = 1e-2

#: For a reduced quaternion with chart k (the index of the component computed from the unit
#: constraint), the indices of the three free components s, in order (Ikits eq. 7).
CHART_OTHERS = np.array([[1, 2, 3], [0, 2, 3], [0, 1, 3], [0, 1, 2]])


def validate_quaternions(q, name: str = 'quaternion') -> np.ndarray:
    """
    Check measured quaternions and return them normalised, in canonical sign (w >= 0).

    Parameters
    ----------
    q : array_like, shape (..., 4)
        Quaternions in (w, x, y, z) order.
    name : str
        What the quaternions are, used in the error message.

    Returns
    -------
    q : ndarray, shape (..., 4)
        Unit quaternions with w >= 0.

    Raises
    ------
    InputError
        If the shape is wrong, a value is NaN or infinite, or a norm differs from 1 by more
        than ``UNIT_NORM_TOLERANCE`` (a zero or malformed quaternion, or a wrong field order).

    """
    q = np.asarray(q, dtype=float)
    if q.ndim == 0 or q.shape[-1] != 4:
        raise InputError(f'{name}: expected shape (..., 4) in (w, x, y, z) order, got {q.shape}')
    finite = np.isfinite(q).all(axis=-1)
    if not finite.all():
        first = int(np.flatnonzero(~finite.reshape(-1))[0])
        raise InputError(
            f'{name}: {int((~finite).sum())} quaternion(s) contain NaN or inf (first at index '
            f'{first}); drop those samples before calibrating')
    with np.errstate(over='ignore', invalid='ignore'):  # 1e300 components: norm inf, said below
        norm = np.linalg.norm(q, axis=-1)
    bad = ~(np.abs(norm - 1.0) <= UNIT_NORM_TOLERANCE)
    if bad.any():
        first = int(np.flatnonzero(bad.reshape(-1))[0])
        raise InputError(
            f'{name}: {int(bad.sum())} quaternion(s) are not unit length (first at index '
            f'{first}, norm {norm.reshape(-1)[first]:.4g}); check the field order '
            f'(w, x, y, z inside, x, y, z, w in ROS messages) and drop zero quaternions')
    # stored row by row whatever the input's layout (a bag's columns come transposed): every
    # later pass reads whole quaternions, which a column layout scatters 4 × N apart
    return canonical(np.divide(q, norm[..., None], order='C'))


def unit_quaternions(q, name: str = 'quaternion') -> np.ndarray:
    """
    ``validate_quaternions`` in one pass for the usual (N, 4) finite, unit-length input.

    Anything else goes to ``validate_quaternions``, which says what is wrong.

    Parameters
    ----------
    q : array_like, shape (N, 4)
        Measured quaternions (w, x, y, z).
    name : str
        What the quaternions are, used in the error message.

    """
    q = np.asarray(q, dtype=float)
    if q.ndim == 2 and q.shape[1] == 4 and np.isfinite(q).all():
        norm = np.sqrt(np.einsum('ij,ij->i', q, q))
        if (np.abs(norm - 1.0) <= UNIT_NORM_TOLERANCE).all():
            # normalised, w >= 0 (canonical), in one division
            return q / (norm * np.where(q[:, 0] < 0.0, -1.0, 1.0))[:, None]
    return validate_quaternions(q, name)


def normalised(q: np.ndarray) -> np.ndarray:
    """
    Return quaternions (N, 4) divided by their norms, in place (unit to rounding).

    For quaternions unit up to a few rounding errors (a slerp's), as ``unit_quaternions``
    divides them; q itself is returned, changed.
    """
    q /= np.sqrt(np.einsum('ij,ij->i', q, q))[:, None]
    return q


def canonical(q: np.ndarray) -> np.ndarray:
    """
    Return the sign-canonical representative (w >= 0) of each quaternion, shape (..., 4).

    q and -q are the same rotation; where a sign must be chosen we keep w >= 0.
    """
    q = np.asarray(q, dtype=float)
    return np.where(q[..., :1] < 0.0, -q, q)


def multiply_parts(p, q) -> tuple:
    """
    Hamilton product p ⊗ q on components: p, q are (w, x, y, z) sequences of arrays.

    The layout-free core of ``multiply``; ``estimator.normal_equations`` calls it on pair-last
    arrays (4, c).
    """
    pw, px, py, pz = p
    qw, qx, qy, qz = q
    return (pw * qw - px * qx - py * qy - pz * qz,
            pw * qx + px * qw + py * qz - pz * qy,
            pw * qy - px * qz + py * qw + pz * qx,
            pw * qz + px * qy - py * qx + pz * qw)


def multiply(p: np.ndarray, q: np.ndarray) -> np.ndarray:
    """
    Hamilton product p ⊗ q of quaternions in (w, x, y, z) order, shapes broadcast to (..., 4).

    With active rotations, ``R(p ⊗ q) = R(p) R(q)``.
    """
    p = np.moveaxis(np.asarray(p, dtype=float), -1, 0)
    q = np.moveaxis(np.asarray(q, dtype=float), -1, 0)
    return np.stack(multiply_parts(p, q), axis=-1)


def conjugate(q: np.ndarray) -> np.ndarray:
    """Return the quaternion conjugate, the inverse of a unit quaternion; shape (..., 4)."""
    q = np.asarray(q, dtype=float)
    return q * np.array([1.0, -1.0, -1.0, -1.0])


def _stacked(rows) -> np.ndarray:
    """
    Return matrices (..., r, c) from rows of entries, each a scalar or an array of shape (...).

    One matrix (scalar entries) is made directly: stacking arrays of one entry each costs
    several times the arithmetic, and the fits make such small matrices by the thousand.
    """
    if np.ndim(rows[0][0]) == 0:
        return np.array(rows, dtype=float)
    return np.stack([np.stack(row, axis=-1) for row in rows], axis=-2)


def left_matrix(q: np.ndarray) -> np.ndarray:
    """
    Matrix L(q), shape (..., 4, 4), such that ``q ⊗ p = L(q) p``.

    Used for derivatives of products with respect to the right operand.
    """
    q = np.asarray(q, dtype=float)
    w, x, y, z = q if q.shape == (4,) else np.moveaxis(q, -1, 0)
    return _stacked([[w, -x, -y, -z], [x, w, -z, y], [y, z, w, -x], [z, -y, x, w]])


def right_matrix(q: np.ndarray) -> np.ndarray:
    """
    Matrix R(q), shape (..., 4, 4), such that ``p ⊗ q = R(q) p``.

    Used for derivatives of products with respect to the left operand.
    """
    q = np.asarray(q, dtype=float)
    w, x, y, z = q if q.shape == (4,) else np.moveaxis(q, -1, 0)
    return _stacked([[w, -x, -y, -z], [x, w, z, -y], [y, -z, w, x], [z, y, -x, w]])


def matrix_parts(w, x, y, z) -> tuple:
    """
    Entries of the rotation matrix of unit quaternions (Ikits eq. 21), as 3 rows of 3 arrays.

    The layout-free core of ``to_matrix``.
    """
    ww, xx, yy, zz = w * w, x * x, y * y, z * z
    xy, xz, yz, wx, wy, wz = x * y, x * z, y * z, w * x, w * y, w * z
    return ((ww + xx - yy - zz, 2 * (xy - wz), 2 * (xz + wy)),
            (2 * (xy + wz), ww - xx + yy - zz, 2 * (yz - wx)),
            (2 * (xz - wy), 2 * (yz + wx), ww - xx - yy + zz))


def to_matrix(q: np.ndarray, pair_last: bool = False) -> np.ndarray:
    """
    Rotation matrix of unit quaternions (Ikits eq. 21), shape (..., 3, 3).

    Parameters
    ----------
    q : ndarray, shape (..., 4), or (4, c) with ``pair_last``
        Unit quaternions (w, x, y, z).
    pair_last : bool
        Quaternions as columns (4, c) and matrices (3, 3, c), the structure-of-arrays layout
        of ``estimator.normal_equations``.

    """
    if pair_last:
        R = np.empty((3, 3, q.shape[1]))
        for i, row in enumerate(matrix_parts(*q)):
            for j, entry in enumerate(row):
                R[i, j] = entry
        return R
    q = np.asarray(q, dtype=float)
    return _stacked(matrix_parts(*(q if q.shape == (4,) else np.moveaxis(q, -1, 0))))


def from_matrix(R: np.ndarray) -> np.ndarray:
    """
    Convert rotation matrices (..., 3, 3) to unit quaternions (..., 4) with w >= 0.

    Uses the largest of the four squared components for numerical stability (Shepperd).
    """
    R = np.asarray(R, dtype=float)
    m00, m11, m22 = R[..., 0, 0], R[..., 1, 1], R[..., 2, 2]
    candidates = np.stack([
        1.0 + m00 + m11 + m22, 1.0 + m00 - m11 - m22,
        1.0 - m00 + m11 - m22, 1.0 - m00 - m11 + m22], axis=-1)
    k = np.argmax(candidates, axis=-1)
    t = np.sqrt(np.maximum(np.take_along_axis(candidates, k[..., None], -1)[..., 0], 1e-300))
    d = 0.5 / t
    r21_12, r02_20, r10_01 = R[..., 2, 1] - R[..., 1, 2], R[..., 0, 2] - R[..., 2, 0], \
        R[..., 1, 0] - R[..., 0, 1]
    r10p01, r02p20, r21p12 = R[..., 1, 0] + R[..., 0, 1], R[..., 0, 2] + R[..., 2, 0], \
        R[..., 2, 1] + R[..., 1, 2]
    rows = (lambda: (0.5 * t, r21_12 * d, r02_20 * d, r10_01 * d),
            lambda: (r21_12 * d, 0.5 * t, r10p01 * d, r02p20 * d),
            lambda: (r02_20 * d, r10p01 * d, 0.5 * t, r21p12 * d),
            lambda: (r10_01 * d, r02p20 * d, r21p12 * d, 0.5 * t))
    if R.shape == (3, 3):  # one matrix: only the chosen row is made
        q = np.array(rows[int(k)]())
    else:
        q = np.select([k[..., None] == 0, k[..., None] == 1, k[..., None] == 2],
                      [np.stack(rows[i](), axis=-1) for i in range(3)],
                      np.stack(rows[3](), axis=-1))
    return canonical(q / np.linalg.norm(q, axis=-1, keepdims=True))


def exp_parts(x, y, z) -> tuple:
    """
    Return the unit quaternion (w, x, y, z) of rotation vectors given by components, rad.

    The layout-free core of ``exp``; accurate near zero angle (Taylor series of sin(θ/2)/θ).
    """
    theta2 = x * x + y * y + z * z
    theta = np.sqrt(theta2)
    small = theta < 1e-6
    safe = np.where(small, 1.0, theta)
    k = np.where(small, 0.5 - theta2 / 48.0, np.sin(0.5 * safe) / safe)
    return np.cos(0.5 * theta), k * x, k * y, k * z


def exp(rotvec: np.ndarray) -> np.ndarray:
    """
    Map rotation vectors (axis times angle, rad), shape (..., 3), to unit quaternions (..., 4).

    Accurate near zero angle (Taylor series of sin(θ/2)/θ).
    """
    v = np.moveaxis(np.asarray(rotvec, dtype=float), -1, 0)
    return np.stack(exp_parts(*v), axis=-1)


def log(q: np.ndarray) -> np.ndarray:
    """
    Rotation vector (rad) of unit quaternions, shape (..., 4) -> (..., 3), angle in [0, π].

    q and -q give the same rotation vector, except at exactly π (w = 0) where the two results
    are opposite vectors, both of angle π: the same rotation.
    """
    q = canonical(q)
    vec = q[..., 1:]
    return _log_scale(q[..., 0], np.linalg.norm(vec, axis=-1))[..., None] * vec


def _log_scale(w: np.ndarray, s: np.ndarray) -> np.ndarray:
    """
    θ / |v| of canonical quaternions (w >= 0) from w and s = |v|: ``log``'s factor on v.

    Accurate as s -> 0 (the limit 2 / w).
    """
    w = np.clip(w, -1.0, 1.0)
    theta = 2.0 * np.arctan2(s, w)
    small = s < 1e-9
    return np.where(small, 2.0 / np.maximum(w, 1e-300), theta / np.where(small, 1.0, s))


def relative_log(q1: np.ndarray, q0: np.ndarray) -> np.ndarray:
    """
    Rotation vector of q1 ⊗ q0* (rad), shapes (N, 4), (N, 4) -> (N, 3).

    ``log(multiply(q1, conjugate(q0)))`` to the bit, on the components: without the (N, 4)
    temporaries of the composed functions (a velocity from a million poses makes several).
    """
    a, b = np.asarray(q1, dtype=float).T, np.asarray(q0, dtype=float).T
    w, x, y, z = multiply_parts(a, (b[0], -b[1], -b[2], -b[3]))
    # log's canonical sign (w >= 0), an exact negation
    flip = w < 0.0
    for part in (w, x, y, z):
        np.negative(part, out=part, where=flip)
    k = _log_scale(w, np.sqrt(x * x + y * y + z * z))
    out = np.empty((a.shape[1], 3))
    for i, part in enumerate((x, y, z)):
        np.multiply(k, part, out=out[:, i])
    return out


def slerp(q0: np.ndarray, q1: np.ndarray, t) -> np.ndarray:
    """
    Spherical linear interpolation from q0 (t = 0) to q1 (t = 1) along the shorter arc.

    The weights sin((1-t)θ)/sin θ and sin(tθ)/sin θ are computed on (...) vectors and the
    (..., 4) arrays are touched only to combine them, which matters when pairing a million
    samples. θ from arccos is imprecise near 0, but the weights depend on θ only at second
    order there.

    Parameters
    ----------
    q0, q1 : ndarray, shape (..., 4)
        Unit quaternions.
    t : ndarray, shape (...)
        Interpolation fractions.

    Returns
    -------
    q : ndarray, shape (..., 4)
        Unit quaternions with w >= 0.

    """
    q0 = np.asarray(q0, dtype=float)
    q1 = np.asarray(q1, dtype=float)
    t = np.asarray(t, dtype=float)
    dot = np.einsum('...i,...i->...', q0, q1)
    shorter = np.where(dot < 0.0, -1.0, 1.0)  # q and -q are one rotation: take the short arc
    theta = np.arccos(np.minimum(np.abs(dot), 1.0))
    small = theta < 1e-6  # sin θ -> 0: the weights tend to the linear ones, error O(θ²)
    sin_theta = np.sin(np.where(small, 1.0, theta))
    w0 = np.where(small, 1.0 - t, np.sin((1.0 - t) * theta) / sin_theta)
    w1 = shorter * np.where(small, t, np.sin(t * theta) / sin_theta)
    # canonical sign (w >= 0) chosen on the scalar part before forming the (..., 4) result
    flip = np.where(w0 * q0[..., 0] + w1 * q1[..., 0] < 0.0, -1.0, 1.0)
    out = q0 * (flip * w0)[..., None]  # in place below: (..., 4) temporaries cost as much
    out += q1 * (flip * w1)[..., None]  # as the arithmetic for a million rows
    return out


def chordal_mean(q: np.ndarray) -> np.ndarray:
    """
    Chordal mean of unit quaternions, shape (N, 4) -> (4,), w >= 0.

    The top eigenvector of Σ q qᵀ: insensitive to the signs of the q.
    """
    q = np.asarray(q, dtype=float)
    _, vec = np.linalg.eigh(q.T @ q)
    return canonical(vec[:, -1])


def angle_between(q0: np.ndarray, q1: np.ndarray) -> np.ndarray:
    """
    Rotation angle (rad, in [0, π]) between two orientations, shape (...).

    ``2 atan2(|v|, |w|)`` of the relative rotation ``q0* ⊗ q1 = (w, v)``: full precision at any
    angle and for quaternions whose norm is 1 only to rounding (``2 arccos(|q0 · q1|)`` loses
    half the digits near 0: 41 % off at 1e-6 rad for a norm off by 1e-13).
    """
    q0 = np.asarray(q0, dtype=float)
    q1 = np.asarray(q1, dtype=float)
    w = np.sum(q0 * q1, axis=-1)
    v = q0[..., :1] * q1[..., 1:] - q1[..., :1] * q0[..., 1:] - np.cross(q0[..., 1:], q1[..., 1:])
    return 2.0 * np.arctan2(np.linalg.norm(v, axis=-1), np.abs(w))


def rotation_error(q_model: np.ndarray, q_meas: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """
    Quaternion error metric of Ikits §3.2 and its derivative with respect to the model.

    The error is the vector part of ``q_model ⊗ q_meas*`` with the sign chosen so that its scalar
    part is >= 0 (q and -q are one rotation). For a measurement ``q_meas = Exp(δθ) ⊗ q_model``,
    the error is ``-sin(|δθ|/2) δθ/|δθ| ≈ -δθ/2``: half the rotation angle (eq. 14), which is
    how a rotation noise covariance enters the metric (``estimator.problem.metric_covariance``).

    Parameters
    ----------
    q_model, q_meas : ndarray, shape (..., 4)
        Modelled and measured orientations.

    Returns
    -------
    e : ndarray, shape (..., 3)
        Error vector (dimensionless, ≈ half-angle, expressed in the base frame of the pose).
    de_dq : ndarray, shape (..., 3, 4)
        ∂e/∂q_model (Ikits eq. 15 in our ordering).

    """
    rm = right_matrix(conjugate(q_meas))
    prod = np.einsum('...ij,...j->...i', rm, q_model)
    sign = np.where(prod[..., :1] < 0.0, -1.0, 1.0)
    return sign * prod[..., 1:], sign[..., None] * rm[..., 1:, :]


def reduce(q: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """
    Reduced quaternion (Ikits eq. 7): the three components other than the largest.

    Parameters
    ----------
    q : ndarray, shape (..., 4)
        Unit quaternions.

    Returns
    -------
    s : ndarray, shape (..., 3)
        The free components, in index order.
    chart : ndarray of int, shape (...)
        Index k of the largest-magnitude component, computed from the unit constraint.
    sign : ndarray, shape (...)
        Sign of that component (+1 or -1), fixed until the next re-chart.

    """
    q = np.asarray(q, dtype=float)
    chart = np.argmax(np.abs(q), axis=-1)
    qk = np.take_along_axis(q, chart[..., None], -1)[..., 0]
    sign = np.where(qk < 0.0, -1.0, 1.0)
    s = np.take_along_axis(q, CHART_OTHERS[chart], -1)
    return s, chart, sign


def expand(s: np.ndarray, chart: np.ndarray, sign: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """
    Full quaternion from a reduced one and the derivative dq/ds (Ikits eqs. 8-10).

    Parameters
    ----------
    s : ndarray, shape (..., 3)
        The reduced quaternion's three free components.
    chart : ndarray of int, shape (...)
        Index of the component computed from the unit constraint.
    sign : ndarray, shape (...)
        Sign of that component.

    Returns
    -------
    q : ndarray, shape (..., 4)
        Unit quaternion; NaN where ``|s| > 1`` (outside the chart, a step to reject).
    dq_ds : ndarray, shape (..., 4, 3)

    """
    s = np.asarray(s, dtype=float)
    if s.shape == (3,):  # one quaternion (every Parameters): the same arithmetic, no scatter
        return _expand_one(s, int(chart), float(sign))
    chart = np.asarray(chart)
    rest = 1.0 - np.sum(s * s, axis=-1)
    qk = np.asarray(sign) * np.sqrt(np.where(rest >= 0.0, rest, np.nan))
    others = CHART_OTHERS[chart]
    q = np.empty(s.shape[:-1] + (4,))
    np.put_along_axis(q, others, s, -1)
    np.put_along_axis(q, chart[..., None], qk[..., None], -1)
    jac = np.zeros(s.shape[:-1] + (4, 3))
    eye = np.broadcast_to(np.eye(3), s.shape[:-1] + (3, 3))
    np.put_along_axis(jac, others[..., None].repeat(3, -1), eye, -2)
    row_k = (-s / qk[..., None])[..., None, :]
    np.put_along_axis(jac, chart[..., None, None].repeat(3, -1), row_k, -2)
    return q, jac


def _expand_one(s: np.ndarray, chart: int, sign: float) -> tuple[np.ndarray, np.ndarray]:
    """``expand`` of one reduced quaternion, shape (3,): q (4,) and dq/ds (4, 3)."""
    rest = 1.0 - np.sum(s * s, axis=-1)
    qk = np.float64(sign) * np.sqrt(rest if rest >= 0.0 else np.nan)
    others = CHART_OTHERS[chart]
    q = np.empty(4)
    q[others] = s
    q[chart] = qk
    jac = np.zeros((4, 3))
    jac[others] = np.eye(3)
    jac[chart] = -s / qk
    return q, jac


def needs_rechart(s: np.ndarray, chart: np.ndarray, sign: np.ndarray) -> np.ndarray:
    """
    Flag where another component has outgrown the computed one (§3.1, re-charting).

    Shape (...). Re-charting keeps dq/ds well conditioned: |q_k| >= 1/2 in every chart.
    """
    q, _ = expand(s, chart, sign)
    qk = np.abs(np.take_along_axis(q, np.asarray(chart)[..., None], -1)[..., 0])
    return np.max(np.abs(s), axis=-1) > qk
