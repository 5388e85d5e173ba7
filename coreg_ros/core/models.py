"""
The three measurement models of Ikits (2000) §4 with analytic Jacobians.

Device A (input x) measures the tool pose ``(p_A, q_A)`` in A's base frame; device B (output y)
measures the marker(s) in B's base frame. Unknown and constant:

- T0 = T_bbase_abase: ``p0`` (m, in B's base frame) and ``q0`` (reduced: ``s0``);
- T1 = T_atool_bmarker: ``p1`` (m, in A's tool frame) and ``q1`` (reduced: ``s1``);
- for three markers, ``p2`` and ``p3`` (m, in A's tool frame).

Parameter vectors φ (reduced quaternions, §3.1):

============== ======================================= ===== ================================
model          φ                                       P     y (residuals per pair m)
============== ======================================= ===== ================================
full_pose      p0, s0, p1, s1                          12    p_B, q_B (6, eq. 16)
position_only  p0, s0, p1                              9     p_B (3, eq. 18)
three_marker   p0, s0, p1, p2, p3                      15    p_B1, p_B2, p_B3 (9, eq. 19)
============== ======================================= ===== ================================

Errors are model minus measurement: position difference (m) and the quaternion metric of §3.2
(``quaternion.rotation_error``, ≈ minus half the rotation angle).
"""

from __future__ import annotations

from dataclasses import dataclass

from coreg_ros.core import quaternion as quat
from coreg_ros.core.so3 import skew
import numpy as np

S0 = slice(3, 6)
S1 = slice(9, 12)


@dataclass(frozen=True)
class ModelSpec:
    """
    Dimensions of a model.

    Attributes
    ----------
    name : str
    n_params : int
        P, the length of φ.
    n_res : int
        m, residuals per pair.
    n_markers : int
        Marker positions in φ (p1 or p1..p3).
    rotation_blocks : tuple of slice
        Where the reduced quaternions sit in φ.

    """

    name: str
    n_params: int
    n_res: int
    n_markers: int
    rotation_blocks: tuple

    @property
    def has_q1(self) -> bool:
        """Tell whether T1's orientation is estimated (full pose only)."""
        return self.name == 'full_pose'

    def marker_slice(self, j: int) -> slice:
        """Slice of marker j (0-based) position in φ."""
        return slice(6 + 3 * j, 9 + 3 * j)


SPECS = {
    'full_pose': ModelSpec('full_pose', 12, 6, 1, (S0, S1)),
    'position_only': ModelSpec('position_only', 9, 3, 1, (S0,)),
    'three_marker': ModelSpec('three_marker', 15, 9, 3, (S0,)),
}


