"""kpi_calib_node: measurement design, live pairing, durable logging and re-identification.

A thin layer over the core: it converts messages, calls the same functions as
``kpi-calib`` and publishes. Live samples go to a
:class:`~kpi_calib_ros.ros.campaign.Campaign`, which pairs them with the code that
pairs bags and logs every accepted measurement to disk before counting it, so a
replayed bag and ``kpi-calib identify`` agree and a killed node loses nothing.

Services (std_srvs/srv/Trigger): ``~/design``, ``~/identify``, ``~/diagnose``, ``~/reset``.
One executor thread serves callbacks in arrival order; long work (design,
identification) runs in a worker thread while the service callback awaits it, so
pairing continues, and a call while another job runs answers
``success=False, message='busy: ...'``. (rclpy's MultiThreadedExecutor could not keep
up with 1 kHz joint states on two cores.)
"""
from __future__ import annotations

import json
import sys
import threading
import time
from pathlib import Path
from typing import Any, Callable

import numpy as np
import rclpy
import yaml
from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import PointStamped, PoseWithCovarianceStamped
from rcl_interfaces.msg import ParameterDescriptor, SetParametersResult
from rclpy.callback_groups import MutuallyExclusiveCallbackGroup, ReentrantCallbackGroup
from rclpy.exceptions import ParameterUninitializedException
from rclpy.executors import ExternalShutdownException
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from rclpy.task import Future
from sensor_msgs.msg import JointState
from std_msgs.msg import String
from std_srvs.srv import Trigger
from trajectory_msgs.msg import JointTrajectory
from visualization_msgs.msg import MarkerArray

from kpi_calib_ros.app.design import design_cell_model
from kpi_calib_ros.app.diagnose import diagnose_cell
from kpi_calib_ros.app.identify import calibration_document, identify_cell
from kpi_calib_ros.core.collision import Capsule
from kpi_calib_ros.core.errors import ConfigError, DataError, KpiCalibError
from kpi_calib_ros.core.estimation import CalibrationResult
from kpi_calib_ros.core.pairing import Decision, Rejection
from kpi_calib_ros.core.residuals import is_adequate
from kpi_calib_ros.io.cell import CellModel, build_cell_model, load_cell, with_overrides
from kpi_calib_ros.io.design_io import write_design
from kpi_calib_ros.io.names import (CALIBRATED_URDF_FILE, CALIBRATED_URDF_TOPIC,
                                    CALIBRATION_TOPIC, DESIGN_FILE, DIAGNOSIS_DIR,
                                    DIAGNOSIS_TOPIC, DIAGNOSTICS_TOPIC, MARKERS_TOPIC,
                                    MEASUREMENT_POSES_TOPIC, TCP_TOPIC)
from kpi_calib_ros.io.report import diagnosis_to_dict, write_report
from kpi_calib_ros.io.results import write_atomic, write_calibration
from kpi_calib_ros.io.urdf_export import calibrated_urdf
from kpi_calib_ros.ros import conversions as cv
from kpi_calib_ros.ros.campaign import Campaign
from kpi_calib_ros.ros.parameters import PARAMETERS, settings_from_parameters, working_poses

NODE_NAME = 'kpi_calib_node'


def _latched(depth: int = 1) -> QoSProfile:
    return QoSProfile(depth=depth, reliability=ReliabilityPolicy.RELIABLE,
                      durability=DurabilityPolicy.TRANSIENT_LOCAL)


def _stream_qos(depth: int) -> QoSProfile:
    return QoSProfile(depth=depth, reliability=ReliabilityPolicy.RELIABLE)


