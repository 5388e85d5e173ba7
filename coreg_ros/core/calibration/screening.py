"""
The robust fit's per-pair statistic d² in one light pass over the pairs.

``linearized.reference_squares`` forms, per pair, the output error e at the *measured* input,
the Jacobians of the model and the effective covariance ``Σ_eff = Σ_y + s F_x Σ_x F_xᵀ``, and
solves an m×m system: about 1.4 µs per pair, more than a whole TLS linearisation. This module
computes the same number with less work:

- OLS (A's noise does not enter): ``Σ_eff = Σ_y``, so ``d² = ‖L_y e‖²``, the squared whitened
  output residual; only the output error is needed (any model).
- TLS, full pose and position only with block-diagonal noise (``normal_equations.applies``): by the
  Woodbury identity ``eᵀ Σ_eff⁻¹ e = ‖r‖² - gᵀ U⁻¹ g`` with ``r = L_y e``, ``U = Σ_x⁻¹/s +
  A_yᵀ A_y`` and ``g = A_yᵀ r`` (``A_y`` the whitened input Jacobian): what eliminating one
  pair's input block from the TLS normal equations leaves at the measured input. The input
  position is eliminated in closed form (scalar or constant 3×3, as in
  ``estimator.normal_equations``), the rotation by a closed-form 3×3 Cholesky factor. The
  channels are those of ``normal_equations._channels``.

Both equal ``linearized.reference_squares`` to rounding (``test_calibrate_speed_paths.py`` compares
them); ``exact_for`` says which problems the fast forms cover.
"""

from __future__ import annotations

from typing import Optional

from coreg_ros.core.estimator import normal_equations as st
from coreg_ros.core.estimator import pair_algebra
from coreg_ros.core.estimator.problem import chunk_slices
from coreg_ros.core.models import output_error, Parameters
from coreg_ros.core.so3 import skew
import numpy as np


def exact_for(problem, tls: bool) -> bool:
    """Tell whether ``normalised_squares`` covers this problem (else use ``linearized``)."""
    return not tls or st.applies(problem)


def normalised_squares(problem, params: Parameters, tls: bool,
                       out: Optional[np.ndarray] = None) -> np.ndarray:
    """
    d² = eᵀ Σ_eff⁻¹ e per pair at the measured input (as ``linearized.reference_squares``).

    Parameters
    ----------
    problem : estimator.Problem
        All pairs (the rejected ones are tested again), with ``exact_for(problem, tls)``.
    params : Parameters
        The calibration the pairs are tested against.
    tls : bool
        Whether A's noise enters (``Σ_eff`` includes it).
    out : ndarray, shape (N,), optional
        Where to write the result.

    Returns
    -------
    ndarray, shape (N,)
        χ²_m distributed per pair when the model holds.

    """
    n = problem.n
    out = np.empty(n) if out is None else out
    if not tls:
        L = problem.whiten_b
        for sl in chunk_slices(n):
            quat_b = None if problem.quat_b is None else problem.quat_b[sl]
            pos_b = problem.pos_b[sl]
            e = output_error(params, problem.pos_a[sl], problem.quat_a[sl], pos_b, quat_b)
            r = e @ L.T
            out[sl] = np.einsum('ij,ij->i', r, r)
        return out
    if not st.applies(problem):
        raise ValueError('the structured d² needs a full-pose or position-only problem with '
                         'block-diagonal noise (screening.exact_for is false)')
    frame = st._Frame.of(problem, params)
    _tls_squares(problem, frame, out)
    return out


def _tls_squares(problem, frame, out: np.ndarray) -> None:
    """Fill ``out`` with ‖r‖² - gᵀU⁻¹g per pair (module docstring), chunk by chunk."""
    Qp_bar = frame.Qp_bar
    lp, lap = st._scalar(frame.Lp), st._scalar(frame.Lap)
    iso = lp is not None and lap is not None
    weighted = problem.a_scale is not None
    # A's rotation information at the measured input (E_A = identity): (L_arᵀ L_ar)/4, as the
    # metric's Jacobian is D = I/2 there (eq. 15; pair_algebra.metric_jacobian)
    Ha = 0.25 * (frame.Lar.T @ frame.Lar)
    if not iso:
        Qap = frame.Lap.T @ frame.Lap
        Mp = np.linalg.inv(Qp_bar + Qap)       # (Q̄p + Q_ap)⁻¹: eliminates δp_A
        Qe = Qp_bar @ Mp @ Qap                 # Q̄p - Q̄p M_p Q̄p without the cancellation
        Qe = 0.5 * (Qe + Qe.T)
        keep = Qap @ Mp                        # I - Q̄p M_p
    else:
        q_p, q_a = lp * lp, lap * lap
    for sl in chunk_slices(problem.n):
        pos_a, quat_a, pos_b, quat_b = st._chunk_of(problem, sl)
        ch = st._channels(frame, pos_a, quat_a, pos_b, quat_b)
        c = ch.c
        w = 1.0 if not weighted else 1.0 / problem.a_scale[sl]
        U = np.empty((3, 3, c.shape[1]))
        U[:] = Ha[:, :, None]
        if weighted:
            U *= w
        if iso:
            extra = q_a * w
            m = 1.0 / (q_p + extra)
            q_e = q_p * extra * m
            cc = c * c
            c2 = cc.sum(axis=0)
            for i in range(3):
                U[i, i] += q_e * (c2 - cc[i])
                for j in range(i):
                    U[i, j] -= q_e * (c[i] * c[j])    # the lower triangle is all L uses
            hp = (extra * m) * ch.gp
            reduction = m * np.einsum('ij,ij->j', ch.gp, ch.gp)
        else:
            C = skew(c, pair_last=True)
            N = np.einsum('abn,bc->acn', C, Qe)
            U -= pair_algebra.mm(N, C)
            hp = keep @ ch.gp
            reduction = np.einsum('ij,ij->j', ch.gp, Mp @ ch.gp)
        g = pair_algebra.cross(c, hp)
        if frame.has_rot:
            U += ch.Hr
            g += ch.gr
        z = pair_algebra.sym_solve3(pair_algebra.cholesky3(U), g[:, None, :],
                                    transpose=False)[:, 0, :]
        out[sl] = (np.einsum('ij,ij->j', ch.r_out, ch.r_out) - reduction
                   - np.einsum('ij,ij->j', z, z))
