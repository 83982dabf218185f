"""Measurements for identification: recorded or live samples paired into
:class:`~kpi_calib_ros.core.measurement.data.Measurements` of a cell, the one path every front
end uses (the CLI, the node and the demo), so a bag replayed into the node and the same bag
read offline give the same rows.

Joint values are mapped from the controller's readings to the URDF chain once, here
(:func:`urdf_measurements`); the tracker's stated σ and tracked 6-DoF poses become row
weights and rotation rows.
"""
from __future__ import annotations

import dataclasses
import sys
import warnings
from pathlib import Path
from typing import Callable, Iterable, Mapping, Sequence

import numpy as np

from kpi_calib_ros.app.cell_model import (
    CellModel,
    build_cell_model,
    carried_limit,
    reading_check,
)
from kpi_calib_ros.core.acquisition.outcomes import PairingResult
from kpi_calib_ros.core.acquisition.pairing import pair_measurements
from kpi_calib_ros.core.acquisition.reflector_frames import split_frame
from kpi_calib_ros.core.acquisition.streams import JointSample, PointSample
from kpi_calib_ros.core.effects.registry import split_specs
from kpi_calib_ros.core.errors import ConfigError, DataError
from kpi_calib_ros.core.measurement.covariates import (
    EFFORT_PREFIX,
    InputSample,
    TemperatureSample,
    effort_name,
    input_covariates,
    plausible_readings,
    range_text,
    temperature_covariates,
    with_covariates,
)
from kpi_calib_ros.core.measurement.data import Measurements
from kpi_calib_ros.core.measurement.payload import PAYLOAD_COM, PAYLOAD_MASS, row_payloads
from kpi_calib_ros.core.measurement.pose_rows import with_rotation_rows
from kpi_calib_ros.core.measurement.recordings import (
    Recording,
    combine,
    concatenate,
    placed_model,
    recording_parameters,
    repeated_rows,
    unread_covariates,
)
from kpi_calib_ros.io.bag import JOINT_STATE_TYPE, read_for_pairing, read_inputs, read_temperatures
from kpi_calib_ros.io.cell import load_cell
from kpi_calib_ros.io.cell_inputs import field_path
from kpi_calib_ros.io.measurement_log import stored_pairing
from kpi_calib_ros.io.recordings_manifest import RecordingSource
from kpi_calib_ros.io.ros_messages import FieldPath


def measurements_from_samples(cm: CellModel, joint_samples: Iterable[JointSample],
                              point_samples: Iterable[PointSample],
                              point_sigma: Mapping[tuple[int, str], np.ndarray] | None = None,
                              **pairer_options) -> tuple[Measurements, PairingResult]:
    """Pair tracker points with still joint states, matching joints by name; the points'
    stated σ by (stamp ns, frame id), if any, weigh their rows (:func:`to_measurements`).

    Raises
    ------
    DataError
        When no point could be paired because the joint states lack the
        chain's joints (wrong robot or renamed joints): names both sets.
    """
    joint_samples = list(joint_samples)
    pairer_options.setdefault('reflectors', reflector_names(cm))
    pairer_options.setdefault('derived', cm.joint_coupling.derived())
    pairer_options.setdefault('joint_check', reading_check(cm))
    pairing = pair_measurements(joint_samples, point_samples, cm.joint_names,
                                cm.cell.tracker_frame, **pairer_options)
    if len(pairing) == 0 and pairing.rejections.get('missing_joints'):
        seen = sorted({n for s in joint_samples for n in s.names})
        raise DataError(f'the joint states name joints {seen}, but the robot chain needs '
                        f'{cm.joint_names}; record the right robot or fix the URDF joint names')
    return urdf_measurements(cm, to_measurements(cm, pairing, point_sigma)), pairing


