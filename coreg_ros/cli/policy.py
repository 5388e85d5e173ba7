"""
One error policy for every ``coreg`` subcommand.

A ``CoregError`` is one line on stderr, ``coreg COMMAND: error: ...``, and exit code 1; the
core names parameters (``sigma_a``), and the line adds how to give them here (``--sigma-a``).
Missing ROS 2 packages are one line naming the fix; Ctrl-C is ``interrupted`` and exit code
130 (SIGTERM while cases run on workers: 143, the workers stopped); a reader that went away
(``| head``) is not an error.
"""

from __future__ import annotations

from collections.abc import Callable
import re
import sys

PROG = 'coreg'
#: Top-level packages whose absence means "ROS 2 is not installed here", not a bug of ours.
ROS_PACKAGES = ('rclpy', 'rosidl_runtime_py', 'geometry_msgs', 'std_msgs', 'std_srvs',
                'diagnostic_msgs', 'visualization_msgs', 'builtin_interfaces')
#: Other optional packages and how to get them.
OPTIONAL_PACKAGES = {'rich': 'pip install rich (or apt install python3-rich)',
                     'matplotlib': "pip install 'coreg_ros[report]'",
                     'dask': "pip install 'coreg_ros[dask]'",
                     'distributed': "pip install 'coreg_ros[dask]'"}
#: Parameter names of the core (``Settings``, the node's parameters) and their flags here.
FLAGS = {'topic_a': '--topic-a', 'topic_b': '--topic-b', 'model': '--model',
         'method': '--method', 'sigma_a': '--sigma-a', 'sigma_b': '--sigma-b',
         'max_gap': '--max-gap', 'time_offset': '--time-offset',
         'estimate_time_offset': '--time-offset auto',
         'estimate_clock_drift': '--clock-drift', 'robust': '--robust',
         'min_pairs': '--min-pairs', 'prior': '--prior',
         'roles_confirmed': '--roles-confirmed'}
_NAMED = re.compile(r'`([a-z_]+)`')


def with_flags(message: str) -> str:
    """Add the flag spelling after each parameter the message names as ```name```."""
    def spell(m: re.Match) -> str:
        flag = FLAGS.get(m.group(1))
        return f'{m.group(0)} ({flag})' if flag else m.group(0)
    return _NAMED.sub(spell, message)


#: What each exit code of the commands that decide something means (their ``--help`` epilog;
#: the README's table says the same). Every command: 1 an error, 130 Ctrl-C.
EXIT_CODES = {
    'calibrate': '0 a consistent calibration; 3 it converged but the data contradict the fit '
                 'or the roles look swapped (the verdict says what to do); 1 an error',
    'diagnose': '0 the diagnosis ran (what it found is the report, not the code); 1 an error',
    'batch': '0 every recording done (calibrate: each consistent); 3 none failed but a '
             'calibration contradicts its data; 1 a recording failed (the table names it) or '
             'an error; 143 SIGTERM (the workers stopped)',
    'validate-diagnosis': '0 every case ran; 1 a case failed (listed) or an error; 143 '
                          'SIGTERM (the workers stopped)',
}


def exit_codes(command: str) -> str:
    """Return the ``--help`` epilog of ``command`` saying what its exit codes mean."""
    return f'exit codes: {EXIT_CODES[command]}; 130 Ctrl-C'


def fail(command: str, message: str) -> int:
    """Print the one-line error of ``coreg COMMAND`` and return exit code 1."""
    print(f'{PROG} {command}: error: {message}', file=sys.stderr)
    return 1


def interrupted(command: str, signum: int = 2) -> int:
    """
    Say that ``coreg COMMAND`` was interrupted; return 128 + the signal (130 for SIGINT).

    ``signum`` is the ``signum`` of the KeyboardInterrupt caught (``parallel.Terminated``
    carries SIGTERM's, 15: exit code 143), else SIGINT's.
    """
    if signum == 2:
        print(f'{PROG} {command}: interrupted', file=sys.stderr)
    else:
        import signal

        print(f'{PROG} {command}: {signal.Signals(signum).name}: stopped (its workers too)',
              file=sys.stderr)
    return 128 + signum


def missing_package(error: ImportError) -> str:
    """Return the one-line fix for a missing ROS 2 or optional package ('' for others)."""
    name = (error.name or '').split('.')[0]
    if name in ROS_PACKAGES:
        return (f'ROS 2 Python packages are missing ({error}); source a Jazzy installation or '
                f'run `make venv`')
    if name in OPTIONAL_PACKAGES:
        return f'{name} is missing ({error}); {OPTIONAL_PACKAGES[name]}'
    return ''


def run_command(command: str, func: Callable, args) -> int:
    """
    Run one subcommand under the policy and return its exit code.

    Parameters
    ----------
    command : str
        The subcommand's name, for the message.
    func : callable
        ``func(args) -> int or None``.
    args : argparse.Namespace
        The parsed command line, passed to ``func``.

    """
    from coreg_ros.core.errors import CoregError

    try:
        return int(func(args) or 0)
    except CoregError as e:
        return fail(command, with_flags(str(e)))
    except ImportError as e:
        # Ctrl-C while an extension module initialises surfaces as an ImportError caused by it
        if isinstance(e.__cause__ or e.__context__, KeyboardInterrupt):
            return interrupted(command)
        fix = missing_package(e)
        if not fix:
            raise
        return fail(command, fix)
    except KeyboardInterrupt as e:
        return interrupted(command, getattr(e, 'signum', 2))
    except BrokenPipeError:
        # the reader (e.g. `| head`) went away: not an error of ours
        sys.stderr.close()
        return 0
