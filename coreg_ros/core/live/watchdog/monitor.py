"""The watchdog itself: per-pair CUSUM, states OK / WARN / ERROR, attribution on alarm."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

from coreg_ros.core.errors import InputError
from coreg_ros.core.live.guidance import (
    device_covariances,
    PairBatch,
)
from coreg_ros.core.live.watchdog.attribution import attribute, Attribution
from coreg_ros.core.live.watchdog.keys import (
    ERROR,
    KEY_ALARM_STAMP,
    KEY_CHANGE,
    KEY_CHANGE_STAMP,
    KEY_CHECKED,
    KEY_CLOCK,
    KEY_MEAN_D2,
    KEY_MESSAGE,
    KEY_NOISE,
    KEY_ROTATION,
    KEY_STALE,
    KEY_STATE,
    KEY_STATISTIC,
    KEY_THRESHOLD,
    KEY_TRANSLATION,
    LEVEL_NAMES,
    OK,
    WARN,
)
from coreg_ros.core.live.watchdog.residuals import Calibration, linearise
from coreg_ros.core.live.watchdog.threshold import (
    cusum_threshold,
    DESIGN_INFLATION,
    llr_constants,
    TARGET_RUN_LENGTH,
)
from coreg_ros.core.types import CalibrationResult
import numpy as np

#: Fewest pairs after the change point before the attribution is trusted, and the fewest
#: seconds (whichever takes longer).
MIN_WINDOW_PAIRS = 100
MIN_WINDOW_S = 0.5
#: Undecided after this long (s) since the change point: ERROR with the ambiguity said.
MAX_UNDECIDED_S = 30.0
#: Pairs the attribution fits at most (evenly decimated beyond).
MAX_FIT_PAIRS = 6000
#: Seconds of recent pairs kept for the attribution.
KEEP_S = 60.0
#: Once ERROR, the size of the change is refined with the growing window for this long (s).
REFINE_S = 10.0
# --------------------------------------------------------------------------- the watchdog


@dataclass(frozen=True)
class WatchState:
    """
    The watchdog's state after an update.

    Attributes
    ----------
    level : int
        ``OK`` (0), ``WARN`` (1) or ``ERROR`` (2), as diagnostic_msgs' levels.
    message : str
        One line for a person.
    n_checked : int
        Pairs checked since the calibration.
    statistic : float
        The CUSUM now.
    threshold : float
        Its alarm threshold h.
    mean_d2 : float
        Mean normalised squared residual per residual component over the last update
        (≈ 1 while the calibration holds).
    change_stamp : int or None
        Estimated change point (B stamp, ns).
    alarm_stamp : int or None
        Stamp of the pair that raised the alarm, ns.
    attribution : Attribution or None

    """

    level: int
    message: str
    n_checked: int
    statistic: float
    threshold: float
    mean_d2: float
    change_stamp: Optional[int] = None
    alarm_stamp: Optional[int] = None
    attribution: Optional[Attribution] = None

    @property
    def level_name(self) -> str:
        """``OK``, ``WARN`` or ``ERROR``."""
        return LEVEL_NAMES[self.level]

    @property
    def stale(self) -> bool:
        """Tell whether the calibration no longer describes the devices (ERROR)."""
        return self.level == ERROR

    def diagnostic_values(self) -> list:
        """(key, value) string pairs for the watchdog status of /diagnostics."""
        att = self.attribution

        def num(v, scale=1.0, fmt='.4g'):
            return 'n/a' if v is None or not np.isfinite(v) else format(v * scale, fmt)

        out = [(KEY_STATE, self.level_name), (KEY_MESSAGE, self.message),
               (KEY_STALE, 'true' if self.stale else 'false'),
               (KEY_CHECKED, str(self.n_checked)), (KEY_STATISTIC, f'{self.statistic:.4g}'),
               (KEY_THRESHOLD, f'{self.threshold:.4g}'), (KEY_MEAN_D2, num(self.mean_d2)),
               (KEY_CHANGE, 'none' if att is None else att.kind),
               (KEY_CHANGE_STAMP, 'n/a' if self.change_stamp is None else str(self.change_stamp)),
               (KEY_ALARM_STAMP, 'n/a' if self.alarm_stamp is None else str(self.alarm_stamp))]
        trans = rot = clock = noise = 'n/a'
        if att is not None and att.translation is not None:
            trans = (f'{np.linalg.norm(att.translation) * 1e3:.4g} ± '
                     f'{att.translation_sigma * 1e3:.2g}')
        if att is not None and att.rotation is not None:
            rot = (f'{np.degrees(np.linalg.norm(att.rotation)):.4g} ± '
                   f'{np.degrees(att.rotation_sigma):.2g}')
        if att is not None and att.time_step is not None:
            clock = f'{att.time_step * 1e3:+.4g} ± {att.time_sigma * 1e3:.2g}'
        if att is not None and att.noise_factor is not None:
            noise = f'{att.noise_factor:.3g}'
        out += [(KEY_TRANSLATION, trans), (KEY_ROTATION, rot), (KEY_CLOCK, clock),
                (KEY_NOISE, noise)]
        return out


class Watchdog:
    """
    Check pairs against a calibration as they arrive; detect and attribute a change.

    Parameters
    ----------
    calibration : Calibration or CalibrationResult
    sigma_a, sigma_b : (float, float) or DeviceNoise
        The stated device noise (position m, rotation rad, or full covariances).
    tls : bool
        Errors in both devices (as the calibration's method).
    noise_scale : float
        Factor on the stated noise variance (e.g. the calibration's χ²/dof when above 1, so
        that a noise slightly above the stated one does not raise false alarms).
    target_run_length : float
        Mean pairs between false alarms (sets the CUSUM threshold).

    Notes
    -----
    Feed ``update`` with ``PairBatch`` es (``guidance.PairFeed``) of pairs made at the
    calibration's time offset. The pairs are checked in order; a batch may be any size.

    """

    def __init__(self, calibration, sigma_a, sigma_b, tls: bool = True,
                 noise_scale: float = 1.0, target_run_length: float = TARGET_RUN_LENGTH):
        if isinstance(calibration, CalibrationResult):
            calibration = Calibration.from_result(calibration)
        if not noise_scale > 0:
            raise InputError('noise_scale must be > 0')
        self.calibration = calibration
        self._settings = (sigma_a, sigma_b, tls, noise_scale, target_run_length)
        self.cov_a, self.cov_b = device_covariances(calibration.model, sigma_a, sigma_b)
        self.tls = bool(tls)
        self.noise_scale = float(noise_scale)
        self.m = self.cov_b.shape[0]
        self.threshold = cusum_threshold(self.m, float(target_run_length))
        self._a, self._b, self._clip = llr_constants(self.m, DESIGN_INFLATION)
        self._recent: list = []  # PairBatch es of the last KEEP_S seconds
        self.statistic = 0.0
        self.n_checked = 0
        self.level = OK
        self.message = 'watching: no pairs yet'
        self.zero_stamp: Optional[int] = None  # last stamp at which the CUSUM stood at zero
        self.change_stamp: Optional[int] = None
        self.alarm_stamp: Optional[int] = None
        self.attribution: Optional[Attribution] = None
        self.transients = 0
        self._mean_d2 = float('nan')
        #: d² of the pairs of the last update (normalised squared residuals, χ²_m in control)
        self.last_d2 = np.zeros(0)

    def reset(self, calibration=None) -> None:
        """Start over (with a new calibration, if given): OK, CUSUM at zero."""
        self.__init__(calibration or self.calibration, *self._settings)

    def _restart(self) -> None:
        self.statistic = 0.0
        self.level = OK
        self.change_stamp = self.alarm_stamp = None
        self.attribution = None

    def state(self) -> WatchState:
        """Return the current state."""
        return WatchState(self.level, self.message, self.n_checked, self.statistic,
                          self.threshold, self._mean_d2, self.change_stamp, self.alarm_stamp,
                          self.attribution)

    def update(self, batch: Optional[PairBatch]) -> WatchState:
        """Check new pairs; detect, attribute; return the state."""
        if batch is None or not len(batch):
            return self.state()
        self._remember(batch)
        d2, _ = linearise(self.calibration, batch, self.cov_a, self.cov_b, self.tls,
                          self.noise_scale)
        self.n_checked += len(batch)
        self.last_d2 = d2
        self._mean_d2 = float(np.mean(d2) / self.m)
        if self.level == OK:
            self._cusum(batch, d2)
        if self.level != OK:
            self._attribute(batch)
        elif self.n_checked == len(batch) or self.message.startswith('watching'):
            self.message = f'watching: the pairs fit the calibration ({self.n_checked} checked)'
        return self.state()

    def _remember(self, batch: PairBatch) -> None:
        self._recent.append(batch)
        last = int(batch.stamps[-1])
        while self._recent and int(self._recent[0].stamps[-1]) < last - int(KEEP_S * 1e9):
            self._recent.pop(0)

    def _cusum(self, batch: PairBatch, d2: np.ndarray) -> None:
        ell = self._a * np.minimum(d2, self._clip) - self._b
        c = np.cumsum(ell)
        # S_k = max(0, S_{k-1} + ℓ_k) in closed form: C_k minus the running minimum of
        # (-S_0, C_1, .., C_k)
        low = np.minimum.accumulate(np.concatenate([[-self.statistic], c]))[1:]
        s = c - low
        zero = np.flatnonzero(s <= 0.0)
        over = np.flatnonzero(s >= self.threshold)
        if over.size == 0:
            self.statistic = float(s[-1])
            if zero.size:
                self.zero_stamp = int(batch.stamps[zero[-1]])
            return
        k = int(over[0])
        before = zero[zero < k]
        if before.size:
            self.zero_stamp = int(batch.stamps[before[-1]])
        self.statistic = float(s[k])
        self.alarm_stamp = int(batch.stamps[k])
        # the change came after the CUSUM last stood at zero
        self.change_stamp = (self.zero_stamp + 1 if self.zero_stamp is not None
                             else int(self._recent[0].stamps[0]))
        self.level = WARN
        self.message = 'the pairs no longer fit the calibration; attributing the change'

    def _window(self) -> Optional[PairBatch]:
        batch = PairBatch.concatenate(self._recent)
        if batch is None:
            return None
        keep = batch.stamps >= self.change_stamp
        if keep.sum() > MAX_FIT_PAIRS:
            idx = np.flatnonzero(keep)
            keep = idx[np.linspace(0, len(idx) - 1, MAX_FIT_PAIRS).round().astype(int)]
        return batch.take(keep)

    def _attribute(self, batch: PairBatch) -> None:
        if (self.level == ERROR
                and (int(batch.stamps[-1]) - self.change_stamp) * 1e-9 > REFINE_S):
            return  # the size is known well enough: no more fits on a stale calibration
        window = self._window()
        if window is None or not len(window):
            return
        span = (int(window.stamps[-1]) - int(window.stamps[0])) * 1e-9
        if len(window) < MIN_WINDOW_PAIRS or span < MIN_WINDOW_S:
            return
        _, lin = linearise(self.calibration, window, self.cov_a, self.cov_b, self.tls,
                           self.noise_scale)
        att = attribute(self.calibration, lin)
        since = (int(batch.stamps[-1]) - self.change_stamp) * 1e-9
        if self.level == ERROR:
            # latched: keep refining the size while the window grows, not the verdict
            if att.kind == self.attribution.kind:
                self.attribution = att
                self.message = f'calibration stale: {att.text}; recalibrate'
            return
        if att.kind == 'none' and att.decided:
            self.transients += 1
            self._restart()
            self.message = ('watching: a transient departure (outliers?) passed; the pairs fit '
                            'the calibration again')
            return
        self.attribution = att
        if att.decided and att.kind != 'none':
            self.level = ERROR
            self.message = f'calibration stale: {att.text}; recalibrate'
        elif since >= MAX_UNDECIDED_S:
            self.level = ERROR
            self.message = (f'calibration stale: the pairs no longer fit; {att.text} '
                            f'after {since:.0f} s; recalibrate')
        else:
            self.message = f'the pairs no longer fit the calibration: {att.text}'
