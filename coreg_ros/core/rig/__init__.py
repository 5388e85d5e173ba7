"""
Whole rigs: device A and K devices B_k calibrated jointly (issue 23).

====================  ===========================================================================
module                what it holds
====================  ===========================================================================
``devices``           the devices as the user gives them (``RigDevice``), checked
``layout``            where each device's φ_k sits in the rig's φ (shared bases once)
``shared_instants``   devices measured at the same instants: one true input pose for all
``joint``             the joint OLS / TLS fit on the devices' own linearisations
``posterior``         the joint covariance over every T0, T1 and clock, ROS layout
``pipeline``          streams to a judged ``RigResult`` (``calibrate_rig``)
``result``            ``RigResult``, ``DeviceResult``
``loops``             the pose of any device's base in another's; pairwise consistency
``text``              the text ``coreg calibrate`` prints for a rig
====================  ===========================================================================
"""
