"""Covariates: per-row causes beside the joint state (the arm's temperature), paired by time.

A measurement row gets the value of a slowly changing quantity at its stamp, as joint
states are paired (:mod:`kpi_calib_ros.core.acquisition.pairing`), and keeps it in
``Measurements.covariates`` under a stable name:

``temperature.<frame_id>``
    A temperature sensor's reading (``sensor_msgs/Temperature``, °C) at the row's stamp.
``delta_temperature``
    ΔT, K: the mean of the cell's configured sensors minus the cell's reference temperature
    (default 20 °C, the reference temperature of dimensional metrology, ISO 1). The
    thermal effects (:mod:`kpi_calib_ros.core.effects.registry`) read this one; at ΔT = 0 they
    vanish, so the geometric parameters are those of the arm at the reference temperature and a
    prediction without covariates (a design, the KPI, fresh poses) is one at it.
``delta_temperature.<frame_id>``
    ΔT of one configured sensor alone, K (its reading minus the reference). A thermal effect
    of a joint the cell assigns to that sensor reads this one in place of the mean (the cell's
    ``temperature.sensors`` mapping; :func:`kpi_calib_ros.core.effects.registry.bind_effect`):
    the upper arm and the forearm warm differently, and a link grows with its own temperature.

A reading is only used when it is plausible: finite and inside the cell's valid range
(``temperature.valid_range``, default :data:`TEMPERATURE_RANGE_C`, -50 to 150 °C; no range
reaches below absolute zero or above :data:`TEMPERATURE_LIMIT_C`). :func:`plausible_readings`
sets the others aside, counted: a broken sensor's 1e12 °C would otherwise become a ΔT that
decides the thermal effects alone.

Measured inputs beyond temperature (an inclinometer's tilt ``tilt.<sensor>.x``, a payload
mass ``payload.mass`` from the cell controller, measured joint torques ``effort.<joint>``,
any named quantity) arrive as :class:`InputSample` (stamp, covariate name, value in SI
units) and are paired the same way (:func:`input_covariates`): interpolated at each row's
stamp within ``max_gap_ns``, a reading that is not finite set aside and counted, a row with no
value of an input refused with the reason, never filled in. A payload (``payload.*``) does not
drift, it steps: a controller reports it when it changes, and a row between a 0 kg and a
5 kg report carries one of them, never 3.4 kg. It is held (:func:`hold`): each row takes the
last reading at or before its stamp, whatever the gap (a report stands until the next), none
before the first.

Only differences of temperature enter a model, so °C and K are interchangeable for ΔT; the
raw readings stay in °C as the message carries them. A stamp is given the value linearly
interpolated between the samples on either side. Temperature changes slowly, yet a value is
never made up: a stamp whose neighbouring samples are more than ``max_gap_ns`` apart, or
that lies beyond the first or last sample by more than ``max_gap_ns``, gets none (NaN) and
its row is refused with the reason (within ``max_gap_ns`` beyond an end, the end value is
held).
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Iterable, Mapping, Sequence

import numpy as np

from kpi_calib_ros.core.measurement.data import Measurements

__all__ = [
    'TEMPERATURE_PREFIX', 'DELTA_TEMPERATURE', 'REFERENCE_TEMPERATURE_C', 'DEFAULT_MAX_GAP_NS',
    'ABSOLUTE_ZERO_C', 'TEMPERATURE_LIMIT_C', 'TEMPERATURE_RANGE_C',
    'TemperatureSample', 'covariate_name', 'delta_temperature_name', 'interpolate',
    'plausible_readings', 'plausible_temperature', 'range_text',
    'temperature_covariates', 'with_covariates', 'shift_temperature',
    'InputSample', 'DEFAULT_INPUT_MAX_GAP_NS', 'EFFORT_PREFIX', 'effort_name', 'input_covariates',
    'STEP_PREFIX', 'hold', 'steps',
    'covariate_unit', 'measured_covariates',
]

TEMPERATURE_PREFIX = 'temperature.'
DELTA_TEMPERATURE = 'delta_temperature'
REFERENCE_TEMPERATURE_C = 20.0  # ISO 1: the reference temperature of length measurement
DEFAULT_MAX_GAP_NS = 120 * 10**9  # a temperature sample at least every 2 minutes
ABSOLUTE_ZERO_C = -273.15
# What a robot cell's arm may read: a cold hall in winter to a hot drive housing, with
# margin. A reading outside is a fault of the sensor or its driver, never a temperature.
TEMPERATURE_RANGE_C = (-50.0, 150.0)
# No cell's range reaches above: far beyond what any arm's grease, cables or encoders stand.
TEMPERATURE_LIMIT_C = 1000.0


# A measured input is bridged over at most this gap between its samples (and beyond the
# first/last): an inclinometer or a controller publishes at 1 Hz or faster.
DEFAULT_INPUT_MAX_GAP_NS = 10 * 10**9
EFFORT_PREFIX = 'effort.'
# Covariates that step rather than drift: held from a reading to the next (:func:`hold`).
STEP_PREFIX = 'payload.'


@dataclass(frozen=True)
class InputSample:
    """One reading of a measured input: header stamp (ns), covariate name, value (SI)."""

    stamp_ns: int
    name: str
    value: float


def effort_name(joint: str) -> str:
    """Return the covariate name of a joint's measured torque: ``effort.<joint>`` (N m)."""
    return EFFORT_PREFIX + joint


