"""
The node's collaborators on their own, in the test's process.

``SampleStore`` with rclpy's logger and real messages into its callbacks, its journal and bags
on disk; ``Calibrator`` with the publishers, clock and parameters of a real rclpy node (a
``RosSession``'s), its results heard on real subscriptions. No node process, no mock of ROS.
"""

import threading

from coreg_ros.core.calibration.pipeline import calibrate_streams
from coreg_ros.core.settings import Settings
from coreg_ros.files.bag.posebag import read_pose_bag
from coreg_ros.ros import persistence
from coreg_ros.ros.alerts import Alerts
from coreg_ros.ros.calibrator import Calibrator
from coreg_ros.ros.interface import LATCHED_QOS
from coreg_ros.ros.messages import make_pose_stamped, msg_to_uncertain_pose, stamp_to_ns
from coreg_ros.ros.parameters import declare_parameters, NodeConfig, ParameterView
from coreg_ros.ros.sample_store import SampleStore
from coreg_ros.ros.tools import wait_for_result
from coreg_ros.sim import simulate_recording
from geometry_msgs.msg import PoseWithCovarianceStamped
import numpy as np
import rclpy
import yaml

A, B = '/device_a/pose', '/device_b/pose'


def _config(tmp_path, **more) -> NodeConfig:
    return NodeConfig(settings=Settings(), buffer_capacity=100_000, qos_reliable=True,
                      frame_base_a='device_a_base', frame_base_b='device_b_base',
                      frame_tool='device_a_tool', frame_marker='device_b_marker',
                      storage_dir=str(tmp_path / 'store'), **more)


def _store(config, logger, name='coreg_node') -> SampleStore:
    key = persistence.config_key(config.settings.as_dict(), config.frames)
    return SampleStore(config, name, key, Alerts(logger, config.storage_dir), logger,
                       threading.Lock(), raw=False)


def _assert_same(streams, rec):
    for topic in (A, B):
        np.testing.assert_array_equal(streams[topic].stamps, rec.streams[topic].stamps)
        np.testing.assert_array_equal(streams[topic].position, rec.streams[topic].position)
        np.testing.assert_array_equal(streams[topic].quat_wxyz, rec.streams[topic].quat_wxyz)


def _info(k: int) -> dict:
    """Return the message info rclpy gives a two-argument callback for a publisher's k-th."""
    return {'publication_sequence_number': k + 1, 'source_timestamp': 0}


