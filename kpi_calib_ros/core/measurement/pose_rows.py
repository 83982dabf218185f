"""The rotation rows of tracked poses added to point data, one after each point that has one.

See :mod:`kpi_calib_ros.core.measurement.pose` for the rotation row itself.
"""
from __future__ import annotations

import numpy as np

from kpi_calib_ros.core.measurement.data import Measurements
from kpi_calib_ros.core.measurement.tracker import MeasurementModel

__all__ = ['with_rotation_rows']


def with_rotation_rows(model: MeasurementModel, data: Measurements,
                       rotations: np.ndarray) -> Measurements:
    """Return ``data`` (point rows) with a rotation row after every row with a body rotation.

    ``rotations`` (N, 3, 3) are the measured body rotations, NaN where a row has none (a plain
    point).

    The rotation row repeats the pose's ``q`` and stamp, has ``eta = 0`` and reflector
    index :meth:`MeasurementModel.rotation_channel` of its point's reflector.

    Raises
    ------
    ValueError
        A row carries a rotation but its reflector has no orientation in the model.
    """
    rotations = np.asarray(rotations, float).reshape(len(data), 3, 3)
    has = np.all(np.isfinite(rotations), axis=(1, 2))
    if not has.any():
        return data
    ref = (np.zeros(len(data), dtype=int) if data.reflector is None
           else np.asarray(data.reflector, dtype=int))
    order, channel = [], []
    for i in range(len(data)):
        order.append(i)
        channel.append(ref[i])
        if has[i]:
            order.append(i)
            channel.append(model.rotation_channel(int(ref[i])))
    rows = np.array(order)
    rotation_row = np.array(channel) >= model.n_reflectors
    expanded = data.subset(rows)
    eta = np.where(rotation_row[:, None], 0.0, expanded.eta)
    rot = np.where(rotation_row[:, None, None], rotations[rows], np.eye(3))
    # A rotation row is in metres at the cell's σ (rotation_scale): no stated point σ.
    sigma = (None if expanded.sigma is None
             else np.where(rotation_row[:, None], np.nan, expanded.sigma))
    return Measurements(q=expanded.q, eta=eta, tau=expanded.tau, stamps_ns=expanded.stamps_ns,
                        reflector=np.array(channel), rotation=rot, sigma=sigma,
                        covariates=expanded.covariates)
