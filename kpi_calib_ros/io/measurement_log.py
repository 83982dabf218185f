"""The "nothing lost" store: accepted measurements appended durably as MCAP bags.

Every accepted measurement (the paired joint state and tracker point, same stamp)
is written and fsynced before it counts. Each process run opens the next
``measurements_<n>.mcap`` in the data directory; every file is itself a bag that
:func:`kpi_calib_ros.io.bag.read_bag` reads, and :func:`load_all` recovers every
complete measurement, including those of a process that was killed.
"""
from __future__ import annotations

import os
import re
from pathlib import Path

from kpi_calib_ros.core.streams import JointSample, PointSample
from kpi_calib_ros.io.bag import (DEFAULT_JOINT_TOPIC, DEFAULT_POINT_TOPIC, BagError, _read,
                                  _Recorder)

_LOG_NAME = re.compile(r'measurements_(\d+)\.mcap')


def _log_files(directory: Path) -> list[Path]:
    numbered = [(int(m.group(1)), p) for p in directory.glob('measurements_*.mcap')
                if (m := _LOG_NAME.fullmatch(p.name))]
    return [p for _, p in sorted(numbered)]


class MeasurementLog:
    """Append-only store of accepted measurements that survives the process being killed.

    Each instance creates the next ``measurements_<n>.mcap`` in ``directory``, an
    unchunked bag with the same topics and types as :func:`write_bag`, readable by
    :func:`read_bag`. :meth:`append` returns only once the measurement is on disk
    (flush + fsync).

    Parameters
    ----------
    directory : path-like
        Created if missing.
    joint_topic, point_topic : str
        Topics the paired joint state and point are stored under.
    """

    def __init__(self, directory: str | os.PathLike, joint_topic: str = DEFAULT_JOINT_TOPIC,
                 point_topic: str = DEFAULT_POINT_TOPIC) -> None:
        self.directory = Path(directory)
        self.directory.mkdir(parents=True, exist_ok=True)
        files = _log_files(self.directory)
        n = int(_LOG_NAME.fullmatch(files[-1].name).group(1)) + 1 if files else 1
        while True:
            try:  # exclusive create: two processes never share a file
                self._file = open(self.directory / f'measurements_{n}.mcap', 'xb')
                break
            except FileExistsError:
                n += 1
        self.path = self.directory / f'measurements_{n}.mcap'
        self.count = 0
        self._recorder = _Recorder(self._file, joint_topic, point_topic, chunked=False)
        # Also flushes the header, schemas and channels: the file is a valid bag at once.
        self._recorder.add_metadata('kpi_calib_ros', {
            'content': 'measurement_log', 'joint_topic': joint_topic, 'point_topic': point_topic})
        self._sync()
        fd = os.open(self.directory, os.O_RDONLY)
        try:  # make the new directory entry itself durable
            os.fsync(fd)
        finally:
            os.close(fd)

    def _sync(self) -> None:
        self._file.flush()
        os.fsync(self._file.fileno())

    @property
    def closed(self) -> bool:
        return self._file.closed

    def append(self, joint_sample: JointSample, point: PointSample) -> None:
        """Store one accepted measurement durably before returning.

        Parameters
        ----------
        joint_sample : JointSample
            The configuration paired with the point (e.g.
            :meth:`PairedMeasurement.joint_sample`), stamped like ``point``.
        point : PointSample
        """
        if self.closed:
            raise ValueError(f'MeasurementLog {self.path} is closed')
        if joint_sample.stamp_ns != point.stamp_ns:
            raise ValueError(f'joint_sample.stamp_ns {joint_sample.stamp_ns} must equal '
                             f'point.stamp_ns {point.stamp_ns}')
        self._recorder.write_joint(joint_sample)
        self._recorder.write_point(point)
        self._sync()
        self.count += 1

    def close(self) -> None:
        """Finalise the bag (summary and footer); idempotent."""
        if not self.closed:
            self._recorder.finish()
            self._sync()
            self._file.close()

    def __enter__(self) -> MeasurementLog:
        return self

    def __exit__(self, *exc_info) -> None:
        self.close()

    @staticmethod
    def load_all(directory: str | os.PathLike, joint_topic: str = DEFAULT_JOINT_TOPIC,
                 point_topic: str = DEFAULT_POINT_TOPIC) -> list[tuple[JointSample, PointSample]]:
        """Every measurement in ``directory``'s logs, oldest file first, in append order.

        Logs of killed processes are included; only an append torn by the kill (a
        joint state without its point, never acknowledged) is left out.
        """
        directory = Path(directory)
        if not directory.is_dir():
            raise BagError(f'{directory}: no such directory of measurement logs')
        pairs: list[tuple[JointSample, PointSample]] = []
        for path in _log_files(directory):
            messages = _read(path, joint_topic, point_topic, require_topics=False)
            for i, message in enumerate(messages):
                if isinstance(message, PointSample):
                    joint = messages[i - 1] if i else None
                    if not isinstance(joint, JointSample) or joint.stamp_ns != message.stamp_ns:
                        raise BagError(f'{path}: point at {message.stamp_ns} ns does not follow '
                                       'its joint state; this file is not a measurement log')
                    pairs.append((joint, message))
                elif i + 1 < len(messages) and not isinstance(messages[i + 1], PointSample):
                    raise BagError(f'{path}: joint state at {message.stamp_ns} ns has no point; '
                                   'this file is not a measurement log')
        return pairs


load_all = MeasurementLog.load_all

