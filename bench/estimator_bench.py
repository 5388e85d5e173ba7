"""
Speed and memory of the estimators against scipy.optimize.least_squares on the same problems.

For each N: synchronised full-pose pairs with the default noise (fixed truth and motion), the
problem whitened exactly as ``calibrate`` does, the same closed-form start. Ours: ``solve_ols``
from the start and ``solve_tls`` from the OLS solution (and the whole ``calibrate`` with TLS, for
reference). scipy: method 'lm' with the analytic Jacobian for OLS; method 'trf' with an explicit
sparse Jacobian over x = [all input poses; φ] for TLS, each input a (δp, δθ) step from its
measured value (``q = Exp(δθ) ⊗ q_meas``), so both minimise the same cost. The scipy runs are
made in a forked child and abandoned after a time cap.

Timings are the best of a few repeats (the machine is shared); peak memory is the tracemalloc
peak during the solve above what was allocated before it (the pairs and the problem).
"""

from __future__ import annotations

from collections.abc import Callable
import gc
import multiprocessing
import os
from pathlib import Path
import pickle
import tempfile
import time
import tracemalloc
from typing import Optional

from coreg_ros.core import quaternion as quat
from coreg_ros.core.calibration.calibrate import calibrate
from coreg_ros.core.calibration.initialize import initialize
from coreg_ros.core.estimator import noise_covariance, Problem, solve_ols, solve_tls, whitening
from coreg_ros.core.estimator.posterior import joint_pose_covariance
from coreg_ros.core.models import (
    error_rotation_jacobian,
    linearize,
    output_error,
    Parameters,
    SPECS,
)
from coreg_ros.core.settings import Settings
from coreg_ros.sim import make_motion, random_truth, simulate_pairs
import numpy as np
from scipy import optimize, sparse

SIGMA_A = (2e-4, 5e-4)
SIGMA_B = (5e-4, 2e-3)
SEED = 7
TLS_SETTINGS = Settings(sigma_a=SIGMA_A, sigma_b=SIGMA_B, method='tls')


# ----------------------------------------------------------------------------------------------
# Problems
# ----------------------------------------------------------------------------------------------

def make_pairs(n: int, seed: int = SEED):
    """Noisy full-pose pairs (fixed truth and motion for every n) and the truth."""
    rng = np.random.default_rng(seed)
    truth = random_truth(rng, 'full_pose')
    motion = make_motion(rng)
    noisy, _, truth = simulate_pairs(np.random.default_rng([seed, n]), n, 'full_pose',
                                     sigma_a=SIGMA_A, sigma_b=SIGMA_B, truth=truth,
                                     motion=motion)
    return noisy, truth


def make_problem(pairs) -> Problem:
    """Build the Problem ``calibrate`` builds for these pairs (full pose, default noise)."""
    spec = SPECS['full_pose']
    return Problem(spec, np.asarray(pairs.pos_a, float), np.asarray(pairs.quat_a, float),
                   np.asarray(pairs.pos_b, float), np.asarray(pairs.quat_b, float),
                   whitening(noise_covariance(SIGMA_B), spec, 'b'),
                   whitening(noise_covariance(SIGMA_A), None, 'a'))


def start_params(problem: Problem) -> Parameters:
    """Return the closed-form start of ``calibrate``."""
    return initialize(problem.spec, problem.pos_a, problem.quat_a, problem.pos_b, problem.quat_b)


# ----------------------------------------------------------------------------------------------
# scipy formulations of the same problems
# ----------------------------------------------------------------------------------------------

def scipy_ols(problem: Problem, start: Parameters, **kw):
    """OLS with scipy 'lm' (MINPACK), analytic Jacobian, same whitening; returns Parameters."""
    spec, charts, L = problem.spec, start.charts, problem.whiten_b

    def fun(x):
        params = Parameters(spec, x, charts)
        e = output_error(params, problem.pos_a, problem.quat_a, problem.pos_b, problem.quat_b)
        return (e @ L.T).ravel()

    def jac(x):
        params = Parameters(spec, x, charts)
        _, j_phi, _ = linearize(params, problem.pos_a, problem.quat_a, problem.pos_b,
                                problem.quat_b, with_input=False)
        return problem.whiten_out(j_phi).reshape(-1, spec.n_params)

    res = optimize.least_squares(fun, start.phi.copy(), jac=jac, method='lm', **kw)
    return Parameters(spec, res.x, charts), res