def urdf_measurements(cm: CellModel, data: Measurements) -> Measurements:
    """``data`` (paired joint states and points) with its joint values mapped from the
    controller's readings to the URDF chain (``robot.joint_coupling``).

    Every path from joint states to the model (bag, measurement log, live node) goes
    through here, so coupled readings are converted once and only once.
    """
    if not len(data) or cm.joint_coupling.is_identity:
        return data
    return dataclasses.replace(data, q=cm.joint_coupling.to_urdf(data.q))


def reflector_names(cm: CellModel) -> tuple[str, ...]:
    """Reflector names points carry after '#' in their frame id ('' : single reflector)."""
    return cm.cell.reflector_names or ('',)


def to_measurements(cm: CellModel, pairing: PairingResult,
                    point_sigma: Mapping[tuple[int, str], np.ndarray] | None = None
                    ) -> Measurements:
    """(pose, reflector) rows of a pairing, reflector indices in the cell's order
    (controller joint values, as paired); ``point_sigma`` the tracker's stated σ (3,) (m)
    by (stamp ns, frame id) (:attr:`kpi_calib_ros.io.bag.BagContents.point_sigma`): a row
    without one takes the cell's noise.sigma."""
    try:
        ref = pairing.reflector_indices(reflector_names(cm))
    except ValueError as exc:
        raise DataError(f'{exc}: point frame ids are <tracker_frame>#<reflector name> for '
                        "the cell's reflectors: list") from None
    data = Measurements(q=pairing.q, eta=pairing.eta, stamps_ns=pairing.stamps_ns,
                        reflector=ref if cm.cell.reflector_names else None,
                        sigma=paired_sigma(pairing, point_sigma))
    return pose_rows(cm, data, pairing)


def paired_sigma(pairing: PairingResult,
                 point_sigma: Mapping[tuple[int, str], np.ndarray] | None) -> np.ndarray | None:
    """(N, 3) σ (m) of the pairing's rows, matched by stamp and reflector (the frame id's
    part after '#'; the tracker frame is the pairing's), NaN where none was stated; None
    when no row has one."""
    if not point_sigma:
        return None
    by_row = {(stamp, split_frame(frame)[1]): s for (stamp, frame), s in point_sigma.items()}
    names = pairing.reflectors or ('',) * len(pairing)
    rows = np.array([by_row.get((int(t), name), np.full(3, np.nan))
                     for t, name in zip(pairing.stamps_ns, names)], dtype=float).reshape(-1, 3)
    return rows if np.isfinite(rows).any() else None


def pose_rows(cm: CellModel, data: Measurements,
              pairing: PairingResult | None) -> Measurements:
    """``data`` with the rotation row of every tracked 6-DoF pose of ``pairing``.

    See :func:`kpi_calib_ros.core.measurement.pose_rows.with_rotation_rows`; None: no pairing,
    as is."""
    if pairing is None or pairing.rotations is None:
        return data
    try:
        return with_rotation_rows(cm.model, data, pairing.rotations)
    except ValueError as exc:
        names = reflector_names(cm)
        raise DataError(f'{exc}; a PoseStamped was recorded for a reflector of the cell '
                        f'{list(names)} that has no orientation: give the tracked body\'s '
                        'orientation in the cell (reflectors[i].orientation: {rpy: [r, p, y]}) '
                        'or record its position as a PointStamped') from None


def measurements_from_bag(cm: CellModel, path: str | Path,
                          joint_topic: str | None = None,
                          point_topic: str | None = None,
                          pose_topic: str | None = None,
                          **pairer_options) -> tuple[Measurements, PairingResult]:
    """Measurements from a recording (paired here) or from the node's measurement log
    (paired when stored), reading only the joint states pairing needs. Topics default
    to the cell's ``topics:``; tracked 6-DoF poses on the pose topic add rotation rows."""
    cell = cm.cell
    contents = read_for_pairing(path, joint_topic or cell.joint_topic,
                                point_topic or cell.point_topic,
                                window_ns=pairer_options.get('window_ns'),
                                pose_topic=pose_topic or cell.pose_topic)
    if contents.measurement_log:
        pairing = stored_pairing(zip(contents.joints, contents.points), list(cm.joint_names),
                                 cm.cell.tracker_frame)
        data = urdf_measurements(cm, to_measurements(cm, pairing, contents.point_sigma))
    else:
        data, pairing = measurements_from_samples(cm, contents.joints, contents.points,
                                                  point_sigma=contents.point_sigma,
                                                  **pairer_options)
    data = with_temperature(cm, data, path)
    sources = input_sources(cm)
    if sources or cm.cell.inputs.topic in contents.topics:
        samples, topics = read_inputs(path, cm.cell.inputs.topic, sources)
        data = with_inputs(cm, data, samples, str(path), topics)
    if contents.row_order_stamps:
        # Stamps that number a table's rows paired its columns; past pairing they are no
        # clock: no time input, no date of the calibration, no drift time from them.
        data = dataclasses.replace(data, stamps_ns=None)
        pairing = dataclasses.replace(pairing, stamps_are_times=False)
    return data, pairing


