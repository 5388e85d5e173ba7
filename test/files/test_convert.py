"""Tests of ``coreg convert`` (CSV exports to rosbag2) and of read_pose_csv."""

from pathlib import Path

from coreg_ros.cli.main import main
from coreg_ros.core import quaternion as quat
from coreg_ros.core.errors import ConfigError, InputError
from coreg_ros.files.bag.posebag import read_pose_bag
from coreg_ros.files.csv_poses import read_pose_csv
from coreg_ros.sim import simulate_recording
import numpy as np
import pytest
from strategies import write_csv

A = '/device_a/pose'
B = '/device_b/pose'
REAL = Path('/work/shared/data/real/eth_hand_eye')


@pytest.fixture(scope='module')
def rec():
    return simulate_recording(8, 4.0)


def assert_same(s, ref, atol=1e-12):
    assert np.array_equal(s.stamps, ref.stamps)
    assert np.allclose(s.position, ref.position, rtol=0, atol=atol)
    assert np.allclose(quat.canonical(s.quat_wxyz), quat.canonical(ref.quat_wxyz), atol=1e-12)


def test_round_trip_through_csv_and_bag(tmp_path, rec, capsys):
    a = write_csv(tmp_path / 'a.csv', rec.stream_a)
    b = write_csv(tmp_path / 'b.csv', rec.streams_b[0])
    assert main(['convert', a, b, str(tmp_path / 'bag')]) == 0
    out = capsys.readouterr().out
    assert '400 samples' in out and '200 samples' in out and 'overlap' in out
    streams = read_pose_bag(tmp_path / 'bag', [A, B])
    assert_same(streams[A], rec.stream_a)
    assert_same(streams[B], rec.streams_b[0])
    assert streams[A].frame_id == 'device_a_base'


def test_wxyz_mm_whitespace_header_mcap_and_topics(tmp_path, rec):
    a = write_csv(tmp_path / 'a.csv', rec.stream_a, order='wxyz', scale=1000.0,
                  header='t x y z qw qx qy qz', sep='  ')
    b = write_csv(tmp_path / 'b.csv', rec.streams_b[0], order='wxyz', scale=1000.0,
                  sep=' ,\t')
    assert main(['convert', a, b, str(tmp_path / 'bag'), '--quaternion-order', 'wxyz',
                 '--units', 'mm', '--storage', 'mcap', '--topic-a', '/robot',
                 '--topic-b', '/cam']) == 0
    streams = read_pose_bag(tmp_path / 'bag', ['/robot', '/cam'])
    assert_same(streams['/robot'], rec.stream_a, atol=1e-12)
    assert_same(streams['/cam'], rec.streams_b[0], atol=1e-12)
    assert (tmp_path / 'bag' / 'metadata.yaml').read_text().count('mcap') >= 1


def test_invert_flags_undo_an_inverted_export(tmp_path, rec):
    a = write_csv(tmp_path / 'a.csv', rec.stream_a, invert=True)
    b = write_csv(tmp_path / 'b.csv', rec.streams_b[0], invert=True)
    assert main(['convert', a, b, str(tmp_path / 'bag'), '--invert-a', '--invert-b']) == 0
    streams = read_pose_bag(tmp_path / 'bag', [A, B])
    assert_same(streams[A], rec.stream_a, atol=1e-12)
    assert_same(streams[B], rec.streams_b[0], atol=1e-12)


def test_time_is_converted_to_ns_exactly(tmp_path):
    path = tmp_path / 'a.csv'
    path.write_text('1491754479.5537522, 0, 0, 0, 0, 0, 0, 1\n'
                    '86.552999999999997 0 0 0 0 0 0 1\n'
                    '1491754479.999999999, 0, 0, 0, 0, 0, 0, 1\n'
                    '1.5e9, 0, 0, 0, 0, 0, 0, 1\n')
    s = read_pose_csv(path, sort=True).stream
    assert s.stamps.dtype == np.int64
    assert s.stamps.tolist() == [86_553_000_000, 1_491_754_479_553_752_200,
                                 1_491_754_479_999_999_999, 1_500_000_000_000_000_000]


