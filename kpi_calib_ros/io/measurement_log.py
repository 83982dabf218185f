"""The "nothing lost" store: accepted measurements appended durably as MCAP bags.

Each process run opens the next ``measurements_<n>.mcap`` in the data directory.
Every accepted measurement (the paired joint state and tracker point, same stamp,
and the point's stated σ when the tracker gave one) is one self-contained record: an
MCAP chunk holding these messages and the CRC of its bytes; a σ that arrives after its
measurement was stored is a record of its own. An append writes the chunk past the
last good offset and fsyncs it before it counts; if writing or syncing fails (a full
disk), the file is cut back to the last good offset and the error propagates, so what
is acknowledged is exactly what is on disk. The reader skips a torn or damaged record
with a warning, so a log stays readable whatever happened;
:meth:`MeasurementLog.load_all` recovers every acknowledged measurement,
including those of a process that was killed.

The file marks itself as a log with a ``kpi_calib_ros`` metadata record, so every
command reading a bag takes its measurements as already paired
(:func:`kpi_calib_ros.io.bag.read_for_pairing`). The record also names the tracker
station (set-up) every measurement of the file was taken from, and whether the probe was
remounted for it (``station``, ``reflector_remounted``): a new station starts a new file.
A log written before stations were stored holds neither: its measurements belong to
:data:`DEFAULT_STATION`.
"""
from __future__ import annotations

import mmap
import os
import re
import zlib
from pathlib import Path
from typing import Iterable

import numpy as np
from mcap.data_stream import RecordBuilder
from mcap.records import Channel, Chunk, DataEnd, Footer, Header, Message, Metadata, Schema
from mcap.well_known import MessageEncoding, SchemaEncoding

from kpi_calib_ros.core.acquisition.outcomes import PairingResult, stacked_rotations
from kpi_calib_ros.core.acquisition.reflector_frames import split_frame
from kpi_calib_ros.core.acquisition.streams import JointSample, PointSample
from kpi_calib_ros.core.errors import DataError
from kpi_calib_ros.core.measurement.covariates import InputSample, TemperatureSample
from kpi_calib_ros.io.bag import (
    DEFAULT_JOINT_TOPIC,
    DEFAULT_POINT_TOPIC,
    LIBRARY,
    LOG_CONTENT,
    LOG_METADATA,
    BagError,
    StreamEncoders,
    read_inputs,
    read_log_with_sigma,
    read_temperatures,
)
from kpi_calib_ros.io.mcap_scan import MAGIC, scan
from kpi_calib_ros.io.names import DEFAULT_POSE_TOPIC, point_sigma_topic

_LOG_NAME = re.compile(r'measurements_(\d+)\.mcap')
# The station of a log that names none (written before stations were stored).
DEFAULT_STATION = 'station_1'


def _log_files(directory: Path) -> list[Path]:
    numbered = [(int(m.group(1)), p) for p in directory.glob('measurements_*.mcap')
                if (m := _LOG_NAME.fullmatch(p.name))]
    return [p for _, p in sorted(numbered)]


