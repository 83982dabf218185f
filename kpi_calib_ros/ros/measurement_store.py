"""The node's measurement store: live pairing of its streams into a durable log.

No rclpy here: the node converts messages to samples and hands them over; this
class pairs them with :class:`~kpi_calib_ros.core.acquisition.pairing.Pairer` (the code that
pairs bags), appends every accepted measurement to a
:class:`~kpi_calib_ros.io.measurement_log.MeasurementLog` before counting it, reloads the logs
of earlier runs in the same folder, and never counts a stamp twice. Thread-safe:
every public method takes the store's lock.

Pairing clock: a point waits for joint states up to the pairer's timeout past its
stamp on a clock that follows the joint stream (newest joint stamp + time since it
arrived), so live streams, backlogs and replayed recordings (old stamps) behave alike.

Stated σ: a point's σ (the tracker's, per axis, m) arrives on its own topic with the
point's stamp and frame id, before or after the point. It is matched by both: stored
with the measurement when it came first, appended to the log when it came after the
measurement was stored, and dropped (``unmatched_sigma``) when no measurement has
claimed it once it has waited ``SIGMA_WAIT_S`` and the pairing clock has passed its
stamp by the pairer's window and timeout (its point, had it come, would be decided by
then). Before the first joint state or point there is no pairing clock and nothing is
decided, so a σ waits (bounded by ``SIGMA_HELD_MAX``); a σ whose point is still waiting for
its joint states waits with it. A measurement without σ takes the cell's, as in a bag.

Kept with the measurements: the joint states' efforts (:mod:`kpi_calib_ros.ros.effort_buffer`)
and the tracker station of each one (:mod:`kpi_calib_ros.ros.stations`). The jobs read them as
the model takes them with :mod:`kpi_calib_ros.ros.stored_measurements`.
"""
from __future__ import annotations

import shutil
import threading
import time
from collections import Counter, deque
from pathlib import Path
from typing import Callable, Mapping, Sequence

import numpy as np

from kpi_calib_ros.app.measurements import paired_sigma
from kpi_calib_ros.core.acquisition.outcomes import (
    REJECTION_REASONS,
    Decision,
    PairedMeasurement,
    PairingResult,
    Rejection,
)
from kpi_calib_ros.core.acquisition.pairing import Pairer
from kpi_calib_ros.core.acquisition.reflector_frames import split_frame
from kpi_calib_ros.core.acquisition.streams import JointSample, PointSample
from kpi_calib_ros.core.errors import DataError
from kpi_calib_ros.core.measurement.covariates import (
    TEMPERATURE_RANGE_C,
    InputSample,
    TemperatureSample,
    plausible_temperature,
)
from kpi_calib_ros.core.measurement.data import Measurements
from kpi_calib_ros.core.measurement.recordings import Recording
from kpi_calib_ros.io.measurement_log import DEFAULT_STATION, MeasurementLog, stored_pairing
from kpi_calib_ros.io.names import DEFAULT_POINT_TOPIC, RESULT_FILES, point_sigma_topic
from kpi_calib_ros.ros.effort_buffer import EffortBuffer
from kpi_calib_ros.ros.stations import Stations, check_station

# The store's reasons besides the pairer's: the measurement could not be written.
NOT_STORED = 'not_stored'
# A stated σ that is not finite and > 0, one no measurement claimed, a second one for
# a measurement: dropped, counted, never used. Not pairing rejections (the point stays).
SIGMA_REASONS = ('invalid_sigma', 'unmatched_sigma', 'duplicate_sigma')
REASONS = REJECTION_REASONS + (NOT_STORED,) + SIGMA_REASONS
# A σ waits this long after its arrival (and until the pairing clock has passed its
# point's decision) for its measurement; a tracker driver sends both together.
SIGMA_WAIT_S = 2.0
# Stated σ held without a measurement (before the robot model is known, a σ topic
# without points): far above what SIGMA_WAIT_S of 50 Hz points leaves.
SIGMA_HELD_MAX = 20_000
# Joint names a joint state may carry while the chain is not known yet (the pairer's
# own limit, 4 x chain + 64, needs the chain): far above any robot cell's joint count,
# far below a hostile message, so the early buffer of 20 000 samples stays small.
EARLY_MAX_NAMES = 256


