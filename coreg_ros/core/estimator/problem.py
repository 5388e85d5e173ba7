"""
The calibration problem and its whitening (Ikits eqs. 28-30).

Residuals are whitened, ``r = L e`` with ``W = LᵀL`` the inverse covariance of the error
metric (eqs. 29-30), so the cost is ``Σ r²`` (eq. 28, the chi-square of eq. 57). The noise is
given in the ROS layout: position (m²) and rotation vector (rad²). The rotation part of the
error metric is the vector part of an error quaternion, ``q_e ≈ k_e θ_e / 2`` (eq. 14): about
*half* the angle. Hence, in this module only, the one statement of it:

    **a rotation covariance Σθ enters the metric as Σθ/4** (and position-rotation cross terms
    as -1/2), by ``metric_covariance``.

Every other place that needs the metric's covariance (the estimator, the robust statistic,
the diagnosis) takes it from here. The work is done in chunks of ``CHUNK`` pairs, one size for
the whole estimator.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Optional

from coreg_ros.core.errors import InputError
from coreg_ros.core.models import ModelSpec
import numpy as np

#: Pairs processed at once, everywhere in the estimator (generic and structured paths, the
#: robust statistic): bounds the transient memory (at most about 3 KB per pair of a chunk)
#: while long vectors amortise numpy's per-call overhead.
CHUNK = 8192

#: ∂(error metric)/∂(ROS-layout noise): identity on position, -1/2 on the rotation vector
#: (eq. 14: the metric is minus half the rotation angle).
_METRIC = np.diag([1.0, 1.0, 1.0, -0.5, -0.5, -0.5])


def metric_covariance(cov: np.ndarray) -> np.ndarray:
    """
    Covariance of the error metric from a 6×6 ROS-layout covariance: Σθ enters as Σθ/4.

    The module docstring says why (Ikits eq. 14).

    Parameters
    ----------
    cov : ndarray, shape (6, 6)
        Position (m²) and rotation-vector (rad²) covariance.

    Returns
    -------
    ndarray, shape (6, 6)

    """
    return _METRIC @ np.asarray(cov, dtype=float).reshape(6, 6) @ _METRIC


def output_covariance(cov_b: np.ndarray, spec: ModelSpec) -> np.ndarray:
    """Metric covariance of B's output (m×m): 6×6 full pose, 3×3 per marker otherwise."""
    metric = metric_covariance(cov_b)
    if spec.name == 'full_pose':
        return metric
    m = 3 * spec.n_markers
    out = np.zeros((m, m))
    for j in range(spec.n_markers):
        out[3 * j:3 * j + 3, 3 * j:3 * j + 3] = metric[0:3, 0:3]
    return out


def whitening(cov: np.ndarray, spec: Optional[ModelSpec], device: str) -> np.ndarray:
    """
    L with LᵀL the inverse covariance of the error metric, for device 'a' (6×6) or 'b' (m×m).

    Parameters
    ----------
    cov : ndarray, shape (6, 6)
        The device's noise covariance, ROS layout (``metric_covariance`` converts it).
    spec : ModelSpec or None
        The model (device 'b' only: it sets the output metric).
    device : {'a', 'b'}
        Which device the noise is of.

    """
    metric = metric_covariance(cov) if device == 'a' else output_covariance(cov, spec)
    try:
        return np.linalg.inv(np.linalg.cholesky(metric))
    except np.linalg.LinAlgError as e:
        raise InputError(f'noise covariance of device {device.upper()} is not positive '
                         f'definite; give positive standard deviations') from e


def chunk_slices(n: int, size: int = CHUNK) -> list:
    """Slices of at most ``size`` pairs covering n pairs."""
    return [slice(i, min(i + size, n)) for i in range(0, n, size)]


def pair_last(n: int, m: int) -> np.ndarray:
    """Return an (n, m) array stored pair-last (chunks of pair-last rows copy in at once)."""
    return np.empty((m, n)).T


class Columns:
    """
    A (rows, N) pair-last result filled chunk by chunk, or only its columns ``kept``.

    Parameters
    ----------
    n : int
        Number of pairs N the chunks cover.
    kept : ndarray of int, shape (K,), optional
        Increasing indices of the columns kept (None: all N); ``out`` is (rows, K).
    rows : int
        Rows of the result.

    """

    def __init__(self, n: int, kept: Optional[np.ndarray] = None, rows: int = 6):
        self.kept = kept
        self.out = np.empty((rows, n if kept is None else len(kept)))

    def put(self, sl: slice, values: np.ndarray, rows: slice = slice(None)) -> None:
        """Write ``values`` (r, c), the chunk ``sl``'s columns, into ``out[rows]``."""
        if self.kept is None:
            self.out[rows, sl] = values
            return
        lo, hi = np.searchsorted(self.kept, (sl.start, sl.stop))
        self.out[rows, lo:hi] = values[:, self.kept[lo:hi] - sl.start]


