"""coreg_ros.ros.throttle: one log line per key and period (node, live checks, outputs)."""

from coreg_ros.ros.throttle import Throttle


def test_one_action_per_key_and_period():
    throttle = Throttle(period=60.0)
    assert throttle.ready(('/a', 'nan'))
    assert not throttle.ready(('/a', 'nan'))   # the same problem again: quiet
    assert throttle.ready(('/b', 'nan'))       # another key has its own period
    assert throttle.ready()                    # and so has the single concern (None)
    assert not throttle.ready()
    assert throttle.ready(('/a', 'nan'), period=0.0)  # a key's own, shorter period
    assert not throttle.ready(('/a', 'nan'), period=60.0)
