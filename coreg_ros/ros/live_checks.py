"""
The node's live checks: guidance while collecting and the watchdog of the published calibration.

Once a second, from the diagnostics timer of the services thread (never in the subscription
callbacks), ``LiveChecks.tick``:

1. pairs only the recent slice of the buffers (B from the last paired stamp minus
   ``OVERLAP_S``, A around it) by the one pairing rule (``pairing.pair_for`` at the published
   calibration's clock offset) and turns the new pairs into a ``PairBatch`` with A's velocity
   (``guidance.PairFeed``, which ignores pairs it has seen);
2. guidance (parameter ``guidance``): adds the batch to a ``GuidanceAccumulator``; until a
   calibration exists its estimate is the closed form of the pairs so far
   (``Estimate.from_pairs`` on an evenly decimated store, every ``ESTIMATE_PERIOD`` s), then
   the calibration's. Publishes the status ``<node>: guidance`` (level OK, message the
   summary, values ``Guidance.diagnostic_values()``). With ``auto_calibrate`` the node
   calibrates (``Calibrator.calibrate_and_publish``, in this thread) once the targets are met
   and no calibration exists;
3. watchdog (parameter ``watchdog``): once a calibration is published (or a stored one
   republished at start-up), checks every new pair against it (``watchdog.Watchdog``) and
   publishes ``<node>: watchdog`` (level, message and values of the ``WatchState``). A stale
   calibration (ERROR) stops ``~/fused_pose`` (unless ``fuse_when_stale``) and is flagged on
   ``~/calibration_stale`` (std_msgs/Bool, transient-local, published on every change).
   With ``auto_recalibrate`` the node recalibrates on the samples since the change point with
   the parts of the old calibration that still hold as a prior
   (``watchdog.recalibration_prior``), ``RECALIBRATE_AFTER_S`` s after the change, and
   publishes the result only if it passes the fit verdict.

``~/reset`` starts guidance and the pairing afresh; the watchdog keeps watching the published
calibration (its verdict is about the calibration, not the samples).
"""

from __future__ import annotations

from dataclasses import dataclass
import time
import traceback
from typing import Optional

from coreg_ros.core.calibration.pairing import pair_for
from coreg_ros.core.errors import CoregError
from coreg_ros.core.live import guidance as gd
from coreg_ros.core.live import watchdog as wd
from coreg_ros.core.planning.crlb import CRLB_DIMENSION
from coreg_ros.core.types import CalibrationResult, PoseStream, TimeOffset, UncertainPose
from coreg_ros.ros.calibrator import Calibrator
from coreg_ros.ros.interface import LATCHED_QOS
from coreg_ros.ros.parameters import ParameterView
from coreg_ros.ros.throttle import Throttle
from coreg_ros.ros.uncertainty_outputs import UncertaintyOutputs
from diagnostic_msgs.msg import DiagnosticStatus, KeyValue
import numpy as np
from std_msgs.msg import Bool

#: B samples before the last paired stamp paired again each tick, s (their A neighbours may
#: have arrived late); the feed ignores the pairs it has already seen.
OVERLAP_S = 0.2
#: A samples kept before the first B stamp of a slice, beyond the offset and max_gap, s.
A_MARGIN_S = 0.1
#: Seconds between two closed-form estimates before a calibration exists.
ESTIMATE_PERIOD = 10.0
#: Pairs kept (evenly decimated) for the closed-form estimate.
ESTIMATE_PAIRS = 20_000
#: Seconds between two automatic calibration attempts.
RETRY_PERIOD = 10.0
#: Seconds of pairs after the change point before an automatic recalibration is tried.
RECALIBRATE_AFTER_S = 10.0
#: Seconds between two automatic recalibration attempts on the same change.
RECALIBRATE_RETRY = 30.0
#: Node parameters of the live checks (changeable at run time; the targets apply at once).
LIVE_KEYS = ('guidance', 'motion_limits', 'target_sigma_position', 'target_sigma_rotation',
             'target_sigma_time', 'auto_calibrate', 'watchdog', 'auto_recalibrate')

