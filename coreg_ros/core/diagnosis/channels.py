"""
The channels a time or mean effect claims, and whether it matters in them at the stated noise.

An effect claims the channels (position, rotation) in which it moves some pair by at least
``SIZE_FLOOR`` of that pair's stated noise (``displacement``). It matters when it lowers the
held-out RMS of a channel it claims by ``MIN_RMS_GAIN`` and raises that of no channel by as
much (``channel_reasons``): a likelihood gain bought by making one channel worse is a trade
between channels, not an explanation.
"""

from __future__ import annotations

from coreg_ros.core.diagnosis.gap import position_rotation_rows
import numpy as np

#: Smallest relative fall of the held-out RMS (stated noise) of a channel a structured effect
#: claims: an error of RMS a under noise σ lowers it by a²/2σ², so 0.5 % is a ≈ σ/10.
MIN_RMS_GAIN = 0.005
#: Smallest displacement of the largest-moved pair, as a share of that pair's stated noise:
#: an offset that moves no pair by more than a tenth of the noise changes nothing a user acts on.
SIZE_FLOOR = 0.1


def displacement(fit, name: str) -> dict:
    """
    Largest displacement of any pair by a time or mean effect, per channel, over its stated noise.

    The final fit's errors with the effect's parameters against those with them zeroed (the
    rest held): per pair and marker the position displacement over the pair's stated position
    σ (RMS over the axes), and the rotation (full pose) over its stated σ.

    Returns
    -------
    dict of str to float
        ``'position'`` and, for a full pose, ``'rotation'``: the largest displacement of any
        pair in that channel over the pair's stated σ there (dimensionless).

    """
    model, state = fit.model, fit.state
    zero = state.copy()
    zero.theta[name] = np.zeros_like(state.theta[name])
    pos, rot = position_rotation_rows(model.data)
    channels = [('position', rows) for rows in (pos[i:i + 3] for i in range(0, len(pos), 3))]
    if rot:
        channels.append(('rotation', rot))
    worst = {key: 0.0 for key, _ in channels}
    for ch in model.chunks(np.arange(model.data.n)):
        a = model.evaluate(state, ch, jac=False)
        b = model.evaluate(zero, ch, jac=False)
        d = a.e - b.e
        for key, rows in channels:
            norm = np.linalg.norm(d[:, rows], axis=1)
            sd = np.sqrt(np.mean(a.sd[:, rows] ** 2, axis=1))
            worst[key] = max(worst[key], float(np.max(norm / np.maximum(sd, 1e-300))))
    return worst


def channel_reasons(moved: dict, test) -> list:
    """
    Why a time or mean effect does not matter at the stated noise, judged per channel.

    Parameters
    ----------
    moved : dict of str to float
        ``displacement``: the largest move of a pair per channel, over its stated σ.
    test : significance.EffectTest or None
        Its re-test in the final model (the held-out RMS gains per channel).

    Returns
    -------
    list of str
        Empty when the effect claims a channel (moves some pair there by ``SIZE_FLOOR``),
        lowers the held-out RMS of a claimed channel by ``MIN_RMS_GAIN`` and raises that of
        no channel by as much.

    """
    claimed = [k for k, v in moved.items() if v >= SIZE_FLOOR]
    if not claimed:
        return [f'it moves no pair by more than {max(moved.values()):.3f} of its stated noise '
                f'(floor {SIZE_FLOOR:g})']
    if test is None:
        return []
    # judged against the stated noise where the re-test gives it (``significance.rms_gain``)
    pairs = (('position', test.rms_gain_position, test.judged_gain_position),
             ('rotation', test.rms_gain_rotation, test.judged_gain_rotation))
    gains = {k: (j if j is not None else g) for k, g, j in pairs
             if (j if j is not None else g) is not None}
    reasons = []
    own = [gains[k] for k in claimed if k in gains]
    if own and max(own) < MIN_RMS_GAIN:
        reasons.append(f'it lowers the held-out RMS of the {" and ".join(claimed)} it moves at '
                       f'the stated noise by {max(own) * 100:.2f} % at most (minimum '
                       f'{MIN_RMS_GAIN * 100:g} %)')
    worse = {k: -g for k, g in gains.items() if -g >= MIN_RMS_GAIN}
    for key, rise in worse.items():
        reasons.append(f'it raises the held-out {key} RMS at the stated noise by '
                       f'{rise * 100:.2f} % (a channel made worse by {MIN_RMS_GAIN * 100:g} % '
                       f'or more)')
    return reasons