class MeasurementStore:
    """Accepted measurements of one campaign in ``data_dir``, and what was rejected.

    Parameters
    ----------
    data_dir : path-like
        Holds the ``measurements_<n>.mcap`` logs (created if missing); the logs
        already there are loaded, a new one is started.
    early_limit : int
        Samples kept while the robot model (joint names) is not known yet; they are
        paired once it is.
    sigma_topic : str
        Where the stated σ comes from (named in the messages of its rejections).
    temperature_topic : str, optional
        The cell's temperature topic: readings (:meth:`receive_temperature`) are logged
        under it and kept, those of earlier runs reloaded; None: none kept.
    temperature_range_c : (low, high)
        The cell's ``temperature.valid_range`` (°C): a reading outside is counted
        (``rejected_temperatures``), never logged nor kept.
    inputs_topic : str, optional
        Where measured input readings (:meth:`receive_inputs`) are logged (the cell's
        ``inputs.topic``, named values) and kept, those of earlier runs reloaded; None: none
        kept.
    record_efforts : bool
        The cell reads measured torques (``compliance.torque_source: measured``): the joint
        states' efforts (:meth:`receive_efforts`) are buffered for the last
        :data:`~kpi_calib_ros.ros.effort_buffer.EFFORT_BUFFER_S` of stream time, and each
        accepted measurement logs the chain joints' efforts interpolated at its stamp as
        ``effort.<joint>`` on ``inputs_topic`` (one record per measurement, not per joint
        state).
    station : str
        The tracker station the measurements arriving now belong to (:meth:`set_station`);
        '' : the station of the newest log in ``data_dir`` (a restart continues it), else
        :data:`~kpi_calib_ros.io.measurement_log.DEFAULT_STATION`.
    reflector_remounted : bool
        With ``station``: the probe was remounted for it.
    """

    def __init__(self, data_dir: str | Path, early_limit: int = 20_000,
                 sigma_topic: str = point_sigma_topic(DEFAULT_POINT_TOPIC),
                 temperature_topic: str | None = None,
                 temperature_range_c: tuple[float, float] = TEMPERATURE_RANGE_C,
                 inputs_topic: str | None = None, record_efforts: bool = False,
                 station: str = '', reflector_remounted: bool = False) -> None:
        if record_efforts and inputs_topic is None:
            raise ValueError('record_efforts needs an inputs_topic to log them on')
        self.data_dir = Path(data_dir)
        self.sigma_topic = sigma_topic
        self.lock = threading.RLock()
        # Keyed by (stamp, frame id): the reflectors of one pose share a stamp.
        self._measurements: dict[tuple[int, str], tuple[JointSample, PointSample]] = {}
        # Stated σ (3,) (m) of stored measurements, and σ waiting for theirs (with the
        # monotonic ns of arrival); keyed by (stamp, tracker frame, reflector).
        self._sigma: dict[tuple[int, str, str], np.ndarray] = {}
        self._held_sigma: dict[tuple[int, str, str], tuple[np.ndarray, int]] = {}
        self._stored_frames: dict[tuple[int, str, str], str] = {}  # σ key -> frame id
        # The stations in the order first measured, and each stored measurement's station.
        self._stations = Stations()
        current = (DEFAULT_STATION, False)
        if self.data_dir.is_dir():
            pairs, sigma = MeasurementLog.load(self.data_dir)
            for name, remounted, logged in MeasurementLog.load_stations(self.data_dir):
                current = (name, remounted)
                for _, point in logged:
                    self._stations.record(point.stamp_ns, name, remounted)
            for joint, point in pairs:
                self._store(joint, point)
            self._sigma = {k: v for k, v in ((_sigma_key(*key), s) for key, s in sigma.items())
                           if k in self._stored_frames}
        self.station: tuple[str, bool] = current
        if station:
            check_station(station)
            why = self.station_conflict(station, reflector_remounted)
            if why:
                raise ValueError(why)
            self.station = (station, bool(reflector_remounted))
        self.restored = len(self._measurements)
        self.temperature_topic = temperature_topic
        self.temperature_range_c = temperature_range_c
        self.rejected_temperatures = 0
        self._temperatures: list[TemperatureSample] = (
            MeasurementLog.load_temperatures(self.data_dir, temperature_topic)
            if temperature_topic and self.data_dir.is_dir() else [])
        self.inputs_topic = inputs_topic
        self.record_efforts = record_efforts
        # The recent joint states' efforts; the chain's joint names
        self._efforts = EffortBuffer()
        self._chain: tuple[str, ...] = ()
        self._effort_stamps: set[int] = set()
        self.rejected_inputs = 0
        self._inputs: list[InputSample] = (
            MeasurementLog.load_inputs(self.data_dir, inputs_topic)
            if inputs_topic and self.data_dir.is_dir() else [])
        self.log = self._new_log()
        self.pairer: Pairer | None = None
        self.rejections: Counter[str] = Counter()
        self.received = {'joint_states': 0, 'points': 0, 'sigma': 0, 'temperatures': 0,
                         'inputs': 0}
        self._early: deque[JointSample | PointSample] = deque(maxlen=early_limit)
        self._clock: tuple[int, int] | None = None     # (stamp ns, monotonic ns of arrival)
        self._point_clock: tuple[int, int] | None = None
        self._epoch = 0  # the pairer's clock epoch the clocks above belong to

    def __len__(self) -> int:
        with self.lock:
            return len(self._measurements)

    def _new_log(self) -> MeasurementLog:
        return MeasurementLog(self.data_dir, temperature_topic=self.temperature_topic,
                              inputs_topic=self.inputs_topic, station=self.station[0],
                              reflector_remounted=self.station[1])

    # ------------------------------------------------------------------ stations
    def station_conflict(self, name: str, reflector_remounted: bool) -> str:
        """Why the station cannot become (``name``, ``reflector_remounted``) now ('' : it
        can): a station already measured keeps whether its probe was remounted."""
        with self.lock:
            return self._stations.conflict(name or self.station[0], reflector_remounted)

    def station_count(self, name: str) -> int:
        """The accepted measurements from station ``name`` ('' : every one)."""
        with self.lock:
            return self._stations.count(name) if name else len(self._measurements)

    def station_remount(self, name: str) -> bool:
        """Whether station ``name`` ('' : the current one) is remounted when set alone: as
        stated for the current station, as measured for another, else False (a new station
        is not remounted unless said)."""
        with self.lock:
            if not name or name == self.station[0]:
                return self.station[1]
            return bool(self._stations.remounted(name))

    def set_station(self, name: str, reflector_remounted: bool = False) -> bool:
        """Make (``name``, ``reflector_remounted``) the station of the measurements stored
        from now on ('' : keep the current name); returns whether it changed. A change
        starts a new log file that names it (OSError: not changed, the old log stays).

        Raises
        ------
        ValueError
            ``name`` is not a station name, or :meth:`station_conflict`.
        """
        with self.lock:
            name = name or self.station[0]
            check_station(name)
            why = self.station_conflict(name, reflector_remounted)
            if why:
                raise ValueError(why)
            wanted = (name, bool(reflector_remounted))
            if wanted == self.station:
                return False
            before = self.station
            self.station = wanted
            try:
                log = self._new_log()
            except OSError:
                self.station = before
                raise
            self.log.close()
            self.log = log
            return True

    def stations(self, stamps_ns: np.ndarray) -> tuple[list[Recording], np.ndarray]:
        """The stations of the measurements stamped ``stamps_ns`` (N,), as recordings in
        the order first measured (the probe's remount as each states it), and each row's
        index into them."""
        with self.lock:
            return self._stations.recordings(stamps_ns, self.station[0])

    # ------------------------------------------------------------------ pairing
    def set_chain(self, joint_names: list[str], tracker_frame: str,
                  reflectors: Sequence[str] = ('',),
                  derived: Mapping[str, tuple[np.ndarray, float]] | None = None,
                  joint_check: Callable[[np.ndarray], str] | None = None
                  ) -> list[Decision]:
        """(Re)start pairing for a robot's joints (and the cell's reflector names, the mimic
        joints' relations and the check of a pose's readings against the joint limits, see
        :mod:`kpi_calib_ros.core.acquisition.pairing`); pairs the samples held until now."""
        with self.lock:
            decisions = self._handle(self.pairer.flush()) if self.pairer else []
            pairer = self.pairer = Pairer(joint_names, tracker_frame,
                                          reflectors=tuple(reflectors), derived=derived,
                                          joint_check=joint_check)
            self._chain = tuple(joint_names)
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

    def receive_sigma(self, stamp_ns: int, frame_id: str, sigma: np.ndarray,
                      now_ns: int | None = None) -> list[Decision]:
        """Take the stated σ (3,) (m) of the point with this stamp and frame id; returns
        its rejection if it is refused (see the module docstring)."""
        now_ns = time.monotonic_ns() if now_ns is None else now_ns
        sigma = np.array(sigma, dtype=float).reshape(-1)
        key = _sigma_key(stamp_ns, frame_id)
        where = f"{self.sigma_topic}, stamp {stamp_ns} ns, frame '{frame_id}'"
        with self.lock:
            self.received['sigma'] += 1
            if sigma.shape != (3,) or not np.all(np.isfinite(sigma)) or np.any(sigma <= 0):
                return self._count([Rejection(stamp_ns, 'invalid_sigma',
                                              f'{where}: sigma {sigma.tolist()} is not 3 '
                                              'values > 0 and finite (m per axis)')])
            if key in self._sigma or key in self._held_sigma:
                return self._count([Rejection(stamp_ns, 'duplicate_sigma',
                                              f'{where}: this point\'s sigma is already '
                                              'given (a replay, or a restart re-receiving '
                                              'it); the first one is kept')])
            stored = self._stored_frames.get(key)
            if stored is None:
                out: list[Rejection] = []
                if len(self._held_sigma) >= SIGMA_HELD_MAX:
                    oldest = min(self._held_sigma, key=lambda k: self._held_sigma[k][1])
                    del self._held_sigma[oldest]
                    out.append(Rejection(oldest[0], 'unmatched_sigma',
                                         f'{self.sigma_topic}: {SIGMA_HELD_MAX} sigma wait for '
                                         'their points; the oldest is dropped'))
                self._held_sigma[key] = (sigma, now_ns)
                return self._count(out)
            try:
                self.log.append_sigma(stamp_ns, stored, sigma)  # on disk before it counts
            except OSError as exc:
                return self._count([Rejection(stamp_ns, NOT_STORED, f'{where}: sigma not '
                                              f'written to {self.log.path}: {exc}')])
            self._sigma[key] = sigma
            return []

    def poll(self, now_ns: int | None = None) -> list[Decision]:
        """Decide points whose joint states are overdue, and drop the stated σ no
        measurement claimed in time; see the module docstring."""
        now_ns = time.monotonic_ns() if now_ns is None else now_ns
        with self.lock:
            clock = self._clock or self._point_clock
            if self.pairer is None:
                return []
            pairing_now = None if clock is None else clock[0] + now_ns - clock[1]
            decisions = ([] if pairing_now is None
                         else self._handle(self.pairer.poll(pairing_now)))
            return decisions + self._expire_sigma(now_ns, pairing_now)

    def _expire_sigma(self, now_ns: int, pairing_now: int | None) -> list[Decision]:
        pairer = self.pairer
        assert pairer is not None
        if pairing_now is None:
            # No joint state or point yet: nothing is decided, so no σ is unmatched (a σ
            # may come first, in either order; SIGMA_HELD_MAX bounds the wait).
            return []
        wait_ns = int(SIGMA_WAIT_S * 1e9)
        decided = pairer.window_ns + pairer.timeout_ns
        # A point still waiting for its joint states (before the first one of its epoch)
        # keeps its σ however long it waits.
        waiting = {_sigma_key(*key) for key in pairer.waiting()} if self._held_sigma else set()
        expired = [k for k, (_, arrived) in self._held_sigma.items()
                   if now_ns - arrived >= wait_ns and pairing_now >= k[0] + decided
                   and k not in waiting]
        out: list[Rejection] = []
        for key in expired:
            del self._held_sigma[key]
            out.append(Rejection(key[0], 'unmatched_sigma',
                                 f"{self.sigma_topic}, stamp {key[0]} ns, frame "
                                 f"'{_frame_id(key)}': no accepted point with this stamp "
                                 f'and frame id within {SIGMA_WAIT_S:g} s (its point was '
                                 'rejected, or never came); dropped'))
        return self._count(out)

    def _count(self, rejections: list[Rejection]) -> list[Decision]:
        for r in rejections:
            self.rejections[r.reason] += 1
        return list(rejections)

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
                    key = _sigma_key(d.stamp_ns, d.frame_id)
                    held = self._held_sigma.get(key)
                    sigma = None if held is None else held[0]
                    try:
                        self.log.append(joint, point, sigma)  # on disk before it counts
                    except OSError as exc:
                        d = Rejection(d.stamp_ns, NOT_STORED, f'not written to {self.log.path}: '
                                      f'{exc}')
                    else:
                        self._store(joint, point)
                        self._stations.record(d.stamp_ns, *self.station)
                        if self.record_efforts:
                            self._log_efforts(d.stamp_ns)
                        if sigma is not None:
                            self._sigma[key] = sigma
                            del self._held_sigma[key]
            if isinstance(d, Rejection):
                self.rejections[d.reason] += 1
            out.append(d)
        return out

    def receive_efforts(self, stamp_ns: int, names: Sequence[str], efforts: np.ndarray) -> None:
        """Buffer one joint state's efforts (N m, N; in the order of ``names``) for the
        measurements it may belong to; ignored unless ``record_efforts``."""
        if not self.record_efforts:
            return
        sample = EffortBuffer.sample(stamp_ns, names, efforts)
        with self.lock:
            self._efforts.append(sample)

    def _log_efforts(self, stamp_ns: int) -> None:
        """Log the chain joints' efforts at an accepted measurement's stamp
        (:meth:`~kpi_calib_ros.ros.effort_buffer.EffortBuffer.at`); those not known there are
        not logged (the measurement is then refused when paired, for want of them)."""
        if stamp_ns in self._effort_stamps or not self._chain:
            return  # the other reflectors of one pose share its stamp
        names, values, missing = self._efforts.at(stamp_ns, self._chain)
        self.rejected_inputs += missing
        if names:
            self.log.append_inputs(stamp_ns, tuple(names), np.array(values))
            self._inputs += [InputSample(stamp_ns, n, v) for n, v in zip(names, values)]
            self._effort_stamps.add(stamp_ns)

    def _store(self, joint: JointSample, point: PointSample) -> None:
        self._measurements[(point.stamp_ns, point.frame_id)] = (joint, point)
        self._stored_frames[_sigma_key(point.stamp_ns, point.frame_id)] = point.frame_id

    # ------------------------------------------------------------------ data
    def measurements(self, joint_names: list[str], tracker_frame: str,
                     reflectors: Sequence[str] = ('',)) -> tuple[Measurements, PairingResult]:
        """Every accepted measurement in stamp order, ``q`` ordered as ``joint_names``,
        with the stated σ of those that have one (``sigma``, NaN rows elsewhere); with
        several ``reflectors`` (the cell's names), each row's reflector index."""
        with self.lock:
            pairs = [self._measurements[k] for k in sorted(self._measurements)]
            rejections = {k: v for k, v in sorted(self.rejections.items())
                          if k not in SIGMA_REASONS}
            point_sigma = {(k[0], _frame_id(k)): s for k, s in self._sigma.items()}
        if not pairs:
            raise DataError('no accepted measurement yet')
        pairing = stored_pairing(pairs, list(joint_names), tracker_frame, rejections)
        q, eta, stamps = pairing.q, pairing.eta, pairing.stamps_ns
        sigma = paired_sigma(pairing, point_sigma)
        if tuple(reflectors) == ('',):
            return Measurements(q=q, eta=eta, stamps_ns=stamps, sigma=sigma), pairing
        try:
            ref = pairing.reflector_indices(reflectors)
        except ValueError as exc:
            raise DataError(f'stored measurements: {exc}; reset the campaign after changing '
                            'the reflectors of the cell') from None
        return Measurements(q=q, eta=eta, stamps_ns=stamps, reflector=ref, sigma=sigma), pairing

    def counts(self) -> dict[str, int]:
        """Accepted, restored, received and rejected (total and per reason) counts."""
        with self.lock:
            counts = {'accepted': len(self._measurements), 'restored': self.restored,
                      'received.joint_states': self.received['joint_states'],
                      'received.points': self.received['points'],
                      'received.sigma': self.received['sigma'],
                      'received.temperatures': self.received['temperatures'],
                      'rejected_temperatures': self.rejected_temperatures,
                      'received.inputs': self.received['inputs'],
                      'rejected_inputs': self.rejected_inputs,
                      'stated_sigma': len(self._sigma),
                      'stations': len(self._stations),
                      'pending_sigma': len(self._held_sigma),
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
            self._sigma.clear()
            self._held_sigma.clear()
            self._stored_frames.clear()
            self.rejections.clear()
            self.rejected_temperatures = 0
            self.rejected_inputs = 0
            self.restored = 0
            self._temperatures.clear()
            self._inputs.clear()
            self._efforts.clear()
            self._effort_stamps.clear()
            self._stations.clear()
            self.log = self._new_log()
            if self.pairer is not None:
                self.pairer.reset()
            self._clock = self._point_clock = None
            self._epoch = 0
            return count, archive

    def receive_temperature(self, sample: TemperatureSample) -> str:
        """Keep one temperature reading, logged durably first (OSError: not kept); returns
        '' when kept, else why not: a reading outside ``temperature_range_c`` (or not
        finite) is a sensor fault, counted and neither logged nor kept (in a log it would
        reach every later identification)."""
        with self.lock:
            self.received['temperatures'] += 1
            if not plausible_temperature(sample.celsius, self.temperature_range_c):
                self.rejected_temperatures += 1
                low, high = self.temperature_range_c
                return (f"{self.temperature_topic}: reading {sample.celsius:g} °C of sensor "
                        f"'{sample.frame_id}' (stamp {sample.stamp_ns} ns) outside "
                        f'temperature.valid_range [{low:g}, {high:g}] °C: not used '
                        f'({self.rejected_temperatures} so far); check the sensor')
            self.log.append_temperature(sample)
            self._temperatures.append(sample)
            return ''

    def receive_inputs(self, samples: Sequence[InputSample]) -> str:
        """Keep the measured input readings of one message, logged durably first (OSError:
        not kept); returns '' when all are finite, else why not: a reading that is not
        finite is counted (``rejected_inputs``), and logged and kept as a reading without a
        value, so that a measurement it falls among is refused when paired
        (:func:`~kpi_calib_ros.core.measurement.covariates.input_covariates`), never given
        its neighbours' value (a payload may step there)."""
        with self.lock:
            self.received['inputs'] += 1
            bad = [s for s in samples if not np.isfinite(s.value)]
            by_stamp: dict[int, list[InputSample]] = {}
            for s in samples:
                by_stamp.setdefault(int(s.stamp_ns), []).append(s)
            for stamp, group in sorted(by_stamp.items()):
                self.log.append_inputs(stamp, tuple(s.name for s in group),
                                       np.array([s.value for s in group]))
                self._inputs += group
            if not bad:
                return ''
            self.rejected_inputs += len(bad)
            return (f'measured input {bad[0].name} = {bad[0].value!r} (stamp '
                    f'{bad[0].stamp_ns} ns) not finite: not used, and a measurement next to '
                    f'it is refused ({self.rejected_inputs} so far); check the sensor or the '
                    'message\'s names and counts')

    def inputs(self) -> list[InputSample]:
        """The measured input readings kept (this run's and the reloaded ones), a copy."""
        with self.lock:
            return list(self._inputs)

    def temperatures(self) -> list[TemperatureSample]:
        """The temperature readings kept (this run's and the reloaded ones), a copy."""
        with self.lock:
            return list(self._temperatures)

    def close(self) -> None:
        """Finalise the current log (idempotent)."""
        with self.lock:
            self.log.close()


def _sigma_key(stamp_ns: int, frame_id: str) -> tuple[int, str, str]:
    """A point's (stamp, tracker frame, reflector) as its σ is matched by (a leading '/'
    of the frame id does not count)."""
    return (int(stamp_ns), *split_frame(frame_id))


def _frame_id(key: tuple[int, str, str]) -> str:
    return key[1] + ('#' + key[2] if key[2] else '')


__all__ = ['MeasurementStore', 'NOT_STORED', 'REASONS', 'SIGMA_REASONS', 'SIGMA_WAIT_S']