def _left_jacobian(v: np.ndarray) -> np.ndarray:
    """SO(3) left Jacobian J_l(v): Exp(v + ε) ≈ Exp(J_l(v) ε) Exp(v), shape (N, 3, 3)."""
    th = np.linalg.norm(v, axis=1)
    small = th < 1e-6
    ths = np.where(small, 1.0, th)
    a = np.where(small, 0.5 - th ** 2 / 24.0, (1.0 - np.cos(ths)) / ths ** 2)
    b = np.where(small, 1.0 / 6.0 - th ** 2 / 120.0, (ths - np.sin(ths)) / ths ** 3)
    K = np.zeros((len(v), 3, 3))
    K[:, 0, 1], K[:, 0, 2], K[:, 1, 2] = -v[:, 2], v[:, 1], -v[:, 0]
    K[:, 1, 0], K[:, 2, 0], K[:, 2, 1] = v[:, 2], -v[:, 1], v[:, 0]
    return np.eye(3) + a[:, None, None] * K + b[:, None, None] * (K @ K)


class ScipyTLS:
    """
    The TLS problem (Ikits B.2) as one scipy least-squares problem over x = [u_1..u_N; φ].

    ``u_i = (δp_i, δθ_i)`` steps pair i's input from its measurement: ``p = p_meas + δp``,
    ``q = Exp(δθ) ⊗ q_meas``. Residuals per pair: 6 whitened input rows (the estimator's own
    input metric) and m whitened output rows; the Jacobian is sparse with 6 + P non-zeros
    per output row and 6 per input row.
    """

    def __init__(self, problem: Problem, start: Parameters):
        self.p, self.spec, self.charts = problem, problem.spec, start.charts
        n, m, P = problem.n, problem.spec.n_res, problem.spec.n_params
        self.n, self.m, self.P = n, m, P
        self.x0 = np.concatenate([np.zeros(6 * n), start.phi])
        # CSR pattern: rows of pair i: 6 input rows (cols 6i..6i+5), then m output rows
        # (cols 6i..6i+5 and the P parameter columns).
        rows_per = 6 + m
        nnz_in, nnz_out = 6, 6 + P
        pair_cols_in = 6 * np.arange(n)[:, None, None] + np.arange(6)[None, None, :]
        cols_in = np.broadcast_to(pair_cols_in, (n, 6, 6))
        cols_out = np.concatenate([np.broadcast_to(pair_cols_in, (n, m, 6)),
                                   np.broadcast_to(6 * n + np.arange(P), (n, m, P))], axis=2)
        self.indices = np.concatenate([cols_in.reshape(n, -1), cols_out.reshape(n, -1)],
                                      axis=1).ravel().astype(np.int64)
        row_nnz = np.tile(np.r_[np.full(6, nnz_in), np.full(m, nnz_out)], n)
        self.indptr = np.r_[0, np.cumsum(row_nnz)].astype(np.int64)
        self.shape = (n * rows_per, 6 * n + P)

    def _state(self, x):
        u = x[:6 * self.n].reshape(self.n, 6)
        pos = self.p.pos_a + u[:, 0:3]
        q = quat.multiply(quat.exp(u[:, 3:6]), self.p.quat_a)
        return u, pos, q, Parameters(self.spec, x[6 * self.n:], self.charts)

    def fun(self, x):
        _, pos, q, params = self._state(x)
        e_rot, _ = error_rotation_jacobian(q, self.p.quat_a)
        r_x = np.concatenate([pos - self.p.pos_a, e_rot], axis=1) @ self.p.whiten_a.T
        e_y = output_error(params, pos, q, self.p.pos_b, self.p.quat_b)
        r_y = e_y @ self.p.whiten_b.T
        return np.concatenate([r_x, r_y], axis=1).ravel()

    def jac(self, x):
        u, pos, q, params = self._state(x)
        Jl = _left_jacobian(u[:, 3:6])
        _, de_da = error_rotation_jacobian(q, self.p.quat_a)
        La = self.p.whiten_a
        A_x = np.empty((self.n, 6, 6))
        A_x[:, :, 0:3] = La[:, 0:3]
        A_x[:, :, 3:6] = La[:, 3:6] @ de_da @ Jl
        _, j_phi, j_x = linearize(params, pos, q, self.p.pos_b, self.p.quat_b, with_input=True)
        j_x[:, :, 3:6] = j_x[:, :, 3:6] @ Jl
        A_y = self.p.whiten_out(j_x)
        B = self.p.whiten_out(j_phi)
        data = np.concatenate([A_x.reshape(self.n, -1),
                               np.concatenate([A_y, B], axis=2).reshape(self.n, -1)], axis=1)
        return sparse.csr_matrix((data.ravel(), self.indices, self.indptr), shape=self.shape)

    def sparsity(self):
        """Return the Jacobian's sparsity pattern (for ``jac_sparsity``)."""
        ones = np.ones(len(self.indices))
        return sparse.csr_matrix((ones, self.indices, self.indptr), shape=self.shape)

    def solve(self, **kw):
        """Run 'trf' with the sparse Jacobian; returns (Parameters, OptimizeResult)."""
        res = optimize.least_squares(self.fun, self.x0, jac=self.jac, method='trf',
                                     tr_solver='lsmr', x_scale='jac', **kw)
        return Parameters(self.spec, res.x[6 * self.n:], self.charts), res


