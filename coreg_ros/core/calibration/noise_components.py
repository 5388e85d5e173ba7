"""
Each device's noise estimated jointly with the calibration: variance components by REML.

To first order every pair's error at the measured input, ``r_i = f(x̃_i, φ̂) - ŷ_i`` (Ikits
eq. 3), is Gaussian with covariance

    M_i = K_i S K_iᵀ,   K_i = [D_B | √s_i F_x,i],   S = blockdiag(S_B, S_A)

(``estimator.linearized``): ``S_B`` B's noise (position, and rotation for the full pose; the
three markers' positions for three markers), ``S_A`` A's (position, rotation, ROS layout),
``D_B`` B's noise in the error metric (the rotation metric is half the angle), ``F_x`` the
input Jacobian (eq. 52), ``s_i`` the interpolation factor. OLS has no errors in A (B.1):
its ``K_i = D_B``, and what it calls B's noise holds A's too.

Each device channel (A position, A rotation, B position, B rotation) is a *component*: its
stated 3×3 covariance times a factor θ (``scale``), or its six entries (``full``, where the
data determine an anisotropic covariance), or ``held`` at the stated value. ``S`` is linear in
θ, so the restricted (REML) likelihood's Fisher scoring is Helmert's iteration:

    score_k = ½ [ Σ_i u_iᵀ E_k u_i - ⟨Σ_i H_i - Σ_i G_i C G_iᵀ, E_k⟩ ],   u_i = K_iᵀ W_i r_i,
    F_kl = ½ Σ_i tr(H_i E_k H_i E_l),   H_i = K_iᵀ W_i K_i,  G_i = K_iᵀ W_i J_φ,i,
    θ ← θ + F⁻¹ score

with ``W_i = M_i⁻¹``, ``E_k`` component k's matrix in ``S``, ``C`` the covariance of φ̂ (the
REML term: φ̂ was fitted to the same pairs). ``F⁻¹`` is the covariance of θ̂. Everything is a
sum over pairs of small matrices, so the work is a pass over (a subsample of) the pairs per
iteration, after one linearisation.

Identifiability is read from ``F``: a component whose relative standard error exceeds
``MAX_RELATIVE_SE`` with the others estimated is held (the one of least stated weight first,
so that two components only their sum shows are split as the stated noise says), and the
components that then became determined are named as those it cannot be told apart from. A's
and B's position noise always reach the pairs as a constant sum (``R0 Σ_A,p R0ᵀ + Σ_B,p``): no
motion tells them apart, except with three markers (A's position noise is common to the three,
B's is not). A's rotation noise also moves B's position through the lever arm, which is what
separates it from B's rotation noise.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Optional

from coreg_ros.core.distributions import chi2_isf, chi2_ppf
from coreg_ros.core.models import linearize, ModelSpec, Parameters
from coreg_ros.core.noise_model import DeviceNoise
import numpy as np

#: Pairs (every k-th) the components are estimated on: a variance is within ~1.5 % at 5k pairs.
SAMPLE = 5_000
#: Relative standard error (at the stated noise) beyond which a component is held before any
#: estimate: no value near the stated one could make it determined.
HOPELESS_SE = 1.0
#: Largest relative standard error of each principal variance of a channel for its full
#: (anisotropic) covariance to be estimated; else a factor on the stated one.
MAX_RELATIVE_SE_FULL = 0.1
#: Smallest spread of the generalised variances (log of largest over smallest) for a full
#: channel: 20 % in σ between the directions most and least off the stated shape.
MIN_ANISOTROPY = 2.0 * float(np.log(1.2))
#: Pairs (every k-th of those) the Fisher information is summed over.
FISHER_SAMPLE = 1_500
#: Largest relative standard error of a component's variance for it to be estimated (its σ
#: then within ~15 %, 1σ); above it the component is held at the stated value. Holding is
#: the worse error when the stated value is off: a component held where the data disagree
#: pushes its partners (A's rotation held 3× too large leaves nothing for B's).
MAX_RELATIVE_SE = 0.3
#: Fisher scoring iterations at most, and the relative change of θ that ends them.
MAX_ITERATIONS = 30
TOLERANCE = 1e-3
#: Rounds of "estimate, look again at what is determined".
MAX_ROUNDS = 2
#: Smallest factor a component may reach (of its stated variance): below it, at the bound.
FLOOR = 1e-4

#: Channels as (device, kind), in the order they are reported.
CHANNELS = (('a', 'position'), ('a', 'rotation'), ('b', 'position'), ('b', 'rotation'))


@dataclass
class _Layout:
    """Where each channel's 3×3 blocks sit in S (d×d), and B's map into the error metric."""

    d_b: int
    d: int
    blocks: dict  # (device, kind) -> list of slices
    D_b: np.ndarray  # (m, d_b)

    @classmethod
    def of(cls, spec: ModelSpec, with_a: bool) -> _Layout:
        if spec.name == 'full_pose':
            d_b, D = 6, np.diag([1.0, 1.0, 1.0, 0.5, 0.5, 0.5])
            blocks = {('b', 'position'): [slice(0, 3)], ('b', 'rotation'): [slice(3, 6)]}
        else:
            k = spec.n_markers
            d_b, D = 3 * k, np.eye(3 * k)
            blocks = {('b', 'position'): [slice(3 * j, 3 * j + 3) for j in range(k)]}
        d = d_b + (6 if with_a else 0)
        if with_a:
            blocks[('a', 'position')] = [slice(d_b, d_b + 3)]
            blocks[('a', 'rotation')] = [slice(d_b + 3, d_b + 6)]
        return cls(d_b, d, blocks, D)

    def place(self, channel: tuple, block: np.ndarray) -> np.ndarray:
        """Return S's d×d matrix with ``block`` (3×3) at every place of ``channel``."""
        out = np.zeros((self.d, self.d))
        for sl in self.blocks[channel]:
            out[sl, sl] = block
        return out