def input_covariates(stamps_ns: np.ndarray, samples: Iterable[InputSample],
                     max_gap_ns: int = DEFAULT_INPUT_MAX_GAP_NS
                     ) -> tuple[dict[str, np.ndarray], list[InputSample]]:
    """Return the covariates (N,) of rows stamped ``stamps_ns`` from measured input readings.

    One covariate per name among ``samples``, :func:`interpolate` d at the stamps (NaN where
    no reading lies within ``max_gap_ns``); readings that are not finite are never used and
    returned as the second value (in the order given). A reading that is not finite is
    still a reading the sensor made: a row it falls among (between the two readings the row
    would be interpolated from, or at its stamp) gets NaN, never a value bridged over it.
    An input may step (a payload picked up between two readings): a NaN 5 kg reading
    between two 0 kg ones gave its row 0 kg, used in the fit, with only a count warned.
    """
    by_name: dict[str, list[tuple[int, float]]] = {}
    unknown: dict[str, list[int]] = {}
    rejected: list[InputSample] = []
    for s in samples:
        if not np.isfinite(s.value):
            rejected.append(s)
            unknown.setdefault(s.name, []).append(int(s.stamp_ns))
            continue
        by_name.setdefault(s.name, []).append((int(s.stamp_ns), float(s.value)))
    stamps = np.asarray(stamps_ns, dtype=np.int64).reshape(-1)
    out = {}
    for name, readings in sorted(by_name.items()):
        t = np.array([r[0] for r in readings], dtype=np.int64)
        v = np.array([r[1] for r in readings], dtype=float)
        voids = np.array(unknown.get(name, ()), dtype=np.int64)
        out[name] = (hold(stamps, t, v, voids) if steps(name)
                     else interpolate(stamps, t, v, max_gap_ns, voids))
    return out, rejected


def steps(name: str) -> bool:
    """Return whether covariate ``name`` steps rather than drifts (a payload)."""
    return name.startswith(STEP_PREFIX)