class Parameters:
    """
    φ with the charts of its reduced quaternions, and the quantities derived from them.

    Parameters
    ----------
    spec : ModelSpec
    phi : ndarray, shape (P,)
    charts : list of (int, float)
        (component index k, sign) of each rotation block, in ``spec.rotation_blocks`` order.

    """

    def __init__(self, spec: ModelSpec, phi: np.ndarray, charts: list):
        self.spec = spec
        self.phi = np.asarray(phi, dtype=float)
        self.charts = [(int(k), float(sg)) for k, sg in charts]
        self.p0 = self.phi[0:3]
        self.q0, self.dq0 = quat.expand(self.phi[S0], self.charts[0][0], self.charts[0][1])
        self.R0 = quat.to_matrix(self.q0)
        self.markers = np.stack([self.phi[spec.marker_slice(j)] for j in range(spec.n_markers)])
        if spec.has_q1:
            self.q1, self.dq1 = quat.expand(self.phi[S1], self.charts[1][0], self.charts[1][1])
        else:
            self.q1, self.dq1 = np.array([1.0, 0.0, 0.0, 0.0]), None

    @classmethod
    def from_transforms(cls, spec: ModelSpec, p0, q0, markers, q1=None) -> Parameters:
        """Build φ from T0 = (p0, q0), marker positions (k, 3) and, for full pose, q1."""
        phi = np.zeros(spec.n_params)
        phi[0:3] = p0
        s0, k0, sg0 = quat.reduce(quat.canonical(np.asarray(q0, dtype=float)))
        phi[S0] = s0
        charts = [(k0, sg0)]
        markers = np.atleast_2d(np.asarray(markers, dtype=float))
        for j in range(spec.n_markers):
            phi[spec.marker_slice(j)] = markers[j]
        if spec.has_q1:
            s1, k1, sg1 = quat.reduce(quat.canonical(np.asarray(q1, dtype=float)))
            phi[S1] = s1
            charts.append((k1, sg1))
        return cls(spec, phi, charts)

    @property
    def valid(self) -> bool:
        """Check the step: False if a reduced quaternion left its chart (|s| > 1), to reject."""
        return bool(np.isfinite(self.q0).all() and np.isfinite(self.q1).all())

    def stepped(self, delta: np.ndarray) -> Parameters:
        """φ + δ in the same charts (Ikits eq. 37)."""
        return Parameters(self.spec, self.phi + delta, self.charts)

    def recharted(self) -> Parameters:
        """
        Return the same rotations in the chart of their largest component (§3.1 re-charting).

        Called after every accepted step, so that |q_k| >= 1/2 keeps dq/ds well conditioned.
        """
        phi = self.phi.copy()
        charts = list(self.charts)
        for i, block in enumerate(self.spec.rotation_blocks):
            k, sg = charts[i]
            if quat.needs_rechart(phi[block], k, sg):
                q, _ = quat.expand(phi[block], k, sg)
                phi[block], k_new, sg_new = quat.reduce(q)
                charts[i] = (int(k_new), float(sg_new))
        return Parameters(self.spec, phi, charts)

    def same_as(self, other: Parameters) -> bool:
        """Tell whether ``other`` holds the very same φ in the same charts (bit for bit)."""
        return (self.spec is other.spec and self.charts == other.charts
                and np.array_equal(self.phi, other.phi))


def predict(params: Parameters, pos_a: np.ndarray, quat_a: np.ndarray):
    """
    Model output f(x, φ) (Ikits eqs. 16, 18, 19).

    Parameters
    ----------
    params : Parameters
        The calibration φ.
    pos_a : ndarray, shape (n, 3)
        Tool position in A's base frame, m.
    quat_a : ndarray, shape (n, 4)
        Tool orientation in A's base frame.

    Returns
    -------
    pos_b : ndarray, shape (n, 3) or (n, 3, 3) for three markers
        Predicted marker position(s) in B's base frame, m.
    quat_b : ndarray, shape (n, 4) or None
        Predicted marker orientation (full pose only).

    """
    Ra = quat.to_matrix(quat_a)
    v = pos_a[:, None, :] + np.einsum('nab,kb->nka', Ra, params.markers)
    pos_b = params.p0 + v @ params.R0.T
    if params.spec.n_markers == 1:
        pos_b = pos_b[:, 0, :]
    quat_b = None
    if params.spec.has_q1:
        quat_b = quat.multiply(params.q0, quat.multiply(quat_a, params.q1))
    return pos_b, quat_b


def output_error(params: Parameters, pos_a, quat_a, pos_b, quat_b) -> np.ndarray:
    """
    Output error e_y = f(x, φ) - ŷ, shape (n, m) (Ikits eq. 3 with the §3.2 metric).

    For three markers the columns are (marker 1 xyz, marker 2 xyz, marker 3 xyz).
    """
    pred_pos, pred_quat = predict(params, pos_a, quat_a)
    e_pos = (pred_pos - pos_b).reshape(len(pos_a), -1)
    if pred_quat is None:
        return e_pos
    e_rot, _ = quat.rotation_error(pred_quat, quat_b)
    return np.concatenate([e_pos, e_rot], axis=1)


def error_rotation_jacobian(q_model: np.ndarray, q_meas: np.ndarray):
    """
    Rotation error e = vec(q_model ⊗ q_meas*) (sign-fixed) and its left-perturbation Jacobian.

    ∂e/∂a is for ``q_model ← Exp(a) ⊗ q_model``.

    With E = q_model ⊗ q_meas* (scalar part >= 0), ``∂e/∂a = (E_w I - [E_v]×) / 2``.

    Returns
    -------
    e : ndarray, shape (n, 3)
    de_da : ndarray, shape (n, 3, 3)

    """
    E = quat.canonical(quat.multiply(q_model, quat.conjugate(q_meas)))
    de_da = skew(-0.5 * E[:, 1:])
    de_da[:, [0, 1, 2], [0, 1, 2]] += 0.5 * E[:, :1]
    return E[:, 1:], de_da


