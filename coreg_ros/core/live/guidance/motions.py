"""Candidate motions to add to the recording, from the tool's current pose."""

from __future__ import annotations

from dataclasses import dataclass

from coreg_ros.core import quaternion as quat
from coreg_ros.core.live.guidance.keys import AXES
import numpy as np

#: Recording time each candidate motion adds, s.
CANDIDATE_SECONDS = 10.0
#: Amplitude (rad) and frequency (Hz) of a candidate rotation about a tool axis.
CANDIDATE_ROTATION = (np.deg2rad(30.0), 0.2)
#: Amplitude (m) and frequency (Hz) of a candidate translation along a base axis.
CANDIDATE_TRANSLATION = (0.10, 0.2)
#: Samples that represent a candidate's added motion (its information is scaled to its pairs).
CANDIDATE_SAMPLES = 100
# --------------------------------------------------------------------------- candidates


@dataclass(frozen=True)
class CandidateMotion:
    """
    A motion that could be added to the recording.

    Attributes
    ----------
    name : str
        ``rotate_x`` .. ``rotate_z`` (about the tool's own axis), ``move_x`` .. ``move_z``
        (along A's base axis) or ``hold_still``.
    description : str
        One line for a person.
    pos_a : ndarray, shape (n, 3)
    quat_a : ndarray, shape (n, 4)
    velocity : ndarray, shape (n, 6)
    n_pairs : int
        Pairs it adds at the current pair rate (each of the n samples stands for
        ``n_pairs / n`` of them).

    """

    name: str
    description: str
    pos_a: np.ndarray
    quat_a: np.ndarray
    velocity: np.ndarray
    n_pairs: int


def candidate_motions(position: np.ndarray, orientation: np.ndarray, rate: float,
                      seconds: float = CANDIDATE_SECONDS,
                      samples: int = CANDIDATE_SAMPLES) -> list:
    """
    Build the candidate additions, each from the tool's current pose.

    Parameters
    ----------
    position : ndarray, shape (3,)
        The tool's current position, A's base frame, m.
    orientation : ndarray, shape (4,)
        The tool's current orientation, (w, x, y, z).
    rate : float
        Pairs per second, Hz.
    seconds : float
        Time each candidate adds, s.
    samples : int
        Samples per candidate at which the information is evaluated.

    Returns
    -------
    list of CandidateMotion

    """
    n_pairs = max(1, int(round(rate * seconds)))
    n = max(8, min(samples, n_pairs))
    t = (np.arange(n) + 0.5) * (seconds / n)
    position = np.asarray(position, dtype=float)
    orientation = quat.canonical(np.asarray(orientation, dtype=float))
    out = []
    amp, freq = CANDIDATE_ROTATION
    phase = 2.0 * np.pi * freq * t
    for k, axis in enumerate(AXES):
        e = np.eye(3)[k]
        q = quat.multiply(np.broadcast_to(orientation, (n, 4)),
                          quat.exp(e[None, :] * (amp * np.sin(phase))[:, None]))
        # body rate about e, expressed in A's base frame (the left perturbation's axes)
        w_body = e[None, :] * (amp * 2.0 * np.pi * freq * np.cos(phase))[:, None]
        w = np.einsum('nij,nj->ni', quat.to_matrix(q), w_body)
        vel = np.hstack([np.zeros((n, 3)), w])
        out.append(CandidateMotion(
            f'rotate_{axis}', f'rotate the tool ±{np.degrees(amp):.0f}° about its own {axis} '
                              f'axis, back and forth, for {seconds:.0f} s',
            np.broadcast_to(position, (n, 3)).copy(), q, vel, n_pairs))
    amp, freq = CANDIDATE_TRANSLATION
    for k, axis in enumerate(AXES):
        e = np.eye(3)[k]
        p = position + e[None, :] * (amp * np.sin(phase))[:, None]
        v = e[None, :] * (amp * 2.0 * np.pi * freq * np.cos(phase))[:, None]
        out.append(CandidateMotion(
            f'move_{axis}', f"move the tool ±{amp * 100:.0f} cm along A's base {axis} axis, "
                            f'back and forth, for {seconds:.0f} s',
            p, np.broadcast_to(orientation, (n, 4)).copy(), np.hstack([v, np.zeros((n, 3))]),
            n_pairs))
    out.append(CandidateMotion(
        'hold_still', f'hold the tool still for {seconds:.0f} s (a pose free of the clock '
                      f'offset)', np.broadcast_to(position, (n, 3)).copy(),
        np.broadcast_to(orientation, (n, 4)).copy(), np.zeros((n, 6)), n_pairs))
    return out
