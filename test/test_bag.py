"""MCAP bags: what rosbag2 records, exact round trips, clear errors, nothing lost on SIGKILL."""
from __future__ import annotations

import errno
import os
import re
import signal
import subprocess
import sys
import threading
import warnings
from pathlib import Path

import numpy as np
import pytest
from mcap.reader import make_reader
from mcap.stream_reader import StreamReader
from mcap_ros2._dynamic import serialize_dynamic
from mcap_ros2.decoder import DecoderFactory

from kpi_calib_ros.core.acquisition.pairing import pair_measurements
from kpi_calib_ros.core.acquisition.streams import JointSample, PointSample, synthesize_streams
from kpi_calib_ros.io.bag import BagError, BagWarning, read_bag, read_for_pairing, write_bag
from kpi_calib_ros.io.bag_writing import JOINT_STATE_TYPE, joint_state_cdr, message_definition
from kpi_calib_ros.io.measurement_log import MeasurementLog
from kpi_calib_ros.io.ros_messages import joint_state_fields

NAMES = ('joint_1', 'joint_2', 'joint_3', 'joint_4', 'joint_5', 'joint_6')
FRAME = 'tracker'
MAGIC = b'\x89MCAP0\r\n'


def make_streams(n_poses: int = 3, seed: int = 11):
    rng = np.random.default_rng(seed)
    q = rng.uniform(-2.0, 2.0, (n_poses, len(NAMES)))
    eta = rng.uniform(-1.5, 1.5, (n_poses, 3))
    joints, points = synthesize_streams(q, NAMES, eta, FRAME, joint_noise_rad=1e-5, rng=rng)
    # What real drivers also send: extra joints, no velocities, odd stamps.
    joints.append(JointSample(joints[-1].stamp_ns + 7, ('gripper',) + NAMES,
                              rng.normal(size=7), None))
    return q, eta, joints, points


def assert_same_joints(actual, expected):
    assert len(actual) == len(expected)
    for a, e in zip(actual, expected):
        assert a.stamp_ns == e.stamp_ns and a.names == e.names
        np.testing.assert_array_equal(a.positions, e.positions)
        if e.velocities is None:
            assert a.velocities is None
        else:
            np.testing.assert_array_equal(a.velocities, e.velocities)


def assert_same_points(actual, expected):
    assert [(p.stamp_ns, p.frame_id) for p in actual] == [(p.stamp_ns, p.frame_id)
                                                          for p in expected]
    np.testing.assert_array_equal([p.xyz for p in actual], [p.xyz for p in expected])


def test_round_trip_is_exact(tmp_path):
    _, _, joints, points = make_streams()
    path = write_bag(tmp_path / 'cell.mcap', joints, points)
    read_joints, read_points = read_bag(path)
    assert_same_joints(read_joints, joints)
    assert_same_points(read_points, points)


def test_pairing_a_bag_equals_pairing_the_streams(tmp_path):
    q, _, joints, points = make_streams()
    path = write_bag(tmp_path / 'cell.mcap', joints, points, joint_topic='/robot/joint_states',
                     point_topic='/tracker/point')
    from_bag = pair_measurements(*read_bag(path, '/robot/joint_states', '/tracker/point'),
                                 NAMES, FRAME)
    direct = pair_measurements(joints, points, NAMES, FRAME)
    assert from_bag.rejections == {} and len(from_bag) == len(q)
    np.testing.assert_array_equal(from_bag.q, direct.q)
    np.testing.assert_array_equal(from_bag.stamps_ns, direct.stamps_ns)


def share_file(relative: str) -> str:
    prefixes = os.environ.get('AMENT_PREFIX_PATH', '').split(os.pathsep) + [sys.prefix]
    for prefix in filter(None, prefixes):
        path = Path(prefix) / 'share' / relative
        if path.is_file():
            return path.read_text()
    raise FileNotFoundError(relative)


def section(type_name: str) -> str:
    return '\n' + '=' * 80 + f'\nMSG: {type_name}\n'


