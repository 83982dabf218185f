"""What one campaign run of the node has found, as plain data: ``~/reset`` starts a new one.

No rclpy here: the node keeps one :class:`RunState` (read and written on its executor
thread only) and replaces it whole on ``~/reset``, so nothing of the last campaign's
results survives by a forgotten attribute. The questions the node asks of it (is a
sequential campaign running, is a step due) are answered here from the state alone.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from kpi_calib_ros.app.cell_model import CellModel
from kpi_calib_ros.app.stored_calibration import StoredCalibration
from kpi_calib_ros.core.campaigns.sequential import SequentialCampaign
from kpi_calib_ros.core.campaigns.settings import MODEL_INADEQUATE, CampaignStatus
from kpi_calib_ros.core.estimation.least_squares import CalibrationResult
from kpi_calib_ros.core.estimation.robust import RobustResult
from kpi_calib_ros.io.campaign_io import CampaignState

# Parameters a running sequential campaign was started with: refused while it runs (its
# status, plan and stop rule rest on them).
CAMPAIGN_FIXED = ('campaign', 'target_tcp_std', 'max_measurements', 'design_seed')


@dataclass
class RunState:
    """The node's results and sequential campaign of the current run.

    ``result``: the last published calibration's fit, ``cell`` the cell model it belongs
    to (with the effects ``identification.model: auto`` added); ``measured`` its fitted points (m)
    and ``marker_rows`` which of them are points to draw residuals from; ``robust`` its
    robust statistics; ``result_error`` why the last identification failed ('' if it did
    not); ``identified_with`` the number of measurements it used; ``auto_pending`` an
    automatic identification is due; ``diagnosis`` the last ~/diagnose document;
    ``learned_residual`` the learned residual of the last ~/identify with
    ``identify_learned_residual`` (``chosen``, ``not chosen``, ``not fitted``; '' without).

After a restart, ``restored`` is data_dir/calibration.yaml read back for this cell
(``restore_pending`` until the robot model is known): the published calibration until
a new one replaces it (``result`` stays None, no fit of this run).

    A sequential campaign (``campaign:=sequential``): ``sequential`` the campaign object
    (handed to the worker of a step job and back), ``sequential_status`` its last
    status, ``sequential_stamps`` the measurement stamps it has been given,
    ``sequential_initial`` the size of its initial design, ``sequential_state`` the
    campaign as data_dir/campaign_state.yaml keeps it; one found at start is resumed
    (``resume_pending``) once the robot model is known, then ``resumed``.
    """

    result: CalibrationResult | None = None
    cell: CellModel | None = None
    measured: np.ndarray | None = None
    marker_rows: np.ndarray | None = None
    result_error: str = ''
    robust: RobustResult | None = None
    identified_with: int = 0
    auto_pending: bool = False
    diagnosis: dict[str, Any] | None = None
    learned_residual: str = ''
    restored: StoredCalibration | None = None
    restore_pending: bool = False
    sequential: SequentialCampaign | None = None
    sequential_status: CampaignStatus | None = None
    sequential_stamps: set[int] = field(default_factory=set)
    sequential_initial: int = 0
    sequential_state: CampaignState | None = None
    # The cell model the campaign plans and identifies in (its station's placement).
    sequential_cm: Any = None
    resume_pending: bool = False
    resumed: bool = False
    # Why the node stopped the campaign itself ('' : it did not): the station changed.
    sequential_stopped: str = ''

    def sequential_running(self) -> bool:
        """A sequential campaign was started (or is to be resumed) and has not stopped."""
        if self.sequential_stopped:
            return False
        if self.resume_pending:
            return self.sequential_state is not None and not self.sequential_state.stopped
        status = self.sequential_status
        return self.sequential is not None and (status is None or not status.stopped)

    def sequential_due(self, accepted: int) -> bool:
        """A step is due: the campaign runs, the initial design is measured and some of
        the ``accepted`` measurements have not been added yet."""
        if self.resume_pending or not self.sequential_running():
            return False
        return accepted >= self.sequential_initial and accepted > len(self.sequential_stamps)

    def refused_change(self, fixed: list[str]) -> str:
        """Why changing the parameters ``fixed`` (of :data:`CAMPAIGN_FIXED`, to new values)
        is refused now ('' : it is not): a running sequential campaign keeps them."""
        if not fixed or not self.sequential_running():
            return ''
        state = self.sequential_state
        now = ('' if state is None else
               f' (target_tcp_std {state.settings.target_std:g} m, max_measurements '
               f'{state.settings.max_measurements})')
        return (f"{', '.join(fixed)}: a sequential campaign is running{now}; it keeps the "
                'values it started with, which ~/campaign_status and /diagnostics show. '
                'Change them after it stops, or call ~/reset and ~/design to start a new '
                'campaign')

    def published_tcp(self) -> tuple[np.ndarray | None, np.ndarray | None]:
        """The published calibration's TCP (t, 3) (m) and its covariance (t, 3, 3) (m²):
        of this run's fit, else of the restored calibration; (None, None) without."""
        if self.result is not None:
            return self.result.tcp, self.result.tcp_covariance
        if self.restored is not None:
            return self.restored.tcp, self.restored.tcp_covariance
        return None, None

    def residual_arrows(self) -> tuple[np.ndarray | None, np.ndarray | None]:
        """The fitted points (m) and their residuals (m) to draw as arrows: the rows that
        are points (``marker_rows``); (None, None) before an identification."""
        result = self.result
        measured, residuals = self.measured, None if result is None else result.residuals
        rows = self.marker_rows
        if (measured is not None and residuals is not None and rows is not None
                and len(rows) == len(measured) == len(residuals)):
            measured, residuals = measured[rows], residuals[rows]
        return measured, residuals

    def campaign_inadequate(self) -> bool:
        """The sequential campaign stopped as model inadequate: a calibration of its
        measurements is never archived as the next cycle's prior."""
        status = self.sequential_status
        return status is not None and status.stop_reason == MODEL_INADEQUATE


__all__ = ['CAMPAIGN_FIXED', 'RunState']
