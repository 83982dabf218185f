"""kpi-calib replay: publish a recorded bag onto the live topics with its timing.

Like ``ros2 bag play`` for the topics the calibration uses: joint states and
tracker points (each point's stated σ, if the bag has it, right after the point on
``<point topic>/sigma``) are published in stamp order, paced by their header stamps (which
equal the log time in bags recorded by ``ros2 bag record`` from the drivers and in
simulated bags) divided by ``rate``. Message contents, stamps included, are
published unchanged. Imported only by the ``replay`` subcommand, so the rest of
the CLI works without ROS.

Nothing is lost silently. DDS acknowledges a reliable message once it is in the
subscriber's queue, not once the node has handled it, and a queue that is full
drops its oldest message; so a fast replay must be paced by the consumer. The
calibration node reports how many joint states and points it has received
(``received.joint_states``, ``received.points`` on /diagnostics). Replay reads those
counts as its acknowledgement: it keeps at most ``JOINT_WINDOW`` joint states and
``POINT_WINDOW`` points beyond what the node has confirmed (fewer than the node's
subscription queues hold), and at the end it reports how many of the messages it
sent the node received, failing if any are missing. Without the node's
diagnostics (another consumer) it can only report the DDS acknowledgement. The
node's counts include messages from other publishers, so run a replay against a
node that receives nothing else.
"""
from __future__ import annotations

import importlib
import mmap
import signal
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from types import FrameType
from typing import cast

import rclpy
from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import PointStamped, PoseStamped, Vector3Stamped
from rclpy.duration import Duration
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from rclpy.qos import QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import JointState

from kpi_calib_ros.core.acquisition.streams import PointSample
from kpi_calib_ros.core.errors import DataError
from kpi_calib_ros.io.bag import (
    DEFAULT_JOINT_TOPIC,
    DEFAULT_POINT_TOPIC,
    is_measurement_log,
    read_bag_with_sigma,
    scanned_bag,
)
from kpi_calib_ros.io.mcap_scan import MAGIC, scan, side_messages
from kpi_calib_ros.io.names import DEFAULT_POSE_TOPIC, point_sigma_topic
from kpi_calib_ros.io.ros_messages import pose_stamped_msg, vector3_stamped_msg
from kpi_calib_ros.ros.conversions import diagnostic_values, point_stamped_msg

# Publisher history at least this deep; it is sized to the whole recording when longer,
# so a message DDS has not yet acknowledged is never overwritten before it is.
QOS_DEPTH = 1000
# Messages in flight beyond the node's confirmed counts: below the node's subscription
# depths (1000 joint states, 100 points) so its queues never overflow.
JOINT_WINDOW = 500
POINT_WINDOW = 50
NODE_STATUS = 'kpi_calib_node'   # diagnostics status name prefix of the calibration node
STALL_S = 10.0                   # no progress of the node's counts for this long: give up
RECEIVED = ('received.joint_states', 'received.points')


@dataclass(frozen=True)
class ReplayReport:
    """What a replay sent and what was confirmed.

    ``delivered`` is (joint states, points) the calibration node counted beyond its
    counts before the replay, or None when no node diagnostics were seen;
    ``acknowledged`` says whether DDS acknowledged every message to every subscriber;
    ``sigma_sent`` the points' stated σ published.
    """

    sent: tuple[int, int]
    delivered: tuple[int, int] | None
    acknowledged: bool
    seconds: float
    sigma_sent: int = 0
    # The bag's other topics (measured inputs, temperatures) sent as recorded, and the
    # topics it could not send (no installed message type, or no header stamp).
    side_sent: int = 0
    side_topics: tuple[str, ...] = ()
    unsent_topics: tuple[str, ...] = ()

    @property
    def lost(self) -> tuple[int, int] | None:
        """(joint states, points) sent but not received by the node (None: unknown)."""
        if self.delivered is None:
            return None
        return (max(0, self.sent[0] - self.delivered[0]), max(0, self.sent[1] - self.delivered[1]))

    @property
    def complete(self) -> bool:
        if self.unsent_topics:
            return False
        return self.acknowledged if self.lost is None else not any(self.lost)


