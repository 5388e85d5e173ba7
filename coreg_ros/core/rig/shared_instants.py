"""
Devices that measure the body at the same instants: one true input pose for all of them.

In Ikits' TLS (B.2) every input pose is a parameter (eq. 42). Sensors of one device sampled
together (several EM sensors on one tool) see the body at the very instants at which A is
interpolated for each of them: the true pose x_i of A's tool at that instant is one parameter
that A and every such device measure. Its block of the normal equations gathers them all,

    U_i = A_xᵀA_x + Σ_k A_y,kᵀA_y,k,   W_i = Σ_k A_y,kᵀ B_k M_k,   g_i = A_xᵀr_x + Σ_k A_y,kᵀ r_y,k

(``M_k`` places φ_k in the rig's φ), and eliminating it (the Schur complement, as ``tls``)
couples the devices: each one's noise and information reach the others through x_i, and A's
noise is counted once per instant, not once per device. Instants are the A-clock times at which
A is interpolated (int64 ns): equal times are one instant.

The blocks are formed from A's input blocks (``estimator.tls.input_blocks``) and each device's
own linearisation (``models.linearize``), and factored by the batched Cholesky of
``estimator.batched``; the input step is ``estimator.tls.back_substitute`` on these factors
(the generic layout of ``tls``).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Optional

from coreg_ros.core.estimator import batched
from coreg_ros.core.estimator.problem import chunk_slices, pair_last, Problem
from coreg_ros.core.estimator.state import InputState
from coreg_ros.core.estimator.tls import input_blocks
from coreg_ros.core.models import linearize, Parameters
import numpy as np


def sharing_groups(query_ns: Sequence[np.ndarray]) -> list:
    """
    Group the devices that share at least one instant (connected through shared instants).

    Parameters
    ----------
    query_ns : sequence of ndarray of int64
        Per device, the A-clock times (ns) of its pairs, increasing.

    Returns
    -------
    list of list of int
        Device indices per group, each group sorted, groups in order of their first device.

    """
    k = len(query_ns)
    parent = list(range(k))

    def root(i):
        while parent[i] != i:
            i = parent[i]
        return i

    for i in range(k):
        for j in range(i + 1, k):
            if np.intersect1d(query_ns[i], query_ns[j], assume_unique=True).size:
                parent[root(j)] = root(i)
    groups: dict = {}
    for i in range(k):
        groups.setdefault(root(i), []).append(i)
    return sorted(groups.values(), key=lambda g: g[0])


@dataclass
class GroupLinearization:
    """One linearisation of a group: its part of the rig's normal equations."""

    S: np.ndarray
    b: np.ndarray
    v_diag: np.ndarray
    output_costs: list
    input_cost: float
    factors: list
    residuals: Optional[list] = None  # per device (N_k, m) whitened output residuals
    input_residuals: Optional[np.ndarray] = None  # (n_instants, 6)


