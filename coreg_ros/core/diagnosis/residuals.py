"""The base model's residuals on all pairs: the gap detected and where it lies."""

from __future__ import annotations

from coreg_ros.core.diagnosis.data import DiagData
from coreg_ros.core.diagnosis.detect import detect, Detection
from coreg_ros.core.diagnosis.fit import Fit
from coreg_ros.core.diagnosis.locate import locate, Location
from coreg_ros.core.models import linearize
import numpy as np


def base_errors(data: DiagData, fit: Fit) -> tuple:
    """
    Errors of a fit on all pairs.

    Returns
    -------
    e : ndarray, shape (N, m)
        Raw output errors (m and half-angle).
    sd : ndarray, shape (N, m)
        Standard deviation of each raw error under the stated noise.
    z : ndarray, shape (N, m)
        Decorrelated errors (``variance.py``).
    lam : ndarray, shape (N, m)
        A's carried noise in the decorrelated coordinates (z has variance 1 + λ).
    fdot : ndarray, shape (N, m)
        Rate of the model output, per s.

    """
    model = fit.model
    idx = np.arange(data.n)
    parts = [model.evaluate(fit.state, ch, jac=False) for ch in model.chunks(idx)]
    e = np.concatenate([p.e for p in parts])
    sd = np.concatenate([p.sd for p in parts])
    z = np.concatenate([p.st.z for p in parts])
    lam = np.concatenate([p.st.lam for p in parts])
    fdot = np.concatenate([p.fdot for p in parts])
    return e, sd, z, lam, fdot


def detect_locate(data: DiagData, base: Fit, errors: tuple) -> tuple[Detection, Location]:
    """
    Detect the gap in the base fit's errors and locate it (``detect.detect``, ``locate.locate``).

    Parameters
    ----------
    data : DiagData
        All pairs.
    base : Fit
        The model with the stated noise and no effect, on all pairs.
    errors : tuple
        ``base_errors(data, base)``.

    Returns
    -------
    detection : Detection
    location : Location

    """
    e, sd, z, lam, fdot = errors
    zstd = z / np.sqrt(1.0 + lam)
    quad = np.sum(zstd ** 2, axis=1)
    detection = detect(quad, zstd, data.m, data.spec.n_params)
    # split ḟ into the parts of linear and angular velocity
    model = base.model
    idx = np.arange(data.n)
    fv, fw = [], []
    for ch in model.chunks(idx):
        _, _, jx = linearize(base.state.params, data.pos_a[ch], data.quat_a[ch],
                             data.pos_b[ch], None if data.quat_b is None else data.quat_b[ch],
                             with_input=True)
        fv.append(np.einsum('nij,nj->ni', jx[:, :, 0:3], data.vel[ch]))
        fw.append(np.einsum('nij,nj->ni', jx[:, :, 3:6], data.omega[ch]))
    fv = np.concatenate(fv) / sd
    fw = np.concatenate(fw) / sd
    step = float(np.median(np.diff(data.t))) if data.n > 1 else 0.0
    location = locate(t=data.t, quad=quad, e_std=e / sd, m=data.m,
                      has_rotation=data.spec.has_q1, points=data.b_points[:, 0, :],
                      speed=data.speed, angular_speed=data.angular_speed, fdot_v=fv,
                      fdot_w=fw, dt=step)
    return detection, location
