"""
The services of coreg_node: calibrate (and publish, and store), reset, save samples; parameters.

``NodeServices`` is a part of ``coreg_ros.ros.node.CoregNode`` (a mixin: it uses the node's
buffers, configuration and publishers); its handlers are wrapped by ``CoregNode._guarded``, so
a failure is answered with success=false and the reason, never raised.
"""

from __future__ import annotations

import os
from pathlib import Path
import time
import traceback
from typing import Optional

from coreg_ros.core.calibration.pipeline import calibrate_streams
from coreg_ros.core.errors import CoregError
from coreg_ros.core.settings import Settings
from coreg_ros.files.results import load_prior
from coreg_ros.ros import persistence
from coreg_ros.ros.messages import ns_to_stamp, uncertain_pose_to_msg
from coreg_ros.ros.parameters import CALIBRATION_KEYS, settings_from_values
from coreg_ros.ros.uncertainty_outputs import stored_result_dict
from rcl_interfaces.msg import SetParametersResult


class NodeServices:
    """The ``~/calibrate``, ``~/reset`` and ``~/save_samples`` services of ``CoregNode``."""

    def current_settings(self) -> Settings:
        """Calibration settings from the current parameter values."""
        return settings_from_values({k: self.get_parameter(k).value for k in CALIBRATION_KEYS})

    def snapshot(self) -> dict:
        """Return copies of the accumulated raw samples: topic -> PoseStream."""
        return {t: b.snapshot() for t, b in self.buffers.items()}

    def _on_calibrate(self, request, response):
        response.success, response.message = self.calibrate_and_publish()
        return response

    def calibrate_and_publish(self, streams: Optional[dict] = None, prior=None,
                              what: str = 'calibrate') -> tuple[bool, str]:
        """
        Calibrate, judge, publish and store (``~/calibrate``, ``auto_calibrate``...).

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
            settings = self.current_settings()
            prior = self._prior() if prior is None else prior
            streams = self.snapshot() if streams is None else streams
            result, report = calibrate_streams(
                streams[settings.topic_a], [streams[t] for t in settings.topic_b], settings,
                prior, frames=(self.config.frame_base_a, self.config.frame_base_b))
        except CoregError as e:
            self.get_logger().warning(f'{what} refused: {e}')
            return False, str(e)
        except Exception as e:  # a bug must not kill the node: answer, log the traceback
            self.get_logger().error(f'{what} failed: {traceback.format_exc()}')
            return False, f'internal error ({type(e).__name__}: {e}); see the node log'
        seconds = time.monotonic() - t0
        chi2_dof = result.chi2 / result.dof if result.dof > 0 else float('nan')
        timing = result.time_offset
        self._last = {'n_pairs': result.n_pairs, 'chi2_dof': chi2_dof,
                      'p_value': result.p_value, 'success': result.success,
                      'seconds': seconds, 'pairing': report.summary(),
                      'fit_consistent': result.fit_consistent,
                      'rejected_pairs': result.n_rejected,
                      'time_offset_s': None if timing is None else timing.value_s,
                      'time_offset_sigma_s': None if timing is None else timing.sigma_s,
                      'verdict': result.verdict}
        inconsistent = result.fit_consistent is False and result.status > 0
        publish_anyway = inconsistent and bool(
            self.get_parameter('publish_inconsistent').value)
        if not result.success and not publish_anyway:
            message = (
                f'not published: {result.verdict} ({report.summary()}); set '
                f'publish_inconsistent:=true to publish it anyway' if inconsistent else
                f'no convergence after {result.iterations} iterations: {result.message}; '
                f'{report.summary()}')
            self.get_logger().warning(f'{what}: {message}')
            return False, message
        stamp_ns = self._publish_result(result.base_to_base, result.tool_to_marker)
        self.uncertainty.set_result(result)
        self.live.set_result(result)
        try:
            with self._io_lock:
                path = persistence.save_result(
                    self.config.storage_dir, stored_result_dict(result), self.config.frames,
                    settings.as_dict(), name=self.result_name,
                    extra={'node': self.get_fully_qualified_name(),
                           'config_key': self.config_key, 'stamp_ns': stamp_ns})
            stored = f'stored in {path}'
        except OSError as e:
            stored = f'NOT stored: {self._storage_failed("store the result", e)}'
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
        self.get_logger().info(f'calibrated ({what}): {message}')
        return not inconsistent, message

    def _prior(self):
        """Return the prior of the next calibration: prior_file, else the stored result."""
        path = str(self.get_parameter('prior_file').value).strip()
        if path:
            return load_prior(os.path.expanduser(path))
        if bool(self.get_parameter('use_last_result_as_prior').value):
            stored = Path(self.config.storage_dir) / self.result_name
            if stored.is_file():
                return load_prior(stored)
        return None

    def _on_reset(self, request, response):
        with self._io_lock:
            held = sum(len(b) for b in self.buffers.values())
            for b in self.buffers.values():
                b.clear()
            for g in self.gaps.values():
                g.restart()
            self._saved_accepted = self._accepted_total()
            # the journal holds the session's samples: forgotten with them
            self._marks = {t: b.accepted for t, b in self.buffers.items()}
            if self.journal is not None:
                self.journal.remove()
                self.journal = None
        self._start_journal()
        self.live.reset()
        response.success = True
        response.message = f'forgot {held} samples; the published result is kept'
        return response

    def _on_save_samples(self, request, response):
        try:
            path = self.save_samples()
        except CoregError as e:
            response.success, response.message = False, str(e)
            return response
        if path is None:
            response.success, response.message = False, 'no samples to save yet'
        elif self._last_save_error:
            response.success = False
            response.message = f'{self._last_save_error}; the samples were saved to {path}'
        else:
            response.success, response.message = True, str(path)
        return response

    def _publish_result(self, base_to_base, tool_to_marker,
                        stamp_ns: Optional[int] = None) -> int:
        """Publish the two transforms stamped ``stamp_ns`` (default: now); return the stamp."""
        if stamp_ns is None:
            stamp_ns = self.get_clock().now().nanoseconds
        stamp = ns_to_stamp(int(stamp_ns))
        self.pub_base.publish(uncertain_pose_to_msg(base_to_base, self.config.frame_base_b,
                                                    stamp))
        self.pub_tool.publish(uncertain_pose_to_msg(tool_to_marker, self.config.frame_tool,
                                                    stamp))
        return int(stamp_ns)

    def _check_parameters(self, params) -> SetParametersResult:
        """Refuse run-time changes that would make invalid Settings."""
        changed = {p.name: p.value for p in params if p.name in CALIBRATION_KEYS}
        if not changed:
            return SetParametersResult(successful=True)
        values = {k: self.get_parameter(k).value for k in CALIBRATION_KEYS
                  if self.has_parameter(k)}
        values.update(changed)
        try:
            settings_from_values(values)
        except CoregError as e:
            return SetParametersResult(successful=False, reason=str(e))
        return SetParametersResult(successful=True)
