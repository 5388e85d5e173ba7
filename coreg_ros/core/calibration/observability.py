"""
What the motion and the prior determine: directions held, said, and carried in the covariance.

Rigs that cannot move in every direction (a SCARA arm turns about one vertical axis, a mobile
robot moves on a floor, a gantry does not turn, a turntable turns about one fixed axis) leave
some directions of (T0, T1) undetermined: for yaw-only motion, T1's offset along the rotation
axis traded against T0's translation along that axis in B's base; for a gantry, T1's position
against T0's. Everything else is determined, and is estimated.

The directions are found from the information the data carry at the estimate (whitened JᵀJ,
Ikits B.4.2), in the tangent coordinates ψ of the parameters (T0's position in B's base frame
m, its rotation about B's base axes rad, the marker position(s) in A's tool frame m, T1's
rotation about A's tool axes rad; ``tangent_matrix``), scaled to unit diagonal. A direction is
**undetermined** when its eigenvalue is below ``WEAK_SHARE`` of the largest, or below
``WOBBLE_FACTOR`` σ²_rot,A of it: the noise of A's orientations makes the measured (and, for
TLS, the estimated) inputs wobble about the axes the tool does not turn about, which lends
spurious information of about 0.04 σ²_rot,A to exactly those directions, while a real rotation
of s rad RMS about a second axis gives about 0.11 s² (measured on SCARA motion: 1e-8 for the
noise of 0.2 mrad, 4.6e-5 for a 0.02 rad rotation; free motion 5e-3 and more). The threshold
1e-5 is what a rotation of about 0.5° RMS about a second axis gives.

An undetermined direction that a prior determines (its variance along it below
``PRIOR_VARIANCE``) is estimated with the prior (``by: prior``). The others are **held**
(``by: held``): the fit holds, per direction, the parameter component that dominates it at the
closed-form start's value (a gauge: an internal prior far tighter than the data on that
component alone, ``hold_prior``), so that the observable part is estimated as if the direction
did not exist: its posterior covariance is exact, the same for any choice of the held
component. Every published covariance carries ``UNKNOWN_VARIANCE`` along a held direction
(``held_covariances``).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

from coreg_ros.core import quaternion as quat
from coreg_ros.core.errors import UnobservableError
from coreg_ros.core.estimator.posterior import joint_pose_covariance, result_poses
from coreg_ros.core.estimator.priors import Prior
from coreg_ros.core.models import Parameters, S0, S1, tangent_of_chart
from coreg_ros.core.types import UncertainPose, Unobservable
import numpy as np

#: A direction whose information is below this share of the best-determined one's is
#: undetermined (about what a 0.5° RMS rotation about a second tool axis gives).
WEAK_SHARE = 1e-5
#: ... or below this many σ²_rot,A of it (A's orientation noise lends ~0.04 σ² there).
WOBBLE_FACTOR = 3.0
#: Variance (m² or rad²) along a held direction in every published covariance. ROS consumers
#: read a large variance as unknown (σ 100 m or 100 rad: no filter will trust it); unlike the
#: -1 that marks a component the model does not have at all, it keeps the matrix positive
#: definite, so whoever inverts it (a filter, a prior of the next calibration) can.
UNKNOWN_VARIANCE = 1e4
#: A prior determines an undetermined direction when its variance along it is below this
#: (σ 10 m or 10 rad); a previous result's unknown directions (UNKNOWN_VARIANCE) do not.
PRIOR_VARIANCE = 1e2
#: A block of a direction (a 3-vector: a position or a rotation) below this share of its
#: largest block is noise, not part of it: A's orientation noise tilts the sampled null
#: direction by about σ_rot,A, which would otherwise carry UNKNOWN_VARIANCE · σ² into
#: components the motion determines (1e-4 rad² on T0's rotation for σ_rot,A = 1e-4).
SNAP_SHARE = 0.01
#: The held component is pinned this much tighter than the data determine it (the gauge
#: dominates the spurious information along the direction by far, and the information matrix
#: stays well conditioned).
HOLD_TIGHTNESS = 1e-3
#: Rotation spread (rad, RMS about a principal axis) below which the tool counts as not turning.
STILL_RAD = 0.02
#: Translation (m, RMS) below which the tool counts as not moving (or 10 σ of A's position).
STILL_M = 1e-3
#: Orientations the motion check reads at most (every k-th, so the whole recording is seen):
#: an RMS spread from 100k of them is within ~0.2 % (1/√(2n)) of that of all.
MOTION_SAMPLE = 100_000

#: The 12 components of (T0, T1) in the covariance's layout: (block, axis, unit).
COMPONENTS = tuple((block, axis, unit) for block, unit in
                   (('base_to_base position', 'm'), ('base_to_base rotation', 'rad'),
                    ('tool_to_marker position', 'm'), ('tool_to_marker rotation', 'rad'))
                   for axis in 'xyz')
_FRAMES = {'base_to_base position': "B's base frame", 'base_to_base rotation': "B's base axes",
           'tool_to_marker position': "A's tool frame",
           'tool_to_marker rotation': "A's tool axes"}
_SHORT = {'base_to_base position': "T0's translation", 'base_to_base rotation': "T0's rotation",
          'tool_to_marker position': "T1's position", 'tool_to_marker rotation': "T1's rotation"}


# ----------------------------------------------------------------------------- coordinates

def tangent_matrix(params: Parameters) -> np.ndarray:
    """
    T with δψ = T δφ: chart steps of the reduced quaternions to rotations (``tangent_of_chart``).

    ψ has φ's layout: positions unchanged, each rotation block the small rotation δθ with
    ``q ← Exp(δθ) ⊗ q`` (about the fixed axes of the frame the pose is expressed in).

    Returns
    -------
    ndarray, shape (P, P)

    """
    T = np.eye(params.spec.n_params)
    T[S0, S0] = tangent_of_chart(params.q0, params.dq0)
    if params.spec.has_q1:
        T[S1, S1] = tangent_of_chart(params.q1, params.dq1)
    return T


def in_tangent(info: np.ndarray, params: Parameters) -> np.ndarray:
    """Information of φ (P×P, chart coordinates) in the tangent coordinates ψ."""
    T_inv = np.linalg.inv(tangent_matrix(params))
    out = T_inv.T @ info @ T_inv
    return 0.5 * (out + out.T)


def pose_layout(u: np.ndarray, spec) -> tuple[np.ndarray, Optional[np.ndarray]]:
    """
    Return a ψ direction in the (T0, T1) layout of the covariance (12,), and the markers' (9,).

    T1's rotation rows are zero where the model has no q1; for three markers T1 is marker 1
    and all three markers' positions are returned beside (else None).
    """
    out = np.zeros(12)
    out[0:9] = u[0:9]
    if spec.has_q1:
        out[9:12] = u[9:12]
    markers = u[6:15].copy() if spec.n_markers == 3 else None
    return out, markers


# ----------------------------------------------------------------------------- the analysis

@dataclass(frozen=True)
class Undetermined:
    """
    The directions of ψ the data leave undetermined at an estimate.

    Attributes
    ----------
    held : ndarray, shape (P, k)
        Orthonormal directions (ψ coordinates) no prior determines: the fit holds them.
    by_prior : ndarray, shape (P, j)
        Orthonormal directions a prior determines.
    scale : ndarray, shape (P,)
        √ of the data information's diagonal in ψ (how well each component alone is known).

    """

    held: np.ndarray
    by_prior: np.ndarray
    scale: np.ndarray

    @property
    def empty(self) -> bool:
        """Tell whether the data determine every direction."""
        return self.held.shape[1] + self.by_prior.shape[1] == 0

    def same_held(self, other: Undetermined, degrees: float = 1.0) -> bool:
        """Tell whether ``other`` holds the same subspace (principal angles below ``degrees``)."""
        if self.held.shape != other.held.shape:
            return False
        if self.held.shape[1] == 0:
            return True
        cosines = np.linalg.svd(self.held.T @ other.held, compute_uv=False)
        return bool(cosines.min() >= np.cos(np.radians(degrees)))


def undetermined(data_info: np.ndarray, prior_info: Optional[np.ndarray], params: Parameters,
                 sigma_rot_a: float) -> Undetermined:
    """
    Find the directions the data leave undetermined, and which of them a prior determines.

    Parameters
    ----------
    data_info : ndarray, shape (P, P)
        Information of φ from the pairs alone (whitened JᵀJ; the TLS Schur complement), chart
        coordinates.
    prior_info : ndarray, shape (P, P), optional
        Information of φ from the user's prior rows (None: no prior).
    params : Parameters
        The estimate the information is taken at.
    sigma_rot_a : float
        Device A's rotation noise, rad (the wobble it lends, ``WOBBLE_FACTOR``).

    Returns
    -------
    Undetermined

    """
    return undetermined_in_tangent(
        in_tangent(data_info, params),
        None if prior_info is None else in_tangent(prior_info, params), sigma_rot_a)


def undetermined_in_tangent(info: np.ndarray, prior_info: Optional[np.ndarray],
                            sigma_rot_a: float) -> Undetermined:
    """
    ``undetermined`` with the information already in the tangent coordinates ψ.

    ψ is also the layout of ``planning.crlb`` (the guidance's information), so the live
    guidance and the calibration judge the motion alike.

    Parameters
    ----------
    info : ndarray, shape (P, P)
        The data's information over ψ.
    prior_info : ndarray, shape (P, P), optional
        The prior's information over ψ.
    sigma_rot_a : float
        Device A's rotation noise, rad.

    """
    P = len(info)
    d = np.sqrt(np.clip(np.diag(info), 0.0, None))
    scale = np.where(d > 0, d, 1.0)
    w, V = np.linalg.eigh(info / np.outer(scale, scale))
    limit = max(WEAK_SHARE, WOBBLE_FACTOR * sigma_rot_a ** 2) * max(w[-1], 0.0)
    weak = w <= limit
    if not weak.any():
        return Undetermined(np.zeros((P, 0)), np.zeros((P, 0)), d)
    # back to ψ (an undetermined direction v of the scaled matrix is D⁻¹v in ψ), orthonormal
    U, _ = np.linalg.qr(_snapped(V[:, weak] / scale[:, None]))
    if prior_info is None:
        return Undetermined(U, np.zeros((P, 0)), d)
    # the prior's information restricted to the undetermined subspace, by its own axes
    m = U.T @ prior_info @ U
    pw, pv = np.linalg.eigh(0.5 * (m + m.T))
    determined = pw >= 1.0 / PRIOR_VARIANCE
    return Undetermined(U @ pv[:, ~determined], U @ pv[:, determined], d)


def _snapped(directions: np.ndarray) -> np.ndarray:
    """Zero each direction's 3-blocks below SNAP_SHARE of its largest block (noise)."""
    out = directions.copy()
    blocks = out.reshape(-1, 3, out.shape[1])  # (P/3, 3, k)
    norms = np.linalg.norm(blocks, axis=1)      # (P/3, k)
    blocks *= (norms >= SNAP_SHARE * norms.max(axis=0))[:, None, :]
    return blocks.reshape(out.shape)


def refuse_if_nothing_moved(pos_a: np.ndarray, quat_a: np.ndarray, sigma_a) -> None:
    """
    Refuse a recording from which nothing can be estimated: device A's tool did not move.

    Any motion determines something (a gantry's translations give T0's rotation; a SCARA's yaw
    gives all but one direction); a tool that neither turned (rotation spread below
    ``STILL_RAD`` or 5 σ_rot,A) nor moved (translation RMS below ``STILL_M`` or 10 σ_pos,A)
    determines only the composite T0 · T_A · T1, not the two transforms.

    Parameters
    ----------
    pos_a : ndarray, shape (N, 3)
        A's tool positions, m.
    quat_a : ndarray, shape (N, 4)
        A's tool orientations.
    sigma_a : (float, float)
        Device A's noise (position m, rotation rad).

    """
    step = max(1, len(quat_a) // MOTION_SAMPLE)
    spread, _ = rotation_spread(quat_a[::step])
    pos = pos_a[::step]
    moved = float(np.sqrt(np.mean(np.sum((pos - pos.mean(axis=0)) ** 2, axis=1))))
    still_rot = max(STILL_RAD, 5.0 * float(sigma_a[1]))
    still_pos = max(STILL_M, 10.0 * float(sigma_a[0]))
    if spread[0] < still_rot and moved < still_pos:
        lost = ['T0 and T1 apart: only their composite T0 · T_A · T1 is determined']
        raise UnobservableError(
            f"device A's tool did not move ({np.degrees(spread[0]):.2f}° RMS rotation, "
            f'{moved * 1e3:.2f} mm RMS translation; noise-level limits '
            f'{np.degrees(still_rot):.2f}°, {still_pos * 1e3:.2f} mm): nothing can be '
            f'estimated, {lost[0]}; move and rotate the tool while recording', directions=lost)


# ----------------------------------------------------------------------------- holding

def _held_components(held: np.ndarray, spec) -> list:
    """
    Choose the component (index of ψ in the (T0, T1) layout) that pins each held direction.

    Per direction, greedily, the one it moves most (T1's components preferred, weighted 2×:
    a lever length is what a user can measure), after the directions already pinned are
    taken out of it, so that the pinned components determine the held subspace.
    """
    allowed = np.zeros(spec.n_params, dtype=bool)
    allowed[0:9] = True
    if spec.has_q1:
        allowed[9:12] = True
    weight = np.where(np.arange(spec.n_params) >= 6, 2.0, 1.0) * allowed
    chosen = []
    basis = held.copy()
    for k in range(held.shape[1]):
        col = basis[:, k]
        i = int(np.argmax(np.abs(col) * weight * ~np.isin(np.arange(len(col)), chosen)))
        chosen.append(i)
        # the later directions no longer move component i (they are combined to cancel it)
        if abs(col[i]) > 0:
            for j in range(k + 1, held.shape[1]):
                basis[:, j] -= basis[i, j] / col[i] * col
    return chosen


def by_component(held: np.ndarray, components: list) -> np.ndarray:
    """
    Turn a held basis so that direction k moves pinned component k alone (of the pinned ones).

    The same subspace, said per pinned component ("T1's position along x together with ..."),
    each direction of unit length (no longer orthogonal to each other).
    """
    basis = held @ np.linalg.inv(held[components, :])
    return basis / np.linalg.norm(basis, axis=0)


def hold_prior(found: Undetermined, start: Parameters, at: Optional[Prior] = None
               ) -> tuple[Optional[Prior], list]:
    """
    Build the gauge that holds the undetermined directions: a prior on one component each.

    Each held direction is pinned by the component of the (T0, T1) layout it moves most
    (``_held_components``), at ``start``'s value (or ``at``'s, for the poses it gives), with σ
    ``HOLD_TIGHTNESS`` times what the data alone give that component. The observable part's
    estimate and covariance do not depend on which component pins a direction (the direction
    carries no information).

    Returns
    -------
    prior : Prior or None
        None when nothing is held.
    components : list of int
        The pinned components (indices of the 12-layout), one per held direction.

    """
    if found.held.shape[1] == 0:
        return None, []
    components = _held_components(found.held, start.spec)
    var = np.full(12, np.inf)
    for i in components:
        var[i] = (HOLD_TIGHTNESS / found.scale[i]) ** 2 if found.scale[i] > 0 else 1e-18
    given0 = None if at is None else at.base_to_base
    given1 = None if at is None else at.tool_to_marker
    t0 = UncertainPose(start.p0.copy() if given0 is None else np.asarray(given0.position),
                       quat.canonical(start.q0 if given0 is None else given0.quat_wxyz),
                       np.diag(var[0:6]))
    t1 = UncertainPose(start.markers[0].copy() if given1 is None else np.asarray(given1.position),
                       quat.canonical(start.q1 if given1 is None else given1.quat_wxyz),
                       np.diag(var[6:12]))
    use_t0, use_t1 = np.isfinite(var[0:6]).any(), np.isfinite(var[6:12]).any()
    return Prior(t0 if use_t0 else None, t1 if use_t1 else None), components


def held_covariances(cov: np.ndarray, params: Parameters, held: np.ndarray
                     ) -> tuple[np.ndarray, np.ndarray]:
    """
    Return φ's covariance published with every held direction unknown, and its determined part.

    The fit's covariance (the gauge's tight component included) is projected onto the
    complement of the held directions in ψ: that is the determined part, whatever component
    pinned them. The published covariance adds ``UNKNOWN_VARIANCE`` along each held direction.

    Parameters
    ----------
    cov : ndarray, shape (P, P)
        Posterior covariance of φ from the fit with the gauge (chart coordinates).
    params : Parameters
        The estimate.
    held : ndarray, shape (P, k)
        Orthonormal held directions in ψ.

    Returns
    -------
    published, determined : ndarray, shape (P, P)
        Chart coordinates, like ``cov``.

    """
    T = tangent_matrix(params)
    c = T @ cov @ T.T
    proj = np.eye(len(c)) - held @ held.T
    determined = proj @ c @ proj
    T_inv = np.linalg.inv(T)

    def back(m):
        out = T_inv @ m @ T_inv.T
        return 0.5 * (out + out.T)

    return back(determined + UNKNOWN_VARIANCE * (held @ held.T)), back(determined)


def result_covariances(params: Parameters, cov: Optional[np.ndarray], held: np.ndarray):
    """
    Return the result's poses and covariances, the held directions unknown in them.

    Returns
    -------
    t0, t1 : UncertainPose
        The published poses (``posterior.result_poses``).
    joint : ndarray, shape (12, 12) or None
        The published joint covariance of (T0, T1).
    determined : ndarray, shape (12, 12) or None
        The joint covariance of the part the motion determines (None when nothing is held):
        what propagates through the model (``CalibrationResult.cov_for_propagation``), which
        does not change along a held direction.

    """
    if cov is None or not held.shape[1]:
        t0, t1, joint = result_poses(params, cov)
        return t0, t1, joint, None
    published, determined = held_covariances(cov, params, held)
    t0, t1, joint = result_poses(params, published)
    return t0, t1, joint, joint_pose_covariance(params, determined)


def held_basis(result, spec) -> np.ndarray:
    """
    Return the orthonormal held directions (ψ, P×k) of a result (``CalibrationResult.held``).

    The inverse of ``pose_layout``: the (T0, T1) layout's components, and for three markers
    the markers' part.
    """
    cols = []
    for u in result.held:
        if spec.n_markers == 3:
            cols.append(np.concatenate([u.direction[0:6], u.markers]))
        else:
            cols.append(u.direction[:spec.n_params])
    if not cols:
        return np.zeros((spec.n_params, 0))
    return np.linalg.qr(np.array(cols).T)[0]


# ----------------------------------------------------------------------------- words

def _axis_words(v: np.ndarray) -> str:
    """'z' for a coordinate axis (within 3°), else the unit vector."""
    v = v / (np.linalg.norm(v) or 1.0)
    k = int(np.argmax(np.abs(v)))
    if abs(v[k]) > np.cos(np.radians(3.0)):
        return ('-' if v[k] < 0 else '') + 'xyz'[k]
    return f'[{v[0]:.2f}, {v[1]:.2f}, {v[2]:.2f}]'


def describe_direction(u12: np.ndarray) -> tuple[str, str]:
    """
    Say a direction of the (T0, T1) layout in words, and what would determine it.

    Returns
    -------
    description : str
        E.g. "T1's position along z (A's tool frame) together with T0's translation along
        [0.10, -0.20, 0.97] (B's base frame)".
    determine : str
        A partial prior (a measured lever, a known orientation) or the motion that shows it.

    """
    blocks = [(COMPONENTS[3 * b][0], u12[3 * b:3 * b + 3]) for b in range(4)]
    size = max(np.linalg.norm(v) for _, v in blocks) or 1.0
    parts = [(name, v) for name, v in blocks if np.linalg.norm(v) >= 0.2 * size]
    parts.sort(key=lambda p: not p[0].startswith('tool_to_marker'))  # the tool side first
    words = [f'{_SHORT[name]} {"about" if "rotation" in name else "along"} {_axis_words(v)} '
             f'({_FRAMES[name]})' for name, v in parts]
    description = ' together with '.join(words)
    first, v = parts[0]
    axis = _axis_words(v)
    per_axis = ('' if len(axis) <= 2 else
                '; a prior on any axis not orthogonal to that direction determines it')
    if 'position' in first:
        prior = (f'a measured lever: a partial prior on {_SHORT[first]} (--prior with sigma '
                 f'per axis{per_axis})')
    else:
        prior = (f'a known orientation: a partial prior on {_SHORT[first]} (--prior with sigma '
                 f'per axis{per_axis}; --gravity-aligned when both bases are z up)')
    motion = ('or rotating the tool about a second axis while recording'
              if 'rotation' not in first else 'or rotating the tool about more axes')
    return description, f'{prior}, {motion}'


def report(found: Undetermined, params: Parameters, components: list,
           prior: Optional[Prior]) -> tuple:
    """
    Return the undetermined directions as ``types.Unobservable`` records, held ones first.

    Parameters
    ----------
    found : Undetermined
        The analysis at the estimate.
    params : Parameters
        The estimate (for the values held).
    components : list of int
        The component pinning each held direction (``hold_prior``).
    prior : Prior, optional
        The user's prior (for the values it holds the prior-determined directions at).

    """
    spec = params.spec
    rotvec = np.concatenate([quat.log(quat.canonical(params.q0)),
                             quat.log(quat.canonical(params.q1))])
    values = np.concatenate([params.p0, rotvec[0:3], params.markers[0], rotvec[3:6]])
    out = []
    held = by_component(found.held, components) if components else found.held
    for kind, basis in (('held', held), ('prior', found.by_prior)):
        for k in range(basis.shape[1]):
            u12, markers = pose_layout(basis[:, k], spec)
            norm = np.linalg.norm(u12) or 1.0
            norm *= np.sign(u12[np.argmax(np.abs(u12))])  # a sign users can compare
            u12 = u12 / norm
            description, determine = describe_direction(u12)
            i = components[k] if kind == 'held' else int(np.argmax(np.abs(u12)))
            block, axis, unit = COMPONENTS[i]
            held_at = {'component': f'{block} {axis}', 'value': float(values[i]), 'unit': unit,
                       'from': 'the closed-form start' if kind == 'held' else 'the prior'}
            out.append(Unobservable(direction=u12, description=description, by=kind,
                                    held_at=held_at, determine=determine,
                                    markers=None if markers is None else markers / norm))
    return tuple(out)


# ----------------------------------------------------------------------------- motion

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
