"""Several recordings (tracker set-ups) of one robot in one identification.

A robot measured from several tracker stations, or with its probe remounted between
recordings, is one robot in several placements. The robot's parameters are shared; each
recording after the first has its own base pose in the tracker frame (6 DoF, a station
metres and tens of degrees away) and, when the probe was remounted, its own reflector
offsets:

* ``recording.<name>.base.{x,y,z,roll,pitch,yaw}`` -- the base frame in that recording's
  tracker frame (full values, URDF roll-pitch-yaw convention, as ``base.*``);
* ``recording.<name>.<reflector prefix>.{x,y,z}`` (``recording.<name>.reflector.x`` for one
  reflector) -- its reflector centres in the tip frame, only when ``reflector_remounted``;
  with a tracked body whose orientation the cell identifies also
  ``recording.<name>.<prefix>.{rx,ry,rz}``, that recording's turn of the stated orientation.

The first recording keeps ``base.*`` and ``reflector.*``: with one recording the model is
the one of a single bag, parameter for parameter. Rows say which recording they belong to
through the one-hot covariate ``recording.<name>`` (1 on its rows, 0 elsewhere), so the
model's CasADi functions select that recording's placement row by row, exactly (a selection,
not a linearisation). Everything that takes no covariates (the design, the KPI at the
working poses, fresh poses) is in the first recording's tracker frame.
"""
from __future__ import annotations

import difflib
import math
import re
from dataclasses import dataclass, field
from typing import Any, Mapping, Sequence

import numpy as np

from kpi_calib_ros.core.errors import ConfigError
from kpi_calib_ros.core.measurement.data import Measurements
from kpi_calib_ros.core.measurement.payload import (
    PAYLOAD_COM,
    PAYLOAD_COM_LIMIT_M,
    PAYLOAD_MASS,
    PAYLOAD_MASS_LIMIT_KG,
    payload_name_error,
)
from kpi_calib_ros.core.measurement.pose import orientation_names
from kpi_calib_ros.core.measurement.tracker import MeasurementModel
from kpi_calib_ros.core.measurement.weighting import noise_weights, row_torques, weighted_rows
from kpi_calib_ros.core.model.kinematics import rpy_matrix
from kpi_calib_ros.core.model.parameters import (
    BASE_COMPONENTS,
    RECORDING_PREFIX,
    ParameterSet,
    recording_names,
    reflector_prefixes,
)

__all__ = [
    'PREFIX', 'NAME_PATTERN', 'Recording', 'covariate', 'base_names', 'reflector_names',
    'recording_parameters', 'recording_names', 'placed_model', 'combine', 'concatenate',
    'row_recording',
    'row_covariates', 'Contribution', 'contributions', 'placement_names', 'to_first_frame',
    'as_first', 'COVARIATE_NAME', 'stated_conditions', 'unread_covariates',
    'repeated_rows',
]

PREFIX = RECORDING_PREFIX
# A recording's name is part of parameter names and YAML keys: letters, digits, _ and -.
NAME_PATTERN = re.compile(r'^[A-Za-z][A-Za-z0-9_\-]*$')


# A covariate name as effects read them: dotted words (payload.mass, temperature.link_2).
COVARIATE_NAME = re.compile(r'^[A-Za-z_][A-Za-z0-9_]*(\.[A-Za-z0-9_\-]+)*$')


