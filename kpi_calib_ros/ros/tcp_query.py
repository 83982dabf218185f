"""Corrected TCP predictions for queried joint positions.

``~/tcp_query`` (sensor_msgs/JointState: the chain's joints matched by name, controller
values as the robot reports them) is answered on ``~/tcp_corrected``
(geometry_msgs/PoseWithCovarianceStamped in the tracker frame, the query's stamp echoed):
the TCP (KPI point) the calibration predicts at those joints, with the learned residual
of learned_residual.yaml in the node's ``data_dir`` when one is there and corrects the
node's calibration, the one it publishes on ``~/tcp``
(:mod:`kpi_calib_ros.app.learned_residual`; with the model it was written for, the
effects ``identification.model: auto`` added included, also after a restart), else the
node's last calibration alone (after a restart, the one restored from calibration.yaml:
:mod:`kpi_calib_ros.app.stored_calibration`). A learned_residual.yaml written for another
calibration (another robot, or ``kpi-calib identify --learned-residual`` into the
data_dir: :meth:`~kpi_calib_ros.io.learned_residual_file.StoredResidual.other_calibration`,
the check ``validate`` makes) or one that cannot be read is not used: the answer is the
physical calibration's, and why is logged and shown as ``tcp_query`` on /diagnostics
(:attr:`TcpQuery.source`). Before any calibration the learned residual's own (the one it
was written with) answers. The
position block of the covariance holds both parts of the uncertainty (the orientation
is not predicted: :data:`kpi_calib_ros.ros.conversions.UNKNOWN_ORIENTATION_VARIANCE`).
A query outside the region the learned residual was fitted on is answered (the
correction returns to the physical model there and the covariance grows) and logged.

A query the robot cannot stand in is dropped and logged, naming the joint: a position not
finite, beyond a joint's URDF limits by more than :data:`LIMIT_TOLERANCE_RAD` (rad;
:data:`LIMIT_TOLERANCE_M` for a prismatic joint), or, on a continuous joint (no limits),
beyond ±:data:`CONTINUOUS_MAX_RAD`. Each kind of warning has its own 5 s log throttle, so a
repeated problem does not hide a different one.

No custom service type: a topic pair keeps the package buildable as pure Python.
"""
from __future__ import annotations

import time
from collections import Counter
from pathlib import Path
from typing import Any, Callable, Protocol

import numpy as np
from geometry_msgs.msg import PoseWithCovarianceStamped
from rclpy.node import Node
from sensor_msgs.msg import JointState

from kpi_calib_ros.app.cell_model import (
    CONTINUOUS_MAX_RAD,
    LIMIT_TOLERANCE_M,
    LIMIT_TOLERANCE_RAD,
    CellModel,
    joint_range_problem,
)
from kpi_calib_ros.app.learned_residual import predict_stored, predict_tcp, stored_cell_model
from kpi_calib_ros.core.errors import KpiCalibError
from kpi_calib_ros.io.learned_residual_file import StoredResidual, read_residual
from kpi_calib_ros.io.names import TCP_CORRECTED_TOPIC, TCP_QUERY_TOPIC
from kpi_calib_ros.io.ros_messages import stamp_ns
from kpi_calib_ros.ros.conversions import tcp_pose_msgs

QUERY_DEPTH = 10
LOG_THROTTLE_S = 5.0
class Fit(Protocol):
    """A calibration's parameters as the query needs them: every parameter's value
    (n_p,), the identified ones' names and their covariance (k, k); a
    :class:`~kpi_calib_ros.core.estimation.least_squares.CalibrationResult` or a
    calibration.yaml read back
    (:class:`~kpi_calib_ros.app.stored_calibration.StoredCalibration`)."""

    @property
    def values(self) -> np.ndarray: ...

    @property
    def estimated(self) -> tuple[str, ...]: ...

    @property
    def covariance(self) -> np.ndarray: ...