def _unit_basis() -> list:
    """Return the six symmetric 3×3 unit matrices (xx, yy, zz, xy, xz, yz)."""
    out = []
    for a, b in ((0, 0), (1, 1), (2, 2), (0, 1), (0, 2), (1, 2)):
        e = np.zeros((3, 3))
        e[a, b] = e[b, a] = 1.0
        out.append(e)
    return out


@dataclass
class Component:
    """
    A channel's noise model in the estimation: held, a factor on the stated one, or full.

    Attributes
    ----------
    channel : (str, str)
        (device, kind).
    stated : ndarray, shape (3, 3)
        The stated covariance (m² or rad², the device's base frame).
    mode : {'held', 'scale', 'full'}
    theta : ndarray
        The factor (scale, shape (1,)) or the six entries (full); unused when held.
    partners : list of (str, str)
        When held for confounding: the channels it cannot be told apart from.
    why : str
        Why it is held ('' when estimated).

    """

    channel: tuple
    stated: np.ndarray
    mode: str = 'scale'
    theta: np.ndarray = field(default_factory=lambda: np.ones(1))
    partners: list = field(default_factory=list)
    why: str = ''

    def basis(self) -> list:
        """Return the 3×3 matrices whose θ-weighted sum is the channel's covariance."""
        if self.mode == 'scale':
            return [self.stated]
        return _unit_basis() if self.mode == 'full' else []

    def covariance(self) -> np.ndarray:
        """Return the channel's covariance now (3×3)."""
        if self.mode == 'held':
            return self.stated
        return sum(t * e for t, e in zip(self.theta, self.basis(), strict=True))

    def go_full(self) -> None:
        """Switch from a factor to the six entries, at the same covariance."""
        c = self.covariance()
        self.mode = 'full'
        self.theta = np.array([c[0, 0], c[1, 1], c[2, 2], c[0, 1], c[0, 2], c[1, 2]])


@dataclass
class _Pairs:
    """The linearised subsample: residuals and Jacobians at φ̂ (fixed while θ moves)."""

    r: np.ndarray        # (n, m)
    K: np.ndarray        # (n, m, d)
    J: np.ndarray        # (n, m, P)
    n_total: int         # pairs φ̂ was fitted on
    Jx: np.ndarray       # (n, m, 6): A's noise into the error (√s_i F_x,i), also for OLS

    def take(self, keep: np.ndarray) -> _Pairs:
        """Return the pairs ``keep`` (a mask or indices)."""
        return _Pairs(self.r[keep], self.K[keep], self.J[keep], self.n_total, self.Jx[keep])