def input_sources(cm: CellModel) -> list[tuple[str, str, tuple[tuple[str, FieldPath], ...]]]:
    """The cell's measured-input sources as (topic, ROS type, ((covariate, field path), ...)),
    with the joint states' efforts (``effort.<joint>`` of every chain joint) when
    ``compliance.torque_source`` is ``measured``."""
    settings = cm.cell.inputs
    out = [(s.topic, s.type, tuple((name, field_path(path, f'inputs.sources.{name}'))
                                   for name, path in s.fields)) for s in settings.sources]
    if settings.torque_source == 'measured':
        out.append((cm.cell.joint_topic, JOINT_STATE_TYPE,
                    tuple((effort_name(j), (('effort', j),)) for j in cm.joint_names)))
    return out


def expected_inputs(cm: CellModel) -> list[str]:
    """The covariate names the cell's sources (:func:`input_sources`) and its named-values
    topic (``inputs.expect``) must give."""
    return [name for _, _, fields in input_sources(cm) for name, _ in fields] \
        + list(cm.cell.inputs.expect)


def with_inputs(cm: CellModel, data: Measurements, samples: Sequence[InputSample],
                where: str, topics: Iterable[str] = ()) -> Measurements:
    """``data`` with the measured input readings ``samples`` paired to its rows by stamp
    (:func:`~kpi_calib_ros.core.measurement.covariates.input_covariates`, the cell's
    ``inputs.max_gap``), the bag's and the node's alike.

    A reading that is not finite is never used (warned with its count); a row with no value
    of an input is refused (warned). Row payloads (``payload.mass``) are checked; with
    ``compliance.torque_source: measured`` the efforts become the rows' torques
    (``Measurements.tau``). ``data`` unchanged without readings or sources.

    Raises
    ------
    DataError
        A source of the cell gave no finite reading (``topics``: the topics the recording
        has, for the message), the rows carry no stamps, or a payload is none.
    """
    expected = expected_inputs(cm)
    if len(data) == 0 or (not samples and not expected):
        return data
    if data.stamps_ns is None:
        raise DataError('the measurements carry no stamps to pair measured inputs with')
    settings = cm.cell.inputs
    cov, rejected = input_covariates(data.stamps_ns, samples, settings.max_gap_ns)
    if rejected:
        first = rejected[0]
        warnings.warn(f'{where}: {len(rejected)} measured input reading(s) not finite, never '
                      f'used (first: {first.name} = {first.value!r} at stamp {first.stamp_ns} '
                      'ns)', stacklevel=3)
    missing = [name for name in expected if name not in cov]
    if missing:
        efforts = [n for n in missing if n.startswith(EFFORT_PREFIX)]
        named = [n for n in missing if n in cm.cell.inputs.expect]
        fix = (f'the joint states on {cm.cell.joint_topic} must name every chain joint '
               f'{list(cm.joint_names)} with one finite effort each, or set '
               'compliance.torque_source: model' if efforts else
               f'publish {named} on {cm.cell.inputs.topic} (sensor_msgs/msg/JointState: name = '
               'covariate, position = value, SI), or remove them from inputs.expect'
               if named else
               'record the topic of each inputs.sources entry, or remove the source')
        raise DataError(f'{where}: no finite reading of the measured input(s) {missing} '
                        f'(topics recorded: {sorted(topics)}); {fix}')
    kept, refused = with_covariates(data, cov, required=sorted(cov), what='measured input')
    if refused:
        warnings.warn(f'{len(refused)} of {len(data)} measurement rows refused: '
                      f'{refused[0][1]} (inputs.max_gap = {settings.max_gap_s:g} s)',
                      stacklevel=3)
    try:
        row_payloads(kept.covariates, len(kept), cm.robot.payload)
    except ValueError as exc:
        raise DataError(f'{where}: payload.mass / payload.com: {exc}') from None
    check_payload_limit(cm, kept.covariates, where)
    if settings.torque_source == 'measured' and len(kept):
        assert kept.covariates is not None
        tau = np.column_stack([kept.covariates[effort_name(j)] for j in cm.joint_names])
        kept = dataclasses.replace(kept, tau=tau)
    return kept