# ----------------------------------------------------------------------------------------------
# Measurement helpers
# ----------------------------------------------------------------------------------------------

def best_time(fn: Callable, repeats: int):
    """Best wall time of ``repeats`` calls and the last return value."""
    best, out = np.inf, None
    for _ in range(max(1, repeats)):
        gc.collect()
        t = time.perf_counter()
        out = fn()
        best = min(best, time.perf_counter() - t)
    return best, out


def peak_bytes(fn: Callable) -> int:
    """Tracemalloc peak during fn() above the memory traced when it starts."""
    gc.collect()
    tracemalloc.start()
    try:
        base = tracemalloc.get_traced_memory()[0]
        tracemalloc.reset_peak()
        fn()
        return int(tracemalloc.get_traced_memory()[1] - base)
    finally:
        tracemalloc.stop()


def run_capped(fn: Callable, cap: float):
    """
    fn() in a forked child, abandoned after ``cap`` seconds.

    Returns (result, None) or (None, reason). Falls back to running inline where fork is
    unavailable.
    """
    if 'fork' not in multiprocessing.get_all_start_methods():
        return fn(), None
    ctx = multiprocessing.get_context('fork')
    fd, path = tempfile.mkstemp(prefix='coreg_bench_', suffix='.pkl')
    os.close(fd)

    def child():
        out = fn()
        with open(path, 'wb') as f:
            pickle.dump(out, f)

    proc = ctx.Process(target=child)
    proc.start()
    proc.join(cap)
    try:
        if proc.is_alive():
            proc.kill()
            proc.join()
            return None, f'skipped (> {cap:.0f} s cap)'
        if proc.exitcode != 0:
            return None, f'failed (exit code {proc.exitcode})'
        with open(path, 'rb') as f:
            return pickle.load(f), None
    finally:
        Path(path).unlink(missing_ok=True)


def pose_difference_sigma(a: Parameters, b: Parameters, joint: np.ndarray) -> float:
    """Largest |pose(a) - pose(b)| over the 12 ROS-layout components, in σ of ``joint``."""
    d = np.concatenate([
        a.p0 - b.p0, quat.log(quat.multiply(a.q0, quat.conjugate(b.q0))),
        a.markers[0] - b.markers[0], quat.log(quat.multiply(a.q1, quat.conjugate(b.q1)))])
    return float(np.max(np.abs(d) / np.sqrt(np.diag(joint))))


