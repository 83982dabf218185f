"""ROS messages <-> core types, and results -> messages for the cell and for RViz.

Pure functions: nothing here creates a node or calls ``rclpy.init``, so every
conversion is tested with plain data. Units are SI; stamps are integer ns.
"""
from __future__ import annotations

from typing import Any, Mapping, Sequence

import numpy as np
import pinocchio as pin
from builtin_interfaces.msg import Duration
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from geometry_msgs.msg import Point, PoseWithCovarianceStamped, Quaternion, Vector3
from std_msgs.msg import ColorRGBA, Header
from trajectory_msgs.msg import JointTrajectory, JointTrajectoryPoint
from visualization_msgs.msg import Marker, MarkerArray

from kpi_calib_ros.core.collision.capsules import BASE, Capsule

# The one message <-> sample and time conversion, shared with the bag reader and writer,
# so live and recorded data agree.
from kpi_calib_ros.io.ros_messages import joint_sample_from_message as joint_sample_from_msg
from kpi_calib_ros.io.ros_messages import joint_state_msg, point_stamped_msg, stamp_ns, time_msg
from kpi_calib_ros.io.ros_messages import point_sample_from_message as point_sample_from_msg
from kpi_calib_ros.io.ros_messages import point_sigma_from_message as point_sigma_from_msg
from kpi_calib_ros.io.ros_messages import pose_sample_from_message as pose_sample_from_msg

# Orientation of a TCP point is not measured: this variance (rad²) says "unknown".
UNKNOWN_ORIENTATION_VARIANCE = 1e6
# Nominal time between two design poses in the published trajectory (move + hold, s);
# the cell controller plans its own motions and only takes the order and positions.
POSE_INTERVAL_S = 4.0
# µm-sized ellipsoids and residuals are drawn this many times larger in RViz.
DEFAULT_EXAGGERATION = 1000.0

LEVELS = {'OK': DiagnosticStatus.OK, 'WARN': DiagnosticStatus.WARN,
          'ERROR': DiagnosticStatus.ERROR, 'STALE': DiagnosticStatus.STALE}


# ------------------------------------------------------------------ time
def _header(ns: int, frame_id: str) -> Header:
    return Header(stamp=time_msg(ns), frame_id=frame_id)


# ------------------------------------------------------------------ design
def joint_trajectory_msg(joint_names: Sequence[str], configurations: np.ndarray,
                         interval_s: float = POSE_INTERVAL_S) -> JointTrajectory:
    """Measurement poses as a trajectory: one point per configuration, in execution order.

    Parameters
    ----------
    joint_names : sequence of str, length n
    configurations : ndarray, shape (N, n)
        Joint positions (rad, m for prismatic joints).
    interval_s : float
        Nominal ``time_from_start`` spacing (s); point k is at (k + 1) · interval_s.
    """
    q = np.atleast_2d(np.asarray(configurations, dtype=float))
    if q.shape[1] != len(joint_names):
        raise ValueError(f'configurations must have shape (N, {len(joint_names)}), '
                         f'got {q.shape}')
    msg = JointTrajectory(joint_names=list(joint_names))
    for k, row in enumerate(q):
        sec, nanosec = divmod(round((k + 1) * interval_s * 1e9), 1_000_000_000)
        msg.points.append(JointTrajectoryPoint(
            positions=[float(x) for x in row],
            time_from_start=Duration(sec=int(sec), nanosec=int(nanosec))))
    return msg


def configurations_from_trajectory(msg: JointTrajectory) -> tuple[list[str], np.ndarray]:
    """Inverse of :func:`joint_trajectory_msg`: joint names and (N, n) positions."""
    n = len(msg.joint_names)
    return list(msg.joint_names), np.array([list(p.positions) for p in msg.points],
                                           dtype=float).reshape(-1, n)


# ------------------------------------------------------------------ results
def tcp_pose_msgs(tcp: np.ndarray, covariance: np.ndarray, frame_id: str,
                  stamp: int) -> list[PoseWithCovarianceStamped]:
    """One PoseWithCovarianceStamped per working pose.

    Parameters
    ----------
    tcp : ndarray, shape (t, 3)
        KPI points (m) in ``frame_id`` (the tracker frame).
    covariance : ndarray, shape (t, 3, 3)
        Their covariance (m²); becomes the position block of the 6x6 row-major
        covariance. Orientation is not measured: identity quaternion with variance
        :data:`UNKNOWN_ORIENTATION_VARIANCE` on the rotation diagonal.
    stamp : int
        Header stamp (ns).
    """
    tcp = np.asarray(tcp, dtype=float).reshape(-1, 3)
    covariance = np.asarray(covariance, dtype=float).reshape(-1, 3, 3)
    if len(tcp) != len(covariance):
        raise ValueError(f'tcp has {len(tcp)} points but covariance {len(covariance)} blocks')
    out = []
    for point, cov in zip(tcp, covariance):
        msg = PoseWithCovarianceStamped(header=_header(stamp, frame_id))
        msg.pose.pose.position = Point(x=float(point[0]), y=float(point[1]), z=float(point[2]))
        msg.pose.pose.orientation = Quaternion(w=1.0)
        full = np.zeros((6, 6))
        full[:3, :3] = cov
        full[3:, 3:] = np.eye(3) * UNKNOWN_ORIENTATION_VARIANCE
        msg.pose.covariance = [float(x) for x in full.ravel()]
        out.append(msg)
    return out


