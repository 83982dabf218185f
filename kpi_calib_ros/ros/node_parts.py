"""What the node's job modules use of the node, declared once.

:class:`~kpi_calib_ros.ros.node.CalibrationNode` is its jobs
(:mod:`~kpi_calib_ros.ros.calibration_jobs`, :mod:`~kpi_calib_ros.ros.restore`,
:mod:`~kpi_calib_ros.ros.sequential_jobs`) over :class:`NodeParts`: the state, publishers
and output methods the node provides, declared here so that each job module is checked
against them. The methods here only raise: the node (or a job module) defines each, and
comes before this class in the method resolution order whatever the order of the jobs.
"""
from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
from rclpy.publisher import Publisher

from kpi_calib_ros.app.cell_model import CellModel
from kpi_calib_ros.ros.job_node import JobNode
from kpi_calib_ros.ros.measurement_store import MeasurementStore
from kpi_calib_ros.ros.parameters import NodeSettings
from kpi_calib_ros.ros.run_state import RunState


class NodeParts(JobNode):
    """The state, publishers and methods of
    :class:`~kpi_calib_ros.ros.node.CalibrationNode` its job modules use (executor thread
    only, as the node's module docstring says)."""

    store: MeasurementStore
    settings: NodeSettings
    data_dir: Path
    _run: RunState
    _design_points: np.ndarray | None
    _calibration_text: str          # the published calibration.yaml
    _identified_stamps: set[int]    # stamps the calibration was fitted to
    _identifications: int
    _pub_poses: Publisher
    _pub_calibration: Publisher
    _pub_change_test: Publisher
    _pub_urdf: Publisher
    _pub_diagnosis: Publisher
    _pub_validation: Publisher
    _pub_campaign_status: Publisher

    def _model(self) -> CellModel:
        raise NotImplementedError

    def _tcp_publisher(self, depth: int) -> Publisher:
        raise NotImplementedError

    def _publish_markers(self) -> None:
        raise NotImplementedError

    def _design_station(self) -> tuple[str, bool, str]:
        raise NotImplementedError

    def _publish_diagnostics(self, force: bool = False) -> None:
        raise NotImplementedError

    def _publish_calibration(self, cal: Any, measured: np.ndarray, marker_rows: np.ndarray,
                             identified_with: int, text: str, urdf: str, tcp: list,
                             stamps: np.ndarray | None) -> None:
        raise NotImplementedError


__all__ = ['NodeParts']