def _readings(sample_stamps_ns: np.ndarray, values: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Return the finite readings by stamp, sorted, those of one stamp averaged."""
    t = np.asarray(sample_stamps_ns, dtype=np.int64).reshape(-1)
    v = np.asarray(values, float).reshape(-1)
    good = np.isfinite(v)
    t, v = t[good], v[good]
    if not len(t):
        return t, v
    t, inverse = np.unique(t, return_inverse=True)
    return t, np.bincount(inverse, weights=v) / np.bincount(inverse)


def hold(stamps_ns: np.ndarray, sample_stamps_ns: np.ndarray, values: np.ndarray,
         unknown_ns: np.ndarray | None = None) -> np.ndarray:
    """Return the values (N,) of a quantity that steps at ``stamps_ns`` (N,).

    The last reading at or before each stamp (readings of one stamp averaged), NaN before the
    first and where a reading without a value (``unknown_ns``) lies between that reading and
    the stamp. Interpolated, a payload reported at 0, 2.5 and 5 kg when it changed gave rows
    0.94, 3.44 and 3.13 kg.
    """
    stamps = np.asarray(stamps_ns, dtype=np.int64).reshape(-1)
    out = np.full(len(stamps), np.nan)
    t, v = _readings(sample_stamps_ns, values)
    if not len(t):
        return out
    last = np.searchsorted(t, stamps, side='right') - 1
    known = last >= 0
    out[known] = v[last[known]]
    if unknown_ns is not None and len(unknown_ns):
        u = np.sort(np.asarray(unknown_ns, dtype=np.int64).reshape(-1))
        since = t[np.clip(last, 0, len(t) - 1)]
        crossed = known & (np.searchsorted(u, stamps, side='right')
                           > np.searchsorted(u, since, side='left'))
        out[crossed] = np.nan
    return out


# The unit of a covariate, from its name (measured inputs are stored in SI units).
_UNITS = ((TEMPERATURE_PREFIX, '°C'), (DELTA_TEMPERATURE, 'K'), ('tilt.', 'rad'),
          ('payload.mass', 'kg'), ('payload.com.', 'm'), (EFFORT_PREFIX, 'N m'))


def covariate_unit(name: str) -> str:
    """Return the unit of covariate ``name`` by its kind ('' for a quantity of its own)."""
    return next((unit for prefix, unit in _UNITS if name.startswith(prefix)), '')


def measured_covariates(covariates: Mapping[str, np.ndarray] | None
                        ) -> dict[str, tuple[np.ndarray, str]]:
    """Return the measured covariates of rows as (values, unit).

    Every one but the derived ΔT (``delta_temperature``, the temperature shifted) and
    measured torques (``effort.*``, the rows' torques themselves).
    """
    return {name: (np.asarray(values, float), covariate_unit(name))
            for name, values in (covariates or {}).items()
            if not name.startswith(DELTA_TEMPERATURE) and not name.startswith(EFFORT_PREFIX)}


@dataclass(frozen=True)
class TemperatureSample:
    """One temperature reading: header stamp (ns), the sensor's frame id, °C."""

    stamp_ns: int
    frame_id: str
    celsius: float


def covariate_name(frame_id: str) -> str:
    """Return the covariate name of a temperature sensor: ``temperature.<frame_id>``."""
    return TEMPERATURE_PREFIX + frame_id


def delta_temperature_name(frame_id: str) -> str:
    """Return the covariate name of one sensor's ΔT: ``delta_temperature.<frame_id>``."""
    return f'{DELTA_TEMPERATURE}.{frame_id}'


def plausible_temperature(celsius: float,
                          valid_range_c: tuple[float, float] = TEMPERATURE_RANGE_C) -> bool:
    """Return whether a reading (°C) is finite and inside ``valid_range_c`` (low, high)."""
    low, high = valid_range_c
    return bool(np.isfinite(celsius) and low <= celsius <= high)


def plausible_readings(samples: Iterable[TemperatureSample],
                       valid_range_c: tuple[float, float] = TEMPERATURE_RANGE_C
                       ) -> tuple[list[TemperatureSample], list[TemperatureSample]]:
    """Split readings into the plausible ones and the others.

    The others (:func:`plausible_temperature` false) are never used: each would be a ΔT no
    arm can have.
    """
    kept: list[TemperatureSample] = []
    rejected: list[TemperatureSample] = []
    for s in samples:
        (kept if plausible_temperature(s.celsius, valid_range_c) else rejected).append(s)
    return kept, rejected


def range_text(rejected: Sequence[TemperatureSample],
               valid_range_c: tuple[float, float] = TEMPERATURE_RANGE_C) -> str:
    """One line on readings set aside: their count, the range and the first one."""
    first = rejected[0]
    return (f'{len(rejected)} temperature reading(s) outside temperature.valid_range '
            f'[{valid_range_c[0]:g}, {valid_range_c[1]:g}] °C not used (first: '
            f'{first.celsius:g} °C from sensor {first.frame_id!r} at stamp {first.stamp_ns} '
            'ns): a fault of the sensor or its driver; the points are paired with the '
            'plausible readings around them')


def interpolate(stamps_ns: np.ndarray, sample_stamps_ns: np.ndarray, values: np.ndarray,
                max_gap_ns: int = DEFAULT_MAX_GAP_NS,
                unknown_ns: np.ndarray | None = None) -> np.ndarray:
    """Values (N,) of a slowly varying signal at ``stamps_ns`` (N,), NaN where unknown.

    Linear between the samples around a stamp when they are at most ``max_gap_ns`` apart;
    the first/last value within ``max_gap_ns`` before/after the samples; NaN elsewhere
    (a gap, outside the recording, no samples). Samples need not be sorted; samples of one
    stamp are averaged. ``unknown_ns``: stamps of readings without a value (not finite):
    a stamp whose value would come across one of them (between its two samples, between it
    and the first or last sample, or at it) is NaN.
    """
    stamps = np.asarray(stamps_ns, dtype=np.int64).reshape(-1)
    out = np.full(len(stamps), np.nan)
    t, v = _readings(sample_stamps_ns, values)
    if not len(t):
        return out
    # offsets from the first sample keep the arithmetic exact in float64 (ns since 1970
    # exceed its integer precision)
    x, xs = (stamps - t[0]).astype(float), (t - t[0]).astype(float)
    right = np.searchsorted(t, stamps, side='left')
    inside = (right > 0) & (right < len(t))
    exact = np.isin(stamps, t)
    gap = np.full(len(stamps), np.inf)
    gap[inside] = (t[right[inside]] - t[right[inside] - 1]).astype(float)
    ok = exact | (inside & (gap <= max_gap_ns))
    out[ok] = np.interp(x[ok], xs, v)
    before = (stamps < t[0]) & (t[0] - stamps <= max_gap_ns)
    after = (stamps > t[-1]) & (stamps - t[-1] <= max_gap_ns)
    out[before], out[after] = v[0], v[-1]
    if unknown_ns is not None and len(unknown_ns):
        u = np.sort(np.asarray(unknown_ns, dtype=np.int64).reshape(-1))
        # The span each stamp's value comes from: its bracketing samples, or the stamp and
        # the end sample it takes; an unknown reading inside it (ends included) voids it.
        low = np.where(exact, stamps, np.where(
            before, stamps, np.where(after, t[-1], t[np.clip(right - 1, 0, len(t) - 1)])))
        high = np.where(exact, stamps, np.where(
            before, t[0], np.where(after, stamps, t[np.clip(right, 0, len(t) - 1)])))
        crossed = np.searchsorted(u, high, side='right') > np.searchsorted(u, low, side='left')
        out[crossed] = np.nan
    return out


def temperature_covariates(stamps_ns: np.ndarray, samples: Iterable[TemperatureSample],
                           sensors: Sequence[str] = (),
                           reference_c: float = REFERENCE_TEMPERATURE_C,
                           max_gap_ns: int = DEFAULT_MAX_GAP_NS) -> dict[str, np.ndarray]:
    """Return the covariates (N,) of rows stamped ``stamps_ns``.

    Every sensor's ``temperature.<frame_id>`` (°C); ``delta_temperature`` (K), the mean of
    ``sensors`` (frame ids; empty: every sensor recorded) minus ``reference_c``; and for each
    of those sensors its own ``delta_temperature.<frame_id>`` (K), its reading minus
    ``reference_c``. NaN where a value is unknown (:func:`interpolate`); the mean is NaN
    where any of its sensors is.

    Raises
    ------
    ValueError
        A sensor in ``sensors`` never published, or ``reference_c`` not finite.
    """
    if not np.isfinite(reference_c):
        raise ValueError(f'reference temperature must be finite (°C), got {reference_c}')
    by_sensor: dict[str, list[tuple[int, float]]] = {}
    for s in samples:
        by_sensor.setdefault(s.frame_id, []).append((int(s.stamp_ns), float(s.celsius)))
    missing = [f for f in sensors if f not in by_sensor]
    if missing:
        raise ValueError(f'temperature sensors {missing} published nothing; recorded: '
                         f'{sorted(by_sensor)}')
    stamps = np.asarray(stamps_ns, dtype=np.int64).reshape(-1)
    out: dict[str, np.ndarray] = {}
    for frame_id, readings in sorted(by_sensor.items()):
        arr = np.array(readings, dtype=object)
        out[covariate_name(frame_id)] = interpolate(
            stamps, arr[:, 0].astype(np.int64), arr[:, 1].astype(float), max_gap_ns)
    used = list(sensors) or sorted(by_sensor)
    if used:
        out[DELTA_TEMPERATURE] = (np.mean([out[covariate_name(f)] for f in used], axis=0)
                                  - reference_c)
    for frame_id in used:
        out[delta_temperature_name(frame_id)] = out[covariate_name(frame_id)] - reference_c
    return out


def with_covariates(data: Measurements, covariates: Mapping[str, np.ndarray],
                    required: Sequence[str] = (DELTA_TEMPERATURE,),
                    what: str = 'temperature'
                    ) -> tuple[Measurements, list[tuple[int, str]]]:
    """Add ``covariates`` (N,) to ``data`` and remove rows that lack a required one.

    A row is removed when it has no finite value of every ``required`` covariate; also returns
    [(row index in ``data``, reason)] of those rows (``what`` names the quantity in it).

    Raises
    ------
    ValueError
        A covariate of another length than ``data``.
    """
    n = len(data)
    merged = dict(data.covariates or {})
    for name, values in covariates.items():
        values = np.asarray(values, float).reshape(-1)
        if values.shape != (n,):
            raise ValueError(f'covariate {name!r} must hold {n} values, one per row, got '
                             f'{values.shape}')
        merged[name] = values
    keep = np.ones(n, bool)
    lacking = np.full(n, '', dtype=object)
    for name in required:
        if name in merged:
            finite = np.isfinite(merged[name])
            lacking[~finite & keep] = name
            keep &= finite
    refused = [(int(i), f'no {what} at its stamp ({lacking[i]}: outside its recording, '
                'in a gap longer than the tolerance, or next to a reading without a value)')
               for i in np.flatnonzero(~keep)]
    full = dataclasses.replace(data, covariates=merged)
    return (full if keep.all() else full.subset(keep)), refused


def shift_temperature(stamps_ns: np.ndarray, start_c: float, rise_k: float,
                      hours: float, start_ns: int | None = None) -> np.ndarray:
    """Return a shift's warm-up, °C at ``stamps_ns``.

    From ``start_c`` rising by ``rise_k`` towards a plateau, ``start_c + rise_k (1 − e^{−t/τ})``
    with τ = ``hours``/3 (95 % of the rise reached after ``hours``); ``t`` from ``start_ns``
    (default the first stamp).
    """
    stamps = np.asarray(stamps_ns, dtype=np.int64)
    t0 = int(stamps.min()) if start_ns is None else int(start_ns)
    t_h = (stamps - t0).astype(float) / 3.6e12
    return start_c + rise_k * (1.0 - np.exp(-3.0 * t_h / hours))