def with_temperature(cm: CellModel, data: Measurements, path: str | Path) -> Measurements:
    """``data`` with the temperatures of the cell's ``temperature:`` topic in the bag
    ``path`` paired to every row by its stamp (:func:`with_readings`).

    Raises
    ------
    DataError
        The section is there but the bag has no temperature on its topic, or a listed
        sensor never published.
    """
    return with_readings(cm, data, lambda topic: read_temperatures(path, topic), str(path))


def with_readings(cm: CellModel, data: Measurements,
                  read: Callable[[str], Sequence[TemperatureSample]],
                  where: str | None = None) -> Measurements:
    """``data`` with the temperature readings ``read(topic)`` of the cell's ``temperature:``
    topic paired to every row by its stamp (:mod:`kpi_calib_ros.core.measurement.covariates`),
    the bag's and the node's alike; rows without a temperature are refused with a warning.
    ``data`` unchanged (nothing read) without the section. ``where`` names the source in
    errors (default: the topic).

    Raises
    ------
    DataError
        No reading on the topic, or a listed sensor never published.
    """
    settings = cm.cell.temperature
    if settings is None or len(data) == 0:
        return data
    kept, refused = paired_temperature(cm, data, read(settings.topic),
                                       where or f'topic {settings.topic}')
    if refused:
        warnings.warn(refused_text(cm, len(data), refused), stacklevel=3)
    return kept


def paired_temperature(cm: CellModel, data: Measurements, samples: Sequence[TemperatureSample],
                       where: str = 'the recording'
                       ) -> tuple[Measurements, list[tuple[int, str]]]:
    """``data`` with the temperature readings ``samples`` paired to its rows by stamp, per
    the cell's ``temperature:`` section, rows without one removed; [(row, reason)] of those.

    Raises
    ------
    DataError
        No reading at all, no stamps, or a listed sensor never published.
    """
    settings = cm.cell.temperature
    assert settings is not None
    if not samples:
        raise DataError(f"{where}: no sensor_msgs/Temperature on '{settings.topic}' "
                        '(temperature.topic in the cell file); record it, or remove the '
                        'temperature: section')
    if data.stamps_ns is None:
        raise DataError('the measurements carry no stamps to pair temperatures with')
    # A reading no arm can have (a sensor fault, a driver's 1e12) is never used: it would be
    # a ΔT that decides the thermal effects alone.
    plausible, implausible = plausible_readings(samples, settings.valid_range_c)
    if implausible:
        if not plausible:
            raise DataError(f'{where}: all {len(implausible)} temperature readings on '
                            f"'{settings.topic}' lie outside temperature.valid_range "
                            f'{list(settings.valid_range_c)} °C (first: '
                            f'{implausible[0].celsius:g} °C from sensor '
                            f'{implausible[0].frame_id!r}): fix the sensor, or set '
                            'temperature.valid_range to what the cell can read')
        warnings.warn(f'{where}: {range_text(implausible, settings.valid_range_c)}',
                      stacklevel=3)
    try:
        cov = temperature_covariates(data.stamps_ns, plausible, settings.sensors,
                                     settings.reference_c, settings.max_gap_ns)
    except ValueError as exc:
        raise DataError(f'temperature.sensors: {exc}'
                        + (' (plausible readings; temperature.valid_range '
                           f'{list(settings.valid_range_c)} °C)' if implausible else '')
                        ) from None
    return with_covariates(data, cov)