def linearised_pairs(params: Parameters, pos_a, quat_a, pos_b, quat_b, a_scale,
                     with_a: bool, sample: int = SAMPLE) -> tuple[_Pairs, _Layout]:
    """
    Linearise every k-th pair (at most ``sample``) at φ̂ for the component estimation.

    Parameters
    ----------
    params : Parameters
        The calibration the pairs are linearised at.
    pos_a, quat_a, pos_b, quat_b : ndarray
        The pairs (inliers), as ``calibrate`` validated them.
    a_scale : ndarray, shape (N,) or None
        A's interpolation variance factor per pair.
    with_a : bool
        A's noise in the model (TLS); False for OLS.
    sample : int
        Pairs used at most.

    """
    spec = params.spec
    n = len(pos_a)
    idx = np.arange(0, n, max(1, n // sample))

    def take(x):
        return None if x is None else np.take(np.asarray(x), idx, axis=0)

    e, j_phi, j_x = linearize(params, take(pos_a), take(quat_a), take(pos_b), take(quat_b),
                              with_input=True)
    layout = _Layout.of(spec, with_a)
    k = len(idx)
    s = np.ones(k) if a_scale is None else np.sqrt(take(a_scale))
    j_x = j_x * s[:, None, None]
    K = np.zeros((k, spec.n_res, layout.d))
    K[:, :, :layout.d_b] = layout.D_b
    if with_a:
        K[:, :, layout.d_b:] = j_x
    return _Pairs(e, K, j_phi, n, j_x), layout


def _assemble(components: list, layout: _Layout) -> np.ndarray:
    """Return S (d×d) from the components' covariances."""
    S = np.zeros((layout.d, layout.d))
    for c in components:
        if c.channel in layout.blocks:
            S += layout.place(c.channel, c.covariance())
    return S


def _estimated(components: list) -> list:
    """(component, basis index, d×d matrix) of every estimated parameter, in θ order."""
    return [(c, j) for c in components if c.mode != 'held' for j in range(len(c.basis()))]


@dataclass
class _Step:
    """One pass over the pairs: the score, the Fisher information, the moments."""

    score: np.ndarray
    fisher: np.ndarray
    H: np.ndarray       # Σ H_i (d×d)
    HH: np.ndarray      # Σ H_i ⊗ H_i as (d, d, d, d)


def _pass(pairs: _Pairs, S: np.ndarray, E: np.ndarray) -> _Step:
    """
    Score and Fisher information of the θ with matrices E (k, d, d) at S (module docstring).

    The score sums every pair; the Fisher information, an expectation, every k-th pair (at
    most ``FISHER_SAMPLE``) scaled up: its products are the costly part.
    """
    K, r, J = pairs.K, pairs.r, pairs.J
    # batched products of small matrices and einsum sums only: a 2-D BLAS product of these thin
    # shapes is 10-100× slower with BLAS threads on a busy machine, and the core sets no threads
    W = np.linalg.inv(K @ S @ K.transpose(0, 2, 1))
    KW = K.transpose(0, 2, 1) @ W                    # (n, d, m)
    u = np.einsum('ndm,nm->nd', KW, r)
    info = np.einsum('nmp,nmq->pq', J, W @ J)
    n, d = len(r), S.shape[0]
    # REML: φ̂ (fitted to all n_total pairs) took out part of each residual's variance
    C = np.linalg.pinv(info * (pairs.n_total / n))
    G = KW @ J                                       # (n, d, P)
    correction = (G @ C @ G.transpose(0, 2, 1)).sum(axis=0)
    H = KW @ K                                       # (n, d, d)
    Hs = H.sum(axis=0)
    every = max(1, n // FISHER_SAMPLE)
    # Σ H_i ⊗ H_i over the upper triangle of the symmetric H_i (a third of the products)
    iu = np.triu_indices(d)
    flat = H[::every, iu[0], iu[1]]
    tri = np.einsum('ni,nj->ij', flat, flat) * (n / len(flat))
    HH = np.zeros((d, d, d, d))
    HH[iu[0][:, None], iu[1][:, None], iu[0][None, :], iu[1][None, :]] = tri
    HH = HH + HH.transpose(1, 0, 2, 3)
    HH[iu[0], iu[0]] *= 0.5  # the diagonal entries (a, a) were added twice
    HH = HH + HH.transpose(0, 1, 3, 2)
    HH[:, :, iu[0], iu[0]] *= 0.5
    U = np.einsum('ni,nj->ij', u, u)
    score = 0.5 * np.einsum('kde,de->k', E, U - Hs + correction)
    fisher = 0.5 * np.einsum('abcd,kbc,lda->kl', HH, E, E)
    return _Step(score, fisher, Hs, HH)


def _matrices(components: list, layout: _Layout) -> np.ndarray:
    """E (k, d, d): every estimated parameter's matrix in S."""
    out = [layout.place(c.channel, c.basis()[j]) for c, j in _estimated(components)]
    return np.array(out) if out else np.zeros((0, layout.d, layout.d))


def _positive(components: list) -> bool:
    return all(np.linalg.eigvalsh(c.covariance())[0] > 0 for c in components)


def _iterate(pairs: _Pairs, layout: _Layout, components: list) -> tuple[np.ndarray, bool]:
    """
    Fisher scoring of the estimated components from where they are; returns (F, converged).

    A step that would leave a covariance not positive definite is halved; a factor is kept
    above ``FLOOR`` (a component the data want at zero is at the bound). F is that of the
    last pass, taken less than ``TOLERANCE`` from the end.
    """
    E = _matrices(components, layout)
    if not len(E):
        return np.zeros((0, 0)), True
    params = _estimated(components)
    step = _pass(pairs, _assemble(components, layout), E)
    for _ in range(MAX_ITERATIONS):
        theta = np.concatenate([c.theta for c in components if c.mode != 'held'])
        size = _size(components, params)
        delta = size * np.linalg.lstsq(step.fisher * np.outer(size, size), step.score * size,
                                       rcond=1e-12)[0]
        old = [c.theta.copy() for c in components]
        for t in range(20):
            new = theta + delta * 0.5 ** t
            _set(components, new)
            for c in components:
                if c.mode == 'scale':
                    c.theta = np.maximum(c.theta, FLOOR)
            if _positive(components):
                break
        else:
            for c, o in zip(components, old, strict=True):
                c.theta = o
            return step.fisher, False
        change = np.max(np.abs(np.concatenate([c.theta for c in components if c.mode != 'held'])
                               - theta) / size)
        if change < TOLERANCE:
            return step.fisher, True
        step = _pass(pairs, _assemble(components, layout), E)
    return step.fisher, False


def _size(components: list, params: list) -> np.ndarray:
    """Each parameter's scale, for a relative change: 1 for factors, the channel's variance."""
    out = []
    for c, _ in params:
        out.append(1.0 if c.mode == 'scale' else float(np.trace(c.covariance())) / 3.0)
    return np.array(out)


def _set(components: list, theta: np.ndarray) -> None:
    k = 0
    for c in components:
        if c.mode != 'held':
            c.theta = np.array(theta[k:k + len(c.theta)], dtype=float)
            k += len(c.theta)


def relative_errors(fisher: np.ndarray, components: list) -> dict:
    """
    Relative standard error of each estimated channel's variance (its size), from F.

    A factor's is ``σ(θ)/θ``; a full channel's, that of its trace. A direction F does not
    determine (a singular F) gives ``inf``.
    """
    params = _estimated(components)
    if not params:
        return {}
    # in units of each parameter's size: factors ~1 beside full entries ~σ² (1e-8 m²)
    size = _size(components, params)
    lam, V = np.linalg.eigh(0.5 * (fisher + fisher.T) * np.outer(size, size))
    good = lam > 1e-9 * max(float(lam.max()), 1e-300)
    cov = (V[:, good] / lam[good]) @ V[:, good].T * np.outer(size, size)
    V = V * size[:, None]  # null directions, in θ's units (only their pattern matters)
    out, k = {}, 0
    for c in components:
        if c.mode == 'held':
            continue
        n = len(c.theta)
        g = np.zeros(len(params))
        if c.mode == 'scale':
            g[k] = 1.0 / max(float(c.theta[0]), 1e-300)
        else:
            g[k:k + 3] = 1.0 / max(float(np.trace(c.covariance())), 1e-300)
        null = V[:, ~good]
        if null.size and np.max(np.abs(g @ null)) > 1e-6 * np.linalg.norm(g):
            out[c.channel] = float('inf')
        else:
            out[c.channel] = float(np.sqrt(max(g @ cov @ g, 0.0)))
        k += n
    return out


def covariance_of_theta(fisher: np.ndarray) -> np.ndarray:
    """Return F⁻¹ (pseudo-inverse where F is singular): the covariance of θ̂."""
    if not fisher.size:
        return fisher
    scale = 1.0 / np.sqrt(np.maximum(np.abs(np.diag(fisher)), 1e-300))
    inner = np.linalg.pinv(0.5 * (fisher + fisher.T) * np.outer(scale, scale), rcond=1e-12)
    return inner * np.outer(scale, scale)


def weight(pairs: _Pairs, layout: _Layout, channel: tuple, cov: np.ndarray) -> float:
    """Return the mean trace the channel's covariance adds to the pairs' M_i."""
    K = pairs.K
    S = layout.place(channel, cov)
    return float(np.mean(np.einsum('nmd,de,nme->n', K, S, K)))


@dataclass
class ComponentFit:
    """
    The outcome of the component estimation.

    Attributes
    ----------
    components : list of Component
    fisher : ndarray
        F of the estimated parameters (θ order of ``components``), at the estimate.
    converged : bool
    n_pairs : int
        Pairs the components were estimated on.
    pairs, layout
        The linearised subsample (for the verdict's weights).

    """

    components: list
    fisher: np.ndarray
    converged: bool
    n_pairs: int
    pairs: object = None
    layout: object = None

    def noise(self, device: str, stated: DeviceNoise) -> DeviceNoise:
        """Return a device's estimated DeviceNoise: held and absent channels as stated."""
        got = {c.channel[1]: c.covariance() for c in self.components if c.channel[0] == device}
        return DeviceNoise.from_covariances(got.get('position', stated.position_cov),
                                            got.get('rotation', stated.rotation_cov),
                                            device.upper())

    def covariances(self) -> dict:
        """Return (device, kind) -> the channel's covariance now (estimated or held)."""
        return {c.channel: c.covariance() for c in self.components}

    def theta_cov(self) -> np.ndarray:
        """Return the covariance of the estimated θ (``covariance_of_theta``)."""
        return covariance_of_theta(self.fisher)


def _hold(components: list, channel: tuple, why: str, partners: list = ()) -> None:
    for c in components:
        if c.channel == channel:
            c.mode, c.theta, c.why, c.partners = 'held', np.zeros(0), why, list(partners)


def _sub_fisher(fisher: np.ndarray, layout_of_theta: list, keep: list) -> np.ndarray:
    """
    Return the Fisher information of the parameters of the channels ``keep`` (same S).

    ``layout_of_theta`` lists (channel, parameter count) in the order of F's rows.
    """
    rows, k = [], 0
    for channel, count in layout_of_theta:
        if channel in keep:
            rows += list(range(k, k + count))
        k += count
    return fisher[np.ix_(rows, rows)]


def _hold_undetermined(pairs: _Pairs, layout: _Layout, components: list,
                       limit: float = MAX_RELATIVE_SE,
                       fisher: Optional[np.ndarray] = None) -> None:
    """
    Hold components the pairs do not determine (relative error above ``limit``), least first.

    A held component's partners are the components that became determined by holding it.
    One pass gives F (or ``fisher``, of the free components at the present S); holding a
    component only takes its rows out (F at the same S).
    """
    E = _matrices(components, layout)
    if not len(E):
        return
    if fisher is None:
        fisher = _pass(pairs, _assemble(components, layout), E).fisher
    free = [c for c in components if c.mode != 'held']
    rows = [(c.channel, len(c.theta)) for c in free]
    while free:
        rel = relative_errors(_sub_fisher(fisher, rows, [c.channel for c in free]), free)
        bad = [ch for ch, v in rel.items() if not v <= limit]
        if not bad:
            return
        lightest = min(bad, key=lambda ch: weight(pairs, layout, ch, _cov_of(free, ch)))
        free = [c for c in free if c.channel != lightest]
        after = relative_errors(_sub_fisher(fisher, rows, [c.channel for c in free]), free)
        partners = [ch for ch in bad if ch != lightest and after.get(ch, np.inf) <= limit]
        why = 'not separable' if partners else (
            f'not determined by this motion (relative error {min(rel[lightest], 99.0):.2g} of '
            f'its variance)')
        _hold(components, lightest, why, partners)


def _cov_of(components: list, channel: tuple) -> np.ndarray:
    return next(c.covariance() for c in components if c.channel == channel)


def estimate_components(pairs: _Pairs, layout: _Layout, stated: dict,
                        anisotropic: bool = True) -> ComponentFit:
    """
    Estimate the noise components jointly identifiable from the pairs (module docstring).

    Parameters
    ----------
    pairs, layout
        From ``linearised_pairs``.
    stated : dict
        (device, kind) -> stated 3×3 covariance, for every channel the model has.
    anisotropic : bool
        Try the six entries of every determined channel (kept where determined).

    Returns
    -------
    ComponentFit

    """
    components = [Component(ch, np.asarray(stated[ch], dtype=float)) for ch in CHANNELS
                  if ch in stated and ch in layout.blocks]
    # first hold what no value could make determined (components only their sum shows), then
    # judge the rest at the estimate: at a stated noise that is off, a component looks better
    # or worse determined than it is (A's rotation stated at half its noise looks a quarter
    # as determined), and holding it there would push its partners off too
    _hold_undetermined(pairs, layout, components, HOPELESS_SE)
    fisher, converged = _iterate(pairs, layout, components)
    for _ in range(MAX_ROUNDS):
        before = [c.mode for c in components]
        _hold_undetermined(pairs, layout, components, fisher=fisher)
        if [c.mode for c in components] == before:
            break
        fisher, converged = _iterate(pairs, layout, components)
    if anisotropic and any(c.mode == 'scale' for c in components):
        trial = [c for c in components if c.mode == 'scale']
        saved = [(c.mode, c.theta.copy()) for c in components]
        for c in trial:
            c.go_full()
        full_fisher, ok = _iterate(pairs, layout, components)
        undetermined = [c for c in trial if not (ok and _full_determined(full_fisher,
                                                                         components, c))]
        if len(undetermined) == len(trial):
            for c, (mode, theta) in zip(components, saved, strict=True):
                c.mode, c.theta = mode, theta
        else:
            for c in undetermined:
                c.mode, c.theta = 'scale', np.array(
                    [float(np.trace(c.covariance()) / np.trace(c.stated))])
            fisher, converged = (full_fisher, ok) if not undetermined else _iterate(
                pairs, layout, components)
    for c in components:
        if c.mode == 'scale' and c.theta[0] <= FLOOR * 1.0001:
            c.why = 'at its bound'
    return ComponentFit(components, fisher, converged, len(pairs.r), pairs, layout)


def _full_determined(fisher: np.ndarray, components: list, target: Component) -> bool:
    """
    Tell whether a full channel is worth its six entries: determined, and not the stated shape.

    Each generalised variance ``λ_j`` of (Σ̂, Σ_stated) (the factor along the direction j
    relative to the stated noise there) must be within ``MAX_RELATIVE_SE_FULL``, and the
    largest and smallest must differ by more than ``MIN_ANISOTROPY`` and by three standard
    errors: else the stated shape times one factor says as much (and keeps the estimator's
    fast paths, which need an isotropic position noise with interpolated pairs).
    """
    cov = covariance_of_theta(fisher)
    k = 0
    for c in components:
        if c.mode == 'held':
            continue
        if c is target:
            block = cov[k:k + 6, k:k + 6]
            Li = np.linalg.inv(np.linalg.cholesky(c.stated))
            lam, U = np.linalg.eigh(Li @ c.covariance() @ Li.T)
            rel = np.zeros(3)
            for j in range(3):
                v = Li.T @ U[:, j]  # λ_j = vᵀ Σ̂ v
                g = np.array([v[0] ** 2, v[1] ** 2, v[2] ** 2, 2 * v[0] * v[1],
                              2 * v[0] * v[2], 2 * v[1] * v[2]])
                se = float(np.sqrt(max(g @ block @ g, 0.0)))
                if not (lam[j] > 0 and se / lam[j] <= MAX_RELATIVE_SE_FULL):
                    return False
                rel[j] = se / lam[j]
            spread = float(np.log(lam[-1] / lam[0]))
            return spread > MIN_ANISOTROPY and spread > 3.0 * float(np.hypot(rel[0], rel[-1]))
        k += len(c.theta)
    return False


def stated_channels(spec: ModelSpec, cov_a: np.ndarray, cov_b: np.ndarray,
                    with_a: bool) -> dict:
    """(device, kind) -> stated 3×3 covariance of the channels the model (and method) has."""
    cov_a, cov_b = np.asarray(cov_a).reshape(6, 6), np.asarray(cov_b).reshape(6, 6)
    out = {('b', 'position'): cov_b[0:3, 0:3]}
    if spec.has_q1:
        out[('b', 'rotation')] = cov_b[3:6, 3:6]
    if with_a:
        out[('a', 'position')] = cov_a[0:3, 0:3]
        out[('a', 'rotation')] = cov_a[3:6, 3:6]
    return out


def screened(pairs: _Pairs, layout: _Layout, S: np.ndarray) -> np.ndarray:
    """
    Flag the pairs within the noise S (d×d), by the rule of ``calibrate``'s robust fit.

    ``d² = rᵀ M⁻¹ r`` scaled by the lower quartile's excess over χ²_m's (a noise understated
    throughout is not an outlier); beyond χ²_m(1 - 10⁻⁴) a pair is out.
    """
    W = np.linalg.inv(pairs.K @ S @ pairs.K.transpose(0, 2, 1))
    d2 = np.einsum('nm,nmk,nk->n', pairs.r, W, pairs.r)
    m = pairs.r.shape[1]
    scale = max(1.0, float(np.quantile(d2, 0.25)) / float(chi2_ppf(0.25, m)))
    return d2 <= scale * float(chi2_isf(1e-4, m))


def noise_matrix(layout: _Layout, covariances: dict) -> np.ndarray:
    """Return S (d×d) of channel covariances ((device, kind) -> 3×3)."""
    return _assemble([Component(ch, np.asarray(c, dtype=float), 'held')
                      for ch, c in covariances.items()], layout)


def unmodelled_correlation(pairs: _Pairs, layout: _Layout, S: np.ndarray) -> float:
    """
    Return the largest correlation of position with rotation errors the noise S leaves.

    The errors whitened by ``M_i^{-1/2}`` (symmetric) are uncorrelated when S holds all there
    is; a device whose position and rotation errors go together (a camera's pose from a
    target) shows as a correlation between the position and rotation rows, which no 3×3
    covariance per channel can state. 0 for models without B's orientation.
    """
    if ('b', 'rotation') not in layout.blocks or len(pairs.r) < 10:
        return 0.0
    lam, V = np.linalg.eigh(pairs.K @ S @ pairs.K.transpose(0, 2, 1))
    z = np.einsum('nij,nj->ni', V / np.sqrt(lam)[:, None, :],
                  np.einsum('nji,nj->ni', V, pairs.r))
    C = z.T @ z / len(z)
    d = np.sqrt(np.diag(C))
    corr = C / np.outer(d, d)
    return float(np.max(np.abs(corr[0:3, 3:6])))


def ols_stated(pairs: _Pairs, layout: _Layout, stated: dict, cov_a: np.ndarray) -> dict:
    """
    Return what OLS's B channels hold as stated: B's noise and A's carried into their rows.

    (device, kind) of B -> the mean trace, over the pairs, of the channel's rows of
    ``D_B S_B D_Bᵀ + F_x Σ_A F_xᵀ`` at the stated noise (error-metric units, as ``weight``).
    """
    A = np.einsum('nmi,ij,nkj->nmk', pairs.Jx, np.asarray(cov_a).reshape(6, 6), pairs.Jx)
    with_rotation = ('b', 'rotation') in layout.blocks
    rows = {'position': slice(0, 3) if with_rotation else slice(0, layout.d_b),
            'rotation': slice(3, 6)}
    out = {}
    for channel in layout.blocks:
        if channel[0] != 'b':
            continue
        sl = rows[channel[1]]
        a_part = float(np.mean(np.trace(A[:, sl, sl], axis1=1, axis2=2)))
        out[channel] = weight(pairs, layout, channel, stated[channel]) + a_part
    return out


def component_of(fit: ComponentFit, channel: tuple) -> Optional[Component]:
    """Return the component of ``channel`` (None when the model has none)."""
    return next((c for c in fit.components if c.channel == channel), None)