#: QoS of ~/calibration_stale: the result topics' (late subscribers get the last state).
STALE_QOS = LATCHED_QOS


@dataclass(frozen=True)
class PublishedPoses:
    """The published calibration's two poses (what ``recalibration_prior`` reads)."""

    base_to_base: UncertainPose
    tool_to_marker: UncertainPose


def _recent(buffer, mark: int, start_ns: Optional[int]) -> tuple[int, PoseStream]:
    """
    Return the samples accepted after ``mark`` and the held ones stamped ``>= start_ns``.

    Returns (the accepted count the slice ends at, the slice). Looks back in growing steps, so
    the cost is that of the new samples, not of the buffer.
    """
    extra = 64 + (buffer.accepted - mark) // 4
    while True:
        first = max(0, mark - extra)
        end, stream, _ = buffer.since(first)
        if (start_ns is None or first == 0 or not len(stream) or len(stream) >= len(buffer)
                or int(stream.stamps[0]) < start_ns):
            break
        extra *= 4
    if start_ns is not None and len(stream):
        stream = stream.take(stream.stamps >= start_ns)
    return end, stream


def stored_calibration(doc: dict, base_to_base: UncertainPose,
                       tool_to_marker: UncertainPose) -> wd.Calibration:
    """
    Return the watchdog's ``Calibration`` of a stored result (``persistence.load_result``).

    The joint covariance of (ψ, τ) is built from the stored ``cov_joint`` (cross terms of T0
    and T1) or the two 6×6 pose covariances, and τ's σ²; components not estimated (-1 on the
    diagonal) have zero rows. The cross terms of τ are not stored (zero).
    """
    r = doc.get('result', {})
    model = r.get('model', 'full_pose')
    d = CRLB_DIMENSION[model]
    joint = r.get('cov_determined', r.get('cov_joint'))  # held directions: left out
    if joint is not None:
        c12 = np.asarray(joint, dtype=float).reshape(12, 12)
    else:
        c12 = np.zeros((12, 12))
        for k, pose in enumerate((base_to_base, tool_to_marker)):
            if pose.covariance is not None:
                c12[6 * k:6 * k + 6, 6 * k:6 * k + 6] = np.reshape(pose.covariance, (6, 6))
    unknown = ~(np.diag(c12) >= 0)
    c12 = np.where(unknown[:, None] | unknown[None, :], 0.0, c12)
    rows = np.arange(12 if model == 'full_pose' else 9)  # ψ's T0, T1 part in crlb order
    cov = np.zeros((d + 1, d + 1))
    cov[np.ix_(rows, rows)] = c12[np.ix_(rows, rows)]
    timing = TimeOffset.from_dict(r.get('time_offset'), r.get('clock_drift'))
    tau = 0.0 if timing is None else float(timing.value_s)
    if timing is not None and timing.estimated and timing.sigma_s is not None:
        cov[d, d] = float(timing.sigma_s) ** 2
    markers = np.atleast_2d(np.asarray(r.get('markers', [tool_to_marker.position]), float))
    estimate = gd.Estimate(model, np.asarray(base_to_base.position, dtype=float),
                           np.asarray(base_to_base.quat_wxyz, dtype=float), markers,
                           np.asarray(tool_to_marker.quat_wxyz, dtype=float))
    return wd.Calibration(estimate, cov, tau)


def _status(name: str, hardware_id: str, level: int, message: str, values) -> DiagnosticStatus:
    return DiagnosticStatus(level=bytes([int(level)]), name=name, message=message,
                            hardware_id=hardware_id,
                            values=[KeyValue(key=k, value=v) for k, v in values])


