"""One calibration campaign as the node lives it: live pairing into a durable store.

No rclpy here: the node converts messages to samples and hands them over; this
class pairs them with :class:`~kpi_calib_ros.core.pairing.Pairer` (the code that
pairs bags), appends every accepted measurement to a
:class:`~kpi_calib_ros.io.measurement_log.MeasurementLog` before counting it, reloads the logs
of earlier runs in the same folder, and never counts a stamp twice. Thread-safe:
every public method takes the campaign's lock.

Pairing clock: a point waits for joint states up to the pairer's timeout past its
stamp on a clock that follows the joint stream (newest joint stamp + time since it
arrived), so live streams, backlogs and replayed recordings (old stamps) behave alike.
"""
from __future__ import annotations

import shutil
import threading
import time
from collections import Counter, deque
from pathlib import Path
from typing import Sequence

from kpi_calib_ros.core.covariates import TemperatureSample
from kpi_calib_ros.core.errors import DataError
from kpi_calib_ros.core.measurement import Measurements
from kpi_calib_ros.core.pairing import (
    REJECTION_REASONS,
    Decision,
    PairedMeasurement,
    Pairer,
    PairingResult,
    Rejection,
)
from kpi_calib_ros.core.streams import JointSample, PointSample
from kpi_calib_ros.io.measurement_log import MeasurementLog, stored_pairing
from kpi_calib_ros.io.names import RESULT_FILES

# Campaign-level reasons besides the pairer's: the measurement could not be written.
NOT_STORED = 'not_stored'
REASONS = REJECTION_REASONS + (NOT_STORED,)
# Joint names a joint state may carry while the chain is not known yet (the pairer's
# own limit, 4 x chain + 64, needs the chain): far above any robot cell's joint count,
# far below a hostile message, so the early buffer of 20 000 samples stays small.
EARLY_MAX_NAMES = 256