def refused_text(cm: CellModel, total: int, refused: list[tuple[int, str]]) -> str:
    """One line on the rows refused for want of a temperature."""
    gap = cm.cell.temperature.max_gap_s if cm.cell.temperature else float('nan')
    return (f'{len(refused)} of {total} measurement rows refused: {refused[0][1]} '
            f'(temperature.max_gap = {gap:g} s)')


def load_measurements(cell_path: str | Path,
                      bag_path: str | Path | Sequence[RecordingSource], effects: str = '',
                      joint_topic: str | None = None, point_topic: str | None = None,
                      allow_code_effects: bool = False, pose_topic: str | None = None
                      ) -> tuple[CellModel, Measurements, PairingResult]:
    """Cell model (with the extra ``effects`` specs, comma-separated) and the paired
    measurements of a bag; rejections are reported on stderr. ``bag_path`` a sequence of
    recordings: :func:`load_recordings` (several set-ups identified together).

    ``joint_topic`` / ``point_topic`` / ``pose_topic`` (``--joint-topic`` /
    ``--point-topic`` / ``--pose-topic``) override the cell's ``topics:``;
    ``allow_code_effects`` lets effects name Python code.
    """
    if not isinstance(bag_path, (str, Path)):
        return load_recordings(cell_path, bag_path, effects, joint_topic, point_topic,
                               allow_code_effects, pose_topic)
    cell = load_cell(cell_path, allow_code_effects=allow_code_effects)
    cm = build_cell_model(cell, effects=tuple(split_specs(effects)))
    data, pairing = measurements_from_bag(cm, bag_path, joint_topic, point_topic, pose_topic)
    print_rejections(pairing)
    return cm, data, pairing


def with_recordings(cm: CellModel, recordings: Sequence[Recording]) -> CellModel:
    """``cm`` with a placement of its own for every recording after the first
    (:mod:`kpi_calib_ros.core.measurement.recordings`); ``cm`` itself for one."""
    if len(recordings) <= 1:
        return cm
    return dataclasses.replace(cm, geometric=recording_parameters(cm.geometric, recordings),
                               model=placed_model(cm.model, recordings))


def merged_pairing(pairings: Sequence[PairingResult]) -> PairingResult:
    """The pairings of several recordings as one (rows in recording order, counts summed)."""
    if len(pairings) == 1:
        return pairings[0]
    first = pairings[0]
    rejections: dict[str, int] = {}
    for p in pairings:
        for k, v in p.rejections.items():
            rejections[k] = rejections.get(k, 0) + v
    reflectors: tuple[str, ...] = ()
    if any(p.reflectors for p in pairings):
        reflectors = tuple(r for p in pairings for r in (p.reflectors or ('',) * len(p)))
    rotations = None
    if any(p.rotations is not None for p in pairings):
        rotations = np.concatenate([np.full((len(p), 3, 3), np.nan) if p.rotations is None
                                    else p.rotations for p in pairings])
    return PairingResult(first.joint_names, first.tracker_frame,
                         np.concatenate([p.q for p in pairings]),
                         np.concatenate([p.eta for p in pairings]),
                         np.concatenate([p.stamps_ns for p in pairings]), rejections,
                         [r for p in pairings for r in p.rejected], reflectors, rotations,
                         all(p.stamps_are_times for p in pairings))


