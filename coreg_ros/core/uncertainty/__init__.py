"""
First-order algebra of uncertain poses: composition, inversion, points, fusion, ellipsoids, cones.

Modules: ``composition`` (compose, chain, through a calibration, invert, points), ``fusion``,
``consistency`` (pose errors, NEES, coverage), ``geometry`` (ellipsoids, axis cones, display
geometry); the small SO(3) algebra is ``coreg_ros.core.so3``. Everything is re-exported here.

Every covariance follows docs/design.md §3 (``geometry_msgs/PoseWithCovariance``): 6×6 over
(x, y, z, δθx, δθy, δθz), the truth being ``p_true = p + δp`` and
``R_true = Exp(δθ) · R`` about the fixed axes of the frame the pose is expressed in. A negative
diagonal entry marks a component that is not known (``covariance.UNKNOWN``); it is carried as
infinite variance: every output that depends on it is marked unknown too, and fusion gives it
zero information.

Functions on arrays (``*_arrays``) are vectorised over leading axes, for Monte Carlo checks and
per-sample streams; the ``UncertainPose`` functions wrap them for one pose.

Method (Hoff & Vincent 2000): the covariance of a function y = g(x, w) of two uncertain
operands is ``C_y = J_x C_x J_xᵀ + J_w C_w J_wᵀ`` (eqs. 6-7; with their cross-covariance when
the operands are correlated, e.g. the two transforms of one calibration); the positional
uncertainty is the ellipsoid ``{z : (z - z̄)ᵀ C_z⁻¹ (z - z̄) ≤ k²}`` of the upper-left 3×3 block
(eqs. 8-9, §3.3); the rotational uncertainty is shown as a cone about each axis a = R e, whose
covariance ``C_a = [a]× C_θ [a]×ᵀ`` has rank 2 (§3.3, Fig. 1); two estimates of one pose are
fused by inverse-covariance weighting on the tangent space (§3.4).

References
----------
Hoff, W., Vincent, T. (2000). Analysis of head pose accuracy in augmented reality. IEEE TVCG
6(4), 319-334.

"""

from coreg_ros.core.estimator.posterior import UNKNOWN
from coreg_ros.core.so3 import left_jacobian, skew
from coreg_ros.core.uncertainty.composition import (
    chain,
    compose,
    compose_arrays,
    compose_jacobians,
    inverse_jacobian,
    invert,
    invert_arrays,
    propagate_point,
    propagate_point_arrays,
    through_calibration,
    through_calibration_arrays,
)
from coreg_ros.core.uncertainty.consistency import (
    coverage_probability,
    nees,
    pose_error,
    sigma_for_probability,
)
from coreg_ros.core.uncertainty.fusion import (
    fuse,
    fuse_arrays,
)
from coreg_ros.core.uncertainty.geometry import (
    axis_cones,
    axis_covariance,
    AxisCone,
    cone_mesh,
    Ellipsoid,
    ellipsoid_axes,
    ellipsoid_orientation,
)

__all__ = [
    'UNKNOWN',
    'left_jacobian',
    'skew',
    'compose_jacobians',
    'compose_arrays',
    'compose',
    'chain',
    'through_calibration_arrays',
    'through_calibration',
    'inverse_jacobian',
    'invert_arrays',
    'invert',
    'propagate_point_arrays',
    'propagate_point',
    'pose_error',
    'nees',
    'coverage_probability',
    'sigma_for_probability',
    'fuse_arrays',
    'fuse',
    'Ellipsoid',
    'ellipsoid_axes',
    'AxisCone',
    'axis_covariance',
    'axis_cones',
    'ellipsoid_orientation',
    'cone_mesh',
]