def test_bag_is_what_ros2_bag_record_writes(tmp_path):
    from geometry_msgs.msg import PointStamped
    from rclpy.serialization import deserialize_message
    from sensor_msgs.msg import JointState

    _, _, joints, points = make_streams()
    path = write_bag(tmp_path / 'cell.mcap', joints, points)
    header = share_file('std_msgs/msg/Header.msg')
    time = share_file('builtin_interfaces/msg/Time.msg')
    # rosbag2's complete definitions: own text, then dependencies depth-first, sorted.
    expected_schemas = {
        'sensor_msgs/msg/JointState': share_file('sensor_msgs/msg/JointState.msg')
        + section('std_msgs/Header') + header + section('builtin_interfaces/Time') + time,
        'geometry_msgs/msg/PointStamped': share_file('geometry_msgs/msg/PointStamped.msg')
        + section('geometry_msgs/Point') + share_file('geometry_msgs/msg/Point.msg')
        + section('std_msgs/Header') + header + section('builtin_interfaces/Time') + time,
    }
    with open(path, 'rb') as f:
        reader = make_reader(f)
        assert reader.get_header().profile == 'ros2'
        summary = reader.get_summary()
        assert {s.name: (s.encoding, s.data.decode()) for s in summary.schemas.values()} == {
            name: ('ros2msg', text) for name, text in expected_schemas.items()}
        assert all(c.compression == '' for c in summary.chunk_indexes)
        channels = {c.topic: c for c in summary.channels.values()}
        assert set(channels) == {'/joint_states', '/laser_tracker/point'}
        for channel in channels.values():
            assert channel.message_encoding == 'cdr'
            assert channel.metadata['topic_type_hash'].startswith('RIHS01_')
            assert '- history: keep_last' in channel.metadata['offered_qos_profiles']
        ros_joints, ros_points = [], []
        for _, channel, message in reader.iter_messages(log_time_order=False):
            assert message.log_time == message.publish_time
            # The real ROS 2 type support reads our bytes.
            if channel.topic == '/joint_states':
                ros_joints.append((message.log_time, deserialize_message(message.data,
                                                                         JointState)))
            else:
                ros_points.append((message.log_time, deserialize_message(message.data,
                                                                         PointStamped)))
    for (log_time, msg), sample in zip(ros_joints, joints, strict=True):
        assert log_time == sample.stamp_ns == msg.header.stamp.sec * 10 ** 9 \
            + msg.header.stamp.nanosec
        assert tuple(msg.name) == sample.names
        np.testing.assert_array_equal(msg.position, sample.positions)
    for (log_time, msg), sample in zip(ros_points, points, strict=True):
        assert log_time == sample.stamp_ns and msg.header.frame_id == FRAME
        np.testing.assert_array_equal([msg.point.x, msg.point.y, msg.point.z], sample.xyz)
    # And so does mcap_ros2's own reader, from the schema text alone.
    with open(path, 'rb') as f:
        decoded = [m.decoded_message for m in make_reader(
            f, decoder_factories=[DecoderFactory()]).iter_decoded_messages('/laser_tracker/point')]
    np.testing.assert_array_equal([[m.point.x, m.point.y, m.point.z] for m in decoded],
                                  [p.xyz for p in points])


@pytest.mark.parametrize('seed', range(3))
def test_joint_states_are_encoded_as_the_dynamic_cdr_encoder_encodes_them(seed):
    """The hand-written JointState encoder against mcap_ros2's, byte for byte: names of
    every length (each alignment), UTF-8, no joints, no velocities, negative stamps, NaN."""
    encode = serialize_dynamic(JOINT_STATE_TYPE, message_definition(JOINT_STATE_TYPE))[
        JOINT_STATE_TYPE]
    rng = np.random.default_rng(seed)
    for _ in range(200):
        n = int(rng.integers(0, 9))
        names = tuple('j' * int(rng.integers(0, 9)) + ('é' if rng.random() < 0.2 else '')
                      + str(i) for i in range(n))
        positions = rng.normal(size=n)
        if n and rng.random() < 0.2:
            positions[0] = np.nan
        velocities = rng.normal(size=n) if rng.random() < 0.5 else None
        stamp = int(rng.integers(-2 ** 62, 2 ** 62)) // 4
        sample = JointSample(stamp, names, positions, velocities)
        assert joint_state_cdr(sample) == encode(joint_state_fields(sample))


