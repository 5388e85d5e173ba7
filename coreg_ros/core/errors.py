"""
Typed errors of coreg_ros.

Every error names what is wrong and what the user can do about it, in one line, so that the
command-line tools and the node can show ``str(error)`` to a person without a traceback.
All are ``ValueError`` compatible, as scipy raises ``ValueError`` for bad input.
"""

import copy


class CoregError(ValueError):
    """Base class of every error coreg_ros raises on purpose."""

    def with_message(self, message: str) -> 'CoregError':
        """
        Return a copy of this error that says ``message``: same class, same attributes.

        A layer that adds what it knows (``'…; but first: positions are in mm'``) keeps what
        the error carries (``UnobservableError.directions``) instead of building a new one.
        """
        out = copy.copy(self)
        out.args = (message,)
        return out


class InputError(CoregError):
    """Input data are malformed: NaN, non-unit quaternions, bad shapes, bad stamps."""


class TooFewPairsError(CoregError):
    """Not enough paired samples to estimate the parameters."""


class UnobservableError(CoregError):
    """The recorded motion leaves some parameter direction unobservable."""

    def __init__(self, message: str, directions: tuple = ()):
        super().__init__(message)
        #: human-readable names of the unobservable parameter directions
        self.directions = tuple(directions)


class ConvergenceError(CoregError):
    """The estimator did not converge."""


class BagError(CoregError):
    """A rosbag2 recording cannot be read or written as asked."""


class ConfigError(CoregError):
    """A configuration value or command-line option is invalid."""


class InconsistentDataError(CoregError):
    """The data are not the model plus a few outliers (too many pairs far outside the noise)."""
