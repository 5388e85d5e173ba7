"""
coreg_node's /diagnostics: its main status, then the live checks' guidance and watchdog.

``StatusPublisher.publish`` (the node's 1 Hz timer, services thread) sends one DiagnosticArray:
``<node>: coregistration`` (``diagnostics``: counts by topic and reason, pairing, the last
calibration, frames, storage, the journal, interrupted sessions, internal errors) and the
statuses of ``LiveChecks.tick``. The set-up checks (swapped devices, a wrong message type on a
pose topic) are warned about in the log too, throttled.
"""

from __future__ import annotations

from collections.abc import Callable
import time
from typing import Optional

from coreg_ros.core.calibration.pairing import pair_for
from coreg_ros.core.errors import CoregError
from coreg_ros.ros.alerts import Alerts
from coreg_ros.ros.buffer import REASONS
from coreg_ros.ros.calibrator import Calibrator
from coreg_ros.ros.interface import POSE_TYPE
from coreg_ros.ros.live_checks import LiveChecks
from coreg_ros.ros.parameters import NodeConfig, ParameterView
from coreg_ros.ros.sample_store import SampleStore
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue

#: Seconds between two warnings about the set-up (swapped frames, a wrong message type).
SETUP_WARN_PERIOD = 60.0
#: Seconds /diagnostics stays WARN after a count of problems (rejected, lost...) went up.
WARN_HOLD = 10.0


