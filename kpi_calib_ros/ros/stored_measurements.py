"""The node's stored measurements as the model takes them, for its identify, diagnose and
campaign jobs.

:func:`model_measurements` reads every accepted measurement of a
:class:`~kpi_calib_ros.ros.measurement_store.MeasurementStore` as a bag's are read
(:mod:`kpi_calib_ros.app.measurements`): every row of each pose, URDF joint values, the
stated σ, and the temperature and measured-input readings paired to the rows by stamp;
:func:`station_measurements` adds each tracker station as a recording, as ``kpi-calib
identify`` takes several.
"""
from __future__ import annotations

import dataclasses

import numpy as np

from kpi_calib_ros.app.cell_model import CellModel
from kpi_calib_ros.app.measurements import (
    pose_rows,
    urdf_measurements,
    with_inputs,
    with_readings,
    with_recordings,
)
from kpi_calib_ros.core.acquisition.outcomes import PairingResult
from kpi_calib_ros.core.measurement.data import Measurements
from kpi_calib_ros.core.measurement.recordings import Recording, row_covariates
from kpi_calib_ros.ros.measurement_store import MeasurementStore


def model_measurements(store: MeasurementStore, cm: CellModel
                       ) -> tuple[Measurements, PairingResult]:
    """Every accepted measurement in ``store`` as the model ``cm`` takes it: every row
    of each pose (reflectors, tracked bodies' rotation rows), URDF joint values (from the
    controller's readings), stamps as int64 ns, each row's stated σ (NaN: the cell's)."""
    data, pairing = store.measurements(cm.joint_names, cm.cell.tracker_frame,
                                       cm.cell.reflector_names or ('',))
    data = urdf_measurements(cm, pose_rows(cm, data, pairing))
    stamps = np.asarray(data.stamps_ns, dtype=np.int64).ravel()
    data = with_temperature_readings(store, cm, dataclasses.replace(data, stamps_ns=stamps))
    return with_input_readings(store, cm, data), pairing


def station_rows(store: MeasurementStore, data: Measurements, pairing: PairingResult,
                 station: str) -> tuple[Measurements, PairingResult]:
    """The rows of ``data`` (and the poses of ``pairing``) measured from ``station``; all
    of them for '' (a campaign state written before stations)."""
    if not station:
        return data, pairing
    stamps = np.asarray(data.stamps_ns, dtype=np.int64).ravel()
    recordings, index = store.stations(stamps)
    names = [r.name for r in recordings]
    mine = (index == names.index(station)) if station in names else np.zeros(len(data), bool)
    keep = np.isin(np.asarray(pairing.stamps_ns, dtype=np.int64), stamps[mine])
    return data.subset(mine), dataclasses.replace(
        pairing, q=pairing.q[keep], eta=pairing.eta[keep], stamps_ns=pairing.stamps_ns[keep],
        rotations=None if pairing.rotations is None else pairing.rotations[keep],
        reflectors=tuple(r for r, k in zip(pairing.reflectors, keep) if k)
        if pairing.reflectors else ())


def station_measurements(store: MeasurementStore, cm: CellModel
                         ) -> tuple[CellModel, Measurements, PairingResult, list[Recording]]:
    """:func:`model_measurements` over every station: with measurements from several, the
    cell model with each further station's placement
    (:func:`kpi_calib_ros.app.measurements.with_recordings`) and each row's one-hot
    ``recording.<station>``, as ``kpi-calib identify`` takes several recordings; the stations
    as recordings, in the order first measured."""
    data, pairing = model_measurements(store, cm)
    recordings, index = store.stations(np.asarray(data.stamps_ns))
    if len(recordings) <= 1:
        return cm, data, pairing, recordings
    covariates = dict(data.covariates or {})
    covariates.update(row_covariates([r.name for r in recordings], index))
    return (with_recordings(cm, recordings), dataclasses.replace(data, covariates=covariates),
            pairing, recordings)


def with_input_readings(store: MeasurementStore, cm: CellModel,
                        data: Measurements) -> Measurements:
    """``data`` with the store's measured input readings paired to its rows by stamp, as
    a bag's are (:func:`kpi_calib_ros.app.measurements.with_inputs`).

    Raises
    ------
    DataError
        A source of the cell gave no finite reading (with ``compliance.torque_source:
        measured``: no effort of every chain joint at the measurements).
    """
    return with_inputs(cm, data, store.inputs(), 'the node\'s measured inputs',
                       [s.topic for s in cm.cell.inputs.sources])


def with_temperature_readings(store: MeasurementStore, cm: CellModel,
                              data: Measurements) -> Measurements:
    """``data`` with the store's temperature readings paired to its rows by stamp, as
    a bag's are (:func:`kpi_calib_ros.app.measurements.with_readings`); unchanged when
    the cell reads no temperature. A row outside the readings is refused with a warning.

    Raises
    ------
    DataError
        The cell reads a temperature but none has arrived (or a listed sensor never did).
    """
    return with_readings(cm, data, lambda _topic: store.temperatures())


__all__ = ['model_measurements', 'station_measurements', 'with_input_readings',
           'with_temperature_readings']
