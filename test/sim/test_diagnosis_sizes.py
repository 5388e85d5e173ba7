"""
Size accuracy of the spatial and local effects, by Monte Carlo on random draws (issue 11).

Each named effect's size should be within 20 % of the truth for medium and large sizes. The
cases are drawn at random (fixed seeds here, for repeatable tests) by the validation
harness's own drawing, one effect at a time: the truth's size and the estimate measure the
same thing (field: the largest error a rigid registration cannot absorb, over the recorded
samples; link flex: the marker's sag when the link is horizontal; non-stationary: the largest
position error while it acts). The tolerance is honest for the rate: with 95 % of the cases
within 20 %, at most one miss in eight happens with probability 0.94.
"""

from coreg_ros.sim.validation import draw_effect_cases, run_case
import numpy as np
import pytest

N_CASES = 8


@pytest.mark.parametrize('name,seed', [('field_distortion', 71), ('link_flex', 72),
                                       ('non_stationary', 73)])
def test_named_sizes_are_within_20_percent_of_the_truth(name, seed):
    cases = draw_effect_cases(np.random.default_rng(seed), name, N_CASES,
                              duration=(40.0, 70.0))
    ratios = []
    for case in cases:
        res = run_case(case)
        if res['size_ratio'] is not None:
            ratios.append(res['size_ratio'])
    ratios = np.array(ratios)
    # named (and sized) in most cases; medium non-stationary errors may stay unseen
    assert len(ratios) >= N_CASES - 2
    within = np.abs(ratios - 1.0) <= 0.2
    assert np.sum(~within) <= 1, ratios
    # and not biased: the median ratio within 10 % of one
    assert abs(float(np.median(ratios)) - 1.0) < 0.1, ratios