def tangent_of_chart(q: np.ndarray, dq_ds: np.ndarray) -> np.ndarray:
    """
    G = ∂θ/∂s (3×3): a chart step δs moves q to Exp(G δs) ⊗ q (to first order).

    From ``δθ = 2 vec(δq ⊗ q*)`` with ``δq = (dq/ds) δs``.
    """
    return 2.0 * quat.right_matrix(quat.conjugate(q))[1:, :] @ dq_ds


def linearize(params: Parameters, pos_a, quat_a, pos_b, quat_b, with_input: bool):
    """
    Output error and its Jacobians with respect to φ and to the input x = (p_A, δ_A).

    Derivatives are taken with respect to left (base-frame) rotation perturbations, in closed
    form, and mapped to the reduced-quaternion coordinates of φ by the constant 3×3 matrices
    ``tangent_of_chart`` (chain rule on Ikits eqs. 10, 15, 22-25). The input orientation
    perturbation δ_A acts as ``q_A ← Exp(δ_A) ⊗ q_A`` (base frame of A): a chart centred at the
    current estimate, re-centred after every step.

    Parameters
    ----------
    params : Parameters
        The calibration φ the model is linearised at.
    pos_a, quat_a : ndarray, shapes (n, 3), (n, 4)
        Input A (measured for OLS, the current estimate for TLS).
    pos_b, quat_b : ndarray
        Measured output.
    with_input : bool
        Also return ∂e_y/∂x (TLS, Ikits eq. 52).

    Returns
    -------
    e : ndarray, shape (n, m)
    j_phi : ndarray, shape (n, m, P)
        E_y F_φ (Ikits eqs. 33, 53).
    j_x : ndarray, shape (n, m, 6) or None
        E_y F_x over (p_A, δ_A).

    """
    spec = params.spec
    n = len(pos_a)
    Ra = quat.to_matrix(quat_a)
    R0 = params.R0
    R0Ra = R0 @ Ra
    G0 = tangent_of_chart(params.q0, params.dq0)
    j_phi = np.empty((n, spec.n_res, spec.n_params))
    j_x = np.empty((n, spec.n_res, 6)) if with_input else None
    errors = []
    for j in range(spec.n_markers):
        rows = slice(3 * j, 3 * j + 3)
        ra_p = Ra @ params.markers[j]  # (n, 3) marker offset rotated into A's base frame
        r0v = (pos_a + ra_p) @ R0.T  # R0 v, v = p_A + R_A p_j
        errors.append(params.p0 + r0v - (pos_b[:, j, :] if pos_b.ndim == 3 else pos_b))
        j_phi[:, rows, :] = 0.0
        j_phi[:, rows, 0:3] = np.eye(3)
        j_phi[:, rows, S0] = skew(-r0v) @ G0  # ∂(R0 v)/∂θ0 = -[R0 v]×
        j_phi[:, rows, spec.marker_slice(j)] = R0Ra
        if with_input:
            j_x[:, rows, 0:3] = R0
            j_x[:, rows, 3:6] = R0 @ skew(-ra_p)  # R0 ∂(R_A p_j)/∂δ_A
    if spec.has_q1:
        q_model = quat.multiply(params.q0, quat.multiply(quat_a, params.q1))
        e_rot, de_da = error_rotation_jacobian(q_model, quat_b)
        errors.append(e_rot)
        G1 = tangent_of_chart(params.q1, params.dq1)
        j_phi[:, 3:6, :] = 0.0
        j_phi[:, 3:6, S0] = de_da @ G0
        # q0 ⊗ q_A ⊗ Exp(θ1) = Exp(R0 R_A θ1) ⊗ q0 ⊗ q_A
        j_phi[:, 3:6, S1] = de_da @ R0Ra @ G1
        if with_input:
            j_x[:, 3:6, 0:3] = 0.0
            j_x[:, 3:6, 3:6] = de_da @ R0  # q0 ⊗ Exp(δ) = Exp(R0 δ) ⊗ q0
    return np.concatenate(errors, axis=1), j_phi, j_x