class SharedInstants:
    """
    A group of devices measured at shared instants, with A's measured pose at each.

    Parameters
    ----------
    problems : list of Problem
        Each device's pairs (its own noise, model and whitening; ``whiten_a`` and
        ``a_scale`` from A), in increasing time.
    query_ns : list of ndarray of int64
        Each device's A-clock times (ns) of its pairs.
    columns : list of ndarray of int
        Each device's φ_k in the rig's φ (``RigLayout.columns``).

    """

    def __init__(self, problems: list, query_ns: list, columns: list):
        self.problems = problems
        times = np.concatenate(query_ns)
        self.times, first = np.unique(times, return_index=True)
        self.instant = [np.searchsorted(self.times, q) for q in query_ns]
        self.cols = np.unique(np.concatenate(columns))
        self.local = [np.searchsorted(self.cols, c) for c in columns]
        pos = np.concatenate([p.pos_a for p in problems])
        quats = np.concatenate([p.quat_a for p in problems])
        self.pos_a, self.quat_a = pos[first], quats[first]
        scales = [p.a_scale for p in problems]
        self.a_scale = None if any(s is None for s in scales) else np.concatenate(scales)[first]
        self.whiten_a = problems[0].whiten_a

    @property
    def n(self) -> int:
        """Return the number of instants."""
        return len(self.times)

    def measured_inputs(self) -> InputState:
        """Return the TLS inputs at A's measured poses."""
        return InputState(self.pos_a, self.quat_a)

    def linearize(self, params: Sequence[Parameters], x: InputState, lam: float,
                  keep_residuals: bool = False,
                  input_columns: Optional[np.ndarray] = None) -> GroupLinearization:
        """
        Linearise: the group's Schur complement over its columns of φ, damped by λ (as ``tls``).

        Parameters
        ----------
        params : sequence of Parameters
            φ_k of the group's devices, in the order of ``problems``.
        x : InputState
            The inputs at the instants.
        lam : float
            Damping of the input blocks and of the φ block (λ·diag).
        keep_residuals : bool
            Also return the whitened residuals.
        input_columns : ndarray, shape (n_instants, 6, n_t), optional
            Further parameters that move A's measured inputs: ∂(input error)/∂θ per instant
            (the clock offset: A's velocity). Appended after the group's columns of φ in
            ``S`` and ``b`` (size P_g + n_t): their information and gradient with the
            inputs eliminated.

        """
        n_t = 0 if input_columns is None else input_columns.shape[2]
        P = len(self.cols)
        S, b, v_diag = np.zeros((P + n_t, P + n_t)), np.zeros(P + n_t), np.zeros(P)
        out_costs = [0.0] * len(self.problems)
        in_cost = 0.0
        factors = []
        res = [pair_last(p.n, p.spec.n_res) for p in self.problems] if keep_residuals else None
        res_x = pair_last(self.n, 6) if keep_residuals else None
        for sl in chunk_slices(self.n):
            r_x, A_x = input_blocks(self, x, sl)
            U = np.swapaxes(A_x, 1, 2) @ A_x
            Wg = np.zeros((sl.stop - sl.start, 6, P + n_t + 1))
            Wg[:, :, -1] = (np.swapaxes(A_x, 1, 2) @ r_x[:, :, None])[:, :, 0]
            if n_t:
                # whitened input rows of the extra parameters: A_x times A's shift per unit
                T = A_x @ input_columns[sl]
                Wg[:, :, P:P + n_t] = np.swapaxes(A_x, 1, 2) @ T
                T2 = T.reshape(-1, n_t)
                S[P:, P:] += T2.T @ T2
                b[P:] -= T2.T @ r_x.reshape(-1)
            for k, problem in enumerate(self.problems):
                j0, j1 = np.searchsorted(self.instant[k], [sl.start, sl.stop])
                if j1 == j0:
                    continue
                idx = self.instant[k][j0:j1]
                r_y, A_y, B = _device_blocks(problem, params[k], x, idx, slice(j0, j1))
                At = np.swapaxes(A_y, 1, 2)
                li, loc = idx - sl.start, self.local[k]
                U[li] += At @ A_y
                part = Wg[li]
                part[:, :, loc] += At @ B
                part[:, :, -1] += (At @ r_y[:, :, None])[:, :, 0]
                Wg[li] = part
                B2 = B.reshape(-1, B.shape[2])
                S[np.ix_(loc, loc)] += B2.T @ B2
                v_diag[loc] += np.einsum('ij,ij->j', B2, B2)
                b[loc] -= B2.T @ r_y.reshape(-1)
                out_costs[k] += float(np.sum(r_y * r_y))
                if res is not None:
                    res[k][j0:j1] = r_y
            if lam:
                U = U.copy()
                U[:, np.arange(6), np.arange(6)] *= 1.0 + lam
            L = batched.cholesky(U)
            Z = batched.solve_lower(L, np.ascontiguousarray(Wg.transpose(1, 2, 0)))
            factors.append((L, Z))
            Zt = Z.transpose(0, 2, 1).reshape(-1, P + n_t + 1)
            S -= Zt[:, :-1].T @ Zt[:, :-1]
            b += Zt[:, :-1].T @ Zt[:, -1]
            in_cost += float(np.sum(r_x * r_x))
            if res_x is not None:
                res_x[sl] = r_x
        S[:P, :P] += np.diag(lam * v_diag)
        b = b if n_t else b[:P]
        return GroupLinearization(S, b, v_diag, out_costs, in_cost, factors, res, res_x)


def _device_blocks(problem: Problem, params: Parameters, x: InputState, idx: np.ndarray,
                   pairs: slice):
    """One device's whitened output residuals r_y, A_y = L ∂e/∂x and B = L ∂e/∂φ_k."""
    pos_b, quat_b = problem.output(pairs)
    e, j_phi, j_x = linearize(params, np.take(x.pos, idx, axis=0),
                              np.take(x.quat, idx, axis=0), pos_b, quat_b, with_input=True)
    return e @ problem.whiten_b.T, problem.whiten_out(j_x), problem.whiten_out(j_phi)
