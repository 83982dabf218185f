"""The placement an identification starts from: the cell's nominal one, or registered
from the points.

An identification converges from the cell's nominal placement of the robot base in the
tracker frame (and the reflector offsets) when that placement predicts the measured
points to within the robot's geometric errors; a placement left out of the cell or far
off is registered from the points first
(:func:`kpi_calib_ros.core.estimation.registration.register`), each further recording
(tracker station) on its own rows. :func:`kpi_calib_ros.app.identify.calibrate_cell`
and the re-identification of a work cycle start from here.
"""
from __future__ import annotations

import numpy as np

from kpi_calib_ros.app.cell_model import CellModel
from kpi_calib_ros.core.errors import DataError
from kpi_calib_ros.core.estimation.registration import Registration, register
from kpi_calib_ros.core.measurement.data import Measurements
from kpi_calib_ros.core.measurement.recordings import (
    base_names,
    row_recording,
)
from kpi_calib_ros.core.measurement.recordings import (
    reflector_names as recording_reflector_names,
)
from kpi_calib_ros.core.measurement.weighting import row_torques
from kpi_calib_ros.core.model.parameters import RECORDING_PREFIX, reflector_prefixes

# Geometric errors of a robot and a surveyed placement move the predicted points by
# millimetres to a centimetre or two (a base yaw of 4 mrad at 3 m is 12 mm); the
# identification absorbs that itself. A nominal placement that misses the points by
# more (median, m) is a wrong or unknown placement: register it first.
REGISTER_ABOVE_M = 0.05
# The registered nominal points may still miss by the robot's geometric errors; far
# more (rms, m) means the model cannot explain the data (units, joint order, tip frame).
REGISTRATION_MAX_RMS_M = 0.02


def places_the_points(cm: CellModel, data: Measurements, p: np.ndarray) -> bool:
    """Do parameters ``p`` predict ``data`` within :data:`REGISTER_ABOVE_M` (median miss)?
    If not, the placement is registered from the points before fitting."""
    tau = row_torques(cm.model, data)
    miss = np.linalg.norm(np.atleast_2d(data.eta)
                          - cm.model.predict(p, data.q, tau, data.reflector, data.rotation,
                                           data.covariates),
                          axis=1)
    return float(np.median(miss)) <= REGISTER_ABOVE_M


def registered_start(cm: CellModel, data: Measurements) -> tuple[np.ndarray, Registration | None]:
    """Start parameters for identification, with the placement registered when needed.

    The cell's nominal values, except when ``tracker.base_in_tracker`` or a reflector
    offset is left out of the cell, or the nominal prediction misses the measured points
    by more than :data:`REGISTER_ABOVE_M` (median): then the base pose in the tracker
    frame is registered from the points
    (:func:`kpi_calib_ros.core.estimation.registration.register`) and replaces the nominal
    one, with the reflector offsets the cell states held (a stated offset is a prior with a
    tolerance: postures that never turn the tool would register it anywhere), or registered
    too when the cell leaves one out or the stated ones miss the points by more than
    :data:`REGISTRATION_MAX_RMS_M` (the plausibility gate then judges the offset found).
    Returns the start vector and the registration (None if not run).

    Raises
    ------
    DataError
        The registered nominal points still miss by more than :data:`REGISTRATION_MAX_RMS_M`
        rms: the message gives the distances and the likely causes (units, joint
        order, tip frame).
    """
    if cm.model.recordings:
        return recordings_start(cm, data)
    return _single_start(cm, data)


def _single_start(cm: CellModel, data: Measurements, held: np.ndarray | None = None
                  ) -> tuple[np.ndarray, Registration | None]:
    """:func:`registered_start` of one recording (the rows of the first, with several).

    ``held`` (R, 3): reflector offsets to hold in the registration instead of the cell's
    (a previous calibration's, :func:`registered_from`); they are registered too when they
    miss the points.
    """
    params = cm.model.params
    p0 = np.array(params.nominal, dtype=float)
    if held is None and not cm.needs_registration and len(data) \
            and places_the_points(cm, data, p0):
        return p0, None
    if data.reflector is not None:  # rotation rows (tracked poses) carry no point
        data = data.subset(np.asarray(data.reflector) < cm.model.n_reflectors)
    tips = np.array([cm.robot.pin_tip_pose(row) for row in np.atleast_2d(data.q)])
    reg = None
    if held is None and cm.cell.reflector_offset_given:
        held = cm.cell.offsets
    if held is not None:
        try:
            reg = register(data.eta, tips, max_rms=REGISTRATION_MAX_RMS_M,
                           reflector=data.reflector, offsets=held)
        except DataError:
            reg = None  # the stated offsets miss the points: register them too
    if reg is None:
        reg = register(data.eta, tips, max_rms=REGISTRATION_MAX_RMS_M, reflector=data.reflector)
    offsets = (reg.reflector_offsets if reg.reflector_offsets is not None
               else reg.reflector_offset.reshape(1, 3))
    values = {f'base.{c}': float(v) for c, v in
              zip(('x', 'y', 'z', 'roll', 'pitch', 'yaw'), reg.base_in_tracker)}
    prefixes = [f'reflector.{n}' for n in cm.cell.reflector_names] or ['reflector']
    for prefix, offset in zip(prefixes, offsets):
        values.update({f'{prefix}.{c}': float(v) for c, v in zip('xyz', offset)})
    return params.with_values(values), reg


