"""
Where each device's parameters sit in the rig's one parameter vector.

A rig is device A and K devices B_k, each with its own φ_k of Ikits' models (``models``:
T0_k = (p0, s0) first, then T1_k's marker position(s) and, for a full pose, s1). Devices that
are sensors of one device share its base: one T0 (and one clock) for all of them ("one base,
several markers"). The rig's vector φ holds each base's T0 once, then each device's own rest:

    φ = [T0 of base 1 (6), T0 of base 2 (6), ..., rest of B_1, rest of B_2, ...]

``RigLayout.columns[k]`` are the indices of φ_k in φ (φ_k = φ[columns[k]]), so a device's
normal equations enter the rig's as ``S[ix(c, c)] += S_k``, ``b[c] += b_k``. ``RigParameters``
is φ as the devices' own ``Parameters``: a shared T0 has one chart, stepped and re-charted
identically in every device that shares it.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

from coreg_ros.core.models import Parameters, SPECS
import numpy as np

#: Names of the components of T0 and of each model's rest, for labels.
T0_NAMES = ('p0x', 'p0y', 'p0z', 's0x', 's0y', 's0z')
REST_NAMES = {
    'full_pose': ('p1x', 'p1y', 'p1z', 's1x', 's1y', 's1z'),
    'position_only': ('p1x', 'p1y', 'p1z'),
    'three_marker': ('p1x', 'p1y', 'p1z', 'p2x', 'p2y', 'p2z', 'p3x', 'p3y', 'p3z'),
}


@dataclass(frozen=True)
class RigLayout:
    """
    The rig's parameter vector: shared bases once, then every device's own parameters.

    Attributes
    ----------
    names : tuple of str
        The devices B_1..B_K.
    models : tuple of str
        Each device's model (``models.SPECS``).
    bases : tuple of str
        Each device's base: devices with the same base share T0 and their clock.
    columns : tuple of ndarray of int
        Indices of φ_k in φ, shape (P_k,) each.
    n_params : int
        Length of φ.

    """

    names: tuple
    models: tuple
    bases: tuple
    columns: tuple
    n_params: int

    @classmethod
    def build(cls, names: Sequence[str], models: Sequence[str],
              bases: Sequence[str]) -> RigLayout:
        """Lay out φ for devices ``names`` with their ``models`` and ``bases``."""
        base_order = list(dict.fromkeys(bases))
        cursor = 6 * len(base_order)
        columns = []
        for model, base in zip(models, bases, strict=True):
            t0 = 6 * base_order.index(base) + np.arange(6)
            n_rest = SPECS[model].n_params - 6
            columns.append(np.concatenate([t0, cursor + np.arange(n_rest)]))
            cursor += n_rest
        return cls(tuple(names), tuple(models), tuple(bases), tuple(columns), cursor)

    @property
    def base_names(self) -> tuple:
        """Return the distinct bases, in the order of their T0 in φ."""
        return tuple(dict.fromkeys(self.bases))

    def sharing(self, k: int) -> int:
        """Return the number of devices that share device k's base (1: its own)."""
        return self.bases.count(self.bases[k])

    def labels(self) -> list:
        """One label per component of φ, e.g. ``'base:em.p0x'``, ``'tool:em2.p1x'``."""
        out = [''] * self.n_params
        for name, model, base, cols in zip(self.names, self.models, self.bases, self.columns,
                                           strict=True):
            for j, c in enumerate(cols):
                out[c] = (f'{base}.{T0_NAMES[j]}' if j < 6 else
                          f'{name}.{REST_NAMES[model][j - 6]}')
        return out


class RigParameters:
    """
    The rig's φ as each device's ``Parameters`` (a shared T0 in one chart for all of them).

    Parameters
    ----------
    layout : RigLayout
    devices : list of Parameters
        φ_k per device, consistent: devices sharing a base hold the same T0 and chart.

    """

    def __init__(self, layout: RigLayout, devices: list):
        self.layout = layout
        self.devices = devices

    @classmethod
    def from_starts(cls, layout: RigLayout, starts: Sequence[Parameters]) -> RigParameters:
        """
        Combine each device's own start: a shared base takes its first device's T0.

        Every other device of that base keeps its T1 (from its own fit, a start near enough).
        """
        first = {}
        devices = []
        for base, p in zip(layout.bases, starts, strict=True):
            if base not in first:
                first[base] = p
            lead = first[base]
            phi = p.phi.copy()
            phi[0:6] = lead.phi[0:6]
            charts = [lead.charts[0]] + list(p.charts[1:])
            devices.append(Parameters(p.spec, phi, charts))
        return cls(layout, devices)

    @property
    def phi(self) -> np.ndarray:
        """Return the rig's vector φ, shape (P,)."""
        out = np.empty(self.layout.n_params)
        for p, cols in zip(self.devices, self.layout.columns, strict=True):
            out[cols] = p.phi
        return out

    @property
    def valid(self) -> bool:
        """Tell whether every reduced quaternion stays in its chart (else the step is refused)."""
        return all(p.valid for p in self.devices)

    def stepped(self, delta: np.ndarray) -> RigParameters:
        """φ + δ, each device in its charts (a shared T0 steps alike everywhere)."""
        return RigParameters(self.layout, [p.stepped(delta[cols]) for p, cols in
                                           zip(self.devices, self.layout.columns, strict=True)])

    def recharted(self) -> RigParameters:
        """Re-chart every rotation (``Parameters.recharted``: a shared T0 re-charts alike)."""
        return RigParameters(self.layout, [p.recharted() for p in self.devices])