class CalibrationNode(Node):
    """The calibration node; the README's "cell controller" section lists its interface."""

    def __init__(self, **kwargs) -> None:
        super().__init__(NODE_NAME, **kwargs)
        for name, (default, read_only, description) in PARAMETERS.items():
            self.declare_parameter(name, default, ParameterDescriptor(
                description=description, read_only=read_only))
        self.settings = settings_from_parameters(self._parameter_values())
        self.add_on_set_parameters_callback(self._on_set_parameters)
        # The cell once, validated; the URDF comes from the parameter or the topic.
        self._cell = load_cell(self.settings.cell_file, urdf_xml='')
        self.data_dir = Path(self.settings.data_dir)
        self.campaign = Campaign(self.data_dir)
        self.get_logger().info(f'{self.campaign.restored} measurement(s) restored from '
                               f'{self.data_dir}; logging to {self.campaign.log.path}')

        self._job = threading.Lock()  # one long job at a time: design, identify, reset
        self._job_name = ''
        self._cm: CellModel | None = None
        self._urdf = ''
        self._model_error = ''
        self._auto_pending = False
        self._result: CalibrationResult | None = None
        self._measured: np.ndarray | None = None
        self._result_error = ''
        self._identified_with = 0
        self._design_points: np.ndarray | None = None
        self._diagnosis: dict[str, Any] | None = None
        self._capsules: list[Capsule] = []
        self._last_diagnostics: tuple[Any, float] = (None, 0.0)

        # One executor thread: pairing callbacks run in arrival order; services await
        # their worker threads in a reentrant group so a second call gets 'busy'.
        streams = MutuallyExclusiveCallbackGroup()
        services = ReentrantCallbackGroup()
        self._pub_poses = self.create_publisher(JointTrajectory, MEASUREMENT_POSES_TOPIC,
                                                _latched())
        self._pub_calibration = self.create_publisher(String, CALIBRATION_TOPIC, _latched())
        self._pub_urdf = self.create_publisher(String, CALIBRATED_URDF_TOPIC, _latched())
        self._pub_markers = self.create_publisher(MarkerArray, MARKERS_TOPIC, _latched())
        self._pub_diagnosis = self.create_publisher(String, DIAGNOSIS_TOPIC, _latched())
        self._pub_diagnostics = self.create_publisher(DiagnosticArray, DIAGNOSTICS_TOPIC, 10)
        self._pub_tcp = None  # latched with one message per working pose: made with the model
        self.create_subscription(JointState, self.settings.joint_states_topic,
                                 self._on_joint_state, _stream_qos(1000), callback_group=streams)
        self.create_subscription(PointStamped, self.settings.point_topic, self._on_point,
                                 _stream_qos(100), callback_group=streams)
        for name, doing, work in (('design', 'designing', self._design),
                                  ('identify', 'identifying', self._identify),
                                  ('diagnose', 'diagnosing', self._diagnose),
                                  ('reset', 'resetting', self._reset)):
            self.create_service(Trigger, f'~/{name}', self._service(name, doing, work),
                                callback_group=services)
        self.create_timer(0.1, self._tick, callback_group=streams)
        if self.settings.robot_description:
            self._set_robot_description(self.settings.robot_description)
        else:
            self.create_subscription(String, self.settings.robot_description_topic,
                                     self._on_robot_description, _latched(),
                                     callback_group=streams)
            self.get_logger().info(f'waiting for {self.settings.robot_description_topic}')

    # ------------------------------------------------------------------ parameters
    def _parameter_values(self, changes: dict[str, Any] | None = None) -> dict[str, Any]:
        values = {}
        for name in PARAMETERS:
            try:
                values[name] = self.get_parameter(name).value
            except ParameterUninitializedException:  # an array parameter left empty
                values[name] = []
        values.update(changes or {})
        return values

    def _on_set_parameters(self, parameters: list[Parameter]) -> SetParametersResult:
        try:
            self.settings = settings_from_parameters(self._parameter_values(
                {p.name: p.value for p in parameters}))
        except ConfigError as exc:
            return SetParametersResult(successful=False, reason=str(exc))
        self._auto_pending = self._auto_wanted()
        return SetParametersResult(successful=True)

    # ------------------------------------------------------------------ robot model
    def _on_robot_description(self, msg: String) -> None:
        if msg.data != self._urdf:
            try:
                self._set_robot_description(msg.data)
            except (KpiCalibError, ValueError) as exc:  # bad URDF / cell: report, keep waiting
                self._model_error = f'robot description rejected: {exc}'
                self.get_logger().error(self._model_error)

    def _set_robot_description(self, urdf_xml: str) -> None:
        cm = build_cell_model(with_overrides(self._cell, urdf_xml=urdf_xml,
                                             working_poses=working_poses(self.settings)))
        scene = cm.collision_scene()
        self._capsules = scene.robot_capsules + [o for o in scene.obstacles
                                                 if isinstance(o, Capsule)]
        if self._pub_tcp is not None:
            self.destroy_publisher(self._pub_tcp)
        self._pub_tcp = self.create_publisher(PoseWithCovarianceStamped, TCP_TOPIC,
                                              _latched(len(cm.working_pose_names)))
        self._cm, self._urdf, self._model_error = cm, urdf_xml, ''
        self._report(self.campaign.set_chain(cm.joint_names, cm.cell.tracker_frame))
        self._auto_pending = self._auto_wanted()
        self.get_logger().info(f'robot model ready: joints {cm.joint_names}, tracker frame '
                               f"'{cm.cell.tracker_frame}', working poses "
                               f'{list(cm.working_pose_names)}')

    # ------------------------------------------------------------------ live pairing
    def _on_joint_state(self, msg: JointState) -> None:
        self._report(self.campaign.receive(cv.joint_sample_from_msg(msg)))

    def _on_point(self, msg: PointStamped) -> None:
        self._report(self.campaign.receive(cv.point_sample_from_msg(msg)))

    def _report(self, decisions: list[Decision]) -> None:
        for d in decisions:
            if isinstance(d, Rejection):
                self.get_logger().warning(f'rejected ({d.reason}): {d.detail}',
                                          throttle_duration_sec=1.0)
            elif self._auto_wanted():
                self._auto_pending = True

    def _auto_wanted(self) -> bool:
        return (self.settings.auto_identify and self._cm is not None
                and len(self.campaign) >= self.settings.min_measurements)

    def _tick(self) -> None:
        self._report(self.campaign.poll())
        if self._auto_pending and self._job.acquire(blocking=False):
            self._auto_pending = False
            self._job_name = 'identifying (automatic)'
            threading.Thread(target=self._run_job, daemon=True,
                             args=('automatic identification', self._identify)).start()
        self._publish_diagnostics()

    # ------------------------------------------------------------------ jobs
    def _service(self, name: str, doing: str, work: Callable[[], tuple[bool, str]]):
        """A Trigger callback that runs ``work`` in a worker thread and answers when it is
        done; the executor keeps serving meanwhile (the callback awaits, it does not block)."""
        async def callback(request: Trigger.Request,
                           response: Trigger.Response) -> Trigger.Response:
            if not self._job.acquire(blocking=False):
                response.success, response.message = False, f'busy: {self._job_name}'
                return response
            self._job_name = doing
            done = Future(executor=self.executor)
            done.add_done_callback(lambda _: None)  # its scheduling wakes the executor
            threading.Thread(target=self._run_job, args=(name, work, done), daemon=True).start()
            response.success, response.message = await done
            return response
        return callback

    def _run_job(self, name: str, work: Callable[[], tuple[bool, str]],
                 done: Future | None = None) -> None:
        """Run ``work`` holding the job lock (acquired by the caller), then release it."""
        try:
            outcome = work()
        except Exception as exc:  # job boundary: answer, log, keep the node up
            self.get_logger().error(f'{name} failed: {exc}')
            outcome = (False, f'{name} failed: {exc}')
        else:
            self.get_logger().info(f'{name}: {outcome[1]}')
        self._job_name = ''
        self._job.release()
        if done is not None:
            done.set_result(outcome)

    def _model(self) -> CellModel:
        if self._cm is None:
            raise DataError(self._model_error or 'no robot model yet: waiting for '
                            f'{self.settings.robot_description_topic}')
        return self._cm

    def _design(self) -> tuple[bool, str]:
        cm, s = self._model(), self.settings
        design = design_cell_model(cm, s.num_measurements, s.criterion, s.design_seed)
        path = write_design(self.data_dir / DESIGN_FILE, design)
        self._pub_poses.publish(cv.joint_trajectory_msg(design.joint_names,
                                                        design.configurations))
        self._design_points = cm.model.predict(cm.model.params.nominal, design.configurations)
        self._publish_markers()
        tcp_um = np.sqrt((design.tcp_std ** 2).sum(axis=1)).max() * 1e6
        return design.verification.ok, (
            f'{len(design.configurations)} poses ({design.criterion}), predicted TCP '
            f'sqrt(trace) <= {tcp_um:.1f} µm; {design.status}; published on '
            f'{self.resolve_topic_name(MEASUREMENT_POSES_TOPIC)}, written to {path}')

    def _identify(self) -> tuple[bool, str]:
        """Identify from every accepted measurement (as ``kpi-calib identify`` does);
        write the results atomically and publish them."""
        cm = self._model()
        data, pairing = self.campaign.measurements(cm.joint_names, cm.cell.tracker_frame)
        try:
            result = identify_cell(cm, data)
        except KpiCalibError as exc:
            self._result_error = f'identification failed: {exc}'
            raise
        doc = calibration_document(cm, result, pairing)
        urdf = calibrated_urdf(cm.cell.urdf_xml, cm.robot,
                               dict(zip(result.names, result.values)))
        write_calibration(self.data_dir, doc)
        write_atomic(self.data_dir / CALIBRATED_URDF_FILE, urdf)
        self._result, self._measured, self._identified_with = result, data.eta, len(data)
        self._result_error = '' if result.converged else f'not converged: {result.status}'
        self._pub_calibration.publish(String(data=yaml.safe_dump(doc, sort_keys=False)))
        self._pub_urdf.publish(String(data=urdf))
        for msg in cv.tcp_pose_msgs(result.tcp, result.tcp_covariance, cm.cell.tracker_frame,
                                    int(data.stamps_ns[-1])):
            self._pub_tcp.publish(msg)
        self._publish_markers()
        self._publish_diagnostics(force=True)
        tcp_um = np.sqrt(np.trace(result.tcp_covariance, axis1=1, axis2=2)).max() * 1e6
        return result.converged, (
            f'identified from {len(data)} measurements: {result.status}; rms '
            f'{result.rms_m * 1e6:.1f} µm, p = {result.p_value:.3g}, TCP sqrt(trace) <= '
            f'{tcp_um:.1f} µm; written to {self.data_dir}')

    def _diagnose(self) -> tuple[bool, str]:
        """Model diagnosis of the accepted measurements (as ``kpi-calib diagnose``): residual
        report, adequacy and the most likely missing effect; report files and ~/diagnosis."""
        cm = self._model()
        data, _ = self.campaign.measurements(cm.joint_names, cm.cell.tracker_frame)
        cd = diagnose_cell(cm, data)
        report = write_report(self.data_dir / DIAGNOSIS_DIR, cd)
        doc = diagnosis_to_dict(cd)
        self._diagnosis = doc
        self._pub_diagnosis.publish(String(data=json.dumps(doc)))
        self._publish_diagnostics(force=True)
        return True, f'{cd.diagnosis.verdict} Report: {report}'

    def _reset(self) -> tuple[bool, str]:
        """Start a new campaign: archive (never delete) the logs and results."""
        count, archive = self.campaign.reset()
        self._result, self._measured, self._result_error = None, None, ''
        self._identified_with, self._auto_pending, self._diagnosis = 0, False, None
        self._publish_markers()
        self._publish_diagnostics(force=True)
        return True, f'archived {count} measurement(s) and the results to {archive}'

    # ------------------------------------------------------------------ outputs
    def _publish_markers(self) -> None:
        cm, result = self._cm, self._result
        if cm is None:
            return
        # Stamp 0: RViz draws latched markers with the latest transforms.
        self._pub_markers.publish(cv.marker_array_msg(
            0, cm.cell.tracker_frame, cm.cell.base_frame, design_points=self._design_points,
            tcp=None if result is None else result.tcp,
            tcp_covariance=None if result is None else result.tcp_covariance,
            capsules=self._capsules, measured=self._measured,
            residuals=None if result is None else result.residuals))

    def status(self) -> tuple[str, str, dict[str, Any]]:
        """(level, message, key values) as /diagnostics reports them."""
        values: dict[str, Any] = {'state': self._job_name or (
            'waiting for robot description' if self._cm is None else 'idle')}
        values.update(self.campaign.counts())
        values.update({'identified_with': self._identified_with,
                       'log_file': str(self.campaign.log.path)})
        result, n, rejected = self._result, values['accepted'], values['rejected']
        if result is not None:
            values.update({'rms_um': round(result.rms_m * 1e6, 3),
                           'p_value': float(result.p_value), 'converged': result.converged})
        if self._diagnosis is not None:
            best = next((c['spec'] for c in self._diagnosis['candidates'] if c['significant']),
                        'none')
            values.update({'model_adequate': self._diagnosis['model_adequate'],
                           'suggested_effect': best})
        error = self._model_error or self._result_error
        if error or values['rejected.not_stored']:
            return 'ERROR', error or 'accepted measurements could not be stored', values
        if result is not None and not is_adequate(result.p_value):
            return 'WARN', f'model inadequate (p = {result.p_value:.2g})', values
        if rejected:
            return 'WARN', f'{n} accepted, {rejected} rejected', values
        if self._cm is None:
            return 'OK', 'waiting for robot description', values
        return 'OK', f'{n} accepted' + ('' if result is None else
                                        f', rms {result.rms_m * 1e6:.1f} µm'), values

    def _publish_diagnostics(self, force: bool = False) -> None:
        level, message, values = self.status()
        key, now = (level, message, tuple(values.items())), time.monotonic()
        last_key, last_time = self._last_diagnostics
        if force or key != last_key or now - last_time >= 1.0:
            self._last_diagnostics = (key, now)
            self._pub_diagnostics.publish(cv.diagnostic_array_msg(
                self.get_clock().now().nanoseconds, f'{self.get_name()}: calibration', level,
                message, values, hardware_id='laser_tracker'))

    def destroy_node(self) -> None:
        self.campaign.close()  # finalise the log; it is complete on disk anyway
        super().destroy_node()


def main(args: list[str] | None = None) -> int:
    rclpy.init(args=args)
    node = None
    try:
        node = CalibrationNode()
        rclpy.spin(node)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except KpiCalibError as exc:
        print(f'{NODE_NAME}: error: {exc}', file=sys.stderr)
        return 2
    finally:
        if node is not None:
            node.destroy_node()
        rclpy.try_shutdown()
    return 0


if __name__ == '__main__':
    sys.exit(main())