def test_sample_store_journals_what_it_takes_and_a_new_one_resumes_it(tmp_path):
    log = rclpy.logging.get_logger('coreg_test_store')
    first = _store(_config(tmp_path), log)
    first.start_journal()
    rec = simulate_recording(2, 2.0)
    for topic, s in rec.streams.items():  # as the subscriptions deliver them, flushed 4 times
        take = first.callback(topic)
        for k in range(len(s)):
            take(make_pose_stamped(int(s.stamps[k]), s.frame_id, s.position[k], s.quat_wxyz[k]),
                 _info(k))
            if k % (len(s) // 4) == 0:
                first.flush_journal()
    s = rec.streams[A]
    again = make_pose_stamped(int(s.stamps[-1]), s.frame_id, s.position[-1], s.quat_wxyz[-1])
    first.callback(A)(again, _info(len(s)))  # sent twice: refused, counted
    assert first.buffers[A].rejected['duplicate_stamp'] == 1
    first.flush_journal()
    journal = first.journal.folder
    assert first.journal.n_chunks > 4
    _assert_same(persistence.read_journal(journal, [A, B]), rec)

    # The session is killed here (no save): a store of the same node and configuration
    # reports the journal; one with resume_samples continues from it.
    plain = _store(_config(tmp_path), log)
    plain.start_journal()
    assert plain.left_over == [journal] and not len(plain.buffers[A])
    plain.journal.remove()
    second = _store(_config(tmp_path, resume_samples=True), log)
    second.start_journal()
    assert second.left_over == [] and not journal.exists()
    _assert_same(second.snapshot(), rec)
    assert second.save_on_shutdown()
    (bag,) = (tmp_path / 'store').glob('samples_*')
    _assert_same(read_pose_bag(bag, [A, B]), rec)
    assert not second.journal.folder.exists()  # a clean end: the samples are in the bag

    # ~/reset forgets the samples and their journal and starts a new one
    assert second.forget() == len(rec.streams[A]) + len(rec.streams[B])
    assert not len(second.buffers[A]) and second.journal.folder.is_dir()
    assert second.on_save_samples(None, _Answer()).message == 'no samples to save yet'


class _Answer:
    """A Trigger response's two fields."""

    success = None
    message = None


class _Listener:
    """What a calibrator told its listener (as it tells the outputs and the live checks)."""

    def __init__(self):
        self.results, self.stored = [], []

    def set_result(self, result):
        self.results.append(result)

    def set_stored(self, doc, base_to_base, tool_to_marker):
        self.stored.append((doc, base_to_base, tool_to_marker))


def test_calibrator_publishes_tells_stores_and_republishes(ros_session, tmp_path):
    node = ros_session.node  # a real rclpy node: its publishers, clock and parameters
    declare_parameters(node)
    config = _config(tmp_path)
    store = _store(config, node.get_logger(), name=node.get_name())
    rec = simulate_recording(3, 3.0)
    for topic, s in rec.streams.items():
        store.buffers[topic].push_many(s.stamps, s.stamps, s.position, s.quat_wxyz, s.frame_id)
    pubs = [node.create_publisher(PoseWithCovarianceStamped, f'~/{n}', LATCHED_QOS)
            for n in ('base_to_base', 'tool_to_marker')]

    def calibrator():
        made = Calibrator(config, store.config_key, node.get_name(),
                          node.get_fully_qualified_name(), ParameterView(node), store, *pubs,
                          node.get_clock(), node.get_logger(),
                          Alerts(node.get_logger(), config.storage_dir), threading.Lock(),
                          wake=lambda: None)
        heard = _Listener()
        made.add_listener(heard)
        return made, heard

    first, heard = calibrator()
    ok, message = first.calibrate_and_publish()
    assert ok, message
    streams = store.snapshot()
    offline, _ = calibrate_streams(streams[A], [streams[B]], Settings(),
                                   frames=('device_a_base', 'device_b_base'))
    (result,) = heard.results
    np.testing.assert_array_equal(result.base_to_base.position, offline.base_to_base.position)
    assert first.summary['n_pairs'] == offline.n_pairs and f'{offline.n_pairs} pairs' in message
    assert first.timing.value_s == offline.time_offset.value_s
    msg = wait_for_result(ros_session, f'/{node.get_name()}/base_to_base', timeout=5)
    assert msg.header.frame_id == 'device_b_base'
    np.testing.assert_array_equal(msg_to_uncertain_pose(msg).position,
                                  offline.base_to_base.position)
    (path,) = (tmp_path / 'store').glob(f'result_{node.get_name()}_*.yaml')
    doc = yaml.safe_load(path.read_text())
    assert doc['stamp_ns'] == stamp_to_ns(msg.header.stamp) and doc['config_key'] == \
        store.config_key

    # Another calibrator of this node and configuration (a restart) republishes it, stamped
    # with its calibration time, and tells its listener.
    again, told = calibrator()
    again.republish_stored()
    (stored, base, _), = told.stored
    assert stored['stamp_ns'] == doc['stamp_ns'] and again.summary['n_pairs'] == offline.n_pairs
    np.testing.assert_allclose(base.position, offline.base_to_base.position, rtol=1e-12)
    assert again.timing.value_s == offline.time_offset.value_s
    republished = wait_for_result(ros_session, f'/{node.get_name()}/base_to_base', timeout=5)
    assert stamp_to_ns(republished.header.stamp) == doc['stamp_ns']