def test_quaternions_are_normalised_and_position_only_files(tmp_path):
    path = tmp_path / 'a.csv'
    path.write_text('0.0, 1, 2, 3, 0, 0, 0, -1.004\n0.1, 1, 2, 3, 0.001, 0, 0, 1\n')
    s = read_pose_csv(path).stream
    assert np.allclose(np.linalg.norm(s.quat_wxyz, axis=1), 1.0)
    assert np.all(s.quat_wxyz[:, 0] >= 0)
    four = tmp_path / 'p.csv'
    four.write_text('# a comment\n0.0, 1, 2, 3\n\n0.1, 1, 2, 4  # trailing comment\n')
    csv = read_pose_csv(four, units='mm')
    assert not csv.has_orientation
    assert np.allclose(csv.stream.position[1], [0.001, 0.002, 0.004])
    assert np.array_equal(csv.stream.quat_wxyz, np.tile([1.0, 0, 0, 0], (2, 1)))
    with pytest.raises(ConfigError, match='cannot be inverted'):
        read_pose_csv(four, invert=True)


def test_sort_drops_repeats_and_reorders(tmp_path):
    path = tmp_path / 'a.csv'
    path.write_text('0.00, 0, 0, 0, 0, 0, 0, 1\n0.02, 2, 0, 0, 0, 0, 0, 1\n'
                    '0.02, 2, 0, 0, 0, 0, 0, 1\n0.01, 1, 0, 0, 0, 0, 0, 1\n')
    with pytest.raises(InputError, match='line 3: time 0.020000000 s repeats.*--sort'):
        read_pose_csv(path)
    csv = read_pose_csv(path, sort=True)
    assert csv.stream.stamps.tolist() == [0, 10_000_000, 20_000_000]
    assert csv.stream.position[:, 0].tolist() == [0.0, 1.0, 2.0]
    assert csv.n_dropped == 1 and csv.n_reordered > 0


@pytest.mark.parametrize('content, needle', [
    ('0.0, 1, 2, 3, 0, 0, 0, 1\n0.1, 1, 2, 3, 0, 0, 1\n', 'line 2: 7 columns'),
    ('0.0, 1, 2, 3, 0, 0\n', 'line 1: 6 columns; expected 8'),
    ('0.0, 1, 2, 3, 0, 0, 0, 1\n0.1, 1, nan, 3, 0, 0, 0, 1\n', 'line 2: NaN'),
    ('0.0, 1, 2, 3, 0, 0, 0, 1\n0.1, 1, abc, 3, 0, 0, 0, 1\n', "line 2: 'abc' is not a number"),
    ('t,x,y,z,qx,qy,qz,qw\n0.0, 1, 2, 3, 0, 0, 0, 2\n', 'line 2: quaternion norm 2'),
    ('0.0, 1, 2, 3, 0, 0, 0, 1\n0.0, 1, 2, 3, 0, 0, 0, 1\n', 'repeats'),
    ('0.1, 1, 2, 3, 0, 0, 0, 1\n0.0, 1, 2, 3, 0, 0, 0, 1\n', 'goes back'),
    ('0.0, 1, 2, 3, 0, 0, 0, 1\n0.1,, 2, 3, 0, 0, 0, 1\n', 'line 2: empty field'),
    ('x,y\n', 'no samples'),
    ('', 'no samples'),
])
def test_bad_csv_gives_one_line_errors(tmp_path, content, needle):
    path = tmp_path / 'bad.csv'
    path.write_text(content)
    with pytest.raises(InputError) as info:
        read_pose_csv(path, name='CSV_A')
    message = str(info.value)
    assert needle in message and '\n' not in message and 'CSV_A' in message
    if 'norm' in needle:
        assert '--quaternion-order' in message


def test_cli_errors_are_one_line(tmp_path, rec, capsys):
    b = write_csv(tmp_path / 'b.csv', rec.streams_b[0])
    code = main(['convert', str(tmp_path / 'missing.csv'), b, str(tmp_path / 'bag')])
    err = capsys.readouterr().err
    assert code == 1 and 'no such file' in err and err.count('\n') == 1
    assert not (tmp_path / 'bag').exists()
    # an existing output is refused by the bag writer
    (tmp_path / 'bag').mkdir()
    code = main(['convert', b, b, str(tmp_path / 'bag')])
    assert code == 1 and capsys.readouterr().err.count('\n') == 1