def load_recordings(cell_path: str | Path, sources: Sequence[RecordingSource],
                    effects: str = '', joint_topic: str | None = None,
                    point_topic: str | None = None, allow_code_effects: bool = False,
                    pose_topic: str | None = None
                    ) -> tuple[CellModel, Measurements, PairingResult]:
    """:func:`load_measurements` of several recordings identified together: the cell model
    with each further recording's placement (:func:`with_recordings`), the rows of every bag
    in order with their recording and constant covariates
    (:func:`kpi_calib_ros.core.measurement.recordings.combine`), and the pairings merged.

    Raises
    ------
    DataError
        A recording gives no measurement (named).
    ConfigError
        The recordings' covariates do not fit together.
    """
    cell = load_cell(cell_path, allow_code_effects=allow_code_effects)
    cm = build_cell_model(cell, effects=tuple(split_specs(effects)))
    check_stated_covariates(cm, [r for s in sources for r in (
        s.recording, *(dataclasses.replace(s.recording, covariates=m.covariates)
                       for m in s.more))])
    parts, pairings, recordings = [], [], []
    for source in sources:
        pieces = []
        for bag, window, values in [(source.bag, source.window, source.recording.covariates),
                                    *((m.bag, (None, None), m.covariates) for m in source.more)]:
            try:
                data, pairing = measurements_from_bag(cm, bag, joint_topic, point_topic,
                                                      pose_topic)
            except DataError as exc:  # which of the recordings says it
                if len(sources) == 1 and not source.more:
                    raise
                raise DataError(f'recording {source.recording.name!r} ({bag}): {exc}') from None
            print_rejections(pairing, f'recording {source.recording.name!r} ({bag.name}): '
                             if len(sources) > 1 or source.more else '')
            data = in_window(data, source.recording.name, bag, window)
            if len(data) == 0:
                raise DataError(f'recording {source.recording.name!r} ({bag}) gives no paired '
                                'measurement: check its topics and the cell\'s joint names')
            # several bags of one placement: each one's conditions on its own rows, checked
            # against those its rows carry, as a recording's are
            pieces.append(_combined([data], [Recording(source.recording.name,
                                                       covariates=values)])
                          if source.more else data)
            pairings.append(pairing)
        parts.append(pieces[0] if len(pieces) == 1 else concatenate(pieces))
        recordings.append(source.fitted)  # several bags: each one's conditions on its rows
    repeated = repeated_rows(parts)
    if repeated:
        i, j, count = repeated[0]
        raise ConfigError('recordings', f'recording {recordings[j].name!r} '
                          f'({sources[j].bag}) repeats {count} of its {len(parts[j])} rows '
                          f'bit for bit from recording {recordings[i].name!r} '
                          f'({sources[i].bag}): the same measurements given twice (a copy '
                          'under another name) would count twice and halve every variance; '
                          'give each recording once')
    data = _combined(parts, recordings)
    check_payload_limit(cm, data.covariates, 'recordings')
    return with_recordings(cm, recordings), data, merged_pairing(pairings)


def _combined(parts: Sequence[Measurements], recordings: Sequence[Recording]) -> Measurements:
    """:func:`~kpi_calib_ros.core.measurement.recordings.combine`, its refusals a ConfigError."""
    try:
        return combine(parts, recordings)
    except ValueError as exc:
        raise ConfigError('recordings', f'{exc}') from None


def in_window(data: Measurements, name: str, bag: Path,
              window: tuple[float | None, float | None]) -> Measurements:
    """The rows of ``data`` (one bag's) in ``window``: s from its first row (a manifest's
    ``split_at``); all of them without one. ``name`` and ``bag`` name the recording.

    Raises
    ------
    DataError
        A window without stamps to place it, or with no row (named with the times).
    """
    lo, hi = window
    if lo is None and hi is None:
        return data
    if data.stamps_ns is None:
        raise DataError(f'recording {name!r} ({bag}): split_at needs '
                        'the rows\' stamps, and they have none')
    t = (np.asarray(data.stamps_ns, np.int64) - int(np.min(data.stamps_ns))) * 1e-9
    keep = (t >= (-np.inf if lo is None else lo)) & (t < (np.inf if hi is None else hi))
    if not keep.any():
        raise DataError(f'recording {name!r} ({bag}): no measurement '
                        f'between {lo or 0:g} s and {"the end" if hi is None else f"{hi:g} s"} '
                        f'of the bag (its rows span {t.max():.1f} s): check split_at')
    return data.subset(keep)