def stated_conditions(values: Any, key: str, where: str = '') -> dict[str, float]:
    """Return a recording's constant covariates, checked, as floats.

    ``values`` as stated, {name: number}: a manifest's ``covariates``, a calibration's
    ``recordings[i].covariates``, ``validate --covariate``.

    Raises
    ------
    ConfigError
        Not a mapping, a name that is no covariate name (or a recording's own one-hot, or a
        ``payload.`` name that is none of the payload's), a value that is not a finite number,
        a payload mass outside 0 to 5000 kg or a centre beyond 2 m per axis; the key is
        ``key`` (``key.<name>`` for a value), the message starts with ``where``.
    """
    if not isinstance(values, dict):
        raise ConfigError(key, f'{where}must be a mapping {{name: number}}, e.g. '
                          '{payload.mass: 5.0}')
    out = {}
    for name, value in values.items():
        if not isinstance(name, str) or not COVARIATE_NAME.match(name) \
                or name.startswith(PREFIX):
            raise ConfigError(key, f'{where}{name!r} is no covariate name (dotted words, e.g. '
                              "payload.mass; recording.* is the recordings' own)")
        misspelled = payload_name_error(name)
        if misspelled:
            raise ConfigError(f'{key}.{name}', f'{where}{misspelled}')
        if isinstance(value, bool) or not isinstance(value, (int, float)) \
                or not math.isfinite(value):
            raise ConfigError(f'{key}.{name}', f'{where}must be a finite number (in the '
                              f"covariate's unit, e.g. kg), got {value!r}")
        if name == PAYLOAD_MASS and not 0.0 <= value <= PAYLOAD_MASS_LIMIT_KG:
            raise ConfigError(f'{key}.{name}', f'{where}{value!r} kg: a payload is 0 to '
                              f'{PAYLOAD_MASS_LIMIT_KG:g} kg (SI kg)')
        if name in PAYLOAD_COM and not abs(value) <= PAYLOAD_COM_LIMIT_M:
            raise ConfigError(f'{key}.{name}', f'{where}{value!r} m: a payload centre within '
                              f'{PAYLOAD_COM_LIMIT_M:g} m of the tip frame (SI metres: 50 mm is '
                              '0.05)')
        out[name] = float(value)
    return out


@dataclass(frozen=True)
class Recording:
    """One recording of a campaign over several set-ups.

    ``name`` (from the bag's file stem or the manifest), ``reflector_remounted``: the probe
    was mounted again (its own reflector offsets), ``covariates``: constant per-row inputs of
    every row of this recording ({covariate name: value}, e.g. ``payload.mass: 5.0``).
    """

    name: str
    reflector_remounted: bool = False
    covariates: Mapping[str, float] = field(default_factory=dict)

    def __post_init__(self) -> None:
        """Check the name (it becomes part of parameter names)."""
        if not isinstance(self.name, str) or not NAME_PATTERN.match(self.name):
            raise ValueError(f'recording name {self.name!r} must start with a letter and hold '
                             'letters, digits, _ or - only')


def repeated_rows(parts: Sequence[Measurements]) -> list[tuple[int, int, int]]:
    """Rows one recording repeats of an earlier one, bit for bit (joint values and point).

    Returns [(earlier, later, count)] of recording indices into ``parts`` with the count of
    the later one's rows found in the earlier one. Two measurements of a tracker never agree
    to the bit: a repeated row is the same file read twice (a copy under another name),
    which would count its rows twice and halve every variance they give.
    """
    seen: dict[bytes, int] = {}
    found: dict[tuple[int, int], int] = {}
    for k, part in enumerate(parts):
        q = np.ascontiguousarray(np.atleast_2d(part.q), float)
        eta = np.ascontiguousarray(np.atleast_2d(part.eta), float)
        for row in range(len(q)):
            key = q[row].tobytes() + eta[row].tobytes()
            first = seen.setdefault(key, k)
            if first != k:
                found[(first, k)] = found.get((first, k), 0) + 1
    return [(i, j, n) for (i, j), n in sorted(found.items())]