def diagnostic_array_msg(stamp: int, name: str, level: str, message: str,
                         values: Mapping[str, Any], hardware_id: str = '') -> DiagnosticArray:
    """A DiagnosticArray with one status; ``level`` is 'OK', 'WARN', 'ERROR' or 'STALE'."""
    if level not in LEVELS:
        raise ValueError(f'level must be one of {sorted(LEVELS)}, got {level!r}')
    status = DiagnosticStatus(level=LEVELS[level], name=name, message=message,
                              hardware_id=hardware_id,
                              values=[KeyValue(key=str(k), value=str(v))
                                      for k, v in values.items()])
    return DiagnosticArray(header=_header(stamp, ''), status=[status])


def diagnostic_values(msg: DiagnosticArray) -> dict[str, str]:
    """Key/values of the first status of ``msg`` (for clients and tests)."""
    return {kv.key: kv.value for kv in msg.status[0].values} if msg.status else {}


# ------------------------------------------------------------------ markers
def quaternion_from_matrix(rotation: np.ndarray) -> Quaternion:
    """Unit quaternion of a proper rotation matrix (3, 3)."""
    # Pinocchio's Quaternion(R) (Eigen: Shepperd's method, stable for any rotation);
    # w >= 0 picks one of the two equal quaternions.
    q = pin.Quaternion(np.asarray(rotation, dtype=float)).normalized().coeffs()  # x, y, z, w
    q = q * (1.0 if q[3] >= 0 else -1.0)
    return Quaternion(x=float(q[0]), y=float(q[1]), z=float(q[2]), w=float(q[3]))


