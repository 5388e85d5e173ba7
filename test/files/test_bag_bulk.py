"""
The bulk PoseStamped path (cdr_pose, bulk_read, bulk_write) against rosbags' per-message path.

Real rosbag2 files of both storages, written either by rosbags' own Writer (message by
message, in shuffled log-time order, with ties, big-endian messages and changing frames) or
by write_pose_bag; every read is done twice, ``bulk=True`` and ``bulk=False``, and the two
results must be identical: stamps exactly, floats bit for bit, or the same BagError.
"""

import re
import shutil
import sqlite3

from coreg_ros.core.errors import BagError
from coreg_ros.core.types import PoseStream
from coreg_ros.files.bag import bulk_read, POSE_STAMPED, read_pose_bag, write_pose_bag
from coreg_ros.files.bag.bulk_read import fetch
from coreg_ros.files.bag.cdr_pose import (
    decode_blocks,
    decode_pose_stamped,
    decode_records,
    encode_pose_stamped,
    encode_records,
)
from coreg_ros.files.bag.posebag import read_fast
import numpy as np
import pytest
from rosbags.interfaces import (
    Qos,
    QosDurability,
    QosHistory,
    QosLiveliness,
    QosReliability,
    QosTime,
)
from rosbags.rosbag2 import CompressionFormat, CompressionMode, Reader, StoragePlugin, Writer
from rosbags.typesys import get_typestore, Stores

STORAGES = {'sqlite3': StoragePlugin.SQLITE3, 'mcap': StoragePlugin.MCAP}
SUFFIX = {'sqlite3': '.db3', 'mcap': '.mcap'}
TYPESTORE = get_typestore(Stores.ROS2_JAZZY)
T = TYPESTORE.types
FRAMES = ['', 'w', 'map', 'world', 'odom_12', 'base_link', 'a' * 13, 'cámara_ø', 'x' * 40]


