"""
Fitting the measurement model extended by effects.

A ``Model`` is a tuple of effect names. Its parameters are the calibration φ, the time and
mean effects' θ (fitted jointly by Gauss-Newton / Levenberg-Marquardt on the per-pair
weighted output error) and the variance effects' parameters (maximum likelihood given the
errors, ``variance.py``), alternated until they settle (IRLS for outliers). A ``Fit``'s
held-out predictions on blocks are ``heldout.py``'s.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Optional

from coreg_ros.core.diagnosis import variance as vm
from coreg_ros.core.diagnosis.data import DiagData
from coreg_ros.core.diagnosis.effects.registry import CANDIDATES
from coreg_ros.core.diagnosis.heldout import Heldout, Pass, predict_blocks, solve_psd
from coreg_ros.core.diagnosis.terms import Context
from coreg_ros.core.models import linearize, Parameters
import numpy as np

CHUNK = 8192
#: Largest number of Jacobian entries kept in memory for held-out predictions.
KEEP_LIMIT = 8_000_000
#: A Gauss-Newton step gaining less than this in -2 log L is not taken (0.05 nats).
OBJ_TOL = 0.1
#: Refused Gauss-Newton steps in a row after which the state is kept.
REJECTIONS = 3


@dataclass
class Eval:
    """
    One evaluation of a model on a chunk of pairs.

    Attributes
    ----------
    st : PairStats
    Jz : ndarray, shape (n, m, n_mean) or None
        ∂z/∂(φ, θ).
    e : ndarray, shape (n, m)
        Raw output error (metric units: m and half-angle), effects included.
    T : ndarray, shape (n, m, m)
        The decorrelating map z = T e.
    sd : ndarray, shape (n, m)
        Standard deviation of each raw error under the stated noise.
    fdot : ndarray, shape (n, m)
        Rate of the model output, per s.

    """

    st: vm.PairStats
    Jz: Optional[np.ndarray]
    e: np.ndarray
    T: np.ndarray
    sd: np.ndarray
    fdot: np.ndarray


@dataclass
class State:
    """Parameters of an extended model: φ, θ per time/mean effect, variance parameters."""

    params: Parameters
    theta: dict = field(default_factory=dict)
    var: vm.VarState = field(default_factory=vm.VarState)

    def copy(self) -> State:
        """Copy (θ arrays copied)."""
        return State(self.params, {k: v.copy() for k, v in self.theta.items()}, self.var)


class Model:
    """
    The measurement model extended by a set of effects, bound to the data.

    Parameters
    ----------
    data : DiagData
    names : tuple of str
        Effect names (``effects.EFFECT_NAMES``); at most one time effect.

    """

    def __init__(self, data: DiagData, names=()):
        self.data = data
        self.names = tuple(names)
        effects = [CANDIDATES[n] for n in self.names]
        self.time = [e.model_term(data) for e in effects if e.acts_on == 'time']
        if len(self.time) > 1:
            raise ValueError('at most one time effect')
        self.mean = [e.model_term(data) for e in effects if e.acts_on == 'mean']
        self.var_names = tuple(p for e in effects for p in e.var_params)
        self.P = data.spec.n_params
        sizes = [(term.name, term.n) for term in self.time + self.mean]
        self.slices = {}
        start = self.P
        for n, k in sizes:
            self.slices[n] = slice(start, start + k)
            start += k
        self.n_mean = start
        self.duration = float(data.t[-1] - data.t[0]) if data.n > 1 else 1.0
        self.L_b = np.linalg.cholesky(data.cov_b)
        self.W_b = np.linalg.inv(self.L_b)
        pts = data.b_points
        if 'noise_source' not in data.cache:
            data.cache['noise_source'] = vm.noise_source(data)
        self.source = data.cache['noise_source']
        r = np.linalg.norm(pts - self.source, axis=2).mean(axis=1)
        self.log_g = np.log(np.maximum(r, 1e-9) / max(float(np.median(r)), 1e-9))

    @property
    def n_params(self) -> int:
        """Return the number of fitted parameters beyond φ."""
        return self.n_mean - self.P + len(self.var_names)

    def initial_state(self, base: State, warm: bool = False) -> State:
        """
        Start from a state of a sub-model, with zero θ for the new effects.

        With ``warm``, a new effect whose term has a ``start`` (a located clock step) starts
        there instead.
        """
        st = base.copy()
        starts = {t.name: t.start() for t in self.time + self.mean if hasattr(t, 'start')}
        for n, sl in self.slices.items():
            if n not in st.theta:
                st.theta[n] = (starts[n] if warm and n in starts
                               else np.zeros(sl.stop - sl.start))
        st.theta = {n: v for n, v in st.theta.items() if n in self.slices}
        var = st.var
        defaults = vm.VarState()
        for name in ('log_s2', 'log_c', 'k', 'log_beta', 'logit_eps', 'log_lam', 'shape',
                     'log_f'):
            if name not in self.var_names:
                var = var.with_values([name], [getattr(defaults, name)])
        st.var = var
        return st

    # ---------------------------------------------------------------------------- evaluation

    def evaluate(self, state: State, idx: np.ndarray, jac: bool = True):
        """
        Output errors of the pairs idx in the decorrelated coordinates (``variance.py``).

        Returns
        -------
        Eval

        """
        d = self.data
        t = d.t[idx]
        if self.time:
            term = self.time[0]
            shift, dshift = term.shift(state.theta[term.name], t, self.duration)
            xp, xq = d.trajectory.pose(t - shift)
            v, w = d.trajectory.velocity(t - shift)
        else:
            xp, xq, v, w = d.pos_a[idx], d.quat_a[idx], d.vel[idx], d.omega[idx]
        pos_b = d.pos_b[idx]
        quat_b = None if d.quat_b is None else d.quat_b[idx]
        e, jphi, jx = linearize(state.params, xp, xq, pos_b, quat_b, with_input=True)
        fdot = np.einsum('nij,nj->ni', jx, np.concatenate([v, w], axis=1))
        cols = [jphi]
        if self.time:
            cols.append(-fdot[:, :, None] * dshift[:, None, :])
        if self.mean:
            k = d.spec.n_markers
            f_pos = (e[:, :3 * k] + pos_b.reshape(len(idx), -1)).reshape(len(idx), k, 3)
            ctx = Context(d, idx, state.params, xq, f_pos, jx, v, jphi)
            for eff in self.mean:
                de, Je = eff.apply(ctx, state.theta[eff.name])
                e = e + de
                cols.append(Je)
        T, lam, sd = self._decorrelation(idx, jx)
        z = np.einsum('nij,nj->ni', T, e)
        u = np.einsum('nij,nj->ni', T, fdot)
        V = None
        if 'shape' in self.var_names:
            # z = Vᵀ W e: V from the decorrelating map T = Vᵀ W and B's Cholesky factor
            V = np.transpose(T @ self.L_b, (0, 2, 1))
        # which pairs follow a located noise step (any model carries it: the screening
        # fits a noise step on the reference's statistics)
        found = d.cache.get('noise_step')
        step = None if found is None else (t >= float(found.at_s)).astype(float)
        st = vm.PairStats(z, lam, u, self.log_g[idx], V, d.spec.n_markers, step)
        Jz = None
        if jac:
            J = np.concatenate(cols, axis=2)
            Jz = np.matmul(T, J)
        return Eval(st, Jz, e, T, sd, fdot)

    def _decorrelation(self, idx: np.ndarray, jx: np.ndarray):
        """
        T (n, m, m) with ``T C_i Tᵀ = I + diag(λ)``, λ (n, m), and sqrt(diag C_i) (n, m).

        Computed at the first evaluation of these pairs and kept (C_i depends on the
        parameters only through A's carried noise, to second order).
        """
        d = self.data
        key = (int(idx[0]), int(idx[-1]), len(idx))
        cache = d.cache.setdefault('decorrelation', {})
        if key not in cache:
            A = self.W_b @ jx  # (n, m, 6)
            scale = d.a_scale[idx][:, None, None]
            CA = np.einsum('nij,jk,nlk->nil', A, d.cov_a, A) * scale
            lam, V = np.linalg.eigh(CA)
            lam = np.maximum(lam, 0.0)
            T = np.einsum('nji,jk->nik', V, self.W_b)
            var = np.diag(d.cov_b)[None, :] + np.einsum(
                'nij,jk,nik->ni', jx, d.cov_a, jx) * d.a_scale[idx][:, None]
            cache[key] = (T, lam, np.sqrt(var))
        return cache[key]

    def _weighted(self, state: State, st: vm.PairStats, Jz: np.ndarray):
        """Weighted residuals r (n, m) and Jacobian (n, m, p) for the mean fit."""
        if state.var.shape:
            # a noise shape: each pair whitened by its own Cholesky factor
            _, _, w = vm.weights(state.var, st)
            L = np.linalg.cholesky(vm.shaped_covariances(state.var, st))
            s = np.sqrt(w)[:, None]
            return (np.linalg.solve(L, st.z[:, :, None])[:, :, 0] * s,
                    np.linalg.solve(L, Jz) * s[:, :, None])
        D, c, w = vm.weights(state.var, st)
        s = np.sqrt(w)[:, None] / np.sqrt(D)
        r = st.z * s
        J = Jz * s[:, :, None]
        if state.var.beta > 0.0:
            up = st.u / np.sqrt(D)
            uu = np.sum(up ** 2, axis=1)
            gamma = np.where(uu > 0, (1.0 - 1.0 / np.sqrt(1.0 + state.var.beta * uu))
                             / np.maximum(uu, 1e-300), 0.0)
            r = r - (gamma * np.sum(up * r, axis=1))[:, None] * up
            J = J - (gamma[:, None] * np.einsum('ni,nik->nk', up, J))[:, None, :] * up[:, :, None]
        return r, J

    def chunks(self, idx: np.ndarray):
        """Chunks of the index array idx."""
        return [idx[i:i + CHUNK] for i in range(0, len(idx), CHUNK)]

    def normal(self, state: State, idx: np.ndarray, folds: Optional[np.ndarray] = None,
               n_folds: int = 0, keep: bool = False) -> Pass:
        """
        Accumulate the normal equations of the mean fit over idx, -2 log L and the stats.

        With ``folds`` (block index per pair of idx) also per-block H_k, g_k; with ``keep``
        also every pair's ∂z/∂(φ, θ), raw error and decorrelating map (for held-out
        predictions without another pass).
        """
        p = self.n_mean
        H = np.zeros((p, p))
        g = np.zeros(p)
        Hk = np.zeros((n_folds, p, p)) if folds is not None else None
        gk = np.zeros((n_folds, p)) if folds is not None else None
        obj = 0.0
        parts, kept = [], []
        pos = 0
        for ch in self.chunks(idx):
            ev = self.evaluate(state, ch)
            st, Jz = ev.st, ev.Jz
            r, J = self._weighted(state, st, Jz)
            obj += -2.0 * float(np.sum(vm.loglik(state.var, st)))
            if folds is None:
                Jf = J.reshape(-1, p)
                H += Jf.T @ Jf
                g += Jf.T @ r.reshape(-1)
            else:
                # the blocks' normal equations sum to the whole: each product is formed once
                fo = folds[pos:pos + len(ch)]
                rest = np.ones(len(ch), dtype=bool)
                for k in range(n_folds):
                    sel = fo == k
                    if sel.any():
                        rest &= ~sel
                        Js = J[sel].reshape(-1, p)
                        hk = Js.T @ Js
                        gs = Js.T @ r[sel].reshape(-1)
                        Hk[k] += hk
                        gk[k] += gs
                        H += hk
                        g += gs
                if rest.any():
                    Js = J[rest].reshape(-1, p)
                    H += Js.T @ Js
                    g += Js.T @ r[rest].reshape(-1)
            parts.append(st)
            if keep:
                kept.append(ev)
            pos += len(ch)
        stats = vm.PairStats(*(np.concatenate([getattr(s, a) for s in parts])
                               for a in ('z', 'lam', 'u', 'log_g')),
                             None if parts[0].V is None else np.concatenate(
                                 [s.V for s in parts]), parts[0].markers,
                             None if parts[0].step is None else np.concatenate(
                                 [s.step for s in parts]))
        return Pass(H, g, obj, stats, folds, Hk, gk, kept if keep else None)

    def step(self, state: State, delta: np.ndarray) -> State:
        """Apply a step of the mean parameters."""
        out = state.copy()
        trial = state.params.stepped(delta[:self.P])
        if not trial.valid:
            return None
        out.params = trial.recharted()
        for n, sl in self.slices.items():
            out.theta[n] = state.theta[n] + delta[sl]
        return out

    # -------------------------------------------------------------------------------- fitting

    def _gauss_newton(self, state: State, ps: Pass, run, max_iter: int = 12):
        # Each trial costs a pass over the pairs, so stop as soon as a step cannot matter:
        # the selection compares held-out gains of hundreds of nats, a step predicted (or
        # seen) to gain less than OBJ_TOL in -2 log L is not worth a pass. A time effect's
        # Jacobian is first order (-ḟ ∂s/∂θ), so at its optimum the step may not descend:
        # after REJECTIONS refusals in a row the state is kept.
        lam = 1e-9
        refused = 0
        for _ in range(max_iter):
            A = ps.H + lam * np.diag(np.diag(ps.H))
            delta = -solve_psd(A, ps.g)
            predicted = -float(2.0 * ps.g @ delta + delta @ ps.H @ delta)
            if predicted < OBJ_TOL or _small_step(delta, ps.H):
                break
            trial = self.step(state, delta)
            if trial is None:
                lam = max(lam * 10.0, 1e-4)
                continue
            ps2 = run(trial)
            if ps2.obj <= ps.obj + 1e-9 * abs(ps.obj):
                done = ps.obj - ps2.obj < OBJ_TOL
                state, ps = trial, ps2
                lam = max(lam * 0.1, 1e-12)
                refused = 0
                if done:
                    break
            else:
                refused += 1
                lam = max(lam * 10.0, 1e-4)
                if refused >= REJECTIONS or lam > 1e6:
                    break
        return state, ps

    def fit(self, start: State, idx: Optional[np.ndarray] = None,
            folds: Optional[np.ndarray] = None, n_folds: int = 0, max_outer: int = 5) -> Fit:
        """
        Fit all parameters of the model on the pairs idx (all by default) from ``start``.

        Parameters
        ----------
        start : State
            A state of this model or of a sub-model (new θ start at zero).
        idx : ndarray of int, optional
            Pairs to fit on (all by default).
        folds : ndarray of int, optional
            Blocks for ``Fit.heldout`` to reuse the last pass with.
        n_folds : int
            Number of blocks.
        max_outer : int
            Alternations of the mean and the variance fits.

        Returns
        -------
        Fit

        """
        idx = np.arange(self.data.n) if idx is None else idx
        keep = folds is not None and len(idx) * self.data.m * self.n_mean <= KEEP_LIMIT

        def run(s):
            return self.normal(s, idx, folds, n_folds, keep)

        state = self.initial_state(start, warm=True)
        ps = run(state)
        if self.var_names:
            state.var = vm.fit_variance(ps.stats, state.var, self.var_names)
            ps = run(state)
        for _ in range(max_outer):
            state, ps = self._gauss_newton(state, ps, run)
            if not self.var_names:
                break
            # warm: the mean moved little since the last variance fit
            new_var = vm.fit_variance(ps.stats, state.var, self.var_names, step=0.05)
            close = _var_close(new_var, state.var, self.var_names)
            state.var = new_var
            ps = run(state)
            if close:
                break
        return Fit(self, state, idx, ps.H, ps.obj, ps.stats, ps)


@dataclass
class Fit:
    """
    A fitted model.

    Attributes
    ----------
    model : Model
    state : State
    idx : ndarray
        Pairs it was fitted on.
    H : ndarray
        Information matrix of the mean parameters (φ, θ).
    obj : float
        -2 log L.
    stats : PairStats
    last : Pass
        The pass at the solution.

    """

    model: Model
    state: State
    idx: np.ndarray
    H: np.ndarray
    obj: float
    stats: vm.PairStats
    last: Optional[Pass] = None

    @property
    def loglik(self) -> float:
        """Log-likelihood."""
        return -0.5 * self.obj

    def mean_cov(self) -> Optional[np.ndarray]:
        """Covariance of (φ, θ), or None if singular."""
        try:
            return np.linalg.pinv(self.H, rcond=1e-12, hermitian=True)
        except np.linalg.LinAlgError:
            return None

    def var_cov(self) -> np.ndarray:
        """Covariance of the variance parameters."""
        return vm.variance_covariance(self.stats, self.state.var, self.model.var_names)

    def heldout(self, folds: np.ndarray, n_folds: int) -> Heldout:
        """
        Held-out evaluation on blocks: each block predicted by the fit on the others.

        Parameters
        ----------
        folds : ndarray of int, shape (len(idx),)
            Block of each pair of ``idx``.
        n_folds : int
            Number of blocks.

        Returns
        -------
        Heldout

        """
        return predict_blocks(self, folds, n_folds)


def _small_step(delta: np.ndarray, H: np.ndarray) -> bool:
    try:
        sd = np.sqrt(np.clip(np.diag(np.linalg.pinv(H, hermitian=True)), 0, None))
    except np.linalg.LinAlgError:
        return False
    return bool(np.all(np.abs(delta) <= 1e-3 * sd + 1e-15))


def _var_close(a: vm.VarState, b: vm.VarState, names) -> bool:
    return all(np.max(np.abs(np.subtract(getattr(a, n), getattr(b, n)))) < 1e-3
               for n in names)


def start_state(params: Parameters) -> State:
    """Return the base model's state from calibrated parameters."""
    return State(params=params, theta={}, var=vm.VarState())
