"""Tuning of the diagnosis (``Options``) and the progress callback it reports to."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

from coreg_ros.core.diagnosis.effects.registry import EFFECT_NAMES

#: ``progress(fraction, text)``, called as the work advances.
Progress = Callable[[float, str], None]


@dataclass(frozen=True)
class Options:
    """
    Tuning of the diagnosis.

    Attributes
    ----------
    n_folds : int
        Blocks of the held-out validation.
    max_effects : int
        Effects accepted at most.
    max_select_pairs : int
        Pairs used to select effects (an even subsample beyond); the final fit uses all.
    practical : float
        Smallest held-out gain that counts, in nats per residual (0.005 ≈ a change of 0.01 in
        chi-square per degree of freedom, or a noise factor off by 7 %).
    practical_next : float
        The same for the second and third effect: by default the same as the first's. An
        effect is held to one threshold whatever the order it is found in (the re-test holds
        every named effect to ``practical`` with the others present); a higher one for the
        later rounds missed the smaller effect of a pair (issue 26: 32 of the 59 pairs not
        both named in the 800-case validation were a small effect beside a larger one).
    min_gain : float
        Smallest held-out gain in nats, whatever the size of the recording.
    not_separable_ratio : float
        A runner-up gaining at least this share of the best candidate's gain is tested for
        separability.
    nested_share : float
        The richer of two nested candidates is preferred when it gains at least this share of
        the practical threshold more than the simpler one.
    candidates : tuple of str
    seed : int
        Seed of the spatial blocks.

    """

    n_folds: int = 5
    max_effects: int = 3
    max_select_pairs: int = 15000
    practical: float = 0.005
    practical_next: float = 0.005
    min_gain: float = 10.0
    not_separable_ratio: float = 0.6
    nested_share: float = 0.25
    candidates: tuple = EFFECT_NAMES
    seed: int = 0