def random_values(rng, n):
    """Stamps (int64 ns, any in [0, 2**31 s)), positions, quaternions with NaN and extremes."""
    stamps = rng.integers(0, 2**31 * 10**9, n)
    pos = rng.normal(size=(n, 3)) * 10.0 ** rng.integers(-300, 300, (n, 1))
    quat = rng.normal(size=(n, 4))
    if n:
        pos[rng.integers(0, n, 1 + n // 50), rng.integers(0, 3)] = np.nan
        quat[rng.integers(0, n), 0] = -0.0
        pos[rng.integers(0, n), 1] = np.inf
    return stamps, pos, quat


def message(stamp, frame, p, q):
    sec, nsec = divmod(int(stamp), 10**9)
    return T[POSE_STAMPED](
        header=T['std_msgs/msg/Header'](
            stamp=T['builtin_interfaces/msg/Time'](sec=sec, nanosec=nsec), frame_id=frame),
        pose=T['geometry_msgs/msg/Pose'](
            position=T['geometry_msgs/msg/Point'](x=p[0], y=p[1], z=p[2]),
            orientation=T['geometry_msgs/msg/Quaternion'](x=q[1], y=q[2], z=q[3], w=q[0])))


def bits(a):
    """Return a float array's bits, so that NaN == NaN and -0.0 != 0.0."""
    return np.ascontiguousarray(a, dtype=np.float64).view(np.int64)


def assert_identical(got, ref):
    assert list(got) == list(ref)
    for topic in ref:
        a, b = got[topic], ref[topic]
        assert a.frame_id == b.frame_id, topic
        for name in ('stamps', 'receive_stamps'):
            x, y = getattr(a, name), getattr(b, name)
            assert x.dtype == y.dtype == np.int64 and x.shape == y.shape, (topic, name)
            assert np.array_equal(x, y), (topic, name)
        for name in ('position', 'quat_wxyz'):
            x, y = getattr(a, name), getattr(b, name)
            assert x.dtype == y.dtype == np.float64 and x.shape == y.shape, (topic, name)
            assert np.array_equal(bits(x), bits(y)), (topic, name)


def outcome(path, topics, bulk):
    """Return the streams, or the BagError text, of read_pose_bag."""
    try:
        return read_pose_bag(path, topics, bulk=bulk)
    except BagError as err:
        return f'BagError: {err}'


def assert_same_outcome(path, topics):
    ref = outcome(path, topics, bulk=False)
    got = outcome(path, topics, bulk=True)
    if isinstance(ref, str) or isinstance(got, str):
        assert got == ref
    else:
        assert_identical(got, ref)
    return ref


# --- the codec ----------------------------------------------------------------------------

@pytest.mark.parametrize('frame', FRAMES)
def test_codec_is_byte_identical_to_rosbags(frame):
    rng = np.random.default_rng(len(frame))
    stamps, pos, quat = random_values(rng, 40)
    blobs = encode_pose_stamped(stamps, frame, pos, quat)
    for i, blob in enumerate(blobs):
        ref = TYPESTORE.serialize_cdr(message(stamps[i], frame, pos[i], quat[i]), POSE_STAMPED)
        assert blob == bytes(ref)
    arrays = decode_pose_stamped(blobs)
    assert arrays.frame_id == frame and len(arrays) == 40
    assert np.array_equal(arrays.stamps_ns, stamps)
    assert np.array_equal(bits(arrays.position), bits(pos))
    assert np.array_equal(bits(arrays.quat_wxyz), bits(quat))


def test_decoder_declines_what_is_not_one_layout():
    rng = np.random.default_rng(7)
    stamps, pos, quat = random_values(rng, 6)
    good = encode_pose_stamped(stamps, 'world', pos, quat)
    assert decode_pose_stamped(good) is not None
    assert decode_pose_stamped([]) is None
    same_size_other_frame = encode_pose_stamped(stamps[:1], 'wörld', pos[:1], quat[:1])
    assert len(same_size_other_frame[0]) == len(good[0])
    assert decode_pose_stamped(good + same_size_other_frame) is None
    assert decode_pose_stamped(good + encode_pose_stamped(stamps[:1], 'map', pos[:1],
                                                          quat[:1])) is None
    big = bytes(TYPESTORE.serialize_cdr(message(stamps[0], 'world', pos[0], quat[0]),
                                        POSE_STAMPED, little_endian=False))
    assert len(big) == len(good[0])
    assert decode_pose_stamped([big]) is None and decode_pose_stamped(good + [big]) is None

    def damaged(at, value):
        blob = bytearray(good[3])
        blob[at] = value
        return good[:3] + [bytes(blob)] + good[4:]

    assert decode_pose_stamped(damaged(1, 2)) is None      # encapsulation kind
    assert decode_pose_stamped(damaged(12, 7)) is None     # frame_id length field
    assert decode_pose_stamped(damaged(16 + 5, 65)) is None  # NUL terminator
    assert decode_pose_stamped(damaged(17, 0x80)) is None  # frame bytes
    assert decode_pose_stamped([good[0][:-1]]) is None     # short
    assert decode_pose_stamped([good[0] + b'\0' * 8]) is None  # long
    invalid_utf8 = bytearray(good[0])
    invalid_utf8[16] = 0xFF
    assert decode_pose_stamped([bytes(invalid_utf8)]) is None


# --- random bags of both storages ---------------------------------------------------------

def write_random_bag(path, storage, rng, *, n_max=1500, mixed=False, compression=None):
    """
    Write a bag message by message with rosbags' Writer, log times shuffled with ties.

    Returns the topic names. With ``mixed`` one topic has messages of two frames and another
    has some big-endian messages (the bulk decoder declines both).
    """
    n_topics = int(rng.integers(1, 4))
    topics = [f'/dev{k}/pose' for k in range(n_topics)]
    plan = []
    for k in range(n_topics):
        n = int(rng.integers(0, n_max)) if k else int(rng.integers(1, n_max))
        frame = FRAMES[int(rng.integers(len(FRAMES)))]
        stamps, pos, quat = random_values(rng, n)
        frames = [frame] * n
        little = [True] * n
        if mixed and k == 0 and n > 2:
            frames[n // 2] = frame + 'z'  # same topic, other frame: per-message path refuses
        if mixed and k == 1 and n > 2:
            little[int(rng.integers(n))] = False
        # Log times: coarse (many ties), not in sample order.
        logs = 10**18 + rng.integers(0, max(n // 3, 1), n) * 1000
        plan += [(k, int(logs[i]), message(stamps[i], frames[i], pos[i], quat[i]), little[i])
                 for i in range(n)]
    order = rng.permutation(len(plan))
    writer = Writer(path, version=9, storage_plugin=STORAGES[storage])
    if compression is not None:
        writer.set_compression(compression, CompressionFormat.ZSTD)
    with writer:
        conns = [writer.add_connection(t, POSE_STAMPED, typestore=TYPESTORE) for t in topics]
        for j in order.tolist():
            k, log_ns, msg, little_endian = plan[j]
            writer.write(conns[k], log_ns, TYPESTORE.serialize_cdr(
                msg, POSE_STAMPED, little_endian=little_endian))
    return topics


@pytest.mark.parametrize('storage', STORAGES)
@pytest.mark.parametrize('seed', range(6))
def test_random_bags_bulk_equals_per_message(tmp_path, storage, seed):
    rng = np.random.default_rng(1000 + seed)
    topics = write_random_bag(tmp_path / 'bag', storage, rng)
    ref = assert_same_outcome(tmp_path / 'bag', topics)
    assert not isinstance(ref, str), ref
    assert sum(len(s) for s in ref.values()) > 0
    assert bulk_path_used(tmp_path / 'bag', topics)
    assert fast_path_used(tmp_path / 'bag', topics)


def bulk_path_used(path, topics):
    """Whether the bulk fetch reads every topic of the bag (no fallback to rosbags)."""
    with Reader(path) as reader:
        got = fetch(reader, [c for c in reader.connections if c.topic in topics])
    return got is not None and all(block is not None for _, block in got.values())


def fast_path_used(path, topics):
    """Whether read_pose_bag's fast try (light open + bulk) answers without plain rosbags."""
    return read_fast(path, list(topics)) is not None


@pytest.mark.parametrize(('storage', 'mode', 'bulk'), [
    ('mcap', CompressionMode.STORAGE, True),   # zstd chunks, what ros2 bag record can write
    ('mcap', CompressionMode.FILE, True),
    ('sqlite3', CompressionMode.FILE, True),
    ('mcap', CompressionMode.MESSAGE, False),  # per-message zstd: rosbags path
    ('sqlite3', CompressionMode.MESSAGE, False),
])
def test_compressed_bags(tmp_path, storage, mode, bulk):
    rng = np.random.default_rng(int(mode))
    topics = write_random_bag(tmp_path / 'bag', storage, rng, n_max=20_000, compression=mode)
    ref = assert_same_outcome(tmp_path / 'bag', topics)
    assert not isinstance(ref, str), ref
    assert bulk_path_used(tmp_path / 'bag', topics) == bulk
    assert fast_path_used(tmp_path / 'bag', topics) == bulk


@pytest.mark.parametrize('cores', [1, 2])
@pytest.mark.parametrize('mode', [None, CompressionMode.STORAGE])
def test_mcap_chunks_read_one_by_one_or_two_at_a_time(tmp_path, monkeypatch, cores, mode):
    """Several chunks, plain (bulk_write's) or zstd (rosbags'): rosbags' arrays both ways."""
    path = tmp_path / 'bag'
    if mode is None:
        write_pose_bag(path, streams_for(np.random.default_rng(8), 12_000), storage='mcap')
        topics = ['/t0', '/t1', '/t2']
    else:
        topics = write_random_bag(path, 'mcap', np.random.default_rng(9), n_max=20_000,
                                  compression=mode)
    monkeypatch.setattr(bulk_read, '_cores', lambda: cores)
    handles = []
    two_at_a_time = bulk_read._two_at_a_time

    def recorded(work, items, hands):
        handles.append((len(items), len(hands)))
        return two_at_a_time(work, items, hands)

    monkeypatch.setattr(bulk_read, '_two_at_a_time', recorded)
    ref = assert_same_outcome(path, topics)
    assert not isinstance(ref, str), ref
    assert fast_path_used(path, topics)
    assert handles and all(n > 1 for n, _ in handles)  # several chunks in every file
    assert {h for _, h in handles} == {cores}  # a second file handle on two cores only


@pytest.mark.parametrize('cores', [1, 2])
@pytest.mark.parametrize('storage', STORAGES)
def test_a_topic_of_two_connections_is_read_whole(tmp_path, monkeypatch, storage, cores):
    """One topic recorded on two connections (two QoS): every message of both, in order."""
    t0 = QosTime(0, 0)
    best_effort = Qos(QosHistory.KEEP_LAST, 1, QosReliability.BEST_EFFORT,
                      QosDurability.VOLATILE, t0, t0, QosLiveliness.AUTOMATIC, t0, False)
    rng = np.random.default_rng(41)
    stamps, pos, quat = random_values(rng, 400)
    path = tmp_path / 'bag'
    with Writer(path, version=9, storage_plugin=STORAGES[storage]) as writer:
        conns = [writer.add_connection('/t', POSE_STAMPED, typestore=TYPESTORE),
                 writer.add_connection('/t', POSE_STAMPED, typestore=TYPESTORE,
                                       offered_qos_profiles=[best_effort])]
        for i in range(400):
            writer.write(conns[int(rng.integers(2))], 10**18 + int(rng.integers(0, 300)) * 1000,
                         TYPESTORE.serialize_cdr(message(stamps[i], 'w', pos[i], quat[i]),
                                                 POSE_STAMPED))
    monkeypatch.setattr(bulk_read, '_cores', lambda: cores)
    ref = assert_same_outcome(path, ['/t'])
    assert not isinstance(ref, str), ref
    assert len(ref['/t']) == 400
    assert fast_path_used(path, ['/t'])


@pytest.mark.parametrize('storage', STORAGES)
@pytest.mark.parametrize('seed', range(3))
def test_fallback_topics_give_the_same_result(tmp_path, storage, seed):
    rng = np.random.default_rng(2000 + seed)
    topics = write_random_bag(tmp_path / 'bag', storage, rng, mixed=True)
    ref = assert_same_outcome(tmp_path / 'bag', topics)
    if len(topics) > 1:
        # Big-endian messages in /dev1/pose are read (per message) when /dev0 is left out.
        assert_same_outcome(tmp_path / 'bag', topics[1:])
    if not isinstance(ref, str):
        return
    assert 'frame_id changes' in ref


@pytest.mark.parametrize('storage', STORAGES)
def test_many_chunks_and_storage_files(tmp_path, storage):
    """Several MCAP chunks (1 MiB each) and a bag split over two storage files."""
    rng = np.random.default_rng(5)
    path = tmp_path / 'big'
    write_random_bag(path, storage, rng, n_max=30_000)
    topics = assert_same_outcome(path, ['/dev0/pose'])
    assert len(topics['/dev0/pose']) > 12_000 or storage == 'sqlite3'
    assert bulk_path_used(path, ['/dev0/pose'])
    # Split bag: the same storage file twice under two names, as rosbag2 --max-bag-size does.
    split = tmp_path / 'split'
    split.mkdir()
    name = f'big{SUFFIX[storage]}'
    for part in ('split_0', 'split_1'):
        shutil.copy(path / name, split / f'{part}{SUFFIX[storage]}')
    meta = (path / 'metadata.yaml').read_text().replace(name, f'split_0{SUFFIX[storage]}')
    meta = meta.replace(f'relative_file_paths:\n  - split_0{SUFFIX[storage]}',
                        f'relative_file_paths:\n  - split_0{SUFFIX[storage]}\n'
                        f'  - split_1{SUFFIX[storage]}')
    (split / 'metadata.yaml').write_text(meta)
    with Reader(split) as reader:
        assert len(reader.storage.storages) == 2
    both = assert_same_outcome(split, ['/dev0/pose'])
    assert bulk_path_used(split, ['/dev0/pose'])
    assert fast_path_used(split, ['/dev0/pose'])
    assert len(both['/dev0/pose']) == 2 * len(topics['/dev0/pose'])


# --- sqlite3: the light open and the paged fetch ------------------------------------------

def sqlite_pages(path):
    """Return the log-time pages bulk_read splits the bag's (first) storage file into."""
    with Reader(path) as reader:
        db = reader.storage.storages[0].dbconn
        (total,), = db.execute('SELECT count(*) FROM messages').fetchall()
        return bulk_read._sqlite_pages(db, total)


def fetch_on_cores(monkeypatch, cores):
    """Have bulk_read see ``cores`` cores; return the list of second readers it opens."""
    opened = []
    second_reader = bulk_read._second_reader

    def recorded(storage):
        other = second_reader(storage)
        opened.append(other)
        return other

    monkeypatch.setattr(bulk_read, '_cores', lambda: cores)
    monkeypatch.setattr(bulk_read, '_second_reader', recorded)
    return opened


@pytest.mark.parametrize('cores', [1, 2])
@pytest.mark.parametrize('page', [1, 7, 100])
@pytest.mark.parametrize('seed', range(3))
def test_sqlite_pages_of_any_size_give_the_same_arrays(tmp_path, monkeypatch, page, seed,
                                                       cores):
    """
    Pages of a few rows, with runs of equal log times longer than a page.

    Fetched one by one (one core) or two at a time on two connections: rosbags' arrays.
    """
    rng = np.random.default_rng(3000 + seed)
    topics = write_random_bag(tmp_path / 'bag', 'sqlite3', rng, n_max=300)
    monkeypatch.setattr(bulk_read, '_SQLITE_PAGE', page)
    opened = fetch_on_cores(monkeypatch, cores)
    assert len(sqlite_pages(tmp_path / 'bag')) > 1
    ref = assert_same_outcome(tmp_path / 'bag', topics)
    assert not isinstance(ref, str), ref
    assert fast_path_used(tmp_path / 'bag', topics)
    # two cores: the light open's reader opened a second time, one core: never asked
    assert (opened and all(r is not None for r in opened)) if cores == 2 else not opened


def test_sqlite_pages_cover_every_row_once(tmp_path, monkeypatch):
    rng = np.random.default_rng(12)
    write_random_bag(tmp_path / 'bag', 'sqlite3', rng, n_max=500)
    monkeypatch.setattr(bulk_read, '_SQLITE_PAGE', 10)
    pages = sqlite_pages(tmp_path / 'bag')
    with sqlite3.connect(tmp_path / 'bag' / 'bag.db3') as db:
        logs = np.array([t for t, in db.execute('SELECT timestamp FROM messages')])
    inside = [(logs >= (lo if lo is not None else -2**63))
              & (logs < (hi if hi is not None else 2**63 - 1)) for lo, hi in pages]
    assert np.array_equal(np.sum(inside, axis=0), np.ones(logs.size))
    assert len(pages) >= logs.size // 10 // 4  # ties make pages longer, not fewer than this


def test_metadata_counts_that_disagree_with_the_storage(tmp_path):
    """The light open takes nothing from the per-topic counts: same arrays as rosbags."""
    rng = np.random.default_rng(21)
    path = tmp_path / 'bag'
    topics = write_random_bag(path, 'sqlite3', rng)
    meta = path / 'metadata.yaml'
    text, n = re.subn(r'message_count: \d+', 'message_count: 3', meta.read_text())
    assert n >= 2
    meta.write_text(text)
    ref = assert_same_outcome(path, topics)
    assert not isinstance(ref, str), ref
    assert fast_path_used(path, topics)


def test_dropped_timestamp_index_reads_through_rosbags(tmp_path):
    """Without the index rosbags sorts, and ties may come otherwise: plain rosbags reads it."""
    rng = np.random.default_rng(22)
    path = tmp_path / 'bag'
    topics = write_random_bag(path, 'sqlite3', rng)
    with sqlite3.connect(path / 'bag.db3') as db:
        db.execute('DROP INDEX timestamp_idx')
    ref = assert_same_outcome(path, topics)
    assert not isinstance(ref, str), ref
    assert not fast_path_used(path, topics)


@pytest.mark.parametrize('page,cores', [(None, 2), (200, 1), (200, 2)])
def test_damaged_timestamp_index_gives_the_same_outcome(tmp_path, monkeypatch, page, cores):
    """
    Byte flips in the index pages: the same arrays or the same BagError both ways.

    In pages of 200 rows too: walked by ranges, a damaged index may leave rows out without
    the error rosbags' full walk gives (``_sqlite_page``'s count of the rows reached); those
    pages fetched one by one or two at a time.
    """
    if page is not None:
        monkeypatch.setattr(bulk_read, '_SQLITE_PAGE', page)
    fetch_on_cores(monkeypatch, cores)
    path = tmp_path / 'bag'
    write_pose_bag(path, streams_for(np.random.default_rng(6), 3000), storage='sqlite3')
    data = path / 'bag.db3'
    with sqlite3.connect(data) as db:
        (page_size,), = db.execute('PRAGMA page_size')
        pages = [p for p, in db.execute(
            "SELECT pageno FROM dbstat WHERE name = 'timestamp_idx' ORDER BY pageno")]
    del db
    assert len(pages) > 3
    pristine = data.read_bytes()
    ref = read_pose_bag(path, ['/t0', '/t1', '/t2'], bulk=False)
    rng = np.random.default_rng(10)
    changed = 0
    for pageno in rng.choice(pages, 4, replace=False).tolist():
        start = (pageno - 1) * page_size
        for where in [start, start + 3, start + 8, *(start + rng.integers(
                page_size // 2, page_size, 5))]:
            damaged = bytearray(pristine)
            damaged[where] ^= 0x5A
            data.write_bytes(bytes(damaged))
            got = assert_same_outcome(path, ['/t0', '/t1', '/t2'])
            try:
                assert not isinstance(got, str)
                assert_identical(got, ref)
            except AssertionError:
                changed += 1  # the damage is seen (an error, or other order or log times)
    assert changed > 0


def test_a_message_stored_as_text_is_left_to_rosbags(tmp_path):
    path = tmp_path / 'bag'
    write_pose_bag(path, streams_for(np.random.default_rng(8), 500), storage='sqlite3')
    with sqlite3.connect(path / 'bag.db3') as db:
        db.execute("UPDATE messages SET data = 'not a blob' WHERE id = 7")
    assert not fast_path_used(path, ['/t0', '/t1', '/t2'])
    assert isinstance(assert_same_outcome(path, ['/t0', '/t1', '/t2']), str)


# --- writing ------------------------------------------------------------------------------

def streams_for(rng, n):
    out = {}
    for k, frame in enumerate(['world', 'map', 'cámara']):
        stamps, pos, quat = random_values(rng, n + k)
        receive = 10**18 + np.sort(rng.integers(0, n, n + k)) * 1000  # ties across topics
        out[f'/t{k}'] = PoseStream(stamps=stamps, position=pos, quat_wxyz=quat,
                                   frame_id=frame, receive_stamps=receive)
    out['/empty'] = PoseStream(stamps=np.zeros(0, np.int64), position=np.zeros((0, 3)),
                               quat_wxyz=np.zeros((0, 4)), frame_id='none')
    return out


def plain_rosbags(path):
    """Everything plain rosbags sees in a bag: messages, counts, times, metadata."""
    with Reader(path) as reader:
        msgs = [(c.topic, c.id, t, bytes(d)) for c, t, d in reader.messages()]
        conns = [(c.id, c.topic, c.msgtype, c.msgcount) for c in reader.connections]
        return msgs, conns, reader.message_count, reader.start_time, reader.end_time


@pytest.mark.parametrize('storage', STORAGES)
def test_bulk_written_bags_read_back_identically_by_plain_rosbags(tmp_path, storage):
    rng = np.random.default_rng(11)
    streams = streams_for(rng, 9000)  # > 1 MiB: several MCAP chunks
    write_pose_bag(tmp_path / 'bulk', streams, storage=storage, bulk=True)
    write_pose_bag(tmp_path / 'ref', streams, storage=storage, bulk=False)
    got, ref = plain_rosbags(tmp_path / 'bulk'), plain_rosbags(tmp_path / 'ref')
    assert got == ref
    assert len(got[0]) == sum(len(s) for s in streams.values())
    meta = [(tmp_path / b / 'metadata.yaml').read_text().replace(b, '') for b in ('bulk', 'ref')]
    assert meta[0] == meta[1]
    back = read_pose_bag(tmp_path / 'bulk', list(streams), bulk=True)
    assert bulk_path_used(tmp_path / 'bulk', list(streams))
    assert_identical(back, read_pose_bag(tmp_path / 'ref', list(streams), bulk=False))
    for topic, stream in streams.items():
        order = np.argsort(stream.receive_stamps if stream.receive_stamps is not None
                           else stream.stamps, kind='stable')
        assert np.array_equal(back[topic].stamps, stream.stamps[order])
        assert np.array_equal(bits(back[topic].position), bits(stream.position[order]))


# --- damaged files --------------------------------------------------------------------------

@pytest.mark.parametrize('storage', STORAGES)
@pytest.mark.parametrize('fraction', [0.3, 0.5, 0.8, 0.97, 0.999])
def test_truncated_files_give_the_same_error(tmp_path, storage, fraction):
    path = tmp_path / 'cut'
    write_pose_bag(path, streams_for(np.random.default_rng(3), 3000), storage=storage)
    data = path / f'cut{SUFFIX[storage]}'
    with data.open('r+b') as f:
        f.truncate(int(data.stat().st_size * fraction))
    ref = assert_same_outcome(path, ['/t0', '/t1'])
    assert isinstance(ref, str) and 'truncated or corrupt' in ref


@pytest.mark.parametrize('storage', STORAGES)
def test_corrupt_bytes_never_give_other_numbers(tmp_path, storage):
    """Byte flips in message headers, lengths, frames and elsewhere: same result both ways."""
    path = tmp_path / 'bag'
    write_pose_bag(path, streams_for(np.random.default_rng(4), 800), storage=storage)
    data = path / f'bag{SUFFIX[storage]}'
    pristine = data.read_bytes()
    rng = np.random.default_rng(9)
    hits = [i for i in range(len(pristine)) if pristine.startswith(b'world\0', i)]
    places = []
    for i in rng.choice(hits, 12, replace=False).tolist():
        places += [i - 16, i - 15, i - 4, i - 1, i + 2, i + 5]  # encapsulation, length, frame
    places += rng.integers(0, len(pristine), 20).tolist()
    errors = 0
    for where in places:
        damaged = bytearray(pristine)
        damaged[where] ^= 0x5A
        data.write_bytes(bytes(damaged))
        errors += isinstance(assert_same_outcome(path, ['/t0', '/t1', '/t2']), str)
    assert errors > 0


@pytest.mark.parametrize('seed', [0, 1, 2])
def test_blocks_decode_as_their_join(seed):
    """decode_blocks of consecutive blocks: decode_records of the joined blocks, bit for bit."""
    rng = np.random.default_rng(seed)
    n = int(rng.integers(1, 500))
    q = rng.normal(size=(n, 4))
    stamps = np.sort(rng.integers(0, 2**31 * 10**9, n))
    records = encode_records(stamps, 'world', rng.normal(size=(n, 3)),
                             q / np.linalg.norm(q, axis=1, keepdims=True))
    rows = np.frombuffer(records, np.uint8).reshape(n, -1)
    cuts = np.sort(rng.integers(0, n + 1, int(rng.integers(0, 6))))
    blocks = np.split(rows, cuts)
    got, whole = decode_blocks(blocks), decode_records(rows.copy(), n)
    assert got.frame_id == whole.frame_id
    for name in ('stamps_ns', 'position', 'quat_wxyz'):
        a, b = getattr(got, name), getattr(whole, name)
        assert a.dtype == b.dtype and a.flags.c_contiguous
        np.testing.assert_array_equal(a.view(np.int64), b.view(np.int64))
    # another frame in a later block: not one stream of fixed layout
    other = np.frombuffer(encode_records(np.arange(3), 'wOrld', np.zeros((3, 3)),
                                         np.tile([1.0, 0, 0, 0], (3, 1))), np.uint8)
    assert decode_blocks([rows, other.reshape(3, -1)]) is None
    assert decode_blocks([rows[:0]]) is None