class StatusPublisher:
    """
    The node's /diagnostics (see the module docstring).

    Parameters
    ----------
    node_name : str
        The node's name (the status is ``<node>: coregistration``).
    config : NodeConfig
        Topics and frames as configured.
    params : ParameterView
        The current settings (pairing).
    store : SampleStore
        The buffers and their counts, the journal and the interrupted sessions.
    calibrator : Calibrator
        The last calibration's figures (``summary``) and clock offset (``timing``).
    live : LiveChecks
        Guidance and watchdog (``tick``: their statuses).
    alerts : Alerts
        Storage and internal errors; throttled warnings.
    publisher : rclpy.publisher.Publisher
        The /diagnostics publisher (diagnostic_msgs/DiagnosticArray).
    clock : rclpy.clock.Clock
        Stamps the messages.
    publishers_info : callable
        ``Node.get_publishers_info_by_topic`` (who publishes on the pose topics, and what).
    noise : live_noise.NoiseSources, optional
        The noise measured while still (the status ``<node>: noise``).

    """

    def __init__(self, node_name: str, config: NodeConfig, params: ParameterView,
                 store: SampleStore, calibrator: Calibrator, live: LiveChecks, alerts: Alerts,
                 publisher, clock, publishers_info: Callable, noise=None):
        self.node_name = node_name
        self.config = config
        self.params = params
        self.store = store
        self.calibrator = calibrator
        self.live = live
        self.alerts = alerts
        self.publisher = publisher
        self.clock = clock
        self.publishers_info = publishers_info
        self.noise = noise
        self.pairing = {'n_paired': None, 'rate': None, 'summary': 'not yet paired',
                        'at_accepted': -1, 'next_time': 0.0}
        self._prev_problems = 0
        self._warn_until = 0.0         # monotonic time until which diagnostics stay WARN

    def publish(self) -> None:
        """Publish the main status and the live checks' (the diagnostics timer)."""
        msg = DiagnosticArray()
        msg.header.stamp = self.clock.now().to_msg()
        live = self.live.tick()  # guidance and watchdog (they never raise)
        msg.status = [self.diagnostics(), *live, *self._noise()]
        self.publisher.publish(msg)

    def _noise(self) -> list:
        """Return ``<node>: noise`` (``live_noise``); a failure is said, never raised."""
        if self.noise is None:
            return []
        try:
            return [self.noise.tick(self.node_name, self.params.settings(), self.store.buffers)]
        except Exception as e:  # noqa: BLE001 - the diagnostics timer must go on
            self.alerts.throttled(('noise',), f'noise monitor failed: {type(e).__name__}: {e}',
                                  period=SETUP_WARN_PERIOD)
            return []

    def _update_pairing(self) -> None:
        """Pair the held samples now and then (rate-limited to a few % of one core)."""
        state = self.pairing
        accepted = self.store.accepted_total()
        now = time.monotonic()
        if accepted == state['at_accepted'] or now < state['next_time']:
            return
        t0 = time.monotonic()
        settings = self.params.settings()
        streams = self.store.snapshot()
        try:
            pairs, report = pair_for(streams[settings.topic_a],
                                     [streams[t] for t in settings.topic_b], settings,
                                     self.calibrator.timing)
            state['n_paired'] = report.n_paired
            state['rate'] = report.n_paired / report.n_b if report.n_b else None
            state['summary'] = report.summary()
        except CoregError as e:
            state['n_paired'], state['rate'], state['summary'] = 0, None, str(e)
        spent = time.monotonic() - t0
        state['at_accepted'] = accepted
        state['next_time'] = now + max(1.0, 20.0 * spent)

    def check_frames(self) -> Optional[str]:
        """Name swapped devices from the frame ids (warned, throttled; not if roles_confirmed)."""
        if bool(self.params('roles_confirmed')):
            return None
        base_a, base_b = self.config.frame_base_a, self.config.frame_base_b
        topic_a, topic_b = self.config.settings.topic_a, self.config.settings.topic_b[0]
        buffers = self.store.buffers
        frame_a, frame_b = buffers[topic_a].frame_id, buffers[topic_b].frame_id
        problem = None
        if base_a != base_b and (frame_a == base_b or frame_b == base_a):
            got = ', '.join(f'{t} in {f!r}' for t, f in ((topic_a, frame_a), (topic_b, frame_b))
                            if f is not None)
            problem = (f"the messages arrive in the other device's base frame ({got}; "
                       f'configured: frame_base_a {base_a!r} for {topic_a}, frame_base_b '
                       f'{base_b!r} for {topic_b}): the devices look swapped; exchange topic_a '
                       f'and topic_b (a calibration would give the inverse transforms)')
            self.alerts.throttled(('frames',), problem, period=SETUP_WARN_PERIOD)
        return problem

    def check_types(self) -> dict:
        """Find publishers of another message type on the pose topics (warned, throttled)."""
        problems = {}
        for topic in self.store.topics:
            try:
                infos = self.publishers_info(topic)
            except Exception:  # the graph is not available (shutting down)
                continue
            wrong = sorted({i.topic_type for i in infos} - {POSE_TYPE})
            if wrong:
                problems[topic] = (f'{topic} is published as {", ".join(wrong)}, but coreg_node '
                                   f'expects {POSE_TYPE}: those messages never arrive; publish '
                                   f'PoseStamped (convert it) or point the topic parameter at '
                                   f'a PoseStamped topic')
                self.alerts.throttled(('type', topic), problems[topic],
                                      period=SETUP_WARN_PERIOD)
        return problems

    def diagnostics(self) -> DiagnosticStatus:
        """Return the diagnostic status: counts by topic and reason, pairing, last result."""
        self._update_pairing()
        store = self.store
        values = []
        problems = 0
        types = self.check_types()
        for topic, b in store.buffers.items():
            rejected = sum(b.rejected.values())
            missing = store.gaps[topic].missing
            undecodable = store.undecodable(topic)
            lost, counted = store.loss(topic)
            problems += rejected + b.dropped + lost + missing + undecodable
            values += [KeyValue(key=f'{topic} received', value=str(b.received)),
                       KeyValue(key=f'{topic} accepted', value=str(b.accepted)),
                       KeyValue(key=f'{topic} rejected', value=str(rejected))]
            values += [KeyValue(key=f'{topic} rejected {r}', value=str(b.rejected[r]))
                       for r in REASONS]
            period = store.gaps[topic].period_ns
            values += [KeyValue(key=f'{topic} held', value=str(len(b))),
                       KeyValue(key=f'{topic} buffer fill',
                                value=f'{len(b) / b.capacity:.3f}'),
                       KeyValue(key=f'{topic} dropped oldest', value=str(b.dropped)),
                       KeyValue(key=f'{topic} lost', value=str(lost)),
                       KeyValue(key=f'{topic} lost counted from', value=counted),
                       KeyValue(key=f'{topic} lost in middleware',
                                value=str(store.lost[topic])),
                       KeyValue(key=f'{topic} missing from stamps', value=str(missing)),
                       KeyValue(key=f'{topic} undecodable', value=str(undecodable)),
                       KeyValue(key=f'{topic} stamp rate',
                                value='n/a' if not period else f'{1e9 / period:.4g} Hz'),
                       KeyValue(key=f'{topic} frame_id', value=str(b.frame_id)),
                       KeyValue(key=f'{topic} type problem', value=types.get(topic, 'none'))]
        pairing = self.pairing
        values += [KeyValue(key='paired', value=str(pairing['n_paired'])),
                   KeyValue(key='pairing rate',
                            value='n/a' if pairing['rate'] is None else f'{pairing["rate"]:.3f}'),
                   KeyValue(key='pairing', value=pairing['summary'])]
        last = self.calibrator.summary or {}
        for key in ('n_pairs', 'chi2_dof', 'p_value', 'success', 'fit_consistent',
                    'time_offset_s', 'time_offset_sigma_s', 'rejected_pairs', 'seconds',
                    'verdict'):
            v = last.get(key)
            values.append(KeyValue(key=f'last calibration {key}',
                                   value='n/a' if v is None else
                                   (f'{v:.6g}' if isinstance(v, float) else str(v))))
        frames = self.check_frames()
        journal = store.journal
        alerts = self.alerts
        values += [KeyValue(key='frames', value=frames or 'as configured'),
                   KeyValue(key='storage', value=alerts.storage_error or 'ok'),
                   KeyValue(key='journal', value='none' if journal is None else
                            f'{journal.folder} ({journal.n_chunks} bags)'),
                   KeyValue(key='interrupted sessions',
                            value=', '.join(map(str, store.left_over)) or 'none'),
                   KeyValue(key='internal error', value=alerts.internal_error or 'none')]
        status = DiagnosticStatus(name=f'{self.node_name}: coregistration',
                                  hardware_id=' + '.join(store.topics), values=values)
        if alerts.storage_error or alerts.internal_error:
            status.level = DiagnosticStatus.ERROR
            status.message = alerts.storage_error or alerts.internal_error
        elif types or frames:
            status.level = DiagnosticStatus.WARN
            status.message = next(iter(types.values())) if types else frames
        elif problems > self._prev_problems or time.monotonic() < self._warn_until:
            if problems > self._prev_problems:  # held a while, so a 1 Hz reader sees it
                self._warn_until = time.monotonic() + WARN_HOLD
            status.level = DiagnosticStatus.WARN
            status.message = ('rejecting, dropping or losing samples (see the counts: lost, '
                              'missing from stamps, rejected, dropped oldest)')
        else:
            status.level = DiagnosticStatus.OK
            status.message = (f'{min(len(b) for b in store.buffers.values())} samples held'
                              if not last else f'last calibration: {last.get("n_pairs")} pairs')
        self._prev_problems = problems
        return status