def unread_covariates(model: MeasurementModel, names: Sequence[str]
                      ) -> tuple[list[tuple[str, str]], list[str]]:
    """Split stated covariate ``names`` that no part of ``model`` reads.

    A covariate is read by an effect's inputs (:attr:`MeasurementModel.inputs`) or, when an
    effect reads the gravity torque, as the payload (``payload.*``). Returns (misspelled,
    unread): ``misspelled`` [(name, the read name it is close to)], ``unread`` the other
    names read by nothing (a condition kept for the record, which changes no prediction).
    """
    read = [n for n in model.inputs if not n.startswith(PREFIX)]
    if model.uses_torque:
        read += [PAYLOAD_MASS, *PAYLOAD_COM]
    known = set(read) | {PAYLOAD_MASS, *PAYLOAD_COM}
    misspelled, unread = [], []
    for name in names:
        if name in read:
            continue
        close = difflib.get_close_matches(name, sorted(known - {name}), n=1, cutoff=0.75)
        if close and name not in known:
            misspelled.append((name, close[0]))
        else:
            unread.append(name)
    return misspelled, unread


def covariate(name: str) -> str:
    """Return the one-hot covariate of recording ``name`` (1 on its rows)."""
    return f'{PREFIX}{name}'


def base_names(name: str) -> list[str]:
    """``recording.<name>.base.{x,y,z,roll,pitch,yaw}``."""
    return [f'{PREFIX}{name}.base.{c}' for c in BASE_COMPONENTS]


def reflector_names(name: str, prefix: str) -> list[str]:
    """``recording.<name>.<prefix>.{x,y,z}`` of the reflector ``prefix`` (e.g. ``reflector``)."""
    return [f'{PREFIX}{name}.{prefix}.{c}' for c in 'xyz']


def recording_parameters(geometric: ParameterSet, recordings: Sequence[Recording]
                         ) -> ParameterSet:
    """``geometric`` with the placement parameters of ``recordings[1:]`` appended.

    Each starts at the first recording's nominal values (``base.*``, ``reflector.*``); the
    identification starts from each recording's own registration. A remounted probe whose
    tracked body's orientation the cell identifies (``<prefix>.r{x,y,z}``) gets its own,
    ``recording.<name>.<prefix>.r{x,y,z}`` (a turn of the stated one, from the first's
    nominal).

    Raises
    ------
    ValueError
        Two recordings share a name, or ``geometric`` already places recordings.
    """
    names = [r.name for r in recordings]
    if len(set(names)) != len(names):
        raise ValueError(f'recording names must be unique, got {names}')
    if recording_names(geometric):
        raise ValueError('the parameter set places recordings already')
    nominal = dict(zip(geometric.names, geometric.nominal))
    out = geometric
    for rec in recordings[1:]:
        extra = base_names(rec.name)
        values = [nominal[f'base.{c}'] for c in BASE_COMPONENTS]
        units = ['m'] * 3 + ['rad'] * 3
        if rec.reflector_remounted:
            for prefix in reflector_prefixes(geometric):
                extra += reflector_names(rec.name, prefix)
                values += [nominal[f'{prefix}.{c}'] for c in 'xyz']
                units += ['m'] * 3
                turned = orientation_names(prefix)
                if turned[0] in nominal:
                    extra += orientation_names(f'{PREFIX}{rec.name}.{prefix}')
                    values += [nominal[n] for n in turned]
                    units += ['rad'] * 3
        out = out.extended(extra, np.array(values), units)
    return out


def placed_model(model: MeasurementModel, recordings: Sequence[Recording]
                 ) -> MeasurementModel:
    """``model`` (one placement) with the placements of ``recordings[1:]`` added.

    Its geometric parameters extended by :func:`recording_parameters`, everything else
    (effects, reflector axis, tracked bodies, joint noise, temperature sensors) kept. One
    recording returns ``model`` itself.
    """
    if len(recordings) <= 1:
        return model
    geometric = recording_parameters(model.geometric, recordings)
    return MeasurementModel(model.robot, geometric, model.effects, model.reflector_axis,
                            model.orientations, model.rotation_scale, model.joint_noise_map,
                            model.joint_temperatures)


