"""Tests of coreg_ros.files.bag: real rosbag2 recordings written and read back in tmp_path."""


from coreg_ros.core.calibration.pairing import pair_streams
from coreg_ros.core.errors import BagError, InputError
from coreg_ros.core.types import PoseStream
from coreg_ros.files.bag import list_topics, POSE_STAMPED, read_pose_bag, write_pose_bag
import numpy as np
import pytest
from rosbags.rosbag2 import Reader, StoragePlugin, Writer
from rosbags.typesys import get_typestore, Stores

STORAGES = ['sqlite3', 'mcap']
STORAGE_FILE = {'sqlite3': '.db3', 'mcap': '.mcap'}
T0 = 1_700_000_000 * 10**9 + 987_654_321
TYPESTORE = get_typestore(Stores.ROS2_JAZZY)


def make_stream(n, seed, *, frame='base', period_ns=10_000_000, start=T0, receive=None):
    rng = np.random.default_rng(seed)
    # Odd nanoseconds on purpose: a float-seconds round trip would lose them.
    stamps = start + np.arange(n, dtype=np.int64) * period_ns + rng.integers(0, 1000, n)
    q = rng.normal(size=(n, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    return PoseStream(stamps=stamps, position=rng.normal(size=(n, 3)), quat_wxyz=q,
                      frame_id=frame, receive_stamps=receive)


def raw_messages(path):
    """(topic, log time, message) in bag order, read with rosbags directly."""
    with Reader(path) as reader:
        return [(c.topic, t, TYPESTORE.deserialize_cdr(raw, c.msgtype))
                for c, t, raw in reader.messages()]


def write_foreign_bag(path, topic, msgtype, msg, storage=StoragePlugin.SQLITE3):
    """Write a bag with one message of another type with rosbags' own Writer."""
    with Writer(path, version=9, storage_plugin=storage) as writer:
        conn = writer.add_connection(topic, msgtype, typestore=TYPESTORE)
        writer.write(conn, T0, TYPESTORE.serialize_cdr(msg, msgtype))


@pytest.mark.parametrize('storage', STORAGES)
def test_round_trip_is_exact(tmp_path, storage):
    a = make_stream(50, 1, frame='robot_base')
    receive = T0 + 3_000_000 + np.arange(40, dtype=np.int64) * 12_500_001
    b = make_stream(40, 2, frame='tracker', period_ns=12_500_000, receive=receive)
    path = tmp_path / 'rec'
    write_pose_bag(path, {'/a/pose': a, '/b/pose': b}, storage=storage)
    assert (path / 'metadata.yaml').is_file()
    assert (path / f'rec{STORAGE_FILE[storage]}').is_file()
    assert list_topics(path) == {'/a/pose': POSE_STAMPED, '/b/pose': POSE_STAMPED}

    got = read_pose_bag(path, ['/a/pose', '/b/pose'])
    for name, ref in (('/a/pose', a), ('/b/pose', b)):
        s = got[name]
        assert s.stamps.dtype == np.int64 and s.receive_stamps.dtype == np.int64
        np.testing.assert_array_equal(s.stamps, ref.stamps)
        np.testing.assert_array_equal(s.position, ref.position)
        np.testing.assert_array_equal(s.quat_wxyz, ref.quat_wxyz)
        assert s.frame_id == ref.frame_id
    # Log time: the receive stamps when given, else the header stamp.
    np.testing.assert_array_equal(got['/b/pose'].receive_stamps, receive)
    np.testing.assert_array_equal(got['/a/pose'].receive_stamps, a.stamps)


@pytest.mark.parametrize('storage', STORAGES)
def test_quaternion_order_in_the_messages(tmp_path, storage):
    # Non-symmetric quaternion: every component different, so any permutation shows.
    q_wxyz = np.array([0.7, 0.1, -0.3, 0.5])
    q_wxyz /= np.linalg.norm(q_wxyz)
    s = PoseStream(np.array([T0], dtype=np.int64), np.array([[1.0, 2.0, 3.0]]), q_wxyz[None],
                   'base')
    write_pose_bag(tmp_path / 'q', {'/p': s}, storage=storage)
    [(topic, log_ns, msg)] = raw_messages(tmp_path / 'q')
    o = msg.pose.orientation
    assert (o.x, o.y, o.z, o.w) == tuple(q_wxyz[[1, 2, 3, 0]])  # ROS order is (x, y, z, w)
    assert (msg.header.stamp.sec, msg.header.stamp.nanosec) == divmod(T0, 10**9)
    assert msg.header.frame_id == 'base' and log_ns == T0 and topic == '/p'
    np.testing.assert_array_equal(read_pose_bag(tmp_path / 'q', ['/p'])['/p'].quat_wxyz[0],
                                  q_wxyz)


@pytest.mark.parametrize('storage', STORAGES)
def test_reads_a_bag_written_by_rosbags_directly(tmp_path, storage):
    pose_cls = TYPESTORE.types[POSE_STAMPED]
    header = TYPESTORE.types['std_msgs/msg/Header']
    time_cls = TYPESTORE.types['builtin_interfaces/msg/Time']
    pose = TYPESTORE.types['geometry_msgs/msg/Pose']
    point = TYPESTORE.types['geometry_msgs/msg/Point']
    quat_cls = TYPESTORE.types['geometry_msgs/msg/Quaternion']
    msg = pose_cls(header=header(stamp=time_cls(sec=12, nanosec=345), frame_id='w'),
                   pose=pose(position=point(x=1.0, y=2.0, z=3.0),
                             orientation=quat_cls(x=0.1, y=0.2, z=0.3, w=0.9)))
    plugin = {'sqlite3': StoragePlugin.SQLITE3, 'mcap': StoragePlugin.MCAP}[storage]
    write_foreign_bag(tmp_path / 'ext', '/pose', POSE_STAMPED, msg, plugin)
    s = read_pose_bag(tmp_path / 'ext', ['/pose'])['/pose']
    np.testing.assert_array_equal(s.stamps, [12 * 10**9 + 345])
    np.testing.assert_array_equal(s.receive_stamps, [T0])
    np.testing.assert_array_equal(s.quat_wxyz, [[0.9, 0.1, 0.2, 0.3]])
    np.testing.assert_array_equal(s.position, [[1.0, 2.0, 3.0]])


def test_topics_are_interleaved_by_log_time(tmp_path):
    a = make_stream(30, 3, period_ns=7_000_000)
    b = make_stream(20, 4, period_ns=11_000_000)
    write_pose_bag(tmp_path / 'mix', {'/a': a, '/b': b})
    msgs = raw_messages(tmp_path / 'mix')
    logs = [t for _, t, _ in msgs]
    assert logs == sorted(logs)
    topics = [topic for topic, _, _ in msgs]
    assert topics.count('/a') == 30 and topics.count('/b') == 20
    assert topics[:30] != ['/a'] * 30  # really interleaved, not one topic after the other


def test_values_are_not_validated_here_but_in_the_core(tmp_path):
    a = make_stream(20, 5)
    pos = a.position.copy()
    pos[7] = np.nan
    bad = PoseStream(a.stamps, pos, a.quat_wxyz, 'base')
    write_pose_bag(tmp_path / 'nan', {'/a': bad, '/b': make_stream(20, 6)})
    got = read_pose_bag(tmp_path / 'nan', ['/a', '/b'])
    assert np.isnan(got['/a'].position[7]).all()
    with pytest.raises(InputError, match='index 7'):
        pair_streams(got['/a'], got['/b'], max_gap_ns=20_000_000)


def test_refuses_to_overwrite(tmp_path):
    path = tmp_path / 'exists'
    write_pose_bag(path, {'/a': make_stream(5, 1)})
    before = sorted(p.name for p in path.iterdir())
    with pytest.raises(BagError, match=r'exists.*not be overwritten.*new bag name') as info:
        write_pose_bag(path, {'/a': make_stream(9, 2)})
    assert str(path) in str(info.value)
    assert sorted(p.name for p in path.iterdir()) == before
    assert len(read_pose_bag(path, ['/a'])['/a']) == 5


def test_failed_write_leaves_nothing_behind(tmp_path):
    # A frame_id that cannot be encoded fails in the middle of serialisation.
    s = make_stream(10, 1, frame='base\udcff')
    with pytest.raises(BagError, match='cannot write bag') as info:
        write_pose_bag(tmp_path / 'half', {'/a': make_stream(10, 2), '/b': s})
    assert isinstance(info.value.__cause__, UnicodeEncodeError)
    assert list(tmp_path.iterdir()) == []  # neither the bag nor the staging directory


def test_write_refuses_bad_input(tmp_path):
    with pytest.raises(BagError, match="unknown storage 'rosbag1'"):
        write_pose_bag(tmp_path / 'x', {'/a': make_stream(3, 1)}, storage='rosbag1')
    s = make_stream(3, 1)
    with pytest.raises(InputError, match='integer nanoseconds'):
        write_pose_bag(tmp_path / 'x', {'/a': PoseStream(s.stamps / 1e9, s.position,
                                                         s.quat_wxyz)})
    with pytest.raises(InputError, match=r'shape \(3, 3\)'):
        write_pose_bag(tmp_path / 'x', {'/a': PoseStream(s.stamps, s.position[:2],
                                                         s.quat_wxyz)})
    with pytest.raises(BagError, match='does not exist; create it first'):
        write_pose_bag(tmp_path / 'no' / 'x', {'/a': s})
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize('msgtype, fields', [
    ('std_msgs/msg/String', {'data': 'hello'}),
    ('geometry_msgs/msg/PoseWithCovarianceStamped', None),
])
def test_wrong_message_type(tmp_path, msgtype, fields):
    cls = TYPESTORE.types[msgtype]
    if fields is None:
        t = TYPESTORE.types
        msg = cls(header=t['std_msgs/msg/Header'](
            stamp=t['builtin_interfaces/msg/Time'](sec=1, nanosec=0), frame_id='w'),
            pose=t['geometry_msgs/msg/PoseWithCovariance'](
                pose=t['geometry_msgs/msg/Pose'](
                    position=t['geometry_msgs/msg/Point'](x=0.0, y=0.0, z=0.0),
                    orientation=t['geometry_msgs/msg/Quaternion'](x=0.0, y=0.0, z=0.0, w=1.0)),
                covariance=np.zeros(36)))
    else:
        msg = cls(**fields)
    write_foreign_bag(tmp_path / 'wrong', '/pose', msgtype, msg)
    with pytest.raises(BagError) as info:
        read_pose_bag(tmp_path / 'wrong', ['/pose'])
    text = str(info.value)
    assert f'has type {msgtype}' in text and f'but {POSE_STAMPED} is needed' in text
    assert '\n' not in text


@pytest.mark.parametrize('storage', STORAGES)
def test_missing_topic_lists_what_is_there(tmp_path, storage):
    write_pose_bag(tmp_path / 'b', {'/a/pose': make_stream(3, 1), '/b/pose': make_stream(3, 2)},
                   storage=storage)
    with pytest.raises(BagError, match=r'topic\(s\) /c/pose not in bag') as info:
        read_pose_bag(tmp_path / 'b', ['/a/pose', '/c/pose'])
    assert f'/a/pose ({POSE_STAMPED}), /b/pose ({POSE_STAMPED})' in str(info.value)


@pytest.mark.parametrize('storage', STORAGES)
@pytest.mark.parametrize('fraction', [0.5, 0.97])
def test_truncated_storage_file(tmp_path, storage, fraction):
    path = tmp_path / 'cut'
    write_pose_bag(path, {'/a': make_stream(3000, 1)}, storage=storage)
    data = path / f'cut{STORAGE_FILE[storage]}'
    with data.open('r+b') as f:
        f.truncate(int(data.stat().st_size * fraction))
    with pytest.raises(BagError, match='truncated or corrupt') as info:
        read_pose_bag(path, ['/a'])
    assert info.value.__cause__ is not None
    assert 'coreg fix-bag' in str(info.value) and '--salvage' in str(info.value)
    assert '\n' not in str(info.value)


def test_missing_or_bad_metadata(tmp_path):
    path = tmp_path / 'meta'
    write_pose_bag(path, {'/a': make_stream(3, 1)})
    (path / 'metadata.yaml').write_text('rosbag2_bagfile_information: [unclosed\n')
    with pytest.raises(BagError, match='metadata.yaml .*unreadable.*coreg fix-bag .*--salvage'):
        read_pose_bag(path, ['/a'])
    (path / 'metadata.yaml').write_text('something: else\n')
    with pytest.raises(BagError, match='metadata.yaml .*unreadable'):
        list_topics(path)
    (path / 'metadata.yaml').unlink()
    with pytest.raises(BagError, match='has no metadata.yaml.*coreg fix-bag .*--salvage'):
        read_pose_bag(path, ['/a'])


def test_not_a_bag_directory(tmp_path):
    with pytest.raises(BagError, match='does not exist'):
        read_pose_bag(tmp_path / 'nope', ['/a'])
    with pytest.raises(BagError, match='has no metadata.yaml'):
        list_topics(tmp_path)
    write_pose_bag(tmp_path / 'bag', {'/a': make_stream(3, 1)}, storage='mcap')
    with pytest.raises(BagError, match=r'is a file, not a rosbag2 directory; pass its dir'):
        read_pose_bag(tmp_path / 'bag' / 'bag.mcap', ['/a'])


def test_changing_frame_id_is_refused(tmp_path):
    write_pose_bag(tmp_path / 'f', {'/a': make_stream(5, 1, frame='one'),
                                    '/b': make_stream(5, 2, frame='two')})
    # Rewrite both streams onto one topic with rosbags directly.
    msgs = raw_messages(tmp_path / 'f')
    with Writer(tmp_path / 'g', version=9) as writer:
        conn = writer.add_connection('/a', POSE_STAMPED, typestore=TYPESTORE)
        for _, log_ns, msg in msgs:
            writer.write(conn, log_ns, TYPESTORE.serialize_cdr(msg, POSE_STAMPED))
    with pytest.raises(BagError, match=r"frame_id changes from 'one' to 'two' at message 1"):
        read_pose_bag(tmp_path / 'g', ['/a'])


@pytest.mark.parametrize('storage', STORAGES)
def test_hundred_thousand_messages_round_trip(tmp_path, storage):
    # Speed goals belong in bench/, not in unit tests.
    n = 50_000
    streams = {'/a': make_stream(n, 1), '/b': make_stream(n, 2, start=T0 + 4_000_000)}
    write_pose_bag(tmp_path / 'big', streams, storage=storage)
    got = read_pose_bag(tmp_path / 'big', ['/a', '/b'])
    np.testing.assert_array_equal(got['/b'].stamps, streams['/b'].stamps)


@pytest.mark.parametrize('storage', ['sqlite3', 'mcap'])
@pytest.mark.parametrize('damage', ['no_metadata', 'truncated'])
def test_salvage_recovers_what_a_damaged_bag_holds(tmp_path, storage, damage):
    from coreg_ros.files.bag.fixbag import fix_bag

    # large enough for several mcap chunks (1 MiB each) and sqlite3 pages
    a, b = make_stream(20000, 1), make_stream(10000, 2)
    path = tmp_path / 'cut'
    write_pose_bag(path, {'/a': a, '/b': b}, storage=storage)
    data = next(p for p in path.iterdir() if p.suffix in ('.mcap', '.db3'))
    if damage == 'no_metadata':
        (path / 'metadata.yaml').unlink()
    else:
        with open(data, 'r+b') as f:
            f.truncate(int(data.stat().st_size * 0.6))
    with pytest.raises(BagError):
        read_pose_bag(path, ['/a', '/b'])
    report = fix_bag(path, tmp_path / 'saved', salvage=True)
    got = read_pose_bag(tmp_path / 'saved', ['/a', '/b'])
    for topic, sent in (('/a', a), ('/b', b)):
        n = len(got[topic])
        if damage == 'no_metadata':
            assert n == len(sent)
        else:
            assert n > 0, report.salvage_stopped  # what was written before the cut
        # exactly the first samples sent, intact
        np.testing.assert_array_equal(got[topic].stamps, sent.stamps[:n])
        np.testing.assert_allclose(got[topic].position, sent.position[:n])
