"""
The estimator, laid out as Ikits (2000) appendix B.

====================  ===========================================================================
module                what it holds
====================  ===========================================================================
``problem``           the problem, its whitening (eqs. 28-30: how the noise enters the metric) and
                      the chunk size
``lm``                the Levenberg-Marquardt driver, its stopping rule and status messages
``ols``               weighted OLS, B.1 (eqs. 32-36)
``tls``               errors-in-variables TLS, B.2: Schur complement, back-substitution
``normal_equations``  the per-pair normal equations of full-pose and position-only problems in
                      closed form (OLS and TLS), used by ``ols`` and ``tls`` where they apply
``linearized``        one pair weighed on its own at the measured input (Σ_eff): the robust
                      statistic d², the clock offset's column
``priors``            a priori estimates as residual rows, B.3 (eqs. 55-56), from a pose ``Prior``
``posterior``         the solution and its covariance, B.4.2 (eq. 58), in the ROS layout
``state``             what a fit carries beyond φ: TLS inputs, how to go on from it (resume)
``refit``             refits that go on from the last fit: pairs taken out (TLS), reweighted
                      0/1 (OLS), a paused fit's heading
``batched``           Cholesky factors and solves of stacks of small SPD blocks (generic TLS)
====================  ===========================================================================

Both solvers work through the pairs in chunks, so memory stays O(chunk) above the O(N) state,
and time is O(N) per iteration.
"""

from coreg_ros.core.estimator.lm import MESSAGES, XTOL
from coreg_ros.core.estimator.ols import ols_cost, ols_information, solve_ols
from coreg_ros.core.estimator.posterior import Solution
from coreg_ros.core.estimator.priors import PriorTerm
from coreg_ros.core.estimator.problem import (
    CHUNK,
    metric_covariance,
    output_covariance,
    Problem,
    whitening,
)
from coreg_ros.core.estimator.refit import (
    can_take_out,
    carried_inputs,
    heading,
    paused,
    reweighted,
    weighable,
    without_pairs,
)
from coreg_ros.core.estimator.state import (
    InputState,
    NormalEquations,
    Resume,
    TlsResume,
    TlsSeed,
    TlsSums,
)
from coreg_ros.core.estimator.tls import (
    back_substitute,
    DAMPING_SHARE,
    solve_tls,
    tls_linearization,
    tls_residuals,
)
from coreg_ros.core.noise_model import noise_covariance  # the noise in any form, as 6×6

__all__ = [
    'back_substitute',
    'can_take_out',
    'carried_inputs',
    'CHUNK',
    'DAMPING_SHARE',
    'heading',
    'ols_cost',
    'ols_information',
    'InputState',
    'MESSAGES',
    'metric_covariance',
    'noise_covariance',
    'NormalEquations',
    'output_covariance',
    'paused',
    'PriorTerm',
    'Problem',
    'Resume',
    'reweighted',
    'Solution',
    'solve_ols',
    'solve_tls',
    'tls_linearization',
    'tls_residuals',
    'TlsResume',
    'TlsSeed',
    'TlsSums',
    'weighable',
    'whitening',
    'without_pairs',
    'XTOL',
]