def to_first_frame(model: MeasurementModel, values: np.ndarray, data: Measurements,
                   vectors: np.ndarray) -> np.ndarray:
    """Turn ``vectors`` (N, 3) of ``data``'s rows into the first recording's tracker frame.

    Each is in its own recording's frame: turned by R_first R_rowᵀ (the base rotations at
    ``values``).
    A residual (a displacement of the tool) compares across recordings only in one frame;
    without recordings ``vectors`` is returned as it is.
    """
    vectors = np.asarray(vectors, float)
    if not model.recordings:
        return vectors
    params = model.params
    values = np.asarray(values, float)

    def rotation(names: list[str]) -> np.ndarray:
        return np.array(rpy_matrix(*values[params.indices(names[3:])]), float)
    first = rotation([f'base.{c}' for c in BASE_COMPONENTS])
    index = row_recording(data, ('',) + tuple(model.recordings))
    out = vectors.copy()
    for i, name in enumerate(model.recordings, 1):
        rows = index == i
        out[rows] = vectors[rows] @ (first @ rotation(base_names(name)).T).T
    return out


def row_recording(data: Measurements, names: Sequence[str]) -> np.ndarray:
    """Index (N,) into ``names`` (all recordings, first included) of every row of ``data``.

    A row with no recording covariate set belongs to the first.
    """
    out = np.zeros(len(data), dtype=int)
    if data.covariates is None:
        return out
    for i, name in enumerate(names):
        values = data.covariates.get(covariate(name))
        if values is not None:
            out[np.asarray(values) > 0.5] = i
    return out


def row_covariates(names: Sequence[str], index: np.ndarray) -> dict[str, np.ndarray]:
    """Return the one-hot covariates of the recordings after the first, rows ``index`` (N,)."""
    index = np.asarray(index, dtype=int)
    return {covariate(name): (index == i).astype(float) for i, name in enumerate(names)
            if i > 0}


def combine(parts: Sequence[Measurements], recordings: Sequence[Recording]) -> Measurements:
    """One :class:`Measurements` of every recording's rows, in order, with their covariates.

    Each row carries the one-hot ``recording.<name>`` of the recordings after the first and
    every constant covariate of its recording; a covariate a bag carries is kept. One
    recording is returned as it is, covariates of its own added.

    Raises
    ------
    ValueError
        Lengths differ, a covariate is given for some recordings and not others (a
        condition of one recording must be stated for every one: 0 is a condition too), or
        a recording states a constant its own rows carry with other values (the constant
        replaced them silently).
    """
    if len(parts) != len(recordings) or not parts:
        raise ValueError('one Measurements per recording, at least one')
    stated = [set(r.covariates) | set(p.covariates or {}) for r, p in zip(recordings, parts)]
    every = set().union(*stated)
    for rec, have in zip(recordings, stated):
        if have != every:
            raise ValueError(f'recording {rec.name!r} states no covariate '
                             f'{sorted(every - have)}: give it for every recording')
    for rec, part in zip(recordings, parts):
        for name, value in rec.covariates.items():
            rows = (part.covariates or {}).get(name)
            if rows is not None and not np.allclose(np.asarray(rows, float), float(value),
                                                    rtol=1e-9, atol=1e-12):
                rows = np.asarray(rows, float)
                raise ValueError(
                    f'recording {rec.name!r} states {name} = {float(value):g} while its rows '
                    f'carry {name} per row ({rows.min():g} to {rows.max():g}): state it in '
                    'one place (drop it from the recording\'s covariates to use the rows\')')
    index = np.concatenate([np.full(len(p), i) for i, p in enumerate(parts)])
    covariates: dict[str, np.ndarray] = {}
    for name in sorted(every):
        covariates[name] = np.concatenate([
            np.full(len(p), float(r.covariates[name])) if name in r.covariates
            else np.asarray((p.covariates or {})[name], float)
            for r, p in zip(recordings, parts)])
    covariates.update(row_covariates([r.name for r in recordings], index))
    return concatenate(parts, covariates or None)