class Campaign:
    """Accepted measurements of one campaign in ``data_dir``, and what was rejected.

    Parameters
    ----------
    data_dir : path-like
        Holds the ``measurements_<n>.mcap`` logs (created if missing); the logs
        already there are loaded, a new one is started.
    early_limit : int
        Samples kept while the robot model (joint names) is not known yet; they are
        paired once it is.
    temperature_topic : str, optional
        The cell's temperature topic: readings (:meth:`receive_temperature`) are logged
        under it and kept, those of earlier runs reloaded; None: none kept.
    """

    def __init__(self, data_dir: str | Path, early_limit: int = 20_000,
                 temperature_topic: str | None = None) -> None:
        self.data_dir = Path(data_dir)
        self.lock = threading.RLock()
        # Keyed by (stamp, frame id): the reflectors of one pose share a stamp.
        self._measurements: dict[tuple[int, str], tuple[JointSample, PointSample]] = {}
        if self.data_dir.is_dir():
            for joint, point in MeasurementLog.load_all(self.data_dir):
                self._measurements[(point.stamp_ns, point.frame_id)] = (joint, point)
        self.restored = len(self._measurements)
        self.temperature_topic = temperature_topic
        self._temperatures: list[TemperatureSample] = (
            MeasurementLog.load_temperatures(self.data_dir, temperature_topic)
            if temperature_topic and self.data_dir.is_dir() else [])
        self.log = MeasurementLog(self.data_dir, temperature_topic=temperature_topic)
        self.pairer: Pairer | None = None
        self.rejections: Counter[str] = Counter()
        self.received = {'joint_states': 0, 'points': 0}
        self._early: deque[JointSample | PointSample] = deque(maxlen=early_limit)
        self._clock: tuple[int, int] | None = None     # (stamp ns, monotonic ns of arrival)
        self._point_clock: tuple[int, int] | None = None
        self._epoch = 0  # the pairer's clock epoch the clocks above belong to

    def __len__(self) -> int:
        with self.lock:
            return len(self._measurements)

    # ------------------------------------------------------------------ pairing
    def set_chain(self, joint_names: list[str], tracker_frame: str,
                  reflectors: Sequence[str] = ('',)) -> list[Decision]:
        """(Re)start pairing for a robot chain (and the cell's reflector names, see
        :mod:`kpi_calib_ros.core.pairing`); pairs the samples held until now."""
        with self.lock:
            decisions = self._handle(self.pairer.flush()) if self.pairer else []
            pairer = self.pairer = Pairer(joint_names, tracker_frame,
                                          reflectors=tuple(reflectors))
            early, self._early = list(self._early), deque(maxlen=self._early.maxlen)
            for sample in early:  # all of them before any timeout is judged
                self._add(pairer, sample)
            return decisions + self.poll()

    def receive(self, sample: JointSample | PointSample,
                now_ns: int | None = None) -> list[Decision]:
        """Take one sample (``now_ns``: monotonic arrival time, default now); returns the
        decisions it completed: accepted measurements (already on disk) and rejections."""
        now_ns = time.monotonic_ns() if now_ns is None else now_ns
        with self.lock:
            joint = isinstance(sample, JointSample)
            self.received['joint_states' if joint else 'points'] += 1
            clock = self._clock if joint else self._point_clock
            if clock is None or sample.stamp_ns > clock[0]:
                if joint:
                    self._clock = (sample.stamp_ns, now_ns)
                else:
                    self._point_clock = (sample.stamp_ns, now_ns)
            if self.pairer is None:
                if isinstance(sample, JointSample) and len(sample.names) > EARLY_MAX_NAMES:
                    rejection = Rejection(sample.stamp_ns, 'oversized_joint_state',
                                          f'joint state names {len(sample.names)} joints '
                                          f'(limit {EARLY_MAX_NAMES} before the robot model '
                                          'is known)')
                    self.rejections[rejection.reason] += 1
                    return [rejection]
                self._early.append(sample)
                return []
            self._add(self.pairer, sample)
            if joint and self.pairer.epoch != self._epoch:  # the joint clock jumped back
                self._epoch, self._clock = self.pairer.epoch, (sample.stamp_ns, now_ns)
            return self.poll(now_ns)

    def poll(self, now_ns: int | None = None) -> list[Decision]:
        """Decide points whose joint states are overdue; see the module docstring."""
        now_ns = time.monotonic_ns() if now_ns is None else now_ns
        with self.lock:
            clock = self._clock or self._point_clock
            if self.pairer is None or clock is None:
                return []
            return self._handle(self.pairer.poll(clock[0] + now_ns - clock[1]))

    @staticmethod
    def _add(pairer: Pairer, sample: JointSample | PointSample) -> None:
        if isinstance(sample, JointSample):
            pairer.add_joint_sample(sample)
        else:
            pairer.add_point(sample)

    def _handle(self, decisions: list[Decision]) -> list[Decision]:
        out: list[Decision] = []
        for d in decisions:
            if isinstance(d, PairedMeasurement):
                if (d.stamp_ns, d.frame_id) in self._measurements:
                    d = Rejection(d.stamp_ns, 'duplicate_stamp', 'this measurement is already '
                                  'stored (a replay, or a restart re-receiving it)')
                else:
                    joint, point = d.joint_sample(), d.point_sample()
                    try:
                        self.log.append(joint, point)  # on disk before it counts
                    except OSError as exc:
                        d = Rejection(d.stamp_ns, NOT_STORED, f'not written to {self.log.path}: '
                                      f'{exc}')
                    else:
                        self._measurements[(d.stamp_ns, d.frame_id)] = (joint, point)
            if isinstance(d, Rejection):
                self.rejections[d.reason] += 1
            out.append(d)
        return out

    # ------------------------------------------------------------------ data
    def measurements(self, joint_names: list[str], tracker_frame: str,
                     reflectors: Sequence[str] = ('',)) -> tuple[Measurements, PairingResult]:
        """Every accepted measurement in stamp order, ``q`` ordered as ``joint_names``;
        with several ``reflectors`` (the cell's names), each row's reflector index."""
        with self.lock:
            pairs = [self._measurements[k] for k in sorted(self._measurements)]
            rejections = {k: v for k, v in sorted(self.rejections.items())}
        if not pairs:
            raise DataError('no accepted measurement yet')
        pairing = stored_pairing(pairs, list(joint_names), tracker_frame, rejections)
        q, eta, stamps = pairing.q, pairing.eta, pairing.stamps_ns
        if tuple(reflectors) == ('',):
            return Measurements(q=q, eta=eta, stamps_ns=stamps), pairing
        try:
            ref = pairing.reflector_indices(reflectors)
        except ValueError as exc:
            raise DataError(f'stored measurements: {exc}; reset the campaign after changing '
                            'the reflectors of the cell') from None
        return Measurements(q=q, eta=eta, stamps_ns=stamps, reflector=ref), pairing

    def counts(self) -> dict[str, int]:
        """Accepted, restored, received and rejected (total and per reason) counts."""
        with self.lock:
            counts = {'accepted': len(self._measurements), 'restored': self.restored,
                      'received.joint_states': self.received['joint_states'],
                      'received.points': self.received['points'],
                      'rejected': sum(self.rejections.values())}
            counts.update({f'rejected.{r}': self.rejections.get(r, 0) for r in REASONS})
            counts.update({'ignored_joint_samples': self.pairer.ignored_joint_samples
                           if self.pairer else 0,
                           'clock_jumps': self.pairer.clock_jumps if self.pairer else 0,
                           'pending_points': self.pairer.pending if self.pairer else 0})
            return counts

    def reset(self) -> tuple[int, Path]:
        """Start over: move (never delete) the logs and result files into
        ``archive/<time>/``; returns the number of measurements archived and where.
        The design (``design.yaml``) stays: it is the plan, not campaign data."""
        with self.lock:
            archive = self.data_dir / 'archive' / time.strftime('%Y%m%dT%H%M%S')
            while archive.exists():
                archive = archive.with_name(archive.name + '_')
            archive.mkdir(parents=True)
            self.log.close()
            moved = sorted(self.data_dir.glob('measurements_*.mcap'))
            moved += [self.data_dir / n for n in RESULT_FILES if (self.data_dir / n).exists()]
            for path in moved:
                shutil.move(str(path), str(archive / path.name))
            count = len(self._measurements)
            self._measurements.clear()
            self.rejections.clear()
            self.restored = 0
            self._temperatures.clear()
            self.log = MeasurementLog(self.data_dir, temperature_topic=self.temperature_topic)
            if self.pairer is not None:
                self.pairer.reset()
            self._clock = self._point_clock = None
            self._epoch = 0
            return count, archive

    def receive_temperature(self, sample: TemperatureSample) -> None:
        """Keep one temperature reading, logged durably first (OSError: not kept)."""
        with self.lock:
            self.log.append_temperature(sample)
            self._temperatures.append(sample)

    def temperatures(self) -> list[TemperatureSample]:
        """The temperature readings kept (this run's and the reloaded ones), a copy."""
        with self.lock:
            return list(self._temperatures)

    def close(self) -> None:
        """Finalise the current log (idempotent)."""
        with self.lock:
            self.log.close()


__all__ = ['Campaign', 'NOT_STORED', 'REASONS']