def _z_to(direction: np.ndarray) -> Quaternion:
    """Rotation taking +z onto ``direction`` (the axis of a cylinder or arrow marker)."""
    d = np.asarray(direction, dtype=float)
    d = d / np.linalg.norm(d)
    helper = np.array([1.0, 0.0, 0.0]) if abs(d[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    x = np.cross(helper, d)
    x /= np.linalg.norm(x)
    return quaternion_from_matrix(np.column_stack([x, np.cross(d, x), d]))


def _point(v) -> Point:
    return Point(x=float(v[0]), y=float(v[1]), z=float(v[2]))


def _marker(ns: str, ident: int, kind: int, frame_id: str, stamp: int,
            color: tuple[float, float, float, float]) -> Marker:
    marker = Marker(header=_header(stamp, frame_id), ns=ns, id=ident, type=kind,
                    action=Marker.ADD, color=ColorRGBA(r=color[0], g=color[1], b=color[2],
                                                       a=color[3]))
    marker.pose.orientation = Quaternion(w=1.0)
    return marker


def ellipsoid_marker(center: np.ndarray, covariance: np.ndarray, frame_id: str, stamp: int,
                     ident: int, n_sigma: float = 3.0,
                     exaggeration: float = DEFAULT_EXAGGERATION) -> Marker:
    """SPHERE marker shaped as the ``n_sigma`` ellipsoid of ``covariance`` (3, 3) m²,
    axes ``exaggeration`` times longer than true."""
    values, vectors = np.linalg.eigh(np.asarray(covariance, dtype=float))
    if np.linalg.det(vectors) < 0:  # a marker orientation must be a proper rotation
        vectors[:, 0] = -vectors[:, 0]
    marker = _marker('tcp_ellipsoids', ident, Marker.SPHERE, frame_id, stamp, (0.1, 0.4, 1.0, 0.6))
    marker.pose.position = _point(center)
    marker.pose.orientation = quaternion_from_matrix(vectors)
    axes = 2.0 * n_sigma * np.sqrt(np.clip(values, 0.0, None)) * exaggeration
    marker.scale = Vector3(x=float(axes[0]), y=float(axes[1]), z=float(axes[2]))
    return marker


def capsule_markers(capsule: Capsule, frame_id: str, stamp: int, first_id: int) -> list[Marker]:
    """A capsule as a cylinder between two spheres, in its own frame (a link, or the
    robot base frame ``frame_id`` for base-frame obstacles)."""
    frame = frame_id if capsule.frame == BASE else capsule.frame
    a, b = np.asarray(capsule.a), np.asarray(capsule.b)
    diameter = 2.0 * capsule.radius
    color = (1.0, 0.55, 0.0, 0.35)
    markers = []
    for k, end in enumerate((a, b)):
        sphere = _marker('capsules', first_id + k, Marker.SPHERE, frame, stamp, color)
        sphere.pose.position = _point(end)
        sphere.scale = Vector3(x=diameter, y=diameter, z=diameter)
        markers.append(sphere)
    length = float(np.linalg.norm(b - a))
    if length > 0:
        cylinder = _marker('capsules', first_id + 2, Marker.CYLINDER, frame, stamp, color)
        cylinder.pose.position = _point((a + b) / 2)
        cylinder.pose.orientation = _z_to(b - a)
        cylinder.scale = Vector3(x=diameter, y=diameter, z=length)
        markers.append(cylinder)
    return markers


def marker_array_msg(stamp: int, tracker_frame: str, base_frame: str,
                     design_points: np.ndarray | None = None,
                     tcp: np.ndarray | None = None, tcp_covariance: np.ndarray | None = None,
                     capsules: Sequence[Capsule] = (),
                     measured: np.ndarray | None = None, residuals: np.ndarray | None = None,
                     exaggeration: float = DEFAULT_EXAGGERATION) -> MarkerArray:
    """Everything worth seeing in RViz, replacing what was shown before (DELETEALL first).

    Parameters
    ----------
    design_points : ndarray, shape (N, 3), optional
        Predicted reflector positions (m) of the design poses, tracker frame (ns
        ``design_poses``, one sphere each, in execution order).
    tcp, tcp_covariance : ndarrays, shapes (t, 3) and (t, 3, 3), optional
        KPI points and covariance, tracker frame (ns ``tcp_ellipsoids``, 3σ).
    capsules : sequence of Capsule
        Robot capsules (drawn in their link frames) and capsule obstacles (base frame).
    measured, residuals : ndarrays, shape (N, 3), optional
        Measured points and residuals η − h(p̂, q) (m), tracker frame (ns
        ``residuals``: an arrow from the model's prediction along the residual).
    exaggeration : float
        Ellipsoid axes and residual arrows are drawn this many times longer.
    """
    markers = [Marker(header=_header(stamp, tracker_frame), action=Marker.DELETEALL)]
    if design_points is not None and len(design_points):
        spheres = _marker('design_poses', 0, Marker.SPHERE_LIST, tracker_frame, stamp,
                          (0.2, 0.8, 0.2, 0.9))
        spheres.scale = Vector3(x=0.03, y=0.03, z=0.03)
        spheres.points = [_point(p) for p in np.asarray(design_points, dtype=float)]
        markers.append(spheres)
        order = _marker('design_poses', 1, Marker.LINE_STRIP, tracker_frame, stamp,
                        (0.2, 0.8, 0.2, 0.4))
        order.scale = Vector3(x=0.004)
        order.points = list(spheres.points)
        markers.append(order)
    if tcp is not None:
        for i, (center, cov) in enumerate(zip(np.asarray(tcp, float),
                                              np.asarray(tcp_covariance, float))):
            markers.append(ellipsoid_marker(center, cov, tracker_frame, stamp, i,
                                            exaggeration=exaggeration))
    for i, capsule in enumerate(capsules):
        markers += capsule_markers(capsule, base_frame, stamp, 3 * i)
    if measured is not None and residuals is not None:
        for i, (eta, r) in enumerate(zip(np.asarray(measured, float),
                                         np.asarray(residuals, float))):
            arrow = _marker('residuals', i, Marker.ARROW, tracker_frame, stamp,
                            (0.9, 0.1, 0.1, 0.9))
            start = eta - r
            arrow.points = [_point(start), _point(start + exaggeration * r)]
            arrow.scale = Vector3(x=0.004, y=0.008, z=0.01)
            markers.append(arrow)
    return MarkerArray(markers=markers)


__all__ = ['DEFAULT_EXAGGERATION', 'POSE_INTERVAL_S', 'UNKNOWN_ORIENTATION_VARIANCE',
           'capsule_markers', 'configurations_from_trajectory', 'diagnostic_array_msg',
           'diagnostic_values', 'ellipsoid_marker', 'joint_sample_from_msg',
           'joint_state_msg', 'joint_trajectory_msg', 'marker_array_msg',
           'point_sample_from_msg', 'point_sigma_from_msg', 'point_stamped_msg',
           'pose_sample_from_msg',
           'quaternion_from_matrix', 'stamp_ns', 'tcp_pose_msgs', 'time_msg']
