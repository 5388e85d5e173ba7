"""
The blocks a candidate effect is judged on, and whether its gain is its own.

A time or mean effect predicts, from its own fit, how much it gains in each held-out block
(``expected_block_gains``: half the sum of the squared moves of the errors it makes over their
variance). It is judged only on the blocks where that prediction stands clear of zero
(``blocks_judged``): elsewhere the held-out sign is a coin flip (a drift from zero in its first
blocks, a change before its instant). And its gain must be its own (``own_gain_reasons``): a
model refitted with an effect whose parameters stay near zero can gain from the others'
parameters alone.
"""

from __future__ import annotations

from typing import Optional, TYPE_CHECKING

from coreg_ros.core.diagnosis import variance as vm
from coreg_ros.core.diagnosis.effects.registry import CANDIDATES
import numpy as np

if TYPE_CHECKING:  # pragma: no cover - annotations only
    from coreg_ros.core.diagnosis.fit import Fit


#: A block is expected to gain from a time or mean effect when the effect's own fit predicts
#: a gain there of at least this many nats. An error the model leaves of noncentrality λ in a
#: block (Σ of its squared moves over the noise) gains λ/2 there on average with a standard
#: deviation of √λ: from λ/2 = 2 nats on (λ = 4) the expected gain stands one standard
#: deviation above zero. Below it the block's sign is a coin flip (a drift from zero in its
#: first blocks, a pose step before its instant, a small effect where the motion hides it).
EXPECTED_BLOCK_GAIN = 2.0


def expected_block_gains(sel, fit: Fit, name: str, labels: np.ndarray
                         ) -> Optional[np.ndarray]:
    """
    Return the gain (nats, per block of ``labels``) a time or mean effect predicts for itself.

    Per pair, ``½ Σ Δz² / D``: the change of the decorrelated error the effect makes in the
    fit (its θ against θ = 0, the rest held), over the fitted noise variance, weighted by the
    pair's inlier weight; summed per block of the selection pairs of ``sel`` (a
    ``selection.Selector``). None for a noise effect (it moves no error).
    """
    if CANDIDATES[name].acts_on not in ('time', 'mean') or fit is None:
        return None
    state = fit.state
    if name not in state.theta:
        return None
    zero = state.copy()
    zero.theta[name] = np.zeros_like(state.theta[name])
    model = fit.model
    per_pair = np.empty(len(sel.idx))
    at = 0
    for ch in model.chunks(sel.idx):
        a = model.evaluate(state, ch, jac=False)
        b = model.evaluate(zero, ch, jac=False)
        D, _, w = vm.weights(state.var, a.st)
        dz = a.st.z - b.st.z
        per_pair[at:at + len(ch)] = 0.5 * w * np.sum(dz ** 2 / D, axis=1)
        at += len(ch)
    return np.bincount(labels, weights=per_pair, minlength=sel.K)


def blocks_judged(sel, name: str, labels: np.ndarray, fit: Optional[Fit] = None,
                  expected: Optional[np.ndarray] = None) -> np.ndarray:
    """
    Return the blocks (bool, K) an effect is judged on.

    Those with pairs; for a change in time (``changes_at``) only those with pairs from its
    instant on; for a time or mean effect with its ``fit`` (or its ``expected`` block gains)
    given, only those where it expects to gain (``EXPECTED_BLOCK_GAIN``,
    ``expected_block_gains``), unless it expects that nowhere (then every block with pairs).
    """
    judged = np.bincount(labels, minlength=sel.K) > 0
    key = CANDIDATES[name].changes_at
    found = sel.data.cache.get(key) if key else None
    if found is not None and labels is sel.tf:
        after = sel.data.t[sel.idx] >= float(found.at_s)
        judged &= np.bincount(labels[after], minlength=sel.K) > 0
    if expected is None:
        expected = expected_block_gains(sel, fit, name, labels)
    if expected is not None:
        gaining = judged & (expected >= EXPECTED_BLOCK_GAIN)
        if gaining.any():
            judged = gaining
    return judged


#: A candidate whose predicted gain is below this share of the practical threshold is not
#: refitted (the screening of ``selection``: its held-out gain cannot reach the threshold),
#: and a time or mean effect's own moves must predict at least this share of it
#: (``own_gain_reasons``); the share leaves room for the linearisation's error.
SCREEN_SHARE = 0.3


def own_gain_reasons(expected: Optional[np.ndarray], thr: float) -> list:
    """
    Why a time or mean effect's gain is not its own, or nothing.

    Its held-out gain must come from the errors it moves: the gain its own θ predicts
    (``expected_block_gains`` summed) must reach ``SCREEN_SHARE`` of the practical ``thr``. A
    model refitted with an effect whose θ stays near zero can still gain when the other
    effects' parameters converge further from the new start: that gain is theirs.
    """
    if expected is None:
        return []
    own = float(np.sum(expected))
    if own >= SCREEN_SHARE * thr:
        return []
    return [f'its own moves predict a gain of {own:.1f} nats, below {SCREEN_SHARE:g} of the '
            f'practical {thr:.1f}: the gain is the refit of the others']
