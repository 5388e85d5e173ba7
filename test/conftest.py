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
    """Mark every test that needs a ROS domain as ``ros``; spread their files through the run."""
    for item in items:
        if 'ros_domain' in getattr(item, 'fixturenames', ()):
            item.add_marker(pytest.mark.ros)
    items[:] = spread_real_time(items)


def spread_real_time(items: list) -> list:
    """
    Return the tests with the files of ROS tests spread evenly among the others, files whole.

    The ROS tests mostly wait on real time (a node, a recording played at its rate) while the
    others compute. ``make test``'s processes (pytest-xdist, ``--dist worksteal``) each start
    on one contiguous share of this list: in path order, one process would get most of
    test/ros and the end of the run would be ROS tests only, the cores idle while they wait.
    Spread, every share mixes waiting and computing. A file is never split here, so its
    module fixtures are made once; the order is the same in every process, as xdist needs.
    """
    files = {}
    for item in items:
        files.setdefault(item.nodeid.split('::')[0], []).append(item)
    groups = list(files.values())
    waiting = [g for g in groups if any(i.get_closest_marker('ros') for i in g)]
    others = [g for g in groups if not any(i.get_closest_marker('ros') for i in g)]
    if not waiting or not others:
        return items
    total = sum(len(g) for g in others)
    out, done, k = [], 0, 0
    for group in others:
        # the k-th waiting file goes where the others' tests reach k / len(waiting) of theirs
        while k < len(waiting) and done >= k * total / len(waiting):
            out.extend(waiting[k])
            k += 1
        out.extend(group)
        done += len(group)
    for group in waiting[k:]:
        out.extend(group)
    return out
