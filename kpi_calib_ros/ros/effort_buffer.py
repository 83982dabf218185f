"""The joint states' efforts the node keeps for its measurements (measured torques).

With ``compliance.torque_source: measured`` a measurement's torques are the efforts its joint
states carried. Joint states come far more often than points, so the
:class:`~kpi_calib_ros.ros.measurement_store.MeasurementStore` buffers their efforts here
and, for each accepted measurement, reads the chain joints' efforts interpolated at its
stamp (:meth:`EffortBuffer.at`) to log them with it, one record per measurement.
"""
from __future__ import annotations

from collections import deque
from typing import Sequence

import numpy as np

from kpi_calib_ros.core.measurement.covariates import effort_name, interpolate

# Joint states' efforts kept for the measurements they belong to: 20 s at 500 Hz (the pairer
# decides a point within seconds of its stamp); an effort is bridged over at most 1 s.
EFFORT_BUFFER_SAMPLES = 10_000
EFFORT_BUFFER_S = 20.0
EFFORT_MAX_GAP_NS = 10**9


class EffortBuffer:
    """The efforts of the last :data:`EFFORT_BUFFER_SAMPLES` joint states (not thread-safe:
    the store's lock guards it)."""

    def __init__(self) -> None:
        # (stamp ns, names, efforts) of the recent joint states
        self._samples: deque[tuple[int, tuple[str, ...], np.ndarray]] = deque(
            maxlen=EFFORT_BUFFER_SAMPLES)

    @staticmethod
    def sample(stamp_ns: int, names: Sequence[str], efforts: np.ndarray
               ) -> tuple[int, tuple[str, ...], np.ndarray]:
        """One joint state's efforts (N m, N; in the order of ``names``) as the buffer keeps
        them: all NaN when their count differs from the names'."""
        efforts = np.asarray(efforts, float).reshape(-1)
        if efforts.shape != (len(names),):
            efforts = np.full(len(names), np.nan)  # counts differ: no effort of this state
        return int(stamp_ns), tuple(names), efforts

    def append(self, sample: tuple[int, tuple[str, ...], np.ndarray]) -> None:
        """Keep one :meth:`sample` (the oldest goes when the buffer is full)."""
        self._samples.append(sample)

    def at(self, stamp_ns: int, chain: Sequence[str]) -> tuple[list[str], list[float], int]:
        """The ``chain`` joints' efforts at ``stamp_ns``, interpolated in the buffer within
        :data:`EFFORT_MAX_GAP_NS`: their names (``effort.<joint>``) and values, and the number
        of joints without one there (neither named nor valued)."""
        names, values, missing = [], [], 0
        for joint in chain:
            rows = [(t, e[n.index(joint)]) for t, n, e in self._samples if joint in n]
            value = float('nan')
            if rows:
                t = np.array([r[0] for r in rows], dtype=np.int64)
                v = np.array([r[1] for r in rows], dtype=float)
                value = float(interpolate(np.array([stamp_ns]), t, v, EFFORT_MAX_GAP_NS)[0])
            if np.isfinite(value):
                names.append(effort_name(joint))
                values.append(value)
            else:
                missing += 1
        return names, values, missing

    def clear(self) -> None:
        """Forget every effort kept."""
        self._samples.clear()


__all__ = ['EFFORT_BUFFER_S', 'EFFORT_BUFFER_SAMPLES', 'EFFORT_MAX_GAP_NS', 'EffortBuffer']