class LiveChecks:
    """
    Guidance and watchdog of coreg_node (see the module docstring).

    Parameters
    ----------
    node_name : str
        The node's name (the statuses are ``<node>: guidance`` and ``<node>: watchdog``).
    topics : sequence of str
        A's topic, then B's (the statuses' hardware id).
    params : ParameterView
        The current settings and the ``LIVE_KEYS`` parameters (and ``fuse_when_stale``).
    buffers : dict of str to StreamBuffer
        The held samples, per topic (``SampleStore.buffers``).
    calibrator : Calibrator
        The published calibration's clock offset (``timing``) and ``calibrate_and_publish``.
    outputs : UncertaintyOutputs
        Told when the calibration is stale (``set_stale``).
    pub_stale : rclpy.publisher.Publisher
        Publisher of ``~/calibration_stale`` (std_msgs/Bool, ``STALE_QOS``).
    logger : rclpy.impl.rcutils_logger.RcutilsLogger
        The node's logger.

    """

    def __init__(self, node_name: str, topics, params: ParameterView, buffers: dict,
                 calibrator: Calibrator, outputs: UncertaintyOutputs, pub_stale, logger):
        self.node_name = node_name
        self.topics = tuple(topics)
        self.params = params
        self.buffers = buffers
        self.calibrator = calibrator
        self.outputs = outputs
        self.pub_stale = pub_stale
        self.logger = logger
        self.poses: Optional[PublishedPoses] = None
        self.watch: Optional[wd.Watchdog] = None
        self.state: Optional[wd.WatchState] = None
        self.stale = False
        self.seconds = 0.0          # wall time of the last tick's work, s
        self._log_throttle = Throttle()  # one line per WARN_PERIOD of a failing tick
        self._error: Optional[str] = None
        self._next_recalibration = 0.0
        self._next_auto = 0.0
        self.reset()

    # --- set-up ----------------------------------------------------------------------------

    def _targets(self) -> tuple:
        tim = float(self.params('target_sigma_time'))
        return (float(self.params('target_sigma_position')),
                float(self.params('target_sigma_rotation')), tim if tim > 0 else None)

    def reset(self) -> None:
        """Start pairing and guidance afresh (at start-up and on ``~/reset``)."""
        settings = self.params.settings()
        self.settings = settings
        self.feed = gd.PairFeed(max_gap=settings.max_gap)
        self.guide = gd.GuidanceAccumulator(
            settings.model, settings.device_noise('a'), settings.device_noise('b'),
            *self._targets(),
            estimate_time_offset=settings.estimate_time_offset, tls=settings.method == 'tls',
            motion_limits=str(self.params('motion_limits')))
        self.guidance: Optional[gd.Guidance] = None
        self._marks = dict.fromkeys(self.buffers, 0)  # since(0): every sample held
        self._last_stamp: Optional[int] = None
        self._store: list = []     # evenly decimated batches for the closed-form estimate
        self._n_store = 0
        self._stride = 1
        self._seen = 0
        self._next_estimate = 0.0
        if self.poses is not None and self.watch is not None:
            self.guide.set_estimate(self.watch.calibration.estimate, force=True)

    def set_result(self, result: CalibrationResult) -> None:
        """Use a published calibration: guidance evaluates there; watch it from now on."""
        self.poses = PublishedPoses(result.base_to_base, result.tool_to_marker)
        chi2_dof = result.chi2 / result.dof if result.dof > 0 else 1.0
        self._watch(wd.Calibration.from_result(result), chi2_dof)
        if self.guide.model == result.model:
            self.guide.set_estimate(gd.Estimate.from_result(result))

    def set_stored(self, doc: dict, base_to_base: UncertainPose,
                   tool_to_marker: UncertainPose) -> None:
        """Watch a stored result republished at start-up."""
        self.poses = PublishedPoses(base_to_base, tool_to_marker)
        r = doc.get('result', {})
        dof, chi2 = r.get('dof') or 0, r.get('chi2')
        calibration = stored_calibration(doc, base_to_base, tool_to_marker)
        self._watch(calibration, chi2 / dof if dof and chi2 is not None else 1.0)
        if self.guide.model == calibration.model:
            self.guide.set_estimate(calibration.estimate)

    def _watch(self, calibration: wd.Calibration, chi2_dof: float) -> None:
        s = self.settings = self.params.settings()
        self.watch = wd.Watchdog(calibration, s.device_noise('a'), s.device_noise('b'),
                                 tls=s.method == 'tls', noise_scale=max(1.0, float(chi2_dof)))
        self.state = None
        self._set_stale(False)

    def _set_stale(self, stale: bool) -> None:
        self.outputs.set_stale(stale)
        if stale != self.stale or self.state is None:
            self.pub_stale.publish(Bool(data=bool(stale)))
        self.stale = stale

    # --- the tick --------------------------------------------------------------------------

    def tick(self) -> list:
        """Pair, update guidance and the watchdog, act; return their DiagnosticStatus es."""
        t0 = time.monotonic()
        try:
            out = self._tick()
            self._error = None
        except Exception as e:  # never end the diagnostics timer: say it, keep the node up
            self._error = f'live checks failed: {type(e).__name__}: {e}'
            if self._log_throttle.ready():
                self.logger.error(f'{self._error}\n{traceback.format_exc()}')
            name = self.node_name
            out = [_status(f'{name}: {gd.STATUS_NAME}', self._hardware_id(), 2, self._error,
                           [])]
        self.seconds = time.monotonic() - t0
        return out

    def _hardware_id(self) -> str:
        return ' + '.join(self.topics)

    def _tick(self) -> list:
        guidance_on = bool(self.params('guidance'))
        watchdog_on = bool(self.params('watchdog')) and self.watch is not None
        if not (guidance_on or watchdog_on):
            if self.stale:
                self._set_stale(False)
            return []
        batch = self._new_batch()
        out = []
        name, hw = self.node_name, self._hardware_id()
        if guidance_on:
            status = self._guidance(batch)
            out.append(_status(f'{name}: {gd.STATUS_NAME}', hw, *status))
        if watchdog_on:
            st = self.state = self.watch.update(batch)
            fuse = bool(self.params('fuse_when_stale'))
            self._set_stale(st.stale)
            message = st.message
            if st.stale:
                message += ('; ~/fused_pose goes on (fuse_when_stale), flagged on '
                            '~/calibration_stale' if fuse else '; ~/fused_pose stopped')
                if bool(self.params('auto_recalibrate')):
                    message += f'; {self._recalibrate(st)}'
            out.append(_status(f'{name}: {wd.STATUS_NAME}', hw, st.level, message,
                               st.diagnostic_values()))
        elif self.stale:
            self._set_stale(False)
        return out

    def _new_batch(self) -> Optional[gd.PairBatch]:
        """Pair the recent slice of the buffers; return the pairs the feed releases."""
        settings = self.params.settings()
        buffers = self.buffers
        start_b = None if self._last_stamp is None else (
            self._last_stamp - int(OVERLAP_S * 1e9))
        ends, streams_b = {}, []
        for topic in settings.topic_b:
            ends[topic], s = _recent(buffers[topic], self._marks[topic], start_b)
            streams_b.append(s)
        if not all(len(s) for s in streams_b):
            return self.feed.push(None, final=True)  # the streams paused: release all held
        if ends[settings.topic_b[0]] == self._marks[settings.topic_b[0]]:
            return self.feed.push(None, final=True)
        timing = self.calibrator.timing
        first_b = int(min(int(s.stamps[0]) for s in streams_b))
        offset_ns = (settings.time_offset_ns if timing is None
                     else timing.offset_ns_at(first_b))
        start_a = first_b - offset_ns - settings.max_gap_ns - int(A_MARGIN_S * 1e9)
        ends[settings.topic_a], stream_a = _recent(buffers[settings.topic_a],
                                                   self._marks[settings.topic_a], start_a)
        self._marks.update(ends)
        try:
            pairs, _ = pair_for(stream_a, streams_b, settings, timing)
        except CoregError:
            return None  # nothing pairable in the slice (yet)
        if not len(pairs):
            return None
        self._last_stamp = int(pairs.stamps[-1])
        return self.feed.push(pairs)

    # --- guidance --------------------------------------------------------------------------

    def _keep(self, batch: gd.PairBatch) -> None:
        idx = np.arange(self._seen, self._seen + len(batch))
        self._seen += len(batch)
        take = idx % self._stride == 0
        if take.any():
            self._store.append(batch.take(take))
            self._n_store += int(take.sum())
        while self._n_store > ESTIMATE_PAIRS:
            every = gd.PairBatch.concatenate(self._store)
            self._store = [every.take(slice(None, None, 2))]
            self._n_store = len(self._store[0])
            self._stride *= 2

    def _guidance(self, batch: Optional[gd.PairBatch]) -> tuple:
        """Update guidance; return (level, message, values) of its status."""
        guide = self.guide
        guide.targets = self._targets()  # targets and limits may change at run time
        guide.motion_limits = str(self.params('motion_limits'))
        if batch is not None and len(batch):
            guide.add(batch)
            if self.poses is None:
                self._keep(batch)
        now = time.monotonic()
        if (self.poses is None and self._n_store >= self.settings.min_pairs
                and now >= self._next_estimate):
            self._next_estimate = now + ESTIMATE_PERIOD
            try:
                guide.set_estimate(gd.Estimate.from_pairs(
                    guide.model, gd.PairBatch.concatenate(self._store)))
            except (CoregError, np.linalg.LinAlgError):
                pass  # not yet enough motion for a closed form: try again later
        if guide.estimate is None:
            self.guidance = None
            message = (f'collecting: {guide.n_pairs} pairs; no estimate yet (it needs '
                       f'{self.settings.min_pairs} pairs and rotations about two axes)')
            return 0, message, [(gd.KEY_PAIRS, str(guide.n_pairs)),
                                (gd.KEY_READY, 'false'), (gd.KEY_SUMMARY, message)]
        g = self.guidance = guide.guidance()
        message = g.summary
        values = g.diagnostic_values()
        if g.ready and self.poses is not None:  # not 'calibrate now': one is published
            values = [(k, 'ready: a calibration is published (~/calibrate refits on all the '
                          'pairs held)' if k == gd.KEY_NEXT_TEXT else v) for k, v in values]
        if g.ready and self.poses is None and bool(self.params('auto_calibrate')):
            message += f'; auto_calibrate: {self._auto_calibrate()}'
        return 0, message, values

    def _auto_calibrate(self) -> str:
        now = time.monotonic()
        if now < self._next_auto:
            return 'retrying later'
        self._next_auto = now + RETRY_PERIOD
        ok, message = self.calibrator.calibrate_and_publish(what='auto_calibrate')
        return 'calibrated' if ok else f'refused ({message})'

    # --- watchdog --------------------------------------------------------------------------

    def _recalibrate(self, st: wd.WatchState) -> str:
        """Recalibrate after a decided change of T0, T1 or the clock; return what happened."""
        att = st.attribution
        if att is None or not att.decided or st.change_stamp is None:
            return 'auto_recalibrate: waiting for the attribution'
        prior = wd.recalibration_prior(self.poses, att.kind)
        if prior is None:
            return f'auto_recalibrate: nothing to recalibrate after "{wd.KIND_TEXT[att.kind]}"'
        last = self._last_stamp or st.change_stamp
        waited = (last - st.change_stamp) * 1e-9
        if waited < RECALIBRATE_AFTER_S:
            return (f'auto_recalibrate in {RECALIBRATE_AFTER_S - waited:.0f} s (pairs since '
                    f'the change)')
        now = time.monotonic()
        if now < self._next_recalibration:
            return 'auto_recalibrate: retrying later'
        self._next_recalibration = now + RECALIBRATE_RETRY
        settings = self.params.settings()
        timing = self.calibrator.timing
        offset_ns = settings.time_offset_ns if timing is None else timing.offset_ns()
        streams = {}
        for topic, b in self.buffers.items():
            s = b.snapshot()
            start = (st.change_stamp if topic in settings.topic_b else
                     st.change_stamp - offset_ns - settings.max_gap_ns - int(1e9))
            streams[topic] = s.take(s.stamps >= start)
        ok, message = self.calibrator.calibrate_and_publish(
            streams=streams, prior=prior, what='auto_recalibrate')
        if ok:
            return f'recalibrated: {message}'
        return (f'auto_recalibrate refused (again in {RECALIBRATE_RETRY:.0f} s on the grown '
                f'window): {message}')
