"""Pairing tracker points with the joint states around them into measurements.

A point becomes a measurement ``(q, eta)`` only if the robot demonstrably stood
still around its stamp. :class:`Pairer` is the one implementation of that rule;
the batch wrapper :func:`pair_measurements` (files) and the ROS node (live) both
use it.

Clock jumps: time may go backwards (sim time restarted, a bag looped or replayed
after a newer one, a driver restarted). A joint state stamped more than ``jump_ns``
before the newest one starts a new *epoch*: the pairer decides the points of the old
epoch with the joint states of the old epoch, clears the buffer and pairs what follows
against the new stream, counting the jump in ``clock_jumps``.

Memory: a joint state naming far more joints than the chain is rejected as
``oversized_joint_state`` before it is buffered; only the chain's columns are kept,
and the name-index cache is a small LRU, so hostile input cannot grow the pairer.

Several reflectors per pose: a point names its reflector in its frame id,
``'<tracker_frame>#<reflector name>'``
(:mod:`kpi_calib_ros.core.acquisition.reflector_frames`). What the pairer decides (a
measurement or a rejection per point) and a batch's result are the types of
:mod:`kpi_calib_ros.core.acquisition.outcomes`.

Units: stamps in integer nanoseconds, joint positions in rad (m for prismatic
joints), velocities in rad/s (m/s), points in metres.
"""
from __future__ import annotations

import bisect
import heapq
import logging
from collections import Counter, OrderedDict, deque
from dataclasses import dataclass
from typing import Any, Callable, Iterable, Mapping, Sequence

import numpy as np

from kpi_calib_ros.core.acquisition.outcomes import (
    Decision,
    PairedMeasurement,
    PairingResult,
    Rejection,
    stacked_rotations,
)
from kpi_calib_ros.core.acquisition.reflector_frames import split_frame, unknown_reflector
from kpi_calib_ros.core.acquisition.streams import JointSample, PointSample, frozen_array

__all__ = ['INDEX_CACHE_SIZE', 'EARLY_POINTS', 'NAMES_KEPT', 'MIMIC_TOL', 'Pairer',
           'pair_measurements']

INDEX_CACHE_SIZE = 16   # distinct joint-name lists remembered (LRU); drivers use one or two
EARLY_POINTS = 1000      # points kept waiting for a clock jump
NAMES_KEPT = 16         # names of a foreign joint state kept for the missing_joints message
# A mimic joint's reading may differ this much from what its master gives (rad or m): the
# readings of one driver agree to round-off, and a disagreement beyond it is a stage that
# did not follow (a slipped belt) or a description that is not the robot's.
MIMIC_TOL = 1e-4
_log = logging.getLogger(__name__)


@dataclass(frozen=True)
class _Entry:
    stamp_ns: int
    q: np.ndarray | None   # (n,) required joints in calibration order, NaN where missing;
    v: np.ndarray | None   # (n,) or None                None: names none of them
    missing: tuple[str, ...]
    names: tuple[str, ...]  # foreign joint states only (at most NAMES_KEPT), else ()
    mismatch: str = ''      # a mimic joint's reading off its relation: why, else ''