def payload_limit(cm: CellModel) -> tuple[float, str] | None:
    """The most ``cm``'s robot carries (kg) and where that figure comes from
    (:func:`~kpi_calib_ros.app.cell_model.carried_limit`)."""
    return carried_limit(cm.cell.payload_limit, cm.robot)


def check_payload_limit(cm: CellModel, covariates: Mapping[str, np.ndarray] | None,
                        where: str) -> None:
    """Refuse rows whose ``payload.mass`` exceeds what the robot carries
    (:func:`payload_limit`): grams written as kg passed the 5000 kg any arm may lift, and
    a fit of 0 and 5000 "kg" published compliances 400-800 times too small as valid.

    Raises
    ------
    DataError
        Naming the field, the rows, the largest value and the fix.
    """
    mass = (covariates or {}).get(PAYLOAD_MASS)
    limit = payload_limit(cm)
    if mass is None or limit is None:
        return
    mass = np.asarray(mass, float)
    over = np.flatnonzero(mass > limit[0])
    if len(over):
        raise DataError(f'{where}: {PAYLOAD_MASS} of {len(over)} of {len(mass)} rows beyond '
                        f'what the robot carries, {limit[0]:.3g} kg ({limit[1]}): largest '
                        f'{float(mass[over].max()):g} kg at row {int(over[0])}; a payload is in '
                        'kg (grams? divide by 1000; the column\'s unit in the mapping); if '
                        'the robot truly carries it, state its rating as payload.limit (kg) '
                        'in the cell')


def check_stated_covariates(cm: CellModel, recordings: Sequence[Recording]) -> None:
    """Refuse a recording's constant covariate that is a misspelling of one the model
    reads, and warn (stderr) of one nothing reads: stored with the calibration, it would
    change no prediction (:func:`kpi_calib_ros.core.measurement.recordings.unread_covariates`).

    Raises
    ------
    ConfigError
        ``recordings[i].covariates.<name>``: the name is close to one the model reads.
    """
    for i, rec in enumerate(recordings):
        misspelled, unread = unread_covariates(cm.model, list(rec.covariates))
        if misspelled:
            name, close = misspelled[0]
            raise ConfigError(f'recordings[{i}].covariates.{name}',
                              f'no effect reads {name!r}: did you mean {close!r}? (a '
                              'condition read by nothing changes no prediction)')
        for name in unread:
            reads = ', '.join(n for n in cm.model.inputs) or 'none'
            if name == PAYLOAD_MASS or name in PAYLOAD_COM:
                # auto may yet add an effect that reads it: not "changes no prediction"
                print(f'warning: recordings[{i}].covariates.{name}: no effect of the model '
                      'reads the payload yet; effects of the gravity torque do '
                      '(joint_compliance, joint_backlash, joint_play) and link_bending '
                      '(--effects, or those --model auto adds), and it is kept with the '
                      'recording for them',
                      file=sys.stderr)
                continue
            print(f'warning: recordings[{i}].covariates.{name}: no effect of the model reads '
                  f'it (the effects read: {reads}{"; the payload" if cm.model.uses_torque else ""}'
                  '); it is kept with the recording and changes no prediction',
                  file=sys.stderr)


def print_rejections(pairing: PairingResult, where: str = '') -> None:
    """Every rejection reason on stderr with its count and the first one's detail (which
    names what was received and the fix); ``where`` names the recording (several)."""
    first: dict[str, str] = {}
    for r in pairing.rejected:
        first.setdefault(r.reason, r.detail)
    for reason, count in sorted(pairing.rejections.items()):
        detail = f' (first: {first[reason]})' if reason in first else ''
        print(f'{where}rejected {count} sample(s): {reason}{detail}', file=sys.stderr)
