"""
The diagnosis report as a typed record (``DiagnosisReport``); ``as_dict()`` is its JSON.

The document of ``coreg diagnose --json`` is ``DiagnosisReport.as_dict()`` with the settings
and the bag added; its parts are the records of the modules that measure them: the effects
found (``effects.finding.Finding``), the gap before and after (``gap.py``), the excess left and
the noise excess (``findings.py``), the located excess (``locate.py``), the detection
(``detect.py``), the candidates' ranking (``selection.py``), the calibration (``summary.py``)
and the stamps (``stamps.py``).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

from coreg_ros.core.diagnosis.detect import Detection
from coreg_ros.core.diagnosis.findings import ExcessLeft, NoiseExcess
from coreg_ros.core.diagnosis.gap import GapAfter, GapBefore
from coreg_ros.core.diagnosis.locate import Location
from coreg_ros.core.diagnosis.record import optional, Record
from coreg_ros.core.diagnosis.stamps import StampReport
from coreg_ros.core.diagnosis.summary import Transforms


@dataclass(frozen=True)
class CalibrationChange(Record):
    """The calibration without the effects (the base model) and with them (the final one)."""

    before: Transforms
    after: Transforms


@dataclass(frozen=True)
class StatedNoise(Record):
    """The noise the recording is judged against: (position m, rotation rad) per device."""

    sigma_a: list
    sigma_b: list


@dataclass(frozen=True, kw_only=True)
class Pairing(Record):
    """
    How the streams were paired (``pairing.pair_for``'s report).

    Attributes
    ----------
    n_a, n_b : int
        Samples of A and B.
    n_paired : int
    unpaired : dict
        B samples left unpaired, per reason.

    """

    n_a: int
    n_b: int
    n_paired: int
    unpaired: dict


@dataclass(frozen=True, kw_only=True)
class DiagnosisReport(Record):
    """
    The diagnosis of a recording: the gap, the effects that explain it, where the rest lies.

    Attributes
    ----------
    gap_detected : bool
        A test found a practically relevant gap, an effect was found or the stamps show
        issues.
    effects : list of Finding
        The effects found, the most telling first.
    not_separable : list of [str, str]
        An accepted effect and a rival that explains the same with the recorded motion.
    gap_before, gap_after : GapBefore, GapAfter
        The held-out gap before and after the accepted effects.
    noise_excess : NoiseExcess or None
        The noise left larger (or smaller) than stated; None when it is as stated.
    excess_left : ExcessLeft
    location : Location
        Where the base fit's excess lies.
    verdict : str
        The answer in one sentence.
    detection : Detection
    candidates : list of list of CandidateScore
        The candidates of each round of the selection, best first.
    calibration : CalibrationChange
    model : str
    n_pairs, n_pairs_selection : int
        Pairs, and those the selection used.
    duration_s : float
    stated_noise : StatedNoise
    stamps : StampReport, optional
        What the stamps say (from the streams).
    coarse_offset_s : float, optional
        The offset the coarse search moved the pairing by, s.
    pairing : Pairing, optional
        How the streams were paired (from the streams).
    noise : dict, optional
        With ``noise: auto``: the noise estimated with the calibration, which the diagnosis
        took as its floor, beside the stated (``noise_verdict.estimate_dict``).

    """

    gap_detected: bool
    effects: list
    not_separable: list
    gap_before: GapBefore
    gap_after: GapAfter
    noise_excess: Optional[NoiseExcess]
    excess_left: ExcessLeft
    location: Location
    verdict: str
    detection: Detection
    candidates: list
    calibration: CalibrationChange
    model: str
    n_pairs: int
    n_pairs_selection: int
    duration_s: float
    stated_noise: StatedNoise
    stamps: Optional[StampReport] = optional()
    coarse_offset_s: Optional[float] = optional()
    pairing: Optional[Pairing] = optional()
    noise: Optional[dict] = optional()
