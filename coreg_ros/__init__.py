"""
coreg_ros: coregistration of two pose measurement devices (Ikits 2000) for ROS 2.

For Python users, the package itself is the front door::

    import coreg_ros as cr
    res = cr.calibrate(pos_a, quat_a_wxyz, pos_b, quat_b_wxyz, sigma_a=(2e-4, 5e-4),
                       sigma_b=(5e-4, 2e-3), method='tls')
    print(res.summary())

Names are imported on first use (PEP 562), so ``coreg --help`` and the ROS entry points do not
pay for numpy and scipy before they need them.
"""

from coreg_ros.lazy import lazy_exports

__version__ = '0.1.0'

#: Public name -> the module that defines it.
_HOMES = {
    # calibration
    'calibrate': 'coreg_ros.api',
    'model_of': 'coreg_ros.api',
    'calibrate_streams': 'coreg_ros.core.calibration.pipeline',
    'calibrate_pairs': 'coreg_ros.core.calibration.auto_noise',
    'pair_streams': 'coreg_ros.core.calibration.pairing',
    'Settings': 'coreg_ros.core.settings',
    'PoseStream': 'coreg_ros.core.types',
    'Pairs': 'coreg_ros.core.types',
    'PairingReport': 'coreg_ros.core.types',
    'CalibrationResult': 'coreg_ros.core.types',
    'UncertainPose': 'coreg_ros.core.types',
    'TimeOffset': 'coreg_ros.core.types',
    'STATUS': 'coreg_ros.core.types',
    'Prior': 'coreg_ros.core.estimator.priors',
    'load_prior': 'coreg_ros.files.results',
    'prior_from_dict': 'coreg_ros.files.results',
    'settings_from_mapping': 'coreg_ros.core.settings',
    'DeviceNoise': 'coreg_ros.core.noise_model',
    # uncertainty (Hoff & Vincent 2000)
    'compose': 'coreg_ros.core.uncertainty',
    'chain': 'coreg_ros.core.uncertainty',
    'invert': 'coreg_ros.core.uncertainty',
    'fuse': 'coreg_ros.core.uncertainty',
    'through_calibration': 'coreg_ros.core.uncertainty',
    'propagate_point': 'coreg_ros.core.uncertainty',
    'ellipsoid_axes': 'coreg_ros.core.uncertainty',
    'axis_cones': 'coreg_ros.core.uncertainty',
    'pose_error': 'coreg_ros.core.uncertainty',
    'nees': 'coreg_ros.core.uncertainty',
    # the gap diagnosis
    'diagnose': 'coreg_ros.core.diagnosis',
    'diagnose_streams': 'coreg_ros.core.diagnosis',
    # errors
    'CoregError': 'coreg_ros.core.errors',
    'InputError': 'coreg_ros.core.errors',
    'TooFewPairsError': 'coreg_ros.core.errors',
    'UnobservableError': 'coreg_ros.core.errors',
    'ConvergenceError': 'coreg_ros.core.errors',
    'InconsistentDataError': 'coreg_ros.core.errors',
    'BagError': 'coreg_ros.core.errors',
    'ConfigError': 'coreg_ros.core.errors',
}

__all__ = sorted(_HOMES)


__getattr__, __dir__ = lazy_exports(__name__, _HOMES, globals())
