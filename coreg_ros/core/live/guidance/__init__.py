r"""
Guidance while collecting: how accurate a calibration would be now, and which motion helps most.

From the pairs accumulated so far, the posterior σ each parameter would have is the inverse of
the information of the accumulated motion at the current estimate, in the errors-in-variables
("effective variance") form of ``crlb``:

.. math::

    \mathcal{I} = \sum_i F_i^T (Σ_b + s_i F_{x,i} Σ_a F_{x,i}^T)^{-1} F_i,

with ``F_i = [F_ψ, c]`` the Jacobian of B's measurement with respect to ψ (T0 and T1 in the ROS
tangents of ``crlb.model_jacobians``) and, when the clock offset is estimated, the offset's
column ``c = -F_x ẋ_A`` (A's interpolated pose moves with its velocity: ``linearized``). This
is the covariance ``calibrate_streams`` reports for TLS (the φ block of the inverse with τ
marginalised), evaluated at the measured inputs.

The sum is accumulated incrementally: each new pair adds its own term once, so an update at
1 Hz with 2 × 1 kHz streams costs about a millisecond. The Jacobians depend on the estimate
only through T0's rotation and the marker positions; when a new estimate moves those by more
than ``RELINEARISE_ROTATION`` / ``RELINEARISE_MARKER``, the sum is rebuilt from a bounded,
evenly decimated store of the pairs (an unbiased estimate of the full sum).

Candidate motions added to the recording (``CANDIDATE_SECONDS`` at the current pair rate,
from the tool's current pose): rotate the tool back and forth about one of its own axes, move
it back and forth along one of A's base axes, or hold it still (a pose that adds information
without coupling to the clock offset). The suggestion is the candidate whose added information
most reduces the worst ratio σ / target over the parameters.

Units SI (m, rad, s); quaternions (w, x, y, z).

Modules: ``keys`` (the /diagnostics vocabulary), ``feed`` (pairs and velocity), ``fisher``
(the estimate and its information), ``motions`` (candidates), ``accumulator`` (the result and
its incremental accumulator).
"""

from coreg_ros.lazy import lazy_exports

#: Public name -> the submodule that defines it (imported on first use, PEP 562, so that light
#: readers such as ``coreg watch`` can import a submodule without the numerical machinery).
_HOMES = {
    'AXES': 'keys',
    'CANDIDATE_ROTATION': 'motions',
    'CANDIDATE_SAMPLES': 'motions',
    'CANDIDATE_SECONDS': 'motions',
    'CANDIDATE_TRANSLATION': 'motions',
    'CHUNK': 'fisher',
    'CandidateMotion': 'motions',
    'Estimate': 'fisher',
    'GROUPS': 'keys',
    'GROUP_TITLES': 'keys',
    'Guidance': 'accumulator',
    'GuidanceAccumulator': 'accumulator',
    'KEY_DURATION': 'keys',
    'KEY_NEXT': 'keys',
    'KEY_NEXT_RATIO': 'keys',
    'KEY_NEXT_TEXT': 'keys',
    'KEY_PAIRS': 'keys',
    'KEY_READY': 'keys',
    'KEY_SIGMA_PREFIX': 'keys',
    'KEY_SUMMARY': 'keys',
    'KEY_TARGET_POSITION': 'keys',
    'KEY_TARGET_ROTATION': 'keys',
    'KEY_TARGET_TIME': 'keys',
    'KEY_WORST': 'keys',
    'KEY_WORST_RATIO': 'keys',
    'MAX_STORED_PAIRS': 'accumulator',
    'MotionOption': 'accumulator',
    'PairBatch': 'feed',
    'PairFeed': 'feed',
    'RELINEARISE_MARKER': 'fisher',
    'RELINEARISE_ROTATION': 'fisher',
    'STATUS_NAME': 'keys',
    'WEAK_PRIOR': 'fisher',
    'batch_from_pairs': 'feed',
    'candidate_motions': 'motions',
    'device_covariances': 'fisher',
    'effective_covariance': 'fisher',
    'information': 'fisher',
    'is_rotation_group': 'keys',
    'jacobians': 'fisher',
    'sigma_groups': 'fisher',
}

__all__ = sorted(_HOMES)


__getattr__, __dir__ = lazy_exports(__name__, _HOMES, globals())