class _NodeCounts:
    """The calibration node's received counts, as last reported on /diagnostics."""

    def __init__(self, node: Node) -> None:
        self.counts: tuple[int, int] | None = None
        self.executor = SingleThreadedExecutor(context=node.context)
        self.executor.add_node(node)
        node.create_subscription(DiagnosticArray, '/diagnostics', self._on_diagnostics, 50)

    def _on_diagnostics(self, msg: DiagnosticArray) -> None:
        if msg.status and msg.status[0].name.startswith(NODE_STATUS):
            values = diagnostic_values(msg)
            if all(k in values for k in RECEIVED):
                self.counts = (int(values[RECEIVED[0]]), int(values[RECEIVED[1]]))

    def spin(self, timeout_s: float) -> None:
        self.executor.spin_once(timeout_sec=timeout_s)

    def wait_first(self, timeout_s: float) -> bool:
        deadline = time.monotonic() + timeout_s
        while self.counts is None and time.monotonic() < deadline:
            self.spin(0.05)
        return self.counts is not None

    def latest(self) -> tuple[int, int]:
        """The last reported counts; only once :meth:`wait_first` returned True."""
        if self.counts is None:
            raise RuntimeError(f'no {NODE_STATUS} counts received yet: call wait_first first')
        return self.counts


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
           wait_s: float = 10.0, pose_topic: str = DEFAULT_POSE_TOPIC) -> ReplayReport:
    """Publish ``path`` through ``node`` in real time scaled by ``rate``, never faster than
    the calibration node confirms receiving (see the module docstring).

    Parameters
    ----------
    node : rclpy.node.Node
        Node that owns the publishers (created here); nothing else may spin it.
    path : path-like
        MCAP bag with ``sensor_msgs/msg/JointState`` on ``joint_topic`` and
        ``geometry_msgs/msg/PointStamped`` on ``point_topic``; tracked 6-DoF poses
        (``geometry_msgs/msg/PoseStamped`` on ``pose_topic``, if any) are published there
        and counted with the points.
    rate : float
        Playback speed factor (> 0); 2 plays twice as fast.
    wait_s : float
        Wait up to this long (s) for a subscriber on each topic before starting.

    Returns
    -------
    ReplayReport
        Messages sent, received by the node, acknowledged, and the wall time (s).
    """
    if not rate > 0:
        raise ValueError(f'rate must be > 0, got {rate}')
    refuse_measurement_log(path)
    _, points, sigma = read_bag_with_sigma(path, joint_topic, point_topic, pose_topic)
    # The joint states and every other topic (measured inputs, temperatures) as recorded:
    # a joint state's efforts and an input read from a topic reach the node unchanged.
    raw, unsent = side_messages(scanned_bag(path)[1], (point_topic, pose_topic,
                                                       point_sigma_topic(point_topic)))
    classes = {name: _message_class(name) for name in {m[2] for m in raw}}
    unsent += sorted({m[1] for m in raw if classes[m[2]] is None})
    joints = [(m[0], 0, m[3]) for m in raw if m[1] == joint_topic]
    side = [(m[0], 2, m) for m in raw if m[1] != joint_topic and classes[m[2]] is not None]
    Item = tuple[int, int, 'bytes | PointSample | tuple[int, str, str, bytes]']
    items: list[Item] = [*joints, *[(p.stamp_ns, 1, p) for p in points], *side]
    stream = sorted(items, key=lambda item: item[:2])
    n_poses = sum(p.orientation is not None for p in points)
    topics = [(JointState, joint_topic, len(joints)), (PointStamped, point_topic, len(points))]
    if n_poses:
        topics.append((PoseStamped, pose_topic, n_poses))
    pubs = [node.create_publisher(kind, topic, QoSProfile(
        depth=max(QOS_DEPTH, n), reliability=ReliabilityPolicy.RELIABLE))
        for kind, topic, n in topics]
    side_pubs = {topic: node.create_publisher(classes[kind], topic, QoSProfile(
        depth=max(QOS_DEPTH, sum(m[2][1] == topic for m in side)),
        reliability=ReliabilityPolicy.RELIABLE))
        for topic, kind in {(m[2][1], m[2][2]) for m in side}}
    side_sent = 0
    # The points' stated σ: not counted by the node's acknowledgement, each sent with its
    # point (so at most POINT_WINDOW of them in flight).
    sigma_pub = node.create_publisher(Vector3Stamped, point_sigma_topic(point_topic), QoSProfile(
        depth=max(QOS_DEPTH, len(sigma)), reliability=ReliabilityPolicy.RELIABLE)) \
        if sigma else None
    sigma_sent = 0
    node_counts = _NodeCounts(node)
    log = node.get_logger()
    if not wait_for_subscribers(node, pubs, wait_s):
        log.warning(f'no subscriber on {joint_topic} and {point_topic} after {wait_s} s; '
                    'publishing anyway')
    # The node reports at least once a second: a few seconds tell whether it is there.
    baseline = node_counts.counts if node_counts.wait_first(min(wait_s, 3.0)) else None
    if baseline is None:
        log.warning(f'no {NODE_STATUS} diagnostics on /diagnostics: only the DDS '
                    'acknowledgement can be checked, not what a node handled')
    windows = (JOINT_WINDOW, POINT_WINDOW)
    sent, stalled = [0, 0], False
    start = time.monotonic()
    first = stream[0][0] if stream else 0
    for stamp, kind, sample in stream:
        delay = start + (stamp - first) * 1e-9 / rate - time.monotonic()
        if delay > 0:
            time.sleep(delay)  # pacing is the point of a player
        if isinstance(sample, tuple):  # a side topic: not counted by the node's counts
            side_pubs[sample[1]].publish(sample[3])
            side_sent += 1
            continue
        if baseline is not None and not stalled:
            if not sum(sent) % 50:  # a spin costs ~1 ms: take new counts now and then
                node_counts.spin(0.0)

            def within_window(kind: int = kind) -> bool:
                return sent[kind] - (node_counts.latest()[kind] - baseline[kind]) < windows[kind]
            stalled = not _await(node_counts, within_window)
            if stalled:
                log.error(f'{NODE_STATUS} stopped counting for {STALL_S} s; publishing the '
                          'rest without waiting for it')
        if isinstance(sample, bytes):
            pubs[0].publish(sample)  # the recorded joint state, efforts included
        elif sample.orientation is not None:  # a tracked pose; counted as a point
            pubs[2].publish(pose_stamped_msg(sample))
        else:
            pubs[1].publish(point_stamped_msg(sample))
        if (sigma_pub is not None and isinstance(sample, PointSample)
                and (stamp, sample.frame_id) in sigma):
            sigma_pub.publish(vector3_stamped_msg(stamp, sample.frame_id,
                                                  sigma[(stamp, sample.frame_id)]))
            sigma_sent += 1
        sent[kind] += 1
    acknowledged = all(p.wait_for_all_acked(Duration(seconds=STALL_S))
                       for p in pubs + list(side_pubs.values())
                       + ([sigma_pub] if sigma_pub is not None else []))
    delivered = None
    if baseline is not None:
        _await(node_counts, lambda: all(node_counts.latest()[k] - baseline[k] >= sent[k]
                                        for k in (0, 1)))
        counts = node_counts.latest()
        delivered = (counts[0] - baseline[0], counts[1] - baseline[1])
    return ReplayReport((sent[0], sent[1]), delivered, acknowledged, time.monotonic() - start,
                        sigma_sent, side_sent, tuple(sorted(side_pubs)), tuple(unsent))


