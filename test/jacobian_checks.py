"""The Jacobian of a measurement model against central finite differences: the check the
effect tests share."""
from __future__ import annotations

from typing import Iterable, Mapping

import numpy as np

from kpi_calib_ros.core.measurement.tracker import MeasurementModel


def assert_jacobian_equals_finite_differences(
        model: MeasurementModel, p: np.ndarray, q: np.ndarray,
        covariates: Mapping[str, np.ndarray] | None, columns: Iterable[int],
        h: float = 1e-7, atol: float = 1e-7) -> None:
    """Assert that the columns ``columns`` of ``model.jacobian`` at parameters ``p`` (n_p,),
    poses ``q`` (N, n) and ``covariates`` (name -> (N,)) equal the central differences of
    ``model.predict`` with step ``h`` (the parameter's unit), within ``atol`` (m per unit)."""
    _, jac = model.jacobian(p, q, covariates=covariates)
    for i in columns:
        step = np.zeros(len(p))
        step[i] = h
        fd = (model.predict(p + step, q, covariates=covariates)
              - model.predict(p - step, q, covariates=covariates)) / (2 * h)
        np.testing.assert_allclose(jac[:, :, i], fd, atol=atol)