class TcpQuery:
    """``~/tcp_query`` → ``~/tcp_corrected`` on ``node`` (executor thread only).

    Parameters
    ----------
    node : Node
    model, result : callables
        The node's current robot model and calibration (None until there is one; the
        one restored from calibration.yaml after a restart).
    path : Path
        learned_residual.yaml; read again whenever it is replaced or changes (inode,
        modification time or size).
    """

    def __init__(self, node: Node, model: Callable[[], CellModel | None],
                 result: Callable[[], Fit | None], path: Path) -> None:
        self._node, self._model, self._result, self._path = node, model, result, Path(path)
        self._stored: StoredResidual | None = None
        self._stamp: tuple[int, int, int] | None = None
        self._read_error = ''  # why the file as last read is not used ('' : it is)
        # What the last answer was predicted with, and why the learned residual was not
        # used when there is one ('' before the first answer): /diagnostics shows it.
        self.source = ''
        # The cell model of the stored residual, built once per file and node model.
        self._stored_cell: tuple[StoredResidual, CellModel, CellModel | KpiCalibError] | None \
            = None
        self.publisher = node.create_publisher(PoseWithCovarianceStamped, TCP_CORRECTED_TOPIC,
                                               QUERY_DEPTH)
        node.create_subscription(JointState, TCP_QUERY_TOPIC, self.answer, QUERY_DEPTH)
        # Queries dropped (or answered with a warning) per kind of problem, and when each
        # kind was last logged (monotonic s): one throttle per kind.
        self.warnings: Counter[str] = Counter()
        self._logged: dict[str, float] = {}
        self._logger: Any = node.get_logger()

    def _warn(self, kind: str, text: str) -> None:
        """Count a ``kind`` of problem and log ``text`` unless that kind was logged within
        LOG_THROTTLE_S (another kind is never held back by it)."""
        self.warnings[kind] += 1
        now = time.monotonic()
        last = self._logged.get(kind)
        if last is None or now - last >= LOG_THROTTLE_S:
            self._logged[kind] = now
            self._logger.warning(text)

    def stored(self) -> StoredResidual | None:
        """learned_residual.yaml as last read (None: no file); a changed file is read again,
        a damaged one is logged and not used."""
        try:
            info = self._path.stat()
        except FileNotFoundError:
            self._stored, self._stamp = None, None
            return None
        # A new file is written atomically (a new inode): mtime alone may repeat within
        # the file system's timestamp granularity.
        stamp = (info.st_ino, info.st_mtime_ns, info.st_size)
        if stamp != self._stamp:
            self._stamp, self._read_error = stamp, ''
            try:
                self._stored = read_residual(self._path)
            except KpiCalibError as exc:
                self._stored, self._read_error = None, str(exc)
            except Exception as exc:  # noqa: BLE001 - a file from outside never stops the node
                self._stored = None
                self._read_error = f'{self._path} cannot be read: {type(exc).__name__}: {exc}'
            if self._read_error:
                self._node.get_logger().error(f'learned residual not used: {self._read_error}')
        return self._stored

    def stored_model(self, cm: CellModel, stored: StoredResidual) -> CellModel:
        """The cell model ``stored`` was written for (:func:`stored_cell_model`): ``cm``
        or its cell with the stored effects, built once per file (KpiCalibError: it
        does not fit this cell)."""
        cached = self._stored_cell
        if cached is None or cached[0] is not stored or cached[1] is not cm:
            try:
                built: CellModel | KpiCalibError = stored_cell_model(cm, stored)
            except KpiCalibError as exc:
                built = exc
            cached = self._stored_cell = (stored, cm, built)
        if isinstance(cached[2], KpiCalibError):
            raise cached[2].with_traceback(None)  # the same error, no traceback piled up
        return cached[2]

    def answer(self, msg: JointState) -> None:
        """Publish the corrected TCP for the query ``msg`` (logged and dropped when the
        robot model, the calibration or a chain joint is missing)."""
        cm = self._model()
        if cm is None:
            self._warn('no_model', 'TCP query dropped: no robot model yet')
            return
        positions = dict(zip(msg.name, msg.position))
        missing = [n for n in cm.joint_names if n not in positions]
        if missing:
            self._warn('missing_joints', f'TCP query dropped: joints {missing} missing (the '
                       f'chain needs {list(cm.joint_names)})')
            return
        controller = np.array([[positions[n] for n in cm.joint_names]], dtype=float)
        with np.errstate(all='ignore'):  # a non-finite reading is named below
            q = cm.joint_coupling.to_urdf(controller)
        problem = joint_range_problem(cm, q[0]) if np.all(np.isfinite(controller)) else (
            f'joint {cm.joint_names[int(np.argmin(np.isfinite(controller[0])))]} position '
            'is not finite')
        if problem:
            self._warn('joint_range', f'TCP query dropped: {problem}')
            return
        stored = self.stored()
        result = self._result()
        unused = self._read_error
        if stored is not None and result is not None:
            # Only a learned residual of the calibration the node publishes corrects it.
            unused = stored.other_calibration(cm.model.params.names, result.values)
            if unused:
                stored = None
        try:
            if stored is not None:
                tcp = predict_stored(self.stored_model(cm, stored).model, stored, q)
                source = 'learned residual' + ('' if result is not None else
                                               ' with the calibration it was written with')
            elif result is not None:
                tcp = predict_tcp(cm.model, result.values, result.estimated,
                                  result.covariance, None, q)
                source = ('physical calibration' if not unused else
                          f'physical calibration only, learned residual not used: {unused}')
            else:
                self._warn('no_calibration', 'TCP query dropped: no calibration yet (call '
                           '~/identify)')
                return
        except KpiCalibError as exc:
            self._warn('model', f'TCP query dropped: {exc}')
            return
        if source != self.source and unused:
            self._node.get_logger().warning(f'TCP query answered with the {source}')
        self.source = source
        if tcp.correction is not None and not tcp.correction.inside[0]:
            self._warn('outside_learned_region', f'TCP query outside the region the learned '
                       f'residual was fitted on (distance {tcp.correction.distance[0]:.2g} '
                       'length scales): the correction returns to the physical model, the '
                       'covariance grows')
        self.publisher.publish(tcp_pose_msgs(tcp.position, tcp.covariance,
                                             cm.cell.tracker_frame, stamp_ns(msg.header))[0])


__all__ = ['CONTINUOUS_MAX_RAD', 'LIMIT_TOLERANCE_M', 'LIMIT_TOLERANCE_RAD', 'TcpQuery',
           'joint_range_problem']