@dataclass
class Problem:
    """
    A calibration problem: pairs, noise whitening and optional priors.

    Attributes
    ----------
    spec : ModelSpec
    pos_a : ndarray, shape (N, 3)
    quat_a : ndarray, shape (N, 4)
        Unit quaternions (w, x, y, z), as ``calibrate`` validates them; the closed forms of
        ``normal_equations`` rely on unit length.
    pos_b : ndarray, shape (N, 3) or (N, 3, 3)
    quat_b : ndarray, shape (N, 4) or None
        Unit quaternions, or None for position-only models.
    whiten_b : ndarray, shape (m, m)
        L_y with ``L_yᵀ L_y`` the inverse covariance of the output error metric.
    whiten_a : ndarray, shape (6, 6)
        L_x for the input error metric (TLS only).
    a_scale : ndarray, shape (N,) or None
        Per-pair factor on A's noise variance.
    priors : list of PriorTerm
    weights : ndarray, shape (N,) or None
        OLS on the structured path only: pair i's terms count w_i times (1 kept, 0 left
        out, its residuals still computed). TLS and the generic path take subsets instead.

    """

    spec: ModelSpec
    pos_a: np.ndarray
    quat_a: np.ndarray
    pos_b: np.ndarray
    quat_b: Optional[np.ndarray]
    whiten_b: np.ndarray
    whiten_a: np.ndarray
    a_scale: Optional[np.ndarray] = None
    priors: list = field(default_factory=list)
    weights: Optional[np.ndarray] = None

    def __post_init__(self):
        # Diagonal output whitening (independent noise per axis, the usual case) is applied by
        # broadcasting instead of a batched matrix product.
        self.diag_b = _diagonal_or_none(self.whiten_b)

    def whiten_out(self, M: np.ndarray) -> np.ndarray:
        """L_y M for a stack M of shape (c, m, k)."""
        return M * self.diag_b[:, None] if self.diag_b is not None else np.matmul(self.whiten_b, M)

    @property
    def n(self) -> int:
        """Return the number of pairs N."""
        return len(self.pos_a)

    @property
    def n_fitted(self) -> int:
        """Return the number of pairs the fit counts (N, or the number of non-zero weights)."""
        return self.n if self.weights is None else int(np.count_nonzero(self.weights))

    def chunks(self):
        """Slices of at most CHUNK pairs covering all pairs."""
        return chunk_slices(self.n)

    def output(self, sl: slice):
        """Measured output of the pairs in ``sl``."""
        return self.pos_b[sl], None if self.quat_b is None else self.quat_b[sl]

    def subset(self, idx: Optional[np.ndarray], priors: Optional[list] = None,
               weights: Optional[np.ndarray] = None, lazy: bool = False) -> Problem:
        """
        Return the problem of the pairs ``idx`` alone, with the same noise.

        Parameters
        ----------
        idx : ndarray of int, shape (K,), or None
            Indices of the pairs (None: all, the arrays themselves, not copied).
        priors : list of PriorTerm, optional
            The subset's priors (default none: a part of the data, e.g. pairs to take out).
        weights : ndarray, shape (K,), optional
            The subset's pair weights (OLS on the structured path); this problem's are not
            carried over.
        lazy : bool
            Gather the pairs chunk by chunk as the solvers read them (``RowsOf``) instead of
            copying them now: for a subset of nearly all pairs (a robust refit) that would
            hold a second copy of every array (112 B a pair) for no speed.

        """
        def sub(x):  # np.take: a boolean index is 6× slower on (N, 4) arrays
            if x is None or idx is None:
                return x
            return RowsOf(x, idx) if lazy else np.take(x, idx, axis=0)

        return Problem(self.spec, sub(self.pos_a), sub(self.quat_a), sub(self.pos_b),
                       sub(self.quat_b), self.whiten_b, self.whiten_a, sub(self.a_scale),
                       [] if priors is None else priors, weights)


class RowsOf:
    """
    The rows ``idx`` of an array, gathered when a slice of them is read (a lazy subset).

    The solvers read a Problem's arrays a chunk at a time (``chunk_slices``); each chunk here
    is ``np.take(base, idx[chunk])``, the very values a copied subset would hold, so results
    are bit for bit those of ``Problem.subset(idx)``. Anything else (``np.asarray``, an
    integer or array index) gets the whole subset as a copy.

    Parameters
    ----------
    base : ndarray, shape (N, ...)
        The full array (not copied; must not change while this view is in use).
    idx : ndarray of int, shape (K,)
        Row indices into ``base``.

    """

    def __init__(self, base: np.ndarray, idx: np.ndarray):
        self.base, self.idx = base, idx

    def __len__(self) -> int:
        return len(self.idx)

    @property
    def shape(self) -> tuple:
        """Shape of the subset, (K, ...)."""
        return (len(self.idx), *self.base.shape[1:])

    @property
    def ndim(self) -> int:
        """Dimensions of the subset (those of ``base``)."""
        return self.base.ndim

    @property
    def dtype(self) -> np.dtype:
        """Element type of ``base``."""
        return self.base.dtype

    def __getitem__(self, key):
        if isinstance(key, slice):
            return np.take(self.base, self.idx[key], axis=0)
        return np.asarray(self)[key]

    def __array__(self, dtype=None, copy=None):
        out = np.take(self.base, self.idx, axis=0)
        return out if dtype is None else out.astype(dtype)


def _diagonal_or_none(L: np.ndarray):
    """Return the diagonal of L if L is diagonal, else None."""
    return np.diag(L).copy() if np.count_nonzero(L - np.diag(np.diag(L))) == 0 else None