class MeasurementLog:
    """Append-only store of accepted measurements that survives kills and full disks.

    Each instance creates the next ``measurements_<n>.mcap`` in ``directory`` (mode
    0644 less the umask), a bag with the same topics and types as :func:`write_bag`:
    header, schemas, channels and the log's metadata, then one chunk per measurement.
    :meth:`append` returns only once the measurement is on disk (fsync).

    Parameters
    ----------
    directory : path-like
        Created if missing.
    joint_topic, point_topic, pose_topic : str
        Topics the paired joint state and point (a tracked 6-DoF pose: PoseStamped on
        ``pose_topic``) are stored under; a point's stated σ goes on
        ``point_sigma_topic(point_topic)`` (Vector3Stamped, as in bags).
    temperature_topic : str, optional
        With it, the temperature readings (:meth:`append_temperature`) are stored too, as
        ``sensor_msgs/Temperature`` on that topic, and paired to the points by time when
        the log is read (:func:`kpi_calib_ros.io.bag.read_temperatures`).
    inputs_topic : str, optional
        With it, measured input readings (:meth:`append_inputs`) are stored too, as named
        values (``sensor_msgs/JointState``) on that topic (the cell's ``inputs.topic``), and
        paired to the points by time when the log is read (:func:`kpi_calib_ros.io.bag.
        read_inputs`).
    station : str
        The tracker station (set-up) of every measurement of this file (a recording's name,
        :data:`kpi_calib_ros.core.measurement.recordings.NAME_PATTERN`).
    reflector_remounted : bool
        The probe was remounted for this station (its reflector offsets its own).
    """

    def __init__(self, directory: str | os.PathLike, joint_topic: str = DEFAULT_JOINT_TOPIC,
                 point_topic: str = DEFAULT_POINT_TOPIC,
                 pose_topic: str = DEFAULT_POSE_TOPIC,
                 temperature_topic: str | None = None,
                 inputs_topic: str | None = None, station: str = DEFAULT_STATION,
                 reflector_remounted: bool = False) -> None:
        self.directory = Path(directory)
        self.station, self.reflector_remounted = station, bool(reflector_remounted)
        self.directory.mkdir(parents=True, exist_ok=True)
        self._encoders = StreamEncoders(joint_topic, point_topic, pose_topic, temperature_topic,
                                        sigma_topic=point_sigma_topic(point_topic),
                                        inputs_topic=inputs_topic)
        self.temperature_topic = temperature_topic
        self.inputs_topic = inputs_topic
        files = _log_files(self.directory)
        last = _LOG_NAME.fullmatch(files[-1].name) if files else None  # files all match
        n = int(last.group(1)) + 1 if last else 1
        while True:
            try:  # exclusive create: two processes never share a file
                self._fd = os.open(self.directory / f'measurements_{n}.mcap',
                                   os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o644)
                break
            except FileExistsError:
                n += 1
        self.path = self.directory / f'measurements_{n}.mcap'
        self.count = 0
        self._size = 0          # bytes known good on disk
        self._closed = False
        self._sequence = 0
        builder = RecordBuilder()
        Header(profile='ros2', library=LIBRARY).write(builder)
        for k, (topic, type_name) in enumerate(self._encoders.topics):
            Schema(id=k + 1, name=type_name, encoding=SchemaEncoding.ROS2,
                   data=self._encoders.text[type_name].encode()).write(builder)
            Channel(id=k, topic=topic, message_encoding=MessageEncoding.CDR, schema_id=k + 1,
                    metadata=self._encoders.metadata[type_name]).write(builder)
        Metadata(name=LOG_METADATA, metadata={'content': LOG_CONTENT, 'joint_topic': joint_topic,
                                              'point_topic': point_topic,
                                              'pose_topic': pose_topic, 'station': station,
                                              'reflector_remounted': str(
                                                  self.reflector_remounted).lower()}
                 ).write(builder)
        try:
            self._commit(MAGIC + builder.end())
            fd = os.open(self.directory, os.O_RDONLY)
            try:  # make the new directory entry itself durable
                os.fsync(fd)
            finally:
                os.close(fd)
        except OSError:
            os.close(self._fd)
            self._closed = True
            raise

    def _commit(self, data: bytes) -> None:
        """Write ``data`` at the last good offset and fsync; on failure cut the file
        back to that offset (what is not acknowledged does not stay) and re-raise."""
        view = memoryview(data)
        try:
            written = 0
            while written < len(data):
                written += os.pwrite(self._fd, view[written:], self._size + written)
            os.fsync(self._fd)
        except OSError:
            try:
                os.ftruncate(self._fd, self._size)
                os.fsync(self._fd)
            except OSError:
                pass  # the torn record fails its length or CRC check: the reader skips it
            raise
        self._size += len(data)

    @property
    def closed(self) -> bool:
        return self._closed

    def append(self, joint_sample: JointSample, point: PointSample,
               sigma: np.ndarray | None = None) -> None:
        """Store one accepted measurement durably before returning.

        Parameters
        ----------
        joint_sample : JointSample
            The configuration paired with the point (e.g.
            :meth:`PairedMeasurement.joint_sample`), stamped like ``point``.
        point : PointSample
        sigma : (3,) ndarray, optional
            The tracker's stated σ of the point per axis (m), > 0 and finite.

        Raises
        ------
        OSError
            Not stored (e.g. ``ENOSPC``); nothing of this measurement is left in the file.
        """
        if self.closed:
            raise ValueError(f'MeasurementLog {self.path} is closed')
        if joint_sample.stamp_ns != point.stamp_ns:
            raise ValueError(f'joint_sample.stamp_ns {joint_sample.stamp_ns} must equal '
                             f'point.stamp_ns {point.stamp_ns}')
        measured = ((2, self._encoders.pose(point)) if point.rotation is not None
                    else (1, self._encoders.point(point)))
        messages = [(0, self._encoders.joint(joint_sample)), measured]
        if sigma is not None:
            messages.append(self._sigma_message(point.stamp_ns, point.frame_id, sigma))
        self._write_record(point.stamp_ns, messages)
        self.count += 1

    def append_sigma(self, stamp_ns: int, frame_id: str, sigma: np.ndarray) -> None:
        """Store the stated σ (3,) (m) of a measurement already stored without one (it
        arrived after its point was paired), durably before returning.

        Raises
        ------
        OSError
            Not stored; nothing of it is left in the file.
        """
        if self.closed:
            raise ValueError(f'MeasurementLog {self.path} is closed')
        self._write_record(stamp_ns, [self._sigma_message(stamp_ns, frame_id, sigma)])

    def _sigma_message(self, stamp_ns: int, frame_id: str, sigma: np.ndarray
                       ) -> tuple[int, bytes]:
        sigma = np.asarray(sigma, dtype=float)
        if sigma.shape != (3,) or not np.all(np.isfinite(sigma)) or np.any(sigma <= 0):
            raise ValueError(f'sigma must be 3 finite values > 0 (m), got {sigma.tolist()}')
        return 3, self._encoders.point_sigma(stamp_ns, frame_id, sigma)

    def _write_record(self, stamp: int, messages: list[tuple[int, bytes]]) -> None:
        """``messages`` (channel, CDR) as one chunk: on disk whole or not at all."""
        inner = RecordBuilder()
        for k, (channel, data) in enumerate(messages):
            Message(channel_id=channel, sequence=self._sequence + 1 + k, log_time=stamp,
                    publish_time=stamp, data=data).write(inner)
        body = inner.end()
        record = RecordBuilder()
        Chunk(compression='', data=body, message_start_time=stamp, message_end_time=stamp,
              uncompressed_crc=zlib.crc32(body), uncompressed_size=len(body)).write(record)
        self._commit(record.end())
        self._sequence += len(messages)

    def append_temperature(self, sample: TemperatureSample) -> None:
        """Store one temperature reading durably before returning (its own chunk).

        Raises
        ------
        ValueError
            The log was opened without a temperature topic, or is closed.
        OSError
            Not stored; nothing of it is left in the file.
        """
        if self.closed or self.temperature_topic is None:
            raise ValueError(f'MeasurementLog {self.path} is closed or stores no temperature')
        stamp = int(sample.stamp_ns)
        channel = [t for t, _ in self._encoders.topics].index(self.temperature_topic)
        self._write_record(stamp, [(channel, self._encoders.temperature(
            stamp, sample.frame_id, sample.celsius))])

    def append_inputs(self, stamp_ns: int, names: tuple[str, ...], values: np.ndarray) -> None:
        """Store measured input readings of one stamp (covariate names, SI values) durably
        before returning (their own chunk).

        Raises
        ------
        ValueError
            The log was opened without an inputs topic, or is closed.
        OSError
            Not stored; nothing of it is left in the file.
        """
        if self.closed or self.inputs_topic is None:
            raise ValueError(f'MeasurementLog {self.path} is closed or stores no inputs')
        channel = [t for t, _ in self._encoders.topics].index(self.inputs_topic)
        self._write_record(int(stamp_ns), [(channel, self._encoders.inputs(
            int(stamp_ns), tuple(names), np.asarray(values, float)))])

    @staticmethod
    def load_inputs(directory: str | os.PathLike, topic: str) -> list[InputSample]:
        """Every measured input reading on ``topic`` in ``directory``'s logs, in stamp order."""
        samples: list[InputSample] = []
        for path in _log_files(Path(directory)):
            samples += read_inputs(path, topic)[0]
        return sorted(samples, key=lambda s: s.stamp_ns)

    @staticmethod
    def load_temperatures(directory: str | os.PathLike,
                          topic: str) -> list[TemperatureSample]:
        """Every temperature reading on ``topic`` in ``directory``'s logs, in stamp order."""
        samples: list[TemperatureSample] = []
        for path in _log_files(Path(directory)):
            samples += read_temperatures(path, topic)
        return sorted(samples, key=lambda s: s.stamp_ns)

    def close(self) -> None:
        """Finalise the bag (data end and footer; the records are read linearly, so no
        summary is written); idempotent. A log that cannot be finalised (disk full)
        stays a valid unfinalised bag."""
        if self.closed:
            return
        self._closed = True
        builder = RecordBuilder()
        DataEnd(data_section_crc=0).write(builder)
        Footer(summary_start=0, summary_offset_start=0, summary_crc=0).write(builder)
        try:
            self._commit(builder.end() + MAGIC)
        except OSError:
            pass  # nothing acknowledged depends on the footer
        finally:
            os.close(self._fd)

    def __enter__(self) -> MeasurementLog:
        return self

    def __exit__(self, *exc_info) -> None:
        self.close()

    @staticmethod
    def load_all(directory: str | os.PathLike, joint_topic: str = DEFAULT_JOINT_TOPIC,
                 point_topic: str = DEFAULT_POINT_TOPIC,
                 pose_topic: str = DEFAULT_POSE_TOPIC) -> list[tuple[JointSample, PointSample]]:
        """Every measurement in ``directory``'s logs, oldest file first, in append order.

        Logs of killed processes are included; a record torn by a kill or a full disk
        (never acknowledged) is skipped with a :class:`~kpi_calib_ros.io.bag.BagWarning`.
        """
        return MeasurementLog.load(directory, joint_topic, point_topic, pose_topic)[0]

    @staticmethod
    def load(directory: str | os.PathLike, joint_topic: str = DEFAULT_JOINT_TOPIC,
             point_topic: str = DEFAULT_POINT_TOPIC, pose_topic: str = DEFAULT_POSE_TOPIC
             ) -> tuple[list[tuple[JointSample, PointSample]], dict[tuple[int, str], np.ndarray]]:
        """:meth:`load_all`, and the points' stated σ (3,) (m) by (stamp ns, frame id)
        (none in logs written before σ was stored: those points take the cell's σ)."""
        directory = Path(directory)
        if not directory.is_dir():
            raise BagError(f'{directory}: no such directory of measurement logs')
        pairs: list[tuple[JointSample, PointSample]] = []
        sigma: dict[tuple[int, str], np.ndarray] = {}
        for path in _log_files(directory):
            more, stated = read_log_with_sigma(path, joint_topic, point_topic, pose_topic)
            pairs += more
            sigma.update(stated)
        return pairs, sigma

    @staticmethod
    def load_stations(directory: str | os.PathLike, joint_topic: str = DEFAULT_JOINT_TOPIC,
                      point_topic: str = DEFAULT_POINT_TOPIC,
                      pose_topic: str = DEFAULT_POSE_TOPIC
                      ) -> list[tuple[str, bool, list[tuple[JointSample, PointSample]]]]:
        """Per log file of ``directory``, oldest first: its station, whether the probe was
        remounted for it (:func:`log_station`) and its measurements."""
        out = []
        for path in _log_files(Path(directory)):
            pairs, _ = read_log_with_sigma(path, joint_topic, point_topic, pose_topic)
            out.append((*log_station(path), pairs))
        return out