def concatenate(parts: Sequence[Measurements],
                covariates: Mapping[str, np.ndarray] | None = None) -> Measurements:
    """Return the rows of ``parts`` in order, with ``covariates`` (N,) per row.

    Default: the covariates of the parts (every part must carry the same names).
    """
    if covariates is None and any(p.covariates for p in parts):
        names = [set(p.covariates or {}) for p in parts]
        if any(n != names[0] for n in names):
            raise ValueError(f'the parts carry different covariates {names}: give each the same')
        covariates = {k: np.concatenate([np.asarray(p.covariates[k], float) for p in parts
                                         if p.covariates is not None])
                      for k in names[0]}

    def stack(field_name: str) -> np.ndarray | None:
        values = [getattr(p, field_name) for p in parts]
        if all(v is None for v in values):
            return None
        if field_name == 'reflector':
            return np.concatenate([np.zeros(len(p), int) if v is None else np.asarray(v)
                                   for p, v in zip(parts, values)])
        if field_name == 'sigma':
            return np.concatenate([np.full((len(p), 3), np.nan) if v is None else v
                                   for p, v in zip(parts, values)])
        if field_name == 'rotation':
            return np.concatenate([np.broadcast_to(np.eye(3), (len(p), 3, 3)) if v is None
                                   else v for p, v in zip(parts, values)])
        if any(v is None for v in values):
            return None  # tau, stamps: recomputed where missing
        return np.concatenate(values)
    return Measurements(q=np.concatenate([np.atleast_2d(p.q) for p in parts]),
                        eta=np.concatenate([np.atleast_2d(p.eta) for p in parts]),
                        tau=stack('tau'), stamps_ns=stack('stamps_ns'),
                        reflector=stack('reflector'), rotation=stack('rotation'),
                        sigma=stack('sigma'), covariates=covariates or None)


def placement_names(params: ParameterSet, index: int, names: Sequence[str]) -> list[str]:
    """Return the placement parameters of recording ``index`` of ``names`` (first included).

    The first: ``base.*`` and ``reflector.*``; a further one: its ``recording.<name>.*``.
    """
    if index == 0:
        return [n for n in params.names if n.startswith(('base.', 'reflector.'))]
    return [n for n in params.names if n.startswith(f'{PREFIX}{names[index]}.')]


def as_first(params: ParameterSet, name: str) -> dict[str, str]:
    """Return the renaming that makes recording ``name`` the first ({old: new}).

    ``recording.<name>.base.*`` and ``base.*`` exchanged, and, for a remounted probe,
    ``recording.<name>.<prefix>.*`` and ``<prefix>.*``; {} when ``params`` places no
    recording ``name`` (the first).

    Rows without a recording covariate are placed by ``base.*``: with the parameter values
    and covariance renamed so, they are placed as that recording's rows were, exactly.
    """
    out: dict[str, str] = {}
    for own in params.names:
        if own.startswith(f'{PREFIX}{name}.'):
            shared = own[len(f'{PREFIX}{name}.'):]
            out[own], out[shared] = shared, own
    return out


@dataclass(frozen=True)
class Contribution:
    """What one recording contributed to a joint identification.

    ``poses``: its distinct poses among the kept rows; ``points``: its point rows (a pose
    gives one per reflector); ``rms_m``: the rms of their residual distance (m);
    ``placement``: {parameter name: value} of its base pose (and reflector, remounted),
    ``placement_std``: their std (NaN: not identified); ``tcp_variance_ratio``: the trace of
    the TCP covariance at the working poses in the robot's base frame (its placement not
    counted) without this recording's rows over the one with every recording (≥ 1; inf:
    without it the identified robot is not determined); None when there are no working poses.
    """

    name: str
    poses: int
    rms_m: float
    placement: dict[str, float]
    placement_std: dict[str, float]
    tcp_variance_ratio: float | None
    points: int = 0