class Pairer:
    """Incremental pairing of tracker points with the joint states around them.

    Feed joint samples and points in any interleaving; a point is decided as soon
    as joint states reaching ``stamp + window_ns`` have arrived (or, on
    :meth:`poll`, once ``timeout_ns`` has passed beyond that without them). A
    point is accepted only if joint states exist within ±window strictly before and
    strictly after its stamp, all carry every joint in ``joint_names``, and the robot is still:
    max position spread < ``still_tol_rad`` and every |velocity| <
    ``still_vel_tol``. Every point ends as exactly one accepted measurement or
    one :class:`Rejection`; so does every joint sample with non-finite values.
    Joint states are expected in stamp order (as one driver publishes them); a
    sample arriving after the point it would belong to was decided does not reopen it.
    Joint samples that carry none of ``joint_names`` (e.g. a gripper driver
    publishing on the same topic) are ignored and counted in ``ignored_joint_samples``;
    a point surrounded only by such samples (a renamed or wrong robot) is rejected
    as ``missing_joints``.

    Parameters
    ----------
    joint_names : sequence of str, length n
        Calibrated joints, matched by name; message order and extra joints do not matter.
    tracker_frame : str
        Frame the points must be expressed in (a leading '/' is ignored).
    still_tol_rad : float
        Largest allowed position spread in the window (rad).
    still_vel_tol : float
        Largest allowed |velocity| in the window (rad/s), where velocities exist.
    window_ns : int
        Half-width of the window around a point's stamp (ns).
    timeout_ns : int
        How long past ``stamp + window_ns`` to wait for joint states (ns).
    buffer_ns : int
        Joint-state history kept, measured back from the newest joint stamp (ns);
        bounds memory and the tolerated lateness of points.
    jump_ns : int
        A joint state carrying calibrated joints stamped more than this before the
        newest joint stamp is a backwards clock jump and starts a new epoch (ns).
        Smaller disorder (several drivers on one topic) is merged in stamp order.
    max_names : int or None
        Joint states naming more joints than this are rejected as
        ``oversized_joint_state``; default ``4 * len(joint_names) + 64``.
    reflectors : sequence of str
        Reflector names a point may carry after ``#`` in its frame id
        (:mod:`~kpi_calib_ros.core.acquisition.reflector_frames`); ``('',)``, the default,
        is the single-reflector cell. Others are rejected as ``unknown_reflector``.
    derived : mapping, optional
        ``{joint: (coefficients (n,), offset)}``: joints a joint state may also carry whose
        value follows from ``joint_names``' (mimic joints: ``coefficients @ q + offset``).
        A joint state whose reading of one differs by more than ``derived_tol`` (rad or
        m) marks the points around it ``mimic_mismatch``; one without them is as good.
    joint_check : callable, optional
        ``q (n,) -> str``: why the mean readings of a still pose cannot be a pose of the
        robot ('' when they can; beyond its joint limits); a point paired with such a pose
        is rejected as ``outside_joint_limits`` with that reason.
    """

    def __init__(
        self,
        joint_names: Sequence[str],
        tracker_frame: str,
        still_tol_rad: float = 2e-4,
        still_vel_tol: float = 2e-3,
        window_ns: int = 200_000_000,
        timeout_ns: int = 1_000_000_000,
        buffer_ns: int = 10_000_000_000,
        jump_ns: int = 1_000_000_000,
        max_names: int | None = None,
        reflectors: Sequence[str] = ('',),
        derived: Mapping[str, tuple[np.ndarray, float]] | None = None,
        derived_tol: float = MIMIC_TOL,
        joint_check: Callable[[np.ndarray], str] | None = None,
    ) -> None:
        names = tuple(joint_names)
        if not names or len(set(names)) != len(names) or not all(
                isinstance(n, str) and n for n in names):
            raise ValueError(f'joint_names must be unique non-empty strings, got {names!r}')
        if not isinstance(tracker_frame, str) or not tracker_frame.strip('/'):
            raise ValueError(f'tracker_frame must be a frame name, got {tracker_frame!r}')
        if not still_tol_rad > 0 or not still_vel_tol > 0:
            raise ValueError('still_tol_rad and still_vel_tol must be positive')
        if window_ns <= 0 or timeout_ns < 0:
            raise ValueError('window_ns must be > 0 and timeout_ns >= 0')
        if buffer_ns <= 2 * window_ns:
            raise ValueError(f'buffer_ns must exceed 2 * window_ns = {2 * window_ns}')
        if jump_ns <= 0:
            raise ValueError(f'jump_ns must be > 0, got {jump_ns}')
        max_names = 4 * len(names) + 64 if max_names is None else int(max_names)
        if max_names < len(names):
            raise ValueError(f'max_names must be >= {len(names)} (the chain), got {max_names}')
        self.joint_names = names
        self.tracker_frame = tracker_frame
        self.still_tol_rad = float(still_tol_rad)
        self.still_vel_tol = float(still_vel_tol)
        self.window_ns = int(window_ns)
        self.timeout_ns = int(timeout_ns)
        self.buffer_ns = int(buffer_ns)
        self.jump_ns = int(jump_ns)
        self.max_names = max_names
        self._frame = tracker_frame.strip('/')
        self.reflectors = tuple(reflectors)
        self.derived = {str(k): (np.asarray(c, float).reshape(len(names)), float(o))
                        for k, (c, o) in (derived or {}).items()}
        if set(self.derived) & set(names) or not derived_tol > 0:
            raise ValueError('derived joints must not be among joint_names, and derived_tol '
                             'must be positive')
        self.derived_tol = float(derived_tol)
        # Why a still pose's readings (joint_names order) cannot be a pose of the robot, ''
        # when they can: beyond the URDF limits is a wrong joint order or unit, not a pose.
        self.joint_check = joint_check
        # Mimic mismatches logged: the first only (a swapped column mismatches at every joint
        # state, a thousand lines for one campaign); the rejections count them all.
        self._mismatches_logged = 0
        self._index_cache: OrderedDict[tuple[str, ...], tuple[np.ndarray, np.ndarray,
                                                              tuple[str, ...]]] = OrderedDict()
        self.reset()

    def reset(self) -> None:
        """Forget every buffered sample, pending point and count: a new campaign."""
        self.ignored_joint_samples = 0
        self.clock_jumps = 0
        self.epoch = 0
        self.rejections: Counter[str] = Counter()
        self._decided: list[Decision] = []
        self._sequence = 0
        self._new_epoch()

    def _new_epoch(self) -> None:
        self._stamps: list[int] = []
        self._entries: list[_Entry] = []
        self._first: int | None = None    # oldest joint stamp of the epoch
        self._latest: int | None = None   # newest joint stamp of the epoch
        self._pruned_before: int | None = None
        self._pending: list[tuple[int, int, PointSample]] = []
        self._early: list[tuple[int, PointSample]] = []  # (deadline, point) before the epoch
        self._seen: set[tuple[int, str]] = set()   # (stamp, reflector)
        self._latest_point: int | None = None
        self._seen_order: deque[tuple[int, str]] = deque()

    @property
    def latest_joint_ns(self) -> int | None:
        """Newest joint stamp of the current epoch (ns), None before any."""
        return self._latest

    @property
    def pending(self) -> int:
        """Points waiting for joint states."""
        return len(self._pending) + len(self._early)

    def waiting(self) -> set[tuple[int, str]]:
        """(stamp ns, frame id) of every point still waiting for joint states (undecided)."""
        return ({(stamp, point.frame_id) for stamp, _, point in self._pending}
                | {(point.stamp_ns, point.frame_id) for _, point in self._early})

    @property
    def index_cache_size(self) -> int:
        """Distinct joint-name lists currently cached (at most ``INDEX_CACHE_SIZE``)."""
        return len(self._index_cache)

    @property
    def buffered_joint_samples(self) -> int:
        """Joint samples held for pairing (bounded by the buffer duration)."""
        return len(self._entries)

    def add_joint_samples(self, samples: Iterable[JointSample]) -> None:
        """Add each of ``samples`` in turn, see :meth:`add_joint_sample`."""
        for sample in samples:
            self.add_joint_sample(sample)

    def add_joint_sample(self, sample: JointSample) -> None:
        """Buffer one joint state and decide the points it completes."""
        if len(sample.names) > self.max_names:
            self._reject(sample.stamp_ns, 'oversized_joint_state',
                         f'joint state names {len(sample.names)} joints, the chain has '
                         f'{len(self.joint_names)} (limit {self.max_names})')
            return
        columns, found, missing = self._indices(sample.names)
        if not len(found):
            self.ignored_joint_samples += 1
            if self._latest is None or sample.stamp_ns >= self._latest - self.jump_ns:
                # Kept (names only) to tell a renamed robot from a silent one.
                self._insert(_Entry(sample.stamp_ns, None, None, self.joint_names,
                                    sample.names[:NAMES_KEPT]))
            return
        q = np.full(len(self.joint_names), np.nan)
        q[found] = sample.positions[columns]
        v = None
        if sample.velocities is not None:
            v = np.zeros(len(self.joint_names))
            v[found] = sample.velocities[columns]
        bad = [self.joint_names[i] for i in found
               if not np.isfinite(q[i]) or (v is not None and not np.isfinite(v[i]))]
        if bad:
            self._reject(sample.stamp_ns, 'non_finite_joint_state',
                         f'joint state has non-finite position/velocity for {bad}')
            return
        if self._latest is not None and sample.stamp_ns < self._latest - self.jump_ns:
            self._restart_epoch(sample.stamp_ns, self._latest)
        mismatch = self._mimic_mismatch(sample, q) if self.derived and not missing else ''
        self._insert(_Entry(sample.stamp_ns, q, v, missing, (), mismatch))

    def _mimic_mismatch(self, sample: JointSample, q: np.ndarray) -> str:
        """Why a derived (mimic) joint's reading in ``sample`` is off its relation, or ''."""
        for i, name in enumerate(sample.names):
            relation = self.derived.get(name)
            if relation is None:
                continue
            expected = float(relation[0] @ q + relation[1])
            value = float(sample.positions[i])
            if not abs(value - expected) <= self.derived_tol:
                if not self._mismatches_logged:
                    _log.warning('joint state at %d ns: mimic joint %s reads %.6g, its master '
                                 'gives %.6g (further mismatches are counted with the '
                                 'rejected points, not logged)', sample.stamp_ns, name, value,
                                 expected)
                self._mismatches_logged += 1
                return (f"mimic joint '{name}' reads {value:.6g}, the URDF's relation to its "
                        f'master gives {expected:.6g} (tolerance {self.derived_tol:g}); the '
                        'stage did not follow its drive, or the URDF is not this robot')
        return ''

    def _restart_epoch(self, stamp_ns: int, latest_ns: int) -> None:
        """Start a new epoch: the joint clock went back from ``latest_ns`` to ``stamp_ns``.

        Close the epoch, pairing its points with its own joint states, and start a new one;
        points that were waiting for it join it.
        """
        back_s = (latest_ns - stamp_ns) * 1e-9
        note = (f' (joint-state clock jumped back {back_s:.3f} s after this point; '
                'no later joint state of its epoch)')
        while self._pending:
            self._decide(heapq.heappop(self._pending)[2], note)
        early = [point for _, point in self._early]
        self.clock_jumps += 1
        self.epoch += 1
        _log.warning('joint-state clock jumped back %.3f s (stamp %d ns after %d ns): '
                     'pairing epoch %d starts', back_s, stamp_ns, latest_ns, self.epoch)
        self._new_epoch()
        for point in early:
            self._queue(point)

    def _insert(self, entry: _Entry) -> None:
        at = bisect.bisect_right(self._stamps, entry.stamp_ns)
        self._stamps.insert(at, entry.stamp_ns)
        self._entries.insert(at, entry)
        if self._first is None or entry.stamp_ns < self._first:
            self._first = entry.stamp_ns
        if self._latest is None or entry.stamp_ns > self._latest:
            self._latest = entry.stamp_ns
            self._prune(entry.stamp_ns)
        self._decide_covered()

    def add_point(self, point: PointSample) -> None:
        """Queue one tracker point; obviously bad points are rejected at once."""
        stamp = point.stamp_ns
        if not np.all(np.isfinite(point.xyz)):
            self._reject(stamp, 'non_finite_point', f'point {point.xyz.tolist()} is not finite')
            return
        if point.rotation is not None and not np.all(np.isfinite(point.rotation)):
            self._reject(stamp, 'invalid_orientation', 'the pose\'s orientation is not a '
                         'finite unit quaternion [x, y, z, w]')
            return
        frame, reflector = split_frame(point.frame_id)
        if frame != self._frame:
            self._reject(stamp, 'wrong_frame',
                         f"point in frame '{point.frame_id}', expected '{self.tracker_frame}'")
            return
        if reflector not in self.reflectors:
            self._reject(stamp, 'unknown_reflector', unknown_reflector(
                point.frame_id, self.tracker_frame, self.reflectors))
            return
        # _first and _latest are set together, by the epoch's first joint state.
        if (self._first is not None and self._latest is not None
                and stamp < self._first - self.window_ns):
            # Older than the whole epoch: the point of a recording whose joint states
            # have not arrived yet (their clock jump is coming), or hopelessly late.
            # Wait for a jump as long as for any joint state, then decide it.
            self._early.append((self._latest + self.window_ns + self.timeout_ns, point))
            if len(self._early) > EARLY_POINTS:  # bounded: the oldest waiter is decided now
                deadline = min(d for d, _ in self._early)
                self._decide_early(lambda d: d == deadline)
            return
        self._queue(point)

    def _queue(self, point: PointSample) -> None:
        stamp = point.stamp_ns
        key = (stamp, split_frame(point.frame_id)[1])
        if key in self._seen:
            self._reject(stamp, 'duplicate_stamp', 'a point with this stamp was already received'
                         + (f' for reflector {key[1]!r}' if key[1] else ''))
            return
        self._seen.add(key)
        self._seen_order.append(key)
        if self._latest_point is None or stamp > self._latest_point:
            self._latest_point = stamp
        # Forget stamps beyond the buffer horizon: memory stays bounded.
        while self._seen_order and self._seen_order[0][0] < self._latest_point - self.buffer_ns:
            self._seen.discard(self._seen_order.popleft())
        heapq.heappush(self._pending, (stamp, self._sequence, point))
        self._sequence += 1
        self._decide_covered()

    def poll(self, now_ns: int) -> list[Decision]:
        """Decide points whose joint states are overdue at ``now_ns``; return the new decisions.

        ``now_ns`` is on the same clock as the stamps. Returns every decision made since the
        last call, oldest first.
        """
        while self._pending and now_ns >= self._pending[0][0] + self.window_ns + self.timeout_ns:
            self._decide(heapq.heappop(self._pending)[2])
        self._decide_early(lambda deadline: now_ns >= deadline)
        decided, self._decided = self._decided, []
        return decided

    def _decide_early(self, due: Callable[[int], bool]) -> None:
        keep = []
        for deadline, point in self._early:
            if due(deadline):
                self._decide(point, ' (point older than every joint state of the current '
                                    'epoch; no backwards clock jump followed)')
            else:
                keep.append((deadline, point))
        self._early = keep

    def flush(self) -> list[Decision]:
        """End of stream: decide every pending point with the joint states at hand."""
        while self._pending:
            self._decide(heapq.heappop(self._pending)[2])
        self._decide_early(lambda deadline: True)
        decided, self._decided = self._decided, []
        return decided

    def _indices(self, names: tuple[str, ...]
                 ) -> tuple[np.ndarray, np.ndarray, tuple[str, ...]]:
        cached = self._index_cache.get(names)
        if cached is not None:
            self._index_cache.move_to_end(names)
        else:
            position: dict[str, int] = {}
            for i, name in enumerate(names):
                position.setdefault(name, i)
            found = [i for i, n in enumerate(self.joint_names) if n in position]
            columns = np.array([position[self.joint_names[i]] for i in found], dtype=int)
            missing = tuple(n for n in self.joint_names if n not in position)
            cached = (columns, np.array(found, dtype=int), missing)
            self._index_cache[names] = cached
            if len(self._index_cache) > INDEX_CACHE_SIZE:  # names keep changing: evict
                self._index_cache.popitem(last=False)
        return cached

    def _prune(self, latest_ns: int) -> None:
        cutoff = latest_ns - self.buffer_ns
        k = bisect.bisect_left(self._stamps, cutoff)
        if k:
            del self._stamps[:k]
            del self._entries[:k]
            self._pruned_before = cutoff

    def _decide_covered(self) -> None:
        while (self._pending and self._latest is not None
               and self._latest >= self._pending[0][0] + self.window_ns):
            self._decide(heapq.heappop(self._pending)[2])

    def _reject(self, stamp_ns: int, reason: str, detail: str) -> None:
        self.rejections[reason] += 1
        self._decided.append(Rejection(stamp_ns, reason, detail))

    def _decide(self, point: PointSample, note: str = '') -> None:
        t, w = point.stamp_ns, self.window_ns
        lo = bisect.bisect_left(self._stamps, t - w)
        hi = bisect.bisect_right(self._stamps, t + w)
        window = [e for e in self._entries[lo:hi] if e.q is not None]
        if not window and any(e.q is None for e in self._entries[lo:hi]):
            seen = sorted({n for e in self._entries[lo:hi] for n in e.names})
            self._reject(t, 'missing_joints', f'joint states around the point name {seen}, '
                         f'none of {list(self.joint_names)}')
            return
        # Stillness must be seen on both sides of the stamp, not merely up to it.
        n_before = sum(e.stamp_ns < t for e in window)
        n_after = sum(e.stamp_ns > t for e in window)
        if not n_before or not n_after:
            detail = (f'{n_before} joint states in [stamp - {w} ns, stamp), '
                      f'{n_after} in (stamp, stamp + {w} ns]; both sides are needed')
            if self._pruned_before is not None and t - w < self._pruned_before:
                detail += f' (point older than the {self.buffer_ns} ns joint-state buffer)'
            detail += note
            self._reject(t, 'no_joint_state', detail)
            return
        missing = sorted({n for e in window for n in e.missing})
        if missing:
            self._reject(t, 'missing_joints', f'joint states around the point lack {missing}')
            return
        mismatch = next((e.mismatch for e in window if e.mismatch), '')
        if mismatch:
            self._reject(t, 'mimic_mismatch', mismatch)
            return
        q = np.stack([e.q for e in window if e.q is not None])  # window has no None q
        spread = q.max(axis=0) - q.min(axis=0)
        velocities = [e.v for e in window if e.v is not None]
        speed = np.max(np.abs(np.stack(velocities)), axis=0) if velocities else np.zeros(
            len(self.joint_names))
        if spread.max() >= self.still_tol_rad or speed.max() >= self.still_vel_tol:
            j = int(np.argmax(np.maximum(spread / self.still_tol_rad, speed / self.still_vel_tol)))
            self._reject(t, 'robot_moving',
                         f"'{self.joint_names[j]}' spread {spread[j]:.3g} rad "
                         f'(tol {self.still_tol_rad:g}), |velocity| up to {speed[j]:.3g} rad/s '
                         f'(tol {self.still_vel_tol:g}) within ±{w} ns')
            return
        # The mean about the first reading: a pose read alike every time is that reading to
        # the bit (a plain mean's rounding made 24 poses of three payloads count as 28).
        mean = q[0] + (q - q[0]).mean(axis=0)
        problem = self.joint_check(mean) if self.joint_check is not None else ''
        if problem:
            self._reject(t, 'outside_joint_limits', problem + '; a reading beyond the limits '
                         'is a wrong joint order, unit or zero, not a pose the robot can take')
            return
        self._decided.append(PairedMeasurement(
            stamp_ns=t, joint_names=self.joint_names, q=frozen_array(
                mean, (len(self.joint_names),), 'q'),
            eta=point.xyz, frame_id=point.frame_id, n_joint_samples=len(window),
            spread_rad=float(spread.max()), orientation=point.orientation))


