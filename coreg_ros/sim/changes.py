"""
Changes in the middle of a simulated recording: T0 or T1 steps and clock steps.

What the watchdog (``coreg_ros.core.live.watchdog``) must notice:

- ``t0_step``: device A's base moves in B's base frame at time t (the base was bumped):
  from then on ``T0' = (p0 + δp, Exp(δθ) R0)``, δp and δθ in B's base axes;
- ``t1_step``: B's marker moves on A's tool (the marker slipped): ``T1' = (p1 + δp,
  Exp(δθ) R1)`` in A's tool axes; for three markers the marker set moves as a rigid body,
  ``p_j' = p1 + δp + Exp(δθ) (p_j - p1)``;
- ``clock_step``: B's clock jumps by S seconds at time t: B's stamps at or after t grow by S
  (B's clock minus A's, the time offset, grows by S);
- ``noise_step``: B's noise grows by a factor F at time t (metal brought near an EM field
  generator, a tracker losing line of sight): independent noise of σ_b √(F² - 1) is added
  to B's samples from then on (``F`` ≥ 1).

The poses are changed as measured, so the device noise of the recording is kept: a T0 step
multiplies B's measured pose on the left by ``T0' T0⁻¹`` (the isotropic noise is rotated, which
leaves its distribution unchanged); a T1 step moves B's measured marker(s) by the true marker
displacement ``R0 R_A(t) (p_j' - p_j)`` and turns B's measured orientation by ``R1⁻¹ R1'`` on
the right (A's true pose from the recording's motion).

Text form (``parse_change``): ``NAME=SIZE[+SIZE][:AXIS]@TIME``, e.g. ``t0_step=2mm@30``,
``t1_step=0.5deg@30``, ``t0_step=1mm+0.2deg@45``, ``t0_step=2mm:z@30``, ``clock_step=0.01@30``,
``clock_step=10ms@30`` or ``noise_step=2@30`` (a factor). Sizes are mm, m, deg or rad (a
clock step s or ms; a bare number is s); TIME is seconds from the start of the recording.
The direction of a step is random (drawn from the seed given to ``apply_changes``) unless
``:AXIS`` (x, y, z, -x, ...) gives it.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
import re
from typing import Optional

from coreg_ros.core import quaternion as quat
from coreg_ros.core.errors import ConfigError
from coreg_ros.sim.motion import random_unit
import numpy as np

#: Names of the changes.
CHANGE_NAMES = ('t0_step', 't1_step', 'clock_step', 'noise_step')

_UNITS = {'mm': ('translation', 1e-3), 'm': ('translation', 1.0),
          'deg': ('rotation', np.pi / 180.0), 'rad': ('rotation', 1.0),
          'ms': ('time', 1e-3), 's': ('time', 1.0), '': ('time', 1.0)}
_AXES = {'x': 0, 'y': 1, 'z': 2}


@dataclass(frozen=True)
class Change:
    """
    One change of a recording.

    Attributes
    ----------
    name : str
        ``t0_step``, ``t1_step`` or ``clock_step``.
    time_s : float
        When, s from the recording's start (``SimRecording.start_ns``).
    translation_m : float
        Size of the translation step, m (steps of T0 or T1).
    rotation_rad : float
        Size of the rotation step, rad.
    clock_s : float
        Clock step S, s.
    noise_factor : float
        Factor F on B's noise σ (``noise_step``).
    axis : ndarray, shape (3,), optional
        Unit direction of the step (translation and rotation alike); random when None.

    """

    name: str
    time_s: float
    translation_m: float = 0.0
    rotation_rad: float = 0.0
    clock_s: float = 0.0
    noise_factor: float = 1.0
    axis: Optional[np.ndarray] = None

    def __post_init__(self):
        if self.name not in CHANGE_NAMES:
            raise ConfigError(f'change {self.name!r} is unknown; use one of '
                              f'{", ".join(CHANGE_NAMES)}')
        if not (np.isfinite(self.noise_factor) and self.noise_factor >= 1.0):
            raise ConfigError(f'change {self.name}: the noise factor must be >= 1, got '
                              f'{self.noise_factor!r}')
        if not (np.isfinite(self.time_s) and self.time_s >= 0):
            raise ConfigError(f'change {self.name}: time must be >= 0 s, got {self.time_s!r}')


def parse_change(text: str) -> Change:
    """
    Parse ``NAME=SIZE[+SIZE][:AXIS]@TIME`` (module docstring).

    Raises
    ------
    ConfigError
        One line saying what is wrong and the expected form.

    """
    form = ('expected NAME=SIZE@TIME, e.g. t0_step=2mm@30, t1_step=0.5deg@30, '
            't0_step=1mm+0.2deg:z@45, clock_step=0.01@30 or noise_step=2@30')
    m = re.fullmatch(r'\s*(\w+)\s*=\s*([^@:]+?)\s*(?::\s*(-?[xyzXYZ]))?\s*@\s*([^@]+?)\s*',
                     text or '')
    if not m:
        raise ConfigError(f'change {text!r}: {form}')
    name, sizes, axis_text, when = m.groups()
    if name not in CHANGE_NAMES:
        raise ConfigError(f'change {text!r}: {name!r} is unknown; use one of '
                          f'{", ".join(CHANGE_NAMES)}')
    try:
        time_s = float(when)
    except ValueError:
        raise ConfigError(f'change {text!r}: the time {when!r} is not a number of seconds; '
                          f'{form}') from None
    if name == 'noise_step':
        try:
            factor = float(sizes)
        except ValueError:
            raise ConfigError(f"change {text!r}: a noise step is a factor >= 1 on B's noise, "
                              f'e.g. noise_step=2@30') from None
        if axis_text:
            raise ConfigError(f'change {text!r}: a noise step has no axis')
        return Change(name, time_s, noise_factor=factor)
    values = {'translation': 0.0, 'rotation': 0.0, 'time': 0.0}
    for part in sizes.split('+'):
        pm = re.fullmatch(r'\s*([-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?)\s*([a-z]*)\s*', part)
        if not pm or pm.group(2) not in _UNITS:
            raise ConfigError(f'change {text!r}: size {part.strip()!r} needs a number and a '
                              f'unit of mm, m, deg, rad (clock: s or ms)')
        kind, factor = _UNITS[pm.group(2)]
        values[kind] += float(pm.group(1)) * factor
    if name == 'clock_step':
        if values['translation'] or values['rotation']:
            raise ConfigError(f'change {text!r}: a clock step is a time (s or ms)')
        if axis_text:
            raise ConfigError(f'change {text!r}: a clock step has no axis')
        return Change(name, time_s, clock_s=values['time'])
    if values['time']:
        raise ConfigError(f'change {text!r}: a step of {name[:2].upper()} is mm, m, deg or rad')
    axis = None
    if axis_text:
        axis = np.zeros(3)
        axis[_AXES[axis_text[-1].lower()]] = -1.0 if axis_text.startswith('-') else 1.0
    return Change(name, time_s, translation_m=values['translation'],
                  rotation_rad=values['rotation'], axis=axis)


def _resolved(change: Change, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """(δp, δθ) of a step: the sizes along the given axis, or along independent random ones."""
    if change.axis is not None:
        axis = np.asarray(change.axis, dtype=float)
        axis = axis / np.linalg.norm(axis)
        return change.translation_m * axis, change.rotation_rad * axis
    return change.translation_m * random_unit(rng), change.rotation_rad * random_unit(rng)


def apply_change(rec, change: Change, rng: Optional[np.random.Generator] = None):
    """
    Apply one change to a simulated recording.

    Parameters
    ----------
    rec : SimRecording
        From ``coreg_ros.sim.simulate_recording`` (its ``motion`` is needed for T1 steps).
    change : Change
        The change (``parse_change`` builds one from its text).
    rng : numpy.random.Generator, optional
        Draws a random step direction (default: a generator seeded with 0).

    Returns
    -------
    SimRecording
        New streams; ``truth.effects`` gains the change's description (``name``, ``time_s``
        and ``start_ns``, and ``translation_m``, ``rotation_rad`` as 3-vectors in B's base
        axes for T0 and A's tool axes for T1, or ``clock_s``). ``truth`` keeps the calibration
        before the change.

    """
    rng = np.random.default_rng(0) if rng is None else rng
    streams, desc = changed_streams(dict(rec.streams), rec.topics_b, rec.truth, rec.motion,
                                    rec.start_ns, change, rng)
    truth = replace(rec.truth, effects=tuple(rec.truth.effects) + (desc,))
    return replace(rec, streams=streams, truth=truth)


def changed_streams(streams: dict, topics_b, truth, motion, start_ns: int, change: Change,
                    rng: np.random.Generator) -> tuple:
    """
    Apply one change to B's streams (``apply_change`` on a recording's parts).

    Returns
    -------
    streams : dict
    desc : dict
        The change's description (``apply_change``).

    """
    at = int(start_ns) + int(round(change.time_s * 1e9))
    desc = {'name': change.name, 'time_s': float(change.time_s), 'start_ns': at}
    if change.name == 'noise_step':
        sigma_pos, sigma_rot = (float(v) * np.sqrt(change.noise_factor ** 2 - 1.0)
                                for v in truth.sigma_b)
        for topic in topics_b:
            s = streams[topic]
            after = s.stamps >= at
            n = int(after.sum())
            pos = s.position.copy()
            q = s.quat_wxyz.copy()
            pos[after] += sigma_pos * rng.standard_normal((n, 3))
            if truth.model == 'full_pose':
                q[after] = quat.canonical(quat.multiply(
                    quat.exp(sigma_rot * rng.standard_normal((n, 3))), q[after]))
            streams[topic] = replace(s, position=pos, quat_wxyz=q)
        desc['noise_factor'] = float(change.noise_factor)
    elif change.name == 'clock_step':
        shift = int(round(change.clock_s * 1e9))
        for topic in topics_b:
            s = streams[topic]
            streams[topic] = replace(s, stamps=step_stamps(s.stamps, at, shift))
        desc['clock_s'] = float(change.clock_s)
    else:
        dp, dtheta = _resolved(change, rng)
        desc['translation_m'] = dp.tolist()
        desc['rotation_rad'] = dtheta.tolist()
        R_d = quat.to_matrix(quat.exp(dtheta))
        for topic_index, topic in enumerate(topics_b):
            s = streams[topic]
            after = s.stamps >= at
            if not after.any():
                continue
            pos = s.position.copy()
            q = s.quat_wxyz.copy()
            if change.name == 't0_step':
                # T0' T0⁻¹ on the left: x ↦ R_d (x - p0) + p0 + δp
                pos[after] = (pos[after] - truth.p0) @ R_d.T + truth.p0 + dp
                if truth.model == 'full_pose':
                    q[after] = quat.canonical(quat.multiply(quat.exp(dtheta), q[after]))
            else:
                if motion is None:
                    raise ConfigError("a T1 step needs the recording's motion (A's true pose)")
                t = (s.stamps[after] - np.int64(start_ns)).astype(float) * 1e-9
                _, q_a = motion.pose(t)
                marker = truth.markers[topic_index]
                moved = truth.p1 + dp + R_d @ (marker - truth.p1)
                R0Ra = quat.to_matrix(truth.q0) @ quat.to_matrix(q_a)
                pos[after] = pos[after] + R0Ra @ (moved - marker)
                if truth.model == 'full_pose':
                    # R_B' = R_B R1ᵀ Exp(δθ) R1: the quaternion q1* ⊗ Exp(δθ) ⊗ q1 on the right
                    right = quat.multiply(quat.conjugate(truth.q1),
                                          quat.multiply(quat.exp(dtheta), truth.q1))
                    q[after] = quat.canonical(quat.multiply(q[after], right))
            streams[topic] = replace(s, position=pos, quat_wxyz=q)
    return streams, desc


def step_stamps(stamps: np.ndarray, at_ns: int, shift_ns: int) -> np.ndarray:
    """Return the stamps with ``shift_ns`` added to those at or after ``at_ns`` (a clock step)."""
    out = np.asarray(stamps, dtype=np.int64).copy()
    out[out >= at_ns] += np.int64(shift_ns)
    return out


#: Unit of a ``StepEffect``'s value, per name.
STEP_UNITS = {'t0_step': 'mm T0 moves (and 0.05 deg per mm), at a random instant',
              't1_step': 'mm T1 (the marker) moves (and 0.05 deg per mm), at a random instant',
              'noise_step': "factor on B's noise from a random instant on"}
#: Rotation that comes with a pose step's translation, rad per m (a 2 mm bump turns 0.1°).
STEP_ROTATION_PER_M = np.radians(0.05) / 1e-3


@dataclass(frozen=True)
class StepEffect:
    """
    A change as an effect of the simulator (``coreg simulate --effect t0_step=2``).

    ``t0_step`` and ``t1_step``: T0 (or T1) moves by ``value`` mm (and turns
    ``STEP_ROTATION_PER_M`` with it) in a random direction; ``noise_step``: B's noise grows
    ``value`` times. At a random instant in 25-75 % of the recording (``at``: a share), as
    ``apply_change`` does it. Applied to the recorded samples, after the other effects.
    """

    name: str
    value: float
    at: Optional[float] = None
    stage = 'measured'
    _found: dict = field(default_factory=dict, init=False, repr=False, compare=False)

    def __call__(self, streams: dict, context, rng) -> dict:
        """Apply the change to B's streams."""
        first = streams[context.topics_b[0]]
        share = rng.uniform(0.25, 0.75) if self.at is None else float(self.at)
        span = (int(first.stamps[-1]) - int(first.stamps[0])) * 1e-9
        when = (int(first.stamps[0]) - int(context.start_ns)) * 1e-9 + share * span
        if self.name == 'noise_step':
            change = Change(self.name, when, noise_factor=self.value)
        else:
            size = self.value * 1e-3
            change = Change(self.name, when, translation_m=size,
                            rotation_rad=size * STEP_ROTATION_PER_M)
        out, desc = changed_streams(dict(streams), context.topics_b, context.truth,
                                    context.motion, context.start_ns, change, rng)
        self._found.update({k: v for k, v in desc.items() if k != 'name'})
        return out

    def as_dict(self) -> dict:
        """Describe the change: its size, instant and direction."""
        return {'name': self.name, 'value': self.value, 'unit': STEP_UNITS[self.name],
                'stage': self.stage, **self._found}


def apply_changes(rec, changes, seed: Optional[int] = None):
    """
    Apply changes in order (each ``Change`` or its text form).

    Parameters
    ----------
    rec : SimRecording
        From ``coreg_ros.sim.simulate_recording``.
    changes : sequence of Change or str
        Applied in this order.
    seed : int, optional
        Seed of the random step directions (default: the recording's seed).

    Returns
    -------
    SimRecording

    """
    seed = rec.seed if seed is None else seed
    rng = np.random.default_rng(np.random.SeedSequence([0 if seed is None else int(seed), 13]))
    for change in changes:
        change = parse_change(change) if isinstance(change, str) else change
        rec = apply_change(rec, change, rng)
    return rec