def test_errors_name_the_file_topic_and_fix(tmp_path):
    _, _, joints, points = make_streams(n_poses=1)
    path = write_bag(tmp_path / 'cell.mcap', joints, points)

    with pytest.raises(BagError, match=r'missing\.mcap: no such file'):
        read_bag(tmp_path / 'missing.mcap')
    (tmp_path / 'notes.mcap').write_text('joint_1: 0.1\n')
    with pytest.raises(BagError, match=r'notes\.mcap is not an MCAP file.*ros2 bag'):
        read_bag(tmp_path / 'notes.mcap')
    with pytest.raises(BagError, match=r"is a directory.*\['cell\.mcap', 'notes\.mcap'\]"):
        read_bag(tmp_path)
    with pytest.raises(BagError) as error:
        read_bag(path, joint_topic='/robot/joint_states')
    message = str(error.value)
    assert str(path) in message and "'/robot/joint_states' is not in the bag" in message
    assert "'/joint_states' (sensor_msgs/msg/JointState)" in message and 'joint_topic=' in message
    with pytest.raises(BagError) as error:
        read_bag(path, joint_topic='/laser_tracker/point', point_topic='/joint_states')
    message = str(error.value)
    assert "topic '/joint_states' carries 'sensor_msgs/msg/JointState', expected " \
        "'geometry_msgs/msg/PointStamped'" in message and 'point_topic=' in message
    assert isinstance(error.value, ValueError)


def read_warned(read, path):
    """``read(path)`` and the messages of the warnings it gave, each a BagWarning."""
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter('always')
        result = read(path)
    assert all(issubclass(w.category, BagWarning) for w in caught), caught
    return result, [str(w.message) for w in caught]


def unreadable_tail(messages: list[str], path: Path, size: int) -> int:
    """Bytes a single warning about ``path`` (``size`` bytes) says are unreadable."""
    assert len(messages) == 1, messages
    match = re.fullmatch(rf'{re.escape(str(path))}: (\d+) of {size} bytes unreadable .*',
                         messages[0])
    assert match, messages
    return int(match.group(1))


@pytest.mark.slow
def test_unfinalised_bag_yields_every_complete_message(tmp_path):
    """A bag cut anywhere yields the beginning of the recording; a cut at a chunk end
    reads silently, any other cut warns once and names exactly the torn tail: the file
    without those bytes reads the same, silently."""
    _, _, joints, points = make_streams()
    path = write_bag(tmp_path / 'cell.mcap', joints, points, chunk_size=4096)
    data = path.read_bytes()
    with open(path, 'rb') as f:
        summary = make_reader(f).get_summary()
    last = summary.chunk_indexes[-1]
    data_end = last.chunk_start_offset + last.chunk_length
    torn = tmp_path / 'torn.mcap'
    counts = []
    first = summary.chunk_indexes[0]
    chunk_ends = {c.chunk_start_offset + c.chunk_length for c in summary.chunk_indexes}
    cuts = list(range(first.chunk_start_offset + first.chunk_length, data_end, 997))
    for cut in cuts + [data_end]:
        torn.write_bytes(data[:cut])
        (read_joints, read_points), warned = read_warned(read_bag, torn)
        # Whatever survives is exactly the beginning of the recording.
        assert_same_joints(read_joints, joints[:len(read_joints)])
        assert_same_points(read_points, points[:len(read_points)])
        counts.append(len(read_joints) + len(read_points))
        if cut in chunk_ends:
            assert warned == [], (cut, warned)
            continue
        torn.write_bytes(data[:cut - unreadable_tail(warned, torn, cut)])
        (clean_joints, clean_points), again = read_warned(read_bag, torn)
        assert again == [] and len(clean_joints) + len(clean_points) == counts[-1], cut
    assert counts == sorted(counts) and counts[0] > 0
    assert counts[-1] == len(joints) + len(points)


def measurement(i: int) -> tuple[JointSample, PointSample]:
    stamp = 1_700_000_000_000_000_000 + i * 4_000_000_000
    return (JointSample(stamp, NAMES, 0.001 * i + np.arange(6.0)),
            PointSample(stamp, FRAME, [i, 2.0 * i, 3.0 * i]))


def assert_measurements(loaded, indices):
    assert len(loaded) == len(indices)
    for (joint, point), i in zip(loaded, indices):
        expected_joint, expected_point = measurement(i)
        assert_same_joints([joint], [expected_joint])
        assert_same_points([point], [expected_point])


