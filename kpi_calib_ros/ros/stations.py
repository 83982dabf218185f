"""The tracker stations of the node's measurements: which station each one was measured
from, and whether the probe was remounted for it.

A campaign may move the tracker (``station`` / ``station_reflector_remounted``): the
:class:`~kpi_calib_ros.ros.measurement_store.MeasurementStore` records here the station of
every measurement it stores, and an identification takes the stations as recordings, each
with its own placement (:func:`kpi_calib_ros.ros.stored_measurements.station_measurements`).
A station keeps whether its probe was remounted; its name becomes part of parameter names
(:func:`check_station`).
"""
from __future__ import annotations

from collections import Counter

import numpy as np

from kpi_calib_ros.core.measurement.recordings import NAME_PATTERN, Recording


class Stations:
    """The stations measured so far, in the order first measured, and each stored
    measurement's station (by stamp). Not thread-safe: the store's lock guards it."""

    def __init__(self) -> None:
        self._remounted: dict[str, bool] = {}  # name -> probe remounted
        self._of: dict[int, str] = {}          # stamp ns -> station name
        # Measurements per station: the node asks after every tick (a sequential step due).
        self._counts: Counter[str] = Counter()

    def __len__(self) -> int:
        return len(self._remounted)

    def record(self, stamp_ns: int, name: str, reflector_remounted: bool) -> None:
        """The measurement stamped ``stamp_ns`` was measured from station ``name`` (the first
        station recorded for a stamp, and the first remount stated for a station, stay)."""
        self._remounted.setdefault(name, reflector_remounted)
        if int(stamp_ns) not in self._of:
            self._of[int(stamp_ns)] = name
            self._counts[name] += 1

    def remounted(self, name: str) -> bool | None:
        """Whether station ``name`` was measured with its probe remounted (None: not
        measured)."""
        return self._remounted.get(name)

    def count(self, name: str) -> int:
        """The measurements recorded from station ``name``."""
        return self._counts[name]

    def conflict(self, name: str, reflector_remounted: bool) -> str:
        """Why station ``name`` cannot be measured with ``reflector_remounted`` ('' : it can):
        a station already measured keeps whether its probe was remounted."""
        known = self._remounted.get(name)
        if known is None or known == bool(reflector_remounted):
            return ''
        return (f'station {name!r} was measured with station_reflector_remounted '
                f'{str(known).lower()}: a station keeps it; name a new station for a '
                'new set-up of the probe')

    def recordings(self, stamps_ns: np.ndarray, current: str
                   ) -> tuple[list[Recording], np.ndarray]:
        """The stations of the measurements stamped ``stamps_ns`` (N,) (``current`` for a
        stamp not recorded), as recordings in the order first measured (the probe's remount
        as each states it), and each row's index into them."""
        names = [self._of.get(int(t), current) for t in np.asarray(stamps_ns).ravel()]
        order = [n for n in self._remounted if n in set(names)]
        order += [n for n in dict.fromkeys(names) if n not in order]
        recordings = [Recording(n, self._remounted.get(n, False)) for n in order]
        index = np.array([order.index(n) for n in names], dtype=int)
        return recordings, index

    def clear(self) -> None:
        """Forget every station and measurement recorded."""
        self._remounted.clear()
        self._of.clear()
        self._counts.clear()


def check_station(name: str) -> str:
    """``name`` if it can name a station (it becomes part of parameter names).

    Raises
    ------
    ValueError
        It cannot: says which characters it may hold.
    """
    if not isinstance(name, str) or not NAME_PATTERN.match(name):
        raise ValueError(f'station name {name!r} must start with a letter and hold letters, '
                         'digits, _ or - only')
    return name


__all__ = ['Stations', 'check_station']