def log_station(path: str | os.PathLike) -> tuple[str, bool]:
    """The station a measurement log names and whether the probe was remounted for it;
    (:data:`DEFAULT_STATION`, False) for a log that names none (written before stations were
    stored) or a file that is not a log."""
    path = Path(path)
    try:
        with open(path, 'rb') as f:
            size = os.fstat(f.fileno()).st_size
            # Mapped, not read: any recording may be asked (``identify --bag``).
            data = mmap.mmap(f.fileno(), 0, access=mmap.ACCESS_READ) if size else b''
        if data[:len(MAGIC)] != MAGIC:
            return DEFAULT_STATION, False
        bag = scan(path, data)
    except (OSError, BagError, ValueError):
        return DEFAULT_STATION, False
    for m in bag.metadata:
        if m.name == LOG_METADATA and m.metadata.get('content') == LOG_CONTENT:
            station = m.metadata.get('station') or DEFAULT_STATION
            return station, m.metadata.get('reflector_remounted') == 'true'
    return DEFAULT_STATION, False



def stored_pairing(pairs: Iterable[tuple[JointSample, PointSample]], joint_names: list[str],
                   tracker_frame: str, rejections: dict[str, int] | None = None
                   ) -> PairingResult:
    """Stored measurements as a pairing result, ``q`` ordered as ``joint_names`` by name.

    Points in another frame are rejected (``wrong_frame``) and counted with
    ``rejections``; non-finite ones as ``non_finite_point``.

    Raises
    ------
    DataError
        A stored configuration lacks a joint of ``joint_names`` (another robot's log).
    """
    frame = tracker_frame.strip('/')
    counts = dict(rejections or {})
    q_rows, eta_rows, stamps, reflectors, rotations = [], [], [], [], []
    for joint, point in sorted(pairs, key=lambda jp: jp[1].stamp_ns):
        reason = ('wrong_frame' if split_frame(point.frame_id)[0] != frame else
                  'non_finite_point' if not np.all(np.isfinite(point.xyz)) else None)
        if reason:
            counts[reason] = counts.get(reason, 0) + 1
            continue
        by_name = dict(zip(joint.names, joint.positions))
        missing = [n for n in joint_names if n not in by_name]
        if missing:
            raise DataError(f'a stored measurement (stamp {point.stamp_ns} ns) lacks joints '
                            f'{missing}; the robot model joints are {list(joint_names)}: '
                            'use the log of this robot, or reset the campaign to start over')
        q_rows.append([by_name[n] for n in joint_names])
        eta_rows.append(point.xyz)
        stamps.append(point.stamp_ns)
        reflectors.append(split_frame(point.frame_id)[1])
        rotations.append(point.rotation)
    n = len(joint_names)
    return PairingResult(tuple(joint_names), tracker_frame,
                         np.array(q_rows, dtype=float).reshape(-1, n),
                         np.array(eta_rows, dtype=float).reshape(-1, 3),
                         np.array(stamps, dtype=np.int64),
                         rejections={k: v for k, v in sorted(counts.items()) if v},
                         reflectors=tuple(reflectors), rotations=stacked_rotations(rotations))


__all__ = ['DEFAULT_STATION', 'MeasurementLog', 'log_station', 'stored_pairing']