def test_measurement_log_round_trip_and_numbering(tmp_path):
    with MeasurementLog(tmp_path / 'run') as log:
        for i in range(3):
            log.append(*measurement(i))
    assert log.path.name == 'measurements_1.mcap' and log.count == 3
    assert log.path.read_bytes().endswith(MAGIC)  # close() finalised it
    second = MeasurementLog(tmp_path / 'run')  # next process run: next file
    second.append(*measurement(3))
    assert second.path.name == 'measurements_2.mcap'
    assert_measurements(MeasurementLog.load_all(tmp_path / 'run'), range(4))
    # A log is an ordinary bag.
    read_joints, read_points = read_bag(log.path)
    assert [j.stamp_ns for j in read_joints] == [p.stamp_ns for p in read_points]
    second.close()
    second.close()
    with pytest.raises(ValueError, match='closed'):
        second.append(*measurement(4))
    with MeasurementLog(tmp_path / 'other') as other, pytest.raises(ValueError, match='stamp_ns'):
        other.append(measurement(5)[0], measurement(6)[1])


@pytest.mark.slow
def test_measurement_log_torn_anywhere_loses_only_the_torn_append(tmp_path):
    with MeasurementLog(tmp_path) as log:
        for i in range(3):
            log.append(*measurement(i))
    data = log.path.read_bytes()
    torn_dir = tmp_path / 'torn'
    torn_dir.mkdir()
    torn = torn_dir / 'measurements_1.mcap'
    counts, silent = [], []
    for cut in [*range(0, len(data), 3), len(data)]:
        torn.write_bytes(data[:cut])
        loaded, warned = read_warned(MeasurementLog.load_all, torn_dir)
        assert_measurements(loaded, range(len(loaded)))
        counts.append(len(loaded))
        # Every loss is reported, naming the torn file.
        assert all(m.startswith(f'{torn}: ') for m in warned), warned
        if not warned:
            silent.append(cut)
    assert counts == sorted(counts) and counts[-1] == 3
    # Only a cut at a record boundary (or inside the magic) loses nothing unreported.
    assert len(data) in silent and len(silent) < 20, silent


KILLED_WRITER = r'''
import sys
sys.path.insert(0, sys.argv[2])
from test_bag import measurement
from kpi_calib_ros.io.measurement_log import MeasurementLog

log = MeasurementLog(sys.argv[1])
i = 0
while True:
    log.append(*measurement(i))
    i += 1
    print(i, flush=True)  # only after the append is durable
'''


def test_measurement_log_survives_sigkill(tmp_path):
    with MeasurementLog(tmp_path) as earlier_run:
        earlier_run.append(*measurement(1000))
    process = subprocess.Popen(
        [sys.executable, '-c', KILLED_WRITER, str(tmp_path), str(Path(__file__).parent)],
        stdout=subprocess.PIPE, text=True)
    watchdog = threading.Timer(120, process.kill)  # a hung writer fails the test, not CI
    watchdog.start()
    try:
        acknowledged = 0
        while acknowledged < 25:
            line = process.stdout.readline()
            assert line, 'writer exited before being killed'
            acknowledged = int(line)
        process.send_signal(signal.SIGKILL)
        assert process.wait() == -signal.SIGKILL
        acknowledged = max([acknowledged] + [int(line) for line in process.stdout])
    finally:
        watchdog.cancel()
        process.kill()
        process.stdout.close()
    killed_file = tmp_path / 'measurements_2.mcap'
    assert not killed_file.read_bytes().endswith(MAGIC)  # never finalised
    loaded = MeasurementLog.load_all(tmp_path)
    # Every acknowledged append is back; at most one more finished before the kill landed.
    assert len(loaded) - 1 in (acknowledged, acknowledged + 1)
    assert_measurements(loaded[:1], [1000])
    assert_measurements(loaded[1:], range(len(loaded) - 1))


