"""kpi-calib replay: publish a recorded bag onto the live topics with its timing.

Like ``ros2 bag play`` for the two topics the calibration uses: joint states and
tracker points are published in stamp order, paced by their header stamps (which
equal the log time in bags recorded by ``ros2 bag record`` from the drivers and in
simulated bags) divided by ``rate``. Message contents, stamps included, are
published unchanged. Imported only by the ``replay`` subcommand, so the rest of
the CLI works without ROS.
"""
from __future__ import annotations

import time
from pathlib import Path

import rclpy
from geometry_msgs.msg import PointStamped
from rclpy.duration import Duration
from rclpy.node import Node
from rclpy.qos import QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import JointState

from kpi_calib_ros.core.streams import JointSample
from kpi_calib_ros.io.bag import DEFAULT_JOINT_TOPIC, DEFAULT_POINT_TOPIC, read_bag
from kpi_calib_ros.ros.conversions import joint_state_msg, point_stamped_msg

# Deep enough that a subscriber busy for a second at 20x replay loses nothing.
QOS_DEPTH = 1000


def wait_for_subscribers(node: Node, publishers: list, timeout_s: float) -> bool:
    """True once every publisher has a subscriber, False after ``timeout_s`` (s)."""
    deadline = time.monotonic() + timeout_s
    while any(p.get_subscription_count() == 0 for p in publishers):
        if time.monotonic() >= deadline:
            return False
        time.sleep(0.02)  # polling the graph: discovery has no waitable event here
    return True


def replay(node: Node, path: str | Path, rate: float = 1.0,
           joint_topic: str = DEFAULT_JOINT_TOPIC, point_topic: str = DEFAULT_POINT_TOPIC,
           wait_s: float = 10.0) -> tuple[int, int, float]:
    """Publish ``path`` through ``node`` in real time scaled by ``rate``.

    Parameters
    ----------
    node : rclpy.node.Node
        Node that owns the publishers (created here).
    path : path-like
        MCAP bag with ``sensor_msgs/msg/JointState`` on ``joint_topic`` and
        ``geometry_msgs/msg/PointStamped`` on ``point_topic``.
    rate : float
        Playback speed factor (> 0); 2 plays twice as fast.
    wait_s : float
        Wait up to this long (s) for a subscriber on each topic before starting.

    Returns
    -------
    (joint states, points, seconds) published and the wall time it took.
    """
    if not rate > 0:
        raise ValueError(f'rate must be > 0, got {rate}')
    joints, points = read_bag(path, joint_topic, point_topic)
    stream = sorted([(s.stamp_ns, 0, s) for s in joints] + [(p.stamp_ns, 1, p) for p in points],
                    key=lambda item: item[:2])
    qos = QoSProfile(depth=QOS_DEPTH, reliability=ReliabilityPolicy.RELIABLE)
    pub_joint = node.create_publisher(JointState, joint_topic, qos)
    pub_point = node.create_publisher(PointStamped, point_topic, qos)
    if not wait_for_subscribers(node, [pub_joint, pub_point], wait_s):
        node.get_logger().warning(f'no subscriber on {joint_topic} and {point_topic} after '
                                  f'{wait_s} s; publishing anyway')
    start = time.monotonic()
    first = stream[0][0] if stream else 0
    for stamp, _, sample in stream:
        delay = start + (stamp - first) * 1e-9 / rate - time.monotonic()
        if delay > 0:
            time.sleep(delay)  # pacing is the point of a player
        if isinstance(sample, JointSample):
            pub_joint.publish(joint_state_msg(sample))
        else:
            pub_point.publish(point_stamped_msg(sample))
    for publisher in (pub_joint, pub_point):
        publisher.wait_for_all_acked(Duration(seconds=5))
    return len(joints), len(points), time.monotonic() - start


def run_replay(bag: str | Path, rate: float = 1.0, joint_topic: str = DEFAULT_JOINT_TOPIC,
               point_topic: str = DEFAULT_POINT_TOPIC, wait_s: float = 10.0) -> int:
    """The ``kpi-calib replay`` subcommand."""
    rclpy.init()
    node = rclpy.create_node('kpi_calib_replay')
    try:
        n_joints, n_points, seconds = replay(node, bag, rate, joint_topic, point_topic, wait_s)
        print(f'replayed {n_joints} joint states and {n_points} tracker points from '
              f'{bag} in {seconds:.1f} s (rate {rate:g})')
    except KeyboardInterrupt:
        return 130
    finally:
        node.destroy_node()
        rclpy.try_shutdown()
    return 0


__all__ = ['replay', 'run_replay', 'wait_for_subscribers']
