"""
One effect the report names (``Finding``): its estimate and how the diagnosis found it.

Most are candidates the selection accepted, with their held-out gain; some are read
elsewhere: a time offset the coarse search found before pairing, stamp jitter read from the
stamps, a non-stationary error named from what the fitted effects leave (no held-out gain of
their own: zero).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

from coreg_ros.core.diagnosis.effects.base import CandidateEffect
from coreg_ros.core.diagnosis.record import apart, optional, Record

#: ``Finding.source`` of an offset the coarse search found, and of jitter read from the stamps.
COARSE_SEARCH = 'coarse search'
STAMPS = 'stamps'


@dataclass(frozen=True, kw_only=True)
class Finding(Record):
    """
    One effect the report names.

    Attributes
    ----------
    name, kind : str
        The effect (``effects.CANDIDATES``) and whether it is structure or noise.
    device : str
        Whose effect it is (``CandidateEffect.device``; from the stamps, the device whose
        stamps scatter).
    estimate : Record
        Its size with uncertainty (an instance of the effect's class, or
        ``stamps.StampJitter``).
    held_out_gain : float
        Gain in held-out log-likelihood over the model without it, nats.
    held_out_gain_per_residual : float
        The same per residual of the selection pairs.
    blocks_improved, blocks : int
        Held-out blocks it improves, of all.
    spatial_held_out_gain : float, optional
        The gain on unseen cells of the workspace (spatial effects).
    not_separable_with : list of str, optional
        Candidates that explain the same with the recorded motion.
    per_block_offsets : DriftCheck, optional
        The offsets fitted per time block that a clock drift must trend with.
    share_of_gap_explained : float, optional
        The held-out excess at the stated noise it takes off with the others present, as a
        share of the excess before any effect (``significance.retest``).
    held_out_rms_gain : dict, optional
        The relative fall of the held-out RMS at the stated noise it makes, per channel
        (``position``, ``rotation``), with the others present.
    renamed_from : str, optional
        The candidate it was found as (``from``: outliers that cluster are non-stationary).
    source : str, optional
        Where it was read when not from the residuals: ``COARSE_SEARCH`` or ``STAMPS``.

    """

    name: str
    kind: str
    device: str
    estimate: Record
    held_out_gain: float = 0.0
    held_out_gain_per_residual: float = 0.0
    blocks_improved: int = 0
    blocks: int = 0
    spatial_held_out_gain: Optional[float] = optional()
    not_separable_with: Optional[list] = optional()
    per_block_offsets: Optional[Record] = optional()
    share_of_gap_explained: Optional[float] = optional()
    held_out_rms_gain: Optional[dict] = optional()
    renamed_from: Optional[str] = optional('from')
    source: Optional[str] = apart()

    @classmethod
    def of(cls, estimate: CandidateEffect, **how) -> Finding:
        """Name the effect of an estimate (its class's name and kind)."""
        return cls(name=estimate.name, kind=estimate.kind, device=estimate.device,
                   estimate=estimate, **how)

    def as_dict(self) -> dict:
        """Return the finding's JSON dict: the source, when given, next to the estimate."""
        doc = super().as_dict()
        if self.source is None:
            return doc
        # what the stamps say is read before any residual; the coarse search refines after
        items = list(doc.items())
        items.insert(3 if self.source == STAMPS else 4, ('source', self.source))
        return dict(items)