# ----------------------------------------------------------------------------------------------
# The benchmark
# ----------------------------------------------------------------------------------------------

def bench_size(n: int, methods=('ols', 'tls'), scipy_cap: float = 120.0,
               with_scipy: bool = True, log: Optional[Callable] = None) -> dict:
    """
    Ours and scipy on one N; returns a dict of rows keyed by method.

    Row keys: ``n``, ``seconds`` (best of the repeats), ``us_per_pair``, ``iterations``,
    ``peak_bytes_per_pair``, ``calibrate_seconds`` (whole ``calibrate``, TLS only),
    ``scipy_seconds``, ``scipy_nfev``, ``scipy_status``, ``speedup``, ``max_diff_sigma``.
    """
    log = log or (lambda s: None)
    pairs, _ = make_pairs(n)
    problem = make_problem(pairs)
    start = start_params(problem)
    repeats = 5 if n <= 100_000 else 1  # best of 5: the machine is shared
    rows = {}
    t_ols, ols = best_time(lambda: solve_ols(problem, start), repeats)
    for method in methods:
        if method == 'ols':
            seconds, sol = t_ols, ols
            peak = peak_bytes(lambda: solve_ols(problem, start))
            total = None
        else:
            seconds, sol = best_time(lambda: solve_tls(problem, ols.params), repeats)
            peak = peak_bytes(lambda: solve_tls(problem, ols.params))
            total, _ = best_time(lambda: calibrate(pairs, TLS_SETTINGS), max(1, repeats // 2))
        row = {'n': n, 'method': method, 'seconds': seconds, 'us_per_pair': 1e6 * seconds / n,
               'iterations': sol.iterations, 'status': sol.status,
               'peak_bytes_per_pair': peak / n, 'calibrate_seconds': total,
               'scipy_seconds': None, 'scipy_nfev': None, 'scipy_status': 'not run',
               'speedup': None, 'max_diff_sigma': None}
        log(f'  ours {method.upper()} N={n}: {seconds:.3f} s, {sol.iterations} it, '
            f'{peak / n:.0f} B/pair')
        if with_scipy:
            joint = joint_pose_covariance(sol.params, sol.cov)
            if method == 'ols':
                def job():
                    t, (params, res) = best_time(lambda: scipy_ols(problem, start),
                                                 min(repeats, 3))
                    return t, params, res.nfev, res.status
            else:
                def job():
                    tls = ScipyTLS(problem, ols.params)
                    t, (params, res) = best_time(tls.solve, 1 if n > 1000 else 3)
                    return t, params, res.nfev, res.status
            out, reason = run_capped(job, scipy_cap)
            if out is None:
                row['scipy_status'] = reason
            else:
                t, params, nfev, status = out
                row.update(scipy_seconds=t, scipy_nfev=int(nfev),
                           scipy_status=f'ok (status {status})', speedup=t / seconds,
                           max_diff_sigma=pose_difference_sigma(sol.params, params, joint))
            log(f'  scipy {method.upper()} N={n}: {row["scipy_status"]} '
                f'{"" if out is None else f"{out[0]:.3f} s"}')
        rows[method] = row
    return rows


def profile_tls(n: int = 100_000, top: int = 12) -> str:
    """Profile ``solve_tls`` at N pairs with cProfile: the top entries by internal time."""
    import cProfile
    import io
    import pstats

    pairs, _ = make_pairs(n)
    problem = make_problem(pairs)
    ols = solve_ols(problem, start_params(problem))
    prof = cProfile.Profile()
    prof.enable()
    solve_tls(problem, ols.params)
    prof.disable()
    out = io.StringIO()
    pstats.Stats(prof, stream=out).sort_stats('tottime').print_stats(top)
    return out.getvalue()
