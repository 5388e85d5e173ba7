"""
Test-wide settings.

Property tests draw the same examples on every run (CI is repeatable), and every test that uses
a ROS domain (the ``ros_domain`` fixture: real rclpy nodes in other processes) is marked ``ros``,
so ``make test-fast`` (``-m "not ros and not slow"``) runs everything else.
"""

from hypothesis import settings
import pytest

settings.register_profile('repeatable', derandomize=True)
settings.load_profile('repeatable')


def pytest_collection_modifyitems(config, items):
    """Mark every test that needs a ROS domain as ``ros``."""
    for item in items:
        if 'ros_domain' in getattr(item, 'fixturenames', ()):
            item.add_marker(pytest.mark.ros)
