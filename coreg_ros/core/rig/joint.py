"""
The rig's joint fit: Ikits' OLS (B.1) or TLS (B.2) over every device at once.

The rig's cost is the sum of its devices' costs, with shared bases once in φ
(``layout``). Its normal equations are the sums of the devices' own, each placed at its
columns of φ: a device that shares no instant with another is linearised exactly as a pair
is (``estimator.tls.tls_linearization``, ``estimator.ols.solve_ols``: the structured paths
and their speed), the devices that share instants together (``shared_instants``). The
Levenberg-Marquardt driver (``estimator.lm``) steps φ and every device's inputs; the posterior
information is the undamped sum at the solution (B.4.2: the inverse Schur complement).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Optional

from coreg_ros.core.estimator.lm import levenberg_marquardt, Linearization, status_message, XTOL
from coreg_ros.core.estimator.ols import solve_ols
from coreg_ros.core.estimator.posterior import covariance
from coreg_ros.core.estimator.problem import Problem
from coreg_ros.core.estimator.state import InputState
from coreg_ros.core.estimator.tls import back_substitute, tls_linearization
from coreg_ros.core.rig.layout import RigLayout, RigParameters
from coreg_ros.core.rig.shared_instants import SharedInstants, sharing_groups
import numpy as np


@dataclass(frozen=True)
class RigSolution:
    """
    The joint fit.

    Attributes
    ----------
    params : RigParameters
    info : ndarray, shape (P, P)
        The posterior information of φ (TLS: the Schur complement) at the solution.
    cov : ndarray, shape (P, P) or None
        Its inverse (None when singular).
    chi2 : float
        The rig's Σ r² at the solution.
    device_chi2 : ndarray, shape (K,)
        Each device's part of it: its output residuals and its pairs' input residuals
        (those of a shared instant split in proportion to the devices' residuals per pair).
    residuals : list of ndarray
        Each device's whitened output residuals, (N_k, m_k).
    iterations, status : int
    message : str
    units : list
        How the devices were linearised: alone, or together where they share instants.
    inputs : list
        Each unit's inputs at the solution (TLS; None for OLS).

    """

    params: RigParameters
    info: np.ndarray
    cov: Optional[np.ndarray]
    chi2: float
    device_chi2: np.ndarray
    residuals: list
    iterations: int
    status: int
    message: str
    units: list = field(default_factory=list)
    inputs: Optional[list] = None


class DeviceAlone:
    """A device that shares no instant: its TLS part is a pair's (``tls_linearization``)."""

    def __init__(self, k: int, problem: Problem, columns: np.ndarray):
        self.devices, self.problem, self.cols = [k], problem, columns

    def start(self) -> InputState:
        """Return the inputs at A's measured poses."""
        return InputState(self.problem.pos_a, self.problem.quat_a)

    def linearize(self, params: RigParameters, x: InputState, lam: float, keep: bool):
        """Return (S, b, costs, damping share, factors, residuals) over ``cols``, damped."""
        S, b, cost, residuals, factors, share = tls_linearization(
            self.problem, params.devices[self.devices[0]], x, lam)
        return S, b, [cost], share, factors, [residuals[0]] if keep else None

    def input_step(self, factors, delta: np.ndarray) -> np.ndarray:
        """Return the inputs' step (6, N) of the step ``delta`` of the unit's columns."""
        return back_substitute(self.problem.n, factors, delta)


class Together:
    """Devices sharing instants (``shared_instants``): one input pose per instant."""

    def __init__(self, devices: list, problems: list, query_ns: list, columns: list):
        self.devices = devices
        self.group = SharedInstants(problems, query_ns, columns)
        self.cols = self.group.cols
        # an instant's input residual counts to the devices that see it in proportion to
        # their residuals per pair (its expectation splits so, as the dof do)
        rows = np.zeros(self.group.n)
        for inst, p in zip(self.group.instant, problems, strict=True):
            rows[inst] += p.spec.n_res
        self.shares = [p.spec.n_res / rows[inst]
                       for inst, p in zip(self.group.instant, problems, strict=True)]

    def start(self) -> InputState:
        """Return the inputs at A's measured poses, one per instant."""
        return self.group.measured_inputs()

    def linearize(self, params: RigParameters, x: InputState, lam: float, keep: bool):
        """Return (S, b, costs, damping share, factors, residuals) over ``cols``, damped."""
        lin = self.group.linearize([params.devices[k] for k in self.devices], x, lam, True)
        per_instant = np.sum(lin.input_residuals ** 2, axis=1)
        costs = [c + float(np.sum(share * per_instant[inst])) for c, share, inst in
                 zip(lin.output_costs, self.shares, self.group.instant, strict=True)]
        share = float(np.max(lam * lin.v_diag / np.diag(lin.S))) if lam > 0 else 0.0
        return lin.S, lin.b, costs, share, lin.factors, lin.residuals if keep else None

    def input_step(self, factors, delta: np.ndarray) -> np.ndarray:
        """Return the inputs' step (6, n_instants) of the step ``delta`` of ``cols``."""
        return back_substitute(self.group.n, factors, delta)

    def time_information(self, params: RigParameters, x: InputState,
                         input_columns: np.ndarray) -> tuple:
        """
        Return (h_φτ over ``cols``, h_ττ, g_τ) of the clock moving A's inputs so.

        The clock shifts the instant at which A is interpolated, once for every device that
        shares it: its column sits in A's input rows and is eliminated with the inputs
        (``SharedInstants.linearize``), so A's noise is counted once.
        """
        lin = self.group.linearize([params.devices[k] for k in self.devices], x, 0.0,
                                   input_columns=input_columns)
        P = len(self.cols)
        return lin.S[:P, P:], lin.S[P:, P:], -lin.b[P:]


def _units(layout: RigLayout, problems: list, query_ns: list) -> list:
    units = []
    for group in sharing_groups(query_ns):
        if len(group) == 1:
            k = group[0]
            units.append(DeviceAlone(k, problems[k], layout.columns[k]))
        else:
            units.append(Together(group, [problems[k] for k in group],
                                  [query_ns[k] for k in group],
                                  [layout.columns[k] for k in group]))
    return units


def solve_rig(problems: list, query_ns: list, start: RigParameters, method: str,
              max_iterations: int = 100) -> RigSolution:
    """
    Fit every device of the rig jointly (OLS or TLS).

    Parameters
    ----------
    problems : list of Problem
        Each device's pairs with A (inliers), no priors.
    query_ns : list of ndarray of int64
        Each device's A-clock times (ns) of its pairs: equal times are shared instants.
    start : RigParameters
        Where φ starts (e.g. the devices' own fits, ``RigParameters.from_starts``).
    method : {'ols', 'tls'}
        The estimator (Ikits B.1 or B.2).
    max_iterations : int
        Largest number of iterations.

    Returns
    -------
    RigSolution

    """
    if method == 'ols':
        return _solve_ols(problems, start, max_iterations)
    layout = start.layout
    units = _units(layout, problems, query_ns)
    K, P = len(problems), layout.n_params

    def assemble(state, lam: float, keep: bool):
        params, xs = state
        S, b = np.zeros((P, P)), np.zeros(P)
        costs, share, factors, residuals = np.zeros(K), 0.0, [], [None] * K
        for unit, x in zip(units, xs, strict=True):
            S_u, b_u, c_u, share_u, f_u, r_u = unit.linearize(params, x, lam, keep)
            S[np.ix_(unit.cols, unit.cols)] += S_u
            b[unit.cols] += b_u
            costs[unit.devices] += c_u
            share = max(share, share_u)
            factors.append(f_u)
            for k, r in zip(unit.devices, r_u or [], strict=False):
                residuals[k] = r
        return S, b, costs, share, factors, residuals

    def linearize(state, lam: float) -> Linearization:
        S, b, costs, share, factors, _ = assemble(state, lam, False)

        def propose(delta, lam_next):
            params, xs = state
            trial = params.stepped(delta)
            if not trial.valid:
                return state, np.inf, None
            steps = [x.stepped(unit.input_step(f, delta[unit.cols]))
                     for unit, x, f in zip(units, xs, factors, strict=True)]
            factors.clear()  # spent: free them before the trial's are made
            lin = linearize((trial.recharted(), steps), lam_next)
            return (trial.recharted(), steps), lin.cost, lin

        return Linearization(S, b, float(costs.sum()), propose, share)

    state = (start, [unit.start() for unit in units])
    (params, xs), status, it, _, _ = levenberg_marquardt(state, linearize, max_iterations, XTOL,
                                                         1e-12, min_steps=1)
    info, _, costs, _, _, residuals = assemble((params, xs), 0.0, True)
    return RigSolution(params, info, covariance(info), float(costs.sum()), costs, residuals,
                       it, status, status_message(status, it, XTOL), units, xs)


def _solve_ols(problems: list, start: RigParameters, max_iterations: int) -> RigSolution:
    """OLS (B.1): the devices' normal equations summed at their columns, one LM over φ."""
    layout = start.layout
    P = layout.n_params

    def normal(params: RigParameters):
        H, g, costs, residuals = np.zeros((P, P)), np.zeros(P), [], []
        for problem, p, cols in zip(problems, params.devices, layout.columns, strict=True):
            # no iteration: the normal equations at p (one pass over the device's pairs)
            ne = solve_ols(problem, p, max_iterations=0).resume
            H[np.ix_(cols, cols)] += ne.info
            g[cols] += ne.gradient
            costs.append(ne.cost)
            residuals.append(ne.residuals)
        return H, g, np.array(costs), residuals

    def linearize(params: RigParameters, lam: float) -> Linearization:
        H, g, costs, _ = normal(params)

        def propose(delta, lam_next):
            trial = params.stepped(delta)
            if not trial.valid:
                return trial, np.inf, None
            lin = linearize(trial.recharted(), lam_next)
            return trial.recharted(), lin.cost, lin

        return Linearization(H + lam * np.diag(np.diag(H)), -g, float(costs.sum()), propose)

    params, status, it, _, _ = levenberg_marquardt(start, linearize, max_iterations, XTOL, 1e-12)
    H, _, costs, residuals = normal(params)
    return RigSolution(params, H, covariance(H), float(costs.sum()), costs, residuals, it,
                       status, status_message(status, it, XTOL))