class DiskFull:
    """os.pwrite / os.fsync that fail with ENOSPC on chosen calls; a failing pwrite first
    writes part of its data, as a filling disk does."""

    def __init__(self, monkeypatch, fail_writes=(), fail_syncs=(), truncate_fails=False):
        self.writes = self.syncs = 0
        self.fail_writes, self.fail_syncs = set(fail_writes), set(fail_syncs)
        real_pwrite, real_fsync, real_ftruncate = os.pwrite, os.fsync, os.ftruncate

        def pwrite(fd, data, offset):
            self.writes += 1
            if self.writes in self.fail_writes:
                real_pwrite(fd, bytes(data[:len(data) // 2]), offset)
                raise OSError(errno.ENOSPC, 'No space left on device')
            return real_pwrite(fd, data, offset)

        def fsync(fd):
            self.syncs += 1
            if self.syncs in self.fail_syncs:
                raise OSError(errno.ENOSPC, 'No space left on device')
            return real_fsync(fd)

        def ftruncate(fd, length):
            if truncate_fails:
                raise OSError(errno.EIO, 'Input/output error')
            return real_ftruncate(fd, length)

        monkeypatch.setattr(os, 'pwrite', pwrite)
        monkeypatch.setattr(os, 'fsync', fsync)
        monkeypatch.setattr(os, 'ftruncate', ftruncate)


@pytest.mark.parametrize('truncate_fails', [False, True])
def test_disk_full_acknowledged_is_exactly_what_is_on_disk(tmp_path, monkeypatch,
                                                           truncate_fails):
    log = MeasurementLog(tmp_path)  # header written before the disk fills
    # One pwrite per append: pwrite calls 3, 4, 9 and 12 (appends i = 2, 3, 8, 11) tear;
    # fsync calls 6 and 7 fail (written but not known durable); space comes back between.
    DiskFull(monkeypatch, fail_writes={3, 4, 9, 12}, fail_syncs={6, 7},
             truncate_fails=truncate_fails)
    acknowledged = []
    not_stored = 0
    for i in range(12):
        try:
            log.append(*measurement(i))
        except OSError as error:
            assert error.errno == errno.ENOSPC
            not_stored += 1
        else:
            acknowledged.append(i)
    assert {2, 3, 8, 11}.isdisjoint(acknowledged) and not_stored >= 5
    assert log.count == len(acknowledged) == 12 - not_stored
    if truncate_fails:
        # The file cannot even be cut back and the process dies: the torn last append
        # stays in the file, and the reader skips it with a warning.
        monkeypatch.undo()
        with pytest.warns(BagWarning, match='bytes unreadable'):
            loaded = MeasurementLog.load_all(tmp_path)
    else:  # every failed append was cut back: the file is clean
        log.close()
        monkeypatch.undo()
        assert log.path.read_bytes().endswith(MAGIC)
        with warnings.catch_warnings():
            warnings.simplefilter('error')
            loaded = MeasurementLog.load_all(tmp_path)
    assert_measurements(loaded, acknowledged)
    # The next run (a restart) appends after all of it; a torn append stays reported.
    with MeasurementLog(tmp_path) as again:
        again.append(*measurement(50))
    loaded, warned = read_warned(MeasurementLog.load_all, tmp_path)
    assert_measurements(loaded, acknowledged + [50])
    assert len(warned) == truncate_fails and all(
        m.startswith(f'{log.path}: ') and 'bytes unreadable' in m for m in warned), warned


def test_disk_full_at_close_leaves_a_readable_log(tmp_path, monkeypatch):
    log = MeasurementLog(tmp_path)
    log.append(*measurement(0))
    DiskFull(monkeypatch, fail_writes={1})
    log.close()  # the footer does not fit: the log stays a valid unfinalised bag
    monkeypatch.undo()
    with warnings.catch_warnings():
        warnings.simplefilter('error')
        assert_measurements(MeasurementLog.load_all(tmp_path), [0])


def test_measurement_log_and_results_are_readable_by_others(tmp_path):
    from kpi_calib_ros.io.results import write_atomic
    umask = os.umask(0)
    os.umask(umask)
    with MeasurementLog(tmp_path) as log:
        log.append(*measurement(0))
    result = write_atomic(tmp_path / 'calibration.yaml', 'a: 1\n')
    for path in (log.path, result):
        assert path.stat().st_mode & 0o777 == 0o644 & ~umask


def test_cut_inside_a_chunk_recovers_every_complete_message(tmp_path):
    _, _, joints, points = make_streams(n_poses=6)
    path = write_bag(tmp_path / 'cell.mcap', joints, points)  # rosbag2's 768 KiB: one chunk
    data = path.read_bytes()
    with open(path, 'rb') as f:
        summary = make_reader(f).get_summary()
    assert len(summary.chunk_indexes) == 1
    chunk = summary.chunk_indexes[0]
    # Where each message record ends in the file, from the writer's own message index.
    records_start = chunk.chunk_start_offset + 9 + 8 + 8 + 8 + 4 + 4 + 8
    ends = []  # (end offset in file, channel id)
    for channel_id, index_offset in chunk.message_index_offsets.items():
        with open(path, 'rb') as f:
            f.seek(index_offset)
            records = StreamReader(f, skip_magic=True).records
            index = next(records)
        for _, offset in index.records:
            start = records_start + offset
            length = int.from_bytes(data[start + 1:start + 9], 'little')
            ends.append((start + 9 + length, channel_id))
    ends.sort()
    joint_channel = next(c.id for c in summary.channels.values() if c.topic == '/joint_states')
    data_end = chunk.chunk_start_offset + chunk.chunk_length
    cut_torn = tmp_path / 'torn.mcap'
    for cut in [round(f * len(data)) for f in (0.25, 0.5, 0.75)] + [ends[10][0] + 5,
                                                                    ends[-1][0] - 1]:
        assert chunk.chunk_start_offset < cut < data_end  # inside the chunk
        cut_torn.write_bytes(data[:cut])
        whole = [c for end, c in ends if end <= cut]
        n_joints = sum(c == joint_channel for c in whole)
        last_end = max(end for end, _ in ends if end <= cut)
        with pytest.warns(BagWarning, match=f': {cut - last_end} of {cut} bytes unreadable'):
            read_joints, read_points = read_bag(cut_torn)
        assert_same_joints(read_joints, joints[:n_joints])
        assert_same_points(read_points, points[:len(whole) - n_joints])


@pytest.mark.parametrize('window_ns', [200_000_000, 60_000_000])
def test_reading_for_pairing_decodes_less_and_pairs_the_same(tmp_path, window_ns):
    rng = np.random.default_rng(4)
    q = rng.uniform(-2.0, 2.0, (8, len(NAMES)))
    eta = rng.uniform(-1.5, 1.5, (8, 3))
    joints, points = synthesize_streams(q, NAMES, eta, FRAME, rate_hz=250.0,
                                        joint_noise_rad=1e-5, rng=rng)
    # Points the pairer rejects belong in the comparison too: one while moving, one late,
    # one with no joint state near it, and a duplicate.
    points += [PointSample(joints[300].stamp_ns + 1, FRAME, [0.1, 0.2, 0.3]),
               PointSample(joints[-1].stamp_ns + 10 ** 9, FRAME, [0.0, 0.0, 1.0]),
               PointSample(points[2].stamp_ns, FRAME, [1.0, 0.0, 0.0])]
    path = write_bag(tmp_path / 'cell.mcap', joints, points, chunk_size=64 * 1024)
    contents = read_for_pairing(path, window_ns=window_ns)
    assert not contents.measurement_log and contents.unreadable_bytes == 0
    assert len(contents.joints) < len(joints) / 4  # only what pairing needs was decoded
    partial = pair_measurements(contents.joints, contents.points, NAMES, FRAME,
                                window_ns=window_ns)
    full = pair_measurements(joints, points, NAMES, FRAME, window_ns=window_ns)
    assert len(full) == 8 and partial.rejections == full.rejections
    assert sum(full.rejections.values()) == 3
    np.testing.assert_array_equal(partial.q, full.q)
    np.testing.assert_array_equal(partial.eta, full.eta)
    np.testing.assert_array_equal(partial.stamps_ns, full.stamps_ns)


def test_measurement_log_damaged_record_is_skipped_and_others_read_it(tmp_path):
    with MeasurementLog(tmp_path) as log:
        for i in range(3):
            log.append(*measurement(i))
    data = bytearray(log.path.read_bytes())
    # Other MCAP readers read the log as an ordinary bag.
    with open(log.path, 'rb') as f:
        decoded = [(channel.topic, message.log_time) for _, channel, message
                   in make_reader(f).iter_messages()]
    assert decoded == [(t, measurement(i)[1].stamp_ns) for i in range(3)
                       for t in ('/joint_states', '/laser_tracker/point')]
    # A flipped bit inside the third measurement's point: that one is skipped, loudly.
    third = data.find(measurement(2)[1].xyz.tobytes())
    assert third > 0 and data.count(measurement(2)[1].xyz.tobytes()) == 1
    data[third] ^= 0x10
    log.path.write_bytes(bytes(data))
    with pytest.warns(BagWarning, match='fails its CRC check'):
        assert_measurements(MeasurementLog.load_all(tmp_path), [0, 1])
