"""
A device's noise measured from a recording where it stands still (``coreg noise``).

==============  ==============================================================================
module          what it holds
==============  ==============================================================================
``still``       the still segments of a stream, found from the shape of the spread alone
``allan``       the Allan deviation: white noise, random walk, drift, how long to average
``distance``    σ against the distance from the base's origin
``measure``     one device: 3×3 covariances with their uncertainty, principal axes, sampling
``recording``   both devices of a recording (``measure_recording``), what the report holds
==============  ==============================================================================

The noise *estimated jointly with a calibration* from a moving recording (``--noise auto``)
is ``calibration.noise_components``.
"""

from coreg_ros.core.noise.measure import ChannelNoise, DeviceMeasurement, measure_device
from coreg_ros.core.noise.recording import measure_recording, NoiseReport

__all__ = ['ChannelNoise', 'DeviceMeasurement', 'NoiseReport', 'measure_device',
           'measure_recording']
