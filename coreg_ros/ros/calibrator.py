"""
coreg_node's calibrations: fit, judge, publish the two transforms, store; the stored result.

``Calibrator`` runs ``calibration.pipeline.calibrate_streams`` (the very function ``coreg
calibrate BAG`` runs, so live and offline results agree) on a snapshot of the held samples.
For ``~/calibrate`` the fit runs in a worker thread while the services executor goes on (the
diagnostics, the fused pose and the journal do not wait for it); what follows the fit
(publishing, telling the listeners, storing) happens back in the executor thread, as it does
for the live checks' calibrations (``auto_calibrate``, ``auto_recalibrate``), which run in it.

A published calibration goes to ``~/base_to_base`` and ``~/tool_to_marker`` (stamped now) and
to /tf_static (``ros.static_tf``, with ``publish_tf``), to
the listeners (``UncertaintyOutputs`` and ``LiveChecks``: ``set_result``) and to
``storage_dir`` under a name of the node and its configuration. At start-up
``republish_stored`` republishes the stored result of this node and configuration only,
stamped with its calibration time (the listeners get ``set_stored``).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import replace
import os
from pathlib import Path
import threading
import time
import traceback
from typing import Optional

from coreg_ros.core.calibration.pipeline import calibrate_streams
from coreg_ros.core.errors import CoregError
from coreg_ros.core.estimator.priors import Prior
from coreg_ros.core.provenance import data_sketch, shared_samples
from coreg_ros.core.types import TimeOffset
from coreg_ros.files.results import load_prior
from coreg_ros.ros import persistence
from coreg_ros.ros.alerts import Alerts
from coreg_ros.ros.messages import ns_to_stamp, uncertain_pose_to_msg
from coreg_ros.ros.parameters import NodeConfig, ParameterView
from coreg_ros.ros.sample_store import SampleStore
from coreg_ros.ros.static_tf import StaticTf
from coreg_ros.ros.uncertainty_outputs import stored_result_dict
from rclpy.task import Future


class Calibrator:
    """
    Calibrate on request and publish, store and hand on the result (see the module docstring).

    Parameters
    ----------
    config : NodeConfig
        Frames and ``storage_dir``.
    config_key : str
        ``persistence.config_key`` of the configuration (names the stored result).
    node_name, node_fqn : str
        The node's name and fully qualified name (stored beside the result).
    params : ParameterView
        The current settings, ``prior_file``, ``use_last_result_as_prior`` and
        ``publish_inconsistent``.
    store : SampleStore
        The held samples (``snapshot``).
    pub_base, pub_tool : rclpy.publisher.Publisher
        PoseWithCovarianceStamped publishers of ``~/base_to_base`` and ``~/tool_to_marker``.
    clock : rclpy.clock.Clock
        Stamps the published transforms.
    logger : rclpy.impl.rcutils_logger.RcutilsLogger
        The node's logger.
    alerts : Alerts
        Where a failure to store the result goes.
    io_lock : threading.Lock
        Taken while the result is written (the node's disk writes, one at a time).
    wake : callable
        Wakes the services executor (a guard condition's ``trigger``) when a fit in the worker
        thread is done, so the waiting ``~/calibrate`` goes on at once.
    static_tf : StaticTf, optional
        Broadcasts what is published on /tf_static too (``ros.static_tf``).

    Attributes
    ----------
    summary : dict or None
        The last calibration's figures for /diagnostics.
    timing : TimeOffset or None
        The clock offset of the published calibration.

    """

    def __init__(self, config: NodeConfig, config_key: str, node_name: str, node_fqn: str,
                 params: ParameterView, store: SampleStore, pub_base, pub_tool, clock, logger,
                 alerts: Alerts, io_lock: threading.Lock, wake: Callable[[], None],
                 static_tf: Optional[StaticTf] = None):
        self.config = config
        self.config_key = config_key
        self.node_name = node_name
        self.node_fqn = node_fqn
        self.params = params
        self.store = store
        self.pub_base = pub_base
        self.pub_tool = pub_tool
        self.clock = clock
        self.logger = logger
        self.alerts = alerts
        self.io_lock = io_lock
        self.wake = wake
        self.static_tf = static_tf
        self.result_name = persistence.result_file_name(node_name, config_key)
        self.summary: Optional[dict] = None
        self.timing: Optional[TimeOffset] = None
        self._listeners: list = []
        self._fit_lock = threading.Lock()  # one fit at a time, in the order asked

    def add_listener(self, listener) -> None:
        """Tell ``listener`` of every published calibration (``set_result``, ``set_stored``)."""
        self._listeners.append(listener)

    # --- calibrating --------------------------------------------------------------------------

    async def on_calibrate(self, request, response):
        """Answer ``~/calibrate`` (std_srvs/Trigger); the fit runs in a worker thread."""
        t0 = time.monotonic()
        try:
            inputs = self._inputs(None, None)
            result, report = await self._in_worker(self._fit, *inputs)
        except Exception as e:
            response.success, response.message = self._refused(e, 'calibrate')
            return response
        response.success, response.message = self._publish(inputs[0], result, report,
                                                           time.monotonic() - t0, 'calibrate',
                                                           inputs[2])
        return response

    def calibrate_and_publish(self, streams: Optional[dict] = None, prior=None,
                              what: str = 'calibrate') -> tuple[bool, str]:
        """
        Calibrate, judge, publish and store, in this thread (``auto_calibrate``...).

        Parameters
        ----------
        streams : dict of topic to PoseStream, optional
            The samples (default: a snapshot of everything held).
        prior : Prior, optional
            Default: ``prior_file``, else the stored result if ``use_last_result_as_prior``.
        what : str
            Who asks, for the log lines.

        Returns
        -------
        (success, message) : (bool, str)
            As the Trigger answer; never raises.

        """
        t0 = time.monotonic()
        try:
            inputs = self._inputs(streams, prior)
            result, report = self._fit(*inputs)
        except Exception as e:
            return self._refused(e, what)
        return self._publish(inputs[0], result, report, time.monotonic() - t0, what, inputs[2])

    def _inputs(self, streams: Optional[dict], prior) -> tuple:
        """Return (settings, prior, streams) of a calibration now (defaults filled in)."""
        settings = self.params.settings()
        streams = self.store.snapshot() if streams is None else streams
        prior = self._prior([streams[t] for t in settings.topic_b]) if prior is None else prior
        return settings, prior, streams

    def _fit(self, settings, prior, streams: dict) -> tuple:
        """Run the shared pipeline: (result, pairing report)."""
        with self._fit_lock:
            return calibrate_streams(
                streams[settings.topic_a], [streams[t] for t in settings.topic_b], settings,
                prior, frames=(self.config.frame_base_a, self.config.frame_base_b),
                roles_confirmed=bool(self.params('roles_confirmed')))

    def _in_worker(self, fit: Callable, *args) -> Future:
        """Run ``fit(*args)`` in a daemon thread; return the Future a coroutine awaits."""
        done = Future()

        def work() -> None:
            try:
                done.set_result(fit(*args))
            except BaseException as e:  # handed to the awaiting service, which answers it
                done.set_exception(e)
            try:
                self.wake()
            except Exception:  # the node is gone (shutting down): nobody waits any more
                pass

        threading.Thread(target=work, name='coreg_calibration', daemon=True).start()
        return done

    def _refused(self, error: Exception, what: str) -> tuple[bool, str]:
        """Log and answer a calibration that could not be made."""
        if isinstance(error, CoregError):
            self.logger.warning(f'{what} refused: {error}')
            return False, str(error)
        # a bug must not kill the node: answer, log the traceback
        trace = ''.join(traceback.format_exception(error))
        self.logger.error(f'{what} failed: {trace}')
        return False, f'internal error ({type(error).__name__}: {error}); see the node log'

    def _prior(self, streams_b: list):
        """
        Return the prior of the next calibration, of the samples ``streams_b`` of B.

        prior_file, else the stored result (``use_last_result_as_prior``), with the gravity
        alignment of ``gravity_aligned_sigma`` when it is set. A stored result calibrated on
        samples that are still held is left out (it would count them twice: the pipeline
        refuses such a prior when the user gives it as prior_file).
        """
        prior = None
        path = str(self.params('prior_file')).strip()
        stored = Path(self.config.storage_dir) / self.result_name
        if path:
            prior = load_prior(os.path.expanduser(path))
        elif bool(self.params('use_last_result_as_prior')) and stored.is_file():
            prior = load_prior(stored)
            if shared_samples(prior.data_sketch, streams_b) is not None:
                self.logger.info('the stored result is not used as the prior: it was calibrated '
                                 'on samples held now (it would count them twice)')
                prior = None
        gravity = float(self.params('gravity_aligned_sigma'))
        if gravity > 0:
            prior = replace(prior or Prior(), gravity_sigma=gravity)
        return prior

    def _publish(self, settings, result, report, seconds: float, what: str,
                 streams: dict) -> tuple[bool, str]:
        """Judge a fit; publish, hand on and store it if it passes; return the answer."""
        chi2_dof = result.chi2 / result.dof if result.dof > 0 else float('nan')
        timing = result.time_offset
        self.summary = {'n_pairs': result.n_pairs, 'chi2_dof': chi2_dof,
                        'p_value': result.p_value, 'success': result.success,
                        'seconds': seconds, 'pairing': report.summary(),
                        'fit_consistent': result.fit_consistent,
                        'rejected_pairs': result.n_rejected,
                        'time_offset_s': None if timing is None else timing.value_s,
                        'time_offset_sigma_s': None if timing is None else timing.sigma_s,
                        'verdict': result.verdict}
        inconsistent = result.flagged
        # a swap is refused whatever publish_inconsistent says: roles_confirmed lifts it
        publish_anyway = (inconsistent and not result.refusals
                          and bool(self.params('publish_inconsistent')))
        if not result.success and not publish_anyway:
            fix = ('set roles_confirmed:=true if topic_a and topic_b are right' if
                   result.refusals else 'set publish_inconsistent:=true to publish it anyway')
            message = (
                f'not published: {result.verdict} ({report.summary()}); {fix}' if inconsistent
                else f'no convergence after {result.iterations} iterations: {result.message}; '
                     f'{report.summary()}')
            self.logger.warning(f'{what}: {message}')
            return False, message
        stamp_ns = self._publish_result(result.base_to_base, result.tool_to_marker)
        self.timing = timing
        for listener in self._listeners:
            listener.set_result(result)
        try:
            with self.io_lock:
                document = stored_result_dict(result)
                # which samples: a calibration of the same ones refuses it as its prior
                document['data_sketch'] = data_sketch([streams[t] for t in settings.topic_b])
                path = persistence.save_result(
                    self.config.storage_dir, document, self.config.frames,
                    settings.as_dict(), name=self.result_name,
                    extra={'node': self.node_fqn, 'config_key': self.config_key,
                           'stamp_ns': stamp_ns})
            stored, kept = f'stored in {path}', True
        except OSError as e:
            # published, but a restart would not have it: not a success (README, the node)
            failed = self.alerts.storage_failed('store the result', e)
            stored, kept = f'published but NOT stored: {failed}', False
        p0 = result.base_to_base.position
        p1 = result.tool_to_marker.position
        offset = '' if timing is None else (
            f'time offset {timing.value_s * 1e3:.3f} ± {timing.sigma_s * 1e3:.3f} ms, '
            if timing.estimated else f'time offset {timing.value_s * 1e3:.3f} ms (given), ')
        message = (
            ('PUBLISHED ALTHOUGH INCONSISTENT: ' + result.verdict + '; ' if inconsistent
             else '') +
            f'{result.n_pairs} pairs, {settings.method}/{settings.model}: chi2/dof '
            f'{chi2_dof:.3g}, p {result.p_value:.3g}, {offset}{result.n_rejected} rejected, '
            f'{result.iterations} iterations, '
            f'{seconds:.2f} s; base_to_base p [{p0[0]:.4f}, {p0[1]:.4f}, {p0[2]:.4f}] m, '
            f'tool_to_marker p [{p1[0]:.4f}, {p1[1]:.4f}, {p1[2]:.4f}] m; {stored}')
        if result.noise is not None:  # noise: auto, what the calibration found of the noise
            message += '; ' + (result.noise.verdict() or 'noise estimated: as stated')
        if result.held:  # a rig that cannot move in every direction: what is unknown
            message += '; held (the motion cannot show it, covariance unknown along it): ' + \
                '; '.join(u.description for u in result.held)
        self.logger.info(f'calibrated ({what}): {message}')
        return not inconsistent and kept, message

    def _publish_result(self, base_to_base, tool_to_marker,
                        stamp_ns: Optional[int] = None) -> int:
        """
        Publish the two transforms stamped ``stamp_ns`` (default: now); return the stamp.

        To ``~/base_to_base``, ``~/tool_to_marker`` and (``publish_tf``) /tf_static.
        """
        if stamp_ns is None:
            stamp_ns = self.clock.now().nanoseconds
        stamp = ns_to_stamp(int(stamp_ns))
        self.pub_base.publish(uncertain_pose_to_msg(base_to_base, self.config.frame_base_b,
                                                    stamp))
        self.pub_tool.publish(uncertain_pose_to_msg(tool_to_marker, self.config.frame_tool,
                                                    stamp))
        if self.static_tf is not None:
            self.static_tf.send(base_to_base, tool_to_marker, stamp)
        return int(stamp_ns)

    # --- the stored result --------------------------------------------------------------------

    def _describe_config(self) -> str:
        return persistence.describe_config({'settings': self.config.settings.as_dict(),
                                            'frames': self.config.frames})

    def republish_stored(self) -> None:
        """Republish the stored result of this node and configuration, and only that."""
        storage, log = self.config.storage_dir, self.logger
        settings, frames = self.config.settings.as_dict(), self.config.frames
        try:
            stored = persistence.load_result(storage, self.result_name)
        except CoregError as e:
            log.error(str(e))
            stored = None
        for path in persistence.other_results(storage, self.node_name, self.config_key):
            try:
                other = persistence.load_result(storage, path.name)
            except CoregError as e:
                log.warning(f'{e} (not republished)')
                continue
            if other is None:
                continue
            if (stored is None and path.name == persistence.RESULT_FILE
                    and persistence.matches_config(other[0], settings, frames)):
                stored = other  # an older version's result.yaml of this very configuration
                continue
            log.info(f'not republishing {path}: it was calibrated for '
                     f'{persistence.describe_config(other[0])}; this node is configured for '
                     f'{self._describe_config()}')
        if stored is None:
            return
        doc, base_to_base, tool_to_marker = stored
        self._publish_result(base_to_base, tool_to_marker, persistence.stamp_ns_of(doc))
        r = doc['result']
        self.timing = TimeOffset.from_dict(r.get('time_offset'), r.get('clock_drift'))
        for listener in self._listeners:
            listener.set_stored(doc, base_to_base, tool_to_marker)
        dof = r.get('dof') or 0
        self.summary = {'n_pairs': r.get('n_pairs'), 'success': r.get('success'),
                        'chi2_dof': (r['chi2'] / dof) if dof and r.get('chi2') is not None
                        else float('nan'),
                        'p_value': r.get('p_value'), 'seconds': None,
                        'pairing': f'stored result of {doc.get("saved_at", "?")}'}
        log.info(f'republished the stored result of {doc.get("saved_at", "?")} '
                 f'({r.get("n_pairs")} pairs, {self._describe_config()}), stamped with its '
                 f'calibration time')