def _message_class(type_name: str) -> type | None:
    """The rclpy message class of ``pkg/msg/Type``, None when it is not installed."""
    parts = type_name.split('/')
    if len(parts) != 3 or parts[1] != 'msg':
        return None
    try:
        return getattr(importlib.import_module(f'{parts[0]}.msg'), parts[2])
    except (ImportError, AttributeError):
        return None


def refuse_measurement_log(path: str | Path) -> None:
    """Raise DataError if ``path`` is a kpi_calib_node measurement log.

    A log holds one averaged joint state per accepted point, not the joint stream the
    node pairs (still joint states around each point), so replayed into a node every
    point would be rejected. Its measurements are already paired: every command reads
    the log directly, and a node restores it from its ``data_dir``.
    """
    path = Path(path)
    if not path.is_file():
        return  # read_bag names the missing file
    with open(path, 'rb') as f:
        if f.read(len(MAGIC)) != MAGIC:
            return  # read_bag explains what the file is not
        # Mapped, not read: only the records' headers and the metadata are touched.
        with mmap.mmap(f.fileno(), 0, access=mmap.ACCESS_READ) as data:
            log = is_measurement_log(scan(path, cast(bytes, data)))  # reads it as bytes
    if log:
        raise DataError(f'{path} is a kpi_calib_node measurement log (one averaged joint '
                        'state per accepted point, already paired), not a recording of the '
                        'joint stream, so a node would reject every point. Use it as it is: '
                        f'`kpi-calib identify --bag {path}` (or diagnose), or copy it into a '
                        "node's data_dir, which restores it at start-up")


