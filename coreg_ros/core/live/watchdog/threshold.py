"""The CUSUM's threshold from its exact in-control run length (Brook & Evans' Markov chain)."""

from __future__ import annotations

import functools

from coreg_ros.core.distributions import chi2_cdf, chi2_isf, scipy_stats
import numpy as np

#: Residual covariance inflation the CUSUM is tuned to (λ: d² ≈ λ χ²_m under the change).
DESIGN_INFLATION = 2.0
#: d² is clipped at the χ²_m quantile 1 - CLIP_TAIL in the CUSUM.
CLIP_TAIL = 1e-3
#: Mean pairs between false alarms the threshold is set for (χ²_m residuals).
TARGET_RUN_LENGTH = 1e9
#: Cells of the Brook-Evans Markov chain.
CHAIN_CELLS = 500
# --------------------------------------------------------------------------- the threshold


def llr_constants(m: int, inflation: float) -> tuple[float, float, float]:
    """Return (a, b, clip) of ``ℓ = a min(d², clip) - b``."""
    a = 0.5 * (1.0 - 1.0 / inflation)
    b = 0.5 * m * np.log(inflation)
    return a, b, float(chi2_isf(CLIP_TAIL, m))


def run_length(threshold: float, m: int, inflation: float = DESIGN_INFLATION,
               noncentrality: float = 0.0, cells: int = CHAIN_CELLS) -> float:
    """
    Mean pairs to an alarm of the CUSUM from zero (Brook & Evans' Markov chain).

    Parameters
    ----------
    threshold : float
        h.
    m : int
        Residuals per pair (χ²_m).
    inflation : float
        λ of the CUSUM's likelihood ratio.
    noncentrality : float
        d² ~ χ²_m(noncentrality) (0: in control, the false-alarm run length; > 0: the
        detection delay of a mean change of that size in σ²).
    cells : int
        States of the chain.

    """
    a, b, clip = llr_constants(m, inflation)
    width = threshold / cells
    values = np.arange(cells) * width
    edges = (np.arange(cells) + 0.5) * width
    edges[-1] = threshold

    def cdf(y):
        x = (y + b) / a
        inner = (scipy_stats().ncx2.cdf(np.maximum(x, 0.0), m, noncentrality) if noncentrality > 0
                 else chi2_cdf(np.maximum(x, 0.0), m))
        return np.where(x >= clip, 1.0, np.where(x < 0.0, 0.0, inner))

    upto = cdf(edges[None, :] - values[:, None])
    P = np.diff(np.concatenate([np.zeros((cells, 1)), upto], axis=1), axis=1)
    return float(np.linalg.solve(np.eye(cells) - P, np.ones(cells))[0])


@functools.lru_cache(maxsize=16)
def cusum_threshold(m: int, target: float = TARGET_RUN_LENGTH,
                    inflation: float = DESIGN_INFLATION) -> float:
    """
    Return the threshold h whose in-control mean run length is ``target`` pairs.

    ln ARL(h) is smooth and increasing in h; Brent's method on ``ln ARL(h) - ln target`` over
    [5, 25] brackets the root and always reaches it (plain regula falsi, used before, could
    keep one end fixed and stop 2.6 % off the target for m = 3).
    """
    def excess(h: float) -> float:
        return float(np.log(run_length(h, m, inflation)) - np.log(target))

    # imported on first use: scipy.optimize adds 0.15 s of CPU to every command's start
    from scipy import optimize
    return float(optimize.brentq(excess, 5.0, 25.0, xtol=1e-9, rtol=1e-12))