def pair_measurements(
    joint_samples: Iterable[JointSample],
    point_samples: Iterable[PointSample],
    joint_names: Sequence[str],
    tracker_frame: str,
    **pairer_options: Any,
) -> PairingResult:
    """Pair recorded streams with :class:`Pairer` (keyword options are passed to it).

    The result does not depend on the order of the inputs: points are queued first
    and joint samples fed in stamp order, then the stream is flushed.

    Returns
    -------
    PairingResult
        ``q`` (N, n) rad in ``joint_names`` order, ``eta`` (N, 3) m, ``stamps_ns`` (N,).
    """
    pairer = Pairer(joint_names, tracker_frame, **pairer_options)
    for point in sorted(point_samples, key=lambda p: p.stamp_ns):
        pairer.add_point(point)
    pairer.add_joint_samples(sorted(joint_samples, key=lambda s: s.stamp_ns))
    decisions = pairer.flush()
    accepted = sorted((d for d in decisions if isinstance(d, PairedMeasurement)),
                      key=lambda m: m.stamp_ns)
    rejected = sorted((d for d in decisions if isinstance(d, Rejection)),
                      key=lambda r: (r.stamp_ns, r.reason, r.detail))
    n = len(pairer.joint_names)
    return PairingResult(
        joint_names=pairer.joint_names,
        tracker_frame=tracker_frame,
        q=np.array([m.q for m in accepted], dtype=float).reshape(-1, n),
        eta=np.array([m.eta for m in accepted], dtype=float).reshape(-1, 3),
        stamps_ns=np.array([m.stamp_ns for m in accepted], dtype=np.int64),
        rejections=dict(Counter(r.reason for r in rejected)),
        rejected=rejected,
        reflectors=tuple(m.reflector for m in accepted),
        rotations=stacked_rotations([m.rotation for m in accepted]),
    )