def registered_from(cm: CellModel, data: Measurements, p: np.ndarray) -> np.ndarray:
    """``p`` with the placement registered from the points of one recording, the reflector
    offsets ``p`` holds kept (a previous calibration's probe: a stated offset, as the cell's)
    unless they miss the points, then registered too.

    A re-identification from another tracker station registered the offsets from the points
    as though the cell had never stated them, and stopped where the postures hardly turn the
    tool (the real UR10's Series D: "the tip orientations hardly vary") though the previous
    calibration knew the probe to 0.1 mm.
    """
    params = cm.model.params
    prefixes = reflector_prefixes(params)
    held = np.array([p[params.indices([f'{prefix}.{c}' for c in 'xyz'])]
                     for prefix in prefixes])
    registered = _single_start(cm, data, held)[0]
    out = np.array(p, dtype=float)
    for i, name in enumerate(params.names):
        if name.startswith(('base.', 'reflector.')):
            out[i] = registered[i]
    return out


def recordings_start(cm: CellModel, data: Measurements
                     ) -> tuple[np.ndarray, Registration | None]:
    """:func:`registered_start` of several recordings: the first recording's rows as one
    recording's, then every further recording registered on its own rows on the nominal
    robot (a station metres and tens of degrees away needs no start), with the first's
    reflector offsets held unless its probe was remounted. Returns the start vector and
    the first recording's registration.

    Raises
    ------
    DataError
        A recording has too few points or its registered nominal points miss (named).
    """
    names = ('',) + cm.model.recordings
    index = row_recording(data, names)
    p0, reg = _single_start(cm, data.subset(index == 0))
    params = cm.model.params
    for i, name in enumerate(names[1:], 1):
        rows = data.subset(index == i)
        if rows.reflector is not None:
            rows = rows.subset(np.asarray(rows.reflector) < cm.model.n_reflectors)
        prefixes = reflector_prefixes(params)
        remounted = f'{RECORDING_PREFIX}{name}.{prefixes[0]}.x' in params.names
        tips = np.array([cm.robot.pin_tip_pose(row) for row in np.atleast_2d(rows.q)])
        first = np.array([p0[params.indices([f'{prefix}.{c}' for c in 'xyz'])]
                          for prefix in prefixes])
        held = None if remounted else first
        try:
            try:
                own = register(rows.eta, tips, max_rms=REGISTRATION_MAX_RMS_M,
                               reflector=rows.reflector, offsets=held)
            except DataError:
                # Remounted: postures that hardly turn the tool cannot register the
                # offset; it starts at the first recording's, and the joint fit takes what
                # they determine of it. Not remounted: the first's offsets held miss these
                # points (the nominal robot's misfit, a column the recording tilts: 20.2 mm
                # where the offsets free placed them within 10 mm); the offsets free give
                # this station's start, the joint fit keeps the shared probe.
                own = register(rows.eta, tips, max_rms=REGISTRATION_MAX_RMS_M,
                               reflector=rows.reflector,
                               offsets=first if remounted else None)
        except (DataError, ValueError) as exc:
            raise DataError(f'recording {name!r}: {exc}') from None
        values = dict(zip(base_names(name), own.base_in_tracker))
        if remounted:
            offsets = (own.reflector_offsets if own.reflector_offsets is not None
                       else own.reflector_offset.reshape(1, 3))
            for prefix, offset in zip(prefixes, offsets):
                values.update(zip(recording_reflector_names(name, prefix), offset))
        for key, value in values.items():
            p0[params.index(key)] = float(value)
    return p0, reg


def registration_text(reg: Registration | None, cm: CellModel) -> str:
    """One readable line on the placement the identification started from."""
    if reg is None:
        return 'placement: the cell\'s tracker.base_in_tracker and reflector.offset'
    why = ('left out of the cell' if cm.needs_registration
           else f'the nominal missed the points by more than {REGISTER_ABOVE_M} m')
    held = reg.offset_std_m is not None and not np.any(reg.offset_std_m)
    return (f'placement registered from the points ({why}): base_in_tracker '
            f'{np.round(reg.base_in_tracker, 5).tolist()}, reflector offset '
            f'{np.round(reg.reflector_offset, 5).tolist()} m'
            + (" (the cell's, held)" if held else '') + ', registered miss '
            f'{reg.rms_m * 1e3:.3g} mm rms'
            + (f'; measurements {list(reg.trimmed)} missed by far more and were left out of '
               'the registration' if reg.trimmed else ''))