def contributions(model: MeasurementModel, data: Measurements, values: np.ndarray,
                  estimated: Sequence[str], std: Sequence[float] | np.ndarray,
                  sigma: np.ndarray,
                  q_work: np.ndarray, names: Sequence[str]) -> list[Contribution]:
    """Per recording of ``names`` (all, first included): :class:`Contribution`.

    ``data`` the rows the fit kept, ``values`` (n_p,) its estimate, ``estimated`` and ``std``
    the identified parameters and their std, ``sigma`` the noise (3,) or (N, 3) (m),
    ``q_work`` (t, n) the working poses. The TCP information is linearised at ``values``
    with the same identified parameters: the robot's (every placement held) TCP covariance
    with the rows of every recording and without those of one.
    """
    params = model.params
    values = np.asarray(values, float)
    index = row_recording(data, names)
    ref = (np.zeros(len(data), int) if data.reflector is None
           else np.asarray(data.reflector, int))
    points = ref < model.n_reflectors
    tau = row_torques(model, data)
    predicted = model.predict(values, data.q, tau, data.reflector, data.rotation,
                              data.covariates)
    miss = np.linalg.norm(np.atleast_2d(data.eta) - predicted, axis=1)
    own = [set(placement_names(params, i, names)) for i in range(len(names))]
    placements = set().union(*own)
    # The first recording's reflector offsets are every recording's that has none of its own
    # (not remounted): without its rows they stay free. Held, they made its ratio 0.075 where
    # joint 6 hardly turned (the offsets trade with the arm), 0.75-0.87 on a real TIAGo.
    if any(not any(n.startswith(f'{PREFIX}{name}.reflector') for n in own[i])
           for i, name in enumerate(names) if i > 0):
        own[0] = {n for n in own[0] if not n.startswith('reflector')}
    robot = [n for n in estimated if n not in placements]
    idx = params.indices(list(estimated))
    w = noise_weights(model, values, data, sigma, tau)
    _, jac = model.jacobian(values, data.q, tau, data.reflector, data.rotation,
                            data.covariates)
    rows = weighted_rows(jac, w, idx).reshape(len(data), 3, len(idx))
    ratio: list[float | None] = [None] * len(names)
    if len(q_work) and robot:
        _, kpi = model.jacobian(values, np.atleast_2d(q_work))
        kpi = kpi.reshape(-1, len(values))[:, idx]
        keep = np.array([n in robot for n in estimated])
        kpi = np.where(keep[None, :], kpi, 0.0)

        def tcp_trace(mask: np.ndarray, drop: set[str]) -> float:
            cols = np.array([n not in drop for n in estimated])
            a = rows[mask][:, :, cols].reshape(-1, int(cols.sum()))
            info = a.T @ a
            if np.linalg.matrix_rank(info) < info.shape[0]:
                return float('inf')
            k = kpi[:, cols]
            return float(np.trace(k @ np.linalg.solve(info, k.T)))
        every = tcp_trace(np.ones(len(data), bool), set())
        # 0 when no robot parameter moves the working poses' TCP (a measured tilt's gains at
        # working poses without a reading): no recording's contribution to it to state
        for i in range(len(names)):
            ratio[i] = (tcp_trace(index != i, own[i]) / every
                        if np.isfinite(every) and every > 0 else None)
    stds = dict(zip(estimated, std))
    value = dict(zip(params.names, values))
    out = []
    for i, name in enumerate(names):
        mine = (index == i) & points
        placed = placement_names(params, i, names)
        poses = len(np.unique(np.atleast_2d(data.q)[mine], axis=0)) if mine.any() else 0
        out.append(Contribution(
            name, int(poses),
            float(np.sqrt(np.mean(miss[mine] ** 2))) if mine.any() else float('nan'),
            {n: float(value[n]) for n in placed},
            {n: float(stds.get(n, float('nan'))) for n in placed}, ratio[i],
            int(np.count_nonzero(mine))))
    return out
