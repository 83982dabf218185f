"""Everything the diagnosis of a cell computes, in one record (:class:`CellDiagnosis`).

Filled by :func:`kpi_calib_ros.app.diagnose.diagnose_cell`, written by the reports.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from kpi_calib_ros.core.diagnosis.misfit import MisfitAnswer
from kpi_calib_ros.core.diagnosis.model_comparison import ModelComparison
from kpi_calib_ros.core.diagnosis.out_of_sample import OutOfSample
from kpi_calib_ros.core.diagnosis.residual_analysis import ResidualAnalysis
from kpi_calib_ros.core.diagnosis.verdict import Diagnosis
from kpi_calib_ros.core.effects.registry import BoundEffect
from kpi_calib_ros.core.estimation.estimability import KpiEstimability
from kpi_calib_ros.core.estimation.least_squares import CalibrationResult
from kpi_calib_ros.core.estimation.precision import ExpectedTcpError
from kpi_calib_ros.core.measurement.data import Measurements
from kpi_calib_ros.core.measurement.tracker import MeasurementModel

__all__ = ['CellDiagnosis']


@dataclass(frozen=True)
class CellDiagnosis:
    """Everything :func:`kpi_calib_ros.app.diagnose.diagnose_cell` computes.

    ``after``/``comparison`` only when an effect was added.
    """

    model: MeasurementModel
    data: Measurements
    result: CalibrationResult
    diagnosis: Diagnosis
    added: BoundEffect | None = None
    after_model: MeasurementModel | None = None
    after: CalibrationResult | None = None
    comparison: ModelComparison | None = None
    # Predicted error of new measurements at fresh poses (core.diagnosis.out_of_sample), of the
    # calibration diagnosed and of the one with the added effect.
    out_of_sample: OutOfSample | None = None
    after_out_of_sample: OutOfSample | None = None
    # The measurements given: ``data`` is those identification keeps (``kept``, (M,) bool;
    # None: all), so the diagnosis describes the calibration the user gets; ``excluded``
    # names the others (indices into the given measurements).
    kept: np.ndarray | None = None
    excluded: tuple[int, ...] = ()

    def given_index(self, rows: np.ndarray) -> list[int]:
        """Return indices into the given measurements of rows (bool mask or indices) of ``data``."""
        rows = np.asarray(rows)
        idx = np.flatnonzero(rows) if rows.dtype == bool else rows.astype(int)
        return [int(i) for i in (idx if self.kept is None else np.flatnonzero(self.kept)[idx])]
    # Expected TCP error at the working poses with the misfit (core.estimation.precision).
    expected: ExpectedTcpError | None = None
    # Where the model fails, model-free (core.diagnosis.residual_analysis), and the four answers
    # (core.diagnosis.misfit: where, what is missing, the command, held-out error before/after).
    residual_analysis: ResidualAnalysis | None = None
    answer: MisfitAnswer | None = None
    # Whether the measurements determine the TCP at the working poses, identify's verdict
    # (core.estimation.estimability); when they do not, ``expected`` is None and the
    # verdict says so.
    estimability: KpiEstimability | None = None
    # What the recordings say before the robot: a probe they disagree on (not declared
    # remounted), a placement that changed while measured (a tracker knocked); each a line
    # naming the recording and the fix. The effects are screened on a fit these bend.
    set_up: tuple[str, ...] = ()

    @property
    def tcp_estimable(self) -> bool:
        """Whether the TCP is estimable at every working pose (True when not checked)."""
        return self.estimability is None or self.estimability.all_estimable