def _await(node_counts: _NodeCounts, done: Callable[[], bool]) -> bool:
    """Spin until ``done()``; False once the node's counts stop moving for ``STALL_S``."""
    last, since = node_counts.counts, time.monotonic()
    while not done():
        node_counts.spin(0.1)
        if node_counts.counts != last:
            last, since = node_counts.counts, time.monotonic()
        elif time.monotonic() - since > STALL_S:
            return False  # the caller reports what was (not) delivered
    return True


def run_replay(bag: str | Path, rate: float = 1.0, joint_topic: str = DEFAULT_JOINT_TOPIC,
               point_topic: str = DEFAULT_POINT_TOPIC, wait_s: float = 10.0,
               pose_topic: str = DEFAULT_POSE_TOPIC) -> int:
    """The ``kpi-calib replay`` subcommand: 0 if every message was delivered, 1 if not."""
    refuse_measurement_log(bag)  # before joining the ROS graph
    interrupted: list[int] = []

    def interrupt(signum: int, frame: FrameType | None) -> None:
        interrupted.append(signum)
        raise KeyboardInterrupt
    # Installed before rclpy's handler, which calls it after waking the executor.
    previous = signal.signal(signal.SIGINT, interrupt)
    rclpy.init()
    node = rclpy.create_node('kpi_calib_replay')
    try:
        report = replay(node, bag, rate, joint_topic, point_topic, wait_s, pose_topic)
    except KeyboardInterrupt:
        return 130
    except RuntimeError:
        # Ctrl-C while rclpy took a /diagnostics message: KeyboardInterrupt was raised in
        # the message constructor rclpy calls, and pybind11 replaced it with a RuntimeError.
        if interrupted:
            return 130
        raise
    finally:
        node.destroy_node()
        rclpy.try_shutdown()
        signal.signal(signal.SIGINT, previous)
    (n_joints, n_points), seconds = report.sent, report.seconds
    print(f'sent {n_joints} joint states and {n_points} tracker points from {bag} in '
          f'{seconds:.1f} s (rate {rate:g})'
          + (f', with the stated sigma of {report.sigma_sent} points on '
             f'{point_sigma_topic(point_topic)}' if report.sigma_sent else '')
          + (f', and {report.side_sent} messages of {", ".join(report.side_topics)}'
             if report.side_sent else ''))
    if report.unsent_topics:
        print(f'NOT SENT: the bag\'s topics {", ".join(report.unsent_topics)} (no installed '
              'message type or no header stamp): a node reading them gets nothing from this '
              'replay')
    if report.delivered is None:
        print('no kpi_calib_node counts seen; DDS acknowledged '
              + ('every message' if report.acknowledged else 'NOT every message'))
    else:
        print(f'kpi_calib_node received {report.delivered[0]} joint states and '
              f'{report.delivered[1]} tracker points')
        lost = report.lost
        if lost is not None and not report.complete:
            print(f'LOST: {lost[0]} joint states and {lost[1]} tracker points')
    return 0 if report.complete else 1


__all__ = ['ReplayReport', 'replay', 'run_replay', 'wait_for_subscribers']