def test_device_a_without_orientation_is_refused(tmp_path, rec, capsys):
    """A is the tool whose orientation every model needs: a t, x, y, z export is refused."""
    b = write_csv(tmp_path / 'b.csv', rec.streams_b[0])
    a = tmp_path / 'a.csv'
    s = rec.streams[rec.topics_a]
    a.write_text(''.join(f'{t * 1e-9:.9f}, {x}, {y}, {z}\n'
                         for t, (x, y, z) in zip(s.stamps, s.position, strict=True)))
    code = main(['convert', str(a), b, str(tmp_path / 'bag')])
    err = capsys.readouterr().err
    assert code == 1 and 'has no orientation columns' in err and err.count('\n') == 1
    assert not (tmp_path / 'bag').exists()
    # as B (a position-only tracker) the same file is taken
    assert main(['convert', b, str(a), str(tmp_path / 'bag2')]) == 0


@pytest.mark.skipif(not REAL.is_dir(), reason='shared real data folder absent')
def test_real_eth_robot_arm_camera(tmp_path, capsys):
    folder = REAL / 'robot_arm_camera_real'
    a = next(folder.glob('*sr300_hinge.csv'))
    b = next(folder.glob('*target_ir.csv'))
    assert main(['convert', str(a), str(b), str(tmp_path / 'bag')]) == 0
    streams = read_pose_bag(tmp_path / 'bag', [A, B])
    assert len(streams[A]) == 2817 and len(streams[B]) == 1703
    assert streams[A].stamps[0] == 1_487_321_563_680_000_000
    assert streams[B].stamps[0] == 1_487_321_563_180_327_900
    first = a.read_text().splitlines()[0].split(',')
    x, y, z, qx, qy, qz, qw = (float(v) for v in first[1:])
    assert np.allclose(streams[A].position[0], [x, y, z])
    assert np.allclose(quat.canonical(streams[A].quat_wxyz[0]),
                       quat.canonical(np.array([qw, qx, qy, qz])))


def test_several_b_exports_make_a_rig_bag(tmp_path, capsys):
    # a rig (issue 23): A and two devices B, one topic per file; the second B on its own clock
    from coreg_ros.sim.rig import SimDevice, simulate_rig
    rig = simulate_rig(3, 4.0, (SimDevice('b1', 'full_pose', 30.0, (5e-4, 2e-3), 0.0),
                                SimDevice('b2', 'full_pose', 40.0, (5e-4, 2e-3), 600.0)))
    a = write_csv(tmp_path / 'a.csv', rig.stream_a)
    b1, b2 = (write_csv(tmp_path / f'b{k}.csv', s[0]) for k, s in enumerate(rig.streams))
    assert main(['convert', a, b1, b2, str(tmp_path / 'bag')]) == 0
    captured = capsys.readouterr()
    topics = ['/device_b1/pose', '/device_b2/pose']
    assert all(t in captured.out for t in topics)
    assert ('/device_b2/pose and A do not overlap in time' in captured.err
            and '/device_b1/pose' not in captured.err)
    streams = read_pose_bag(tmp_path / 'bag', [A, *topics])
    assert_same(streams[A], rig.stream_a)
    for t, s in zip(topics, rig.streams, strict=True):
        assert_same(streams[t], s[0])
    for argv, words in ((['--topic-b', '/cam'], '1 topic(s) for 2 B export(s)'),
                        (['--topic-b', '/cam', '/cam'], 'names /cam twice'),
                        (['--topic-b', '/cam', A], 'both /device_a/pose')):
        assert main(['convert', a, b1, b2, str(tmp_path / 'bag2'), *argv]) == 1
        err = capsys.readouterr().err
        assert words in err and err.count('\n') == 1, err
    assert not (tmp_path / 'bag2').exists()
