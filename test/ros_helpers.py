"""What every ROS test shares: a ROS domain of its own, a test client, the node process.

ROS domains: parallel test runs on one machine (two checkouts, CI jobs) must not hear
each other's nodes, or one run counts the other's measurements. A domain id is taken
by an exclusive ``flock`` on ``<tmp>/kpi_calib_ros_domain_<id>.lock``, held for as long
as the tests use the domain; the kernel drops the lock when the process ends, however
it ends, so a crashed run never leaves an id taken. Discovery is limited to localhost
on top of that.
"""
from __future__ import annotations

import contextlib
import fcntl
import os
import signal
import subprocess
import sys
import tempfile
import threading
import time
from collections import defaultdict
from pathlib import Path
from typing import Any, Callable, Iterator

import numpy as np
import pytest
import rclpy
import yaml
from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import PointStamped, PoseWithCovarianceStamped
from rclpy.context import Context
from rclpy.executors import SingleThreadedExecutor
from rclpy.parameter import Parameter
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import JointState
from std_msgs.msg import String
from std_srvs.srv import Trigger
from trajectory_msgs.msg import JointTrajectory
from visualization_msgs.msg import MarkerArray

from kpi_calib_ros.core.acquisition.streams import synthesize_streams
from kpi_calib_ros.core.errors import ConfigError
from kpi_calib_ros.io.cell import DEFAULT_CELL
from kpi_calib_ros.io.ros_messages import time_msg
from kpi_calib_ros.ros import conversions as cv
from kpi_calib_ros.ros.node import CalibrationNode

REPO = Path(__file__).resolve().parents[1]
BIN = Path(sys.executable).parent
PARAMS_FILE = REPO / 'config' / 'kpi_calib.params.yaml'
KR15_URDF = (DEFAULT_CELL.parent.parent / 'robots' / 'kr15_class.urdf').read_text()
NS = '/kpi_calib_node'
RATE = 20.0
CHUNK_S = 5.0  # stream time publish_measurements sends unpaced (half the node's buffer)
LATCHED = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE,
                     durability=DurabilityPolicy.TRANSIENT_LOCAL)

# 0 is every ROS installation's default domain; ids above 101 can collide with the
# ephemeral ports Linux hands out (ROS 2 documentation, "The ROS_DOMAIN_ID").
DOMAIN_IDS = range(1, 102)
LOCK_DIR = Path(tempfile.gettempdir())


@contextlib.contextmanager
def idle_node(data_dir: Path, domain: int) -> Iterator[CalibrationNode]:
    """The KR15-class node in this process, on a private context in ``domain``, with
    ``data_dir`` and no automatic identification; destroyed and shut down on exit."""
    context = Context()
    rclpy.init(context=context, domain_id=domain)
    made = None
    try:
        made = CalibrationNode(context=context, parameter_overrides=[
            Parameter('robot_description', value=KR15_URDF),
            Parameter('data_dir', value=str(data_dir)),
            Parameter('auto_identify', value=False)])
        yield made
    finally:
        if made is not None:
            made.destroy_node()
        rclpy.shutdown(context=context)

@contextlib.contextmanager
def exclusive_ros_domain(lock_dir: Path = LOCK_DIR, ids: range = DOMAIN_IDS) -> Iterator[int]:
    """Hold a ROS domain id among ``ids`` that no other holder (this process or another)
    has taken through this function.

    Ids are tried from a process-dependent start (so concurrent runs rarely contend);
    the first whose lock file can be locked exclusively without waiting is yielded and
    stays locked until the ``with`` block ends.
    """
    start = os.getpid() % len(ids)
    for i in range(len(ids)):
        domain = ids[(start + i) % len(ids)]
        handle = open(lock_dir / f'kpi_calib_ros_domain_{domain}.lock', 'a')
        try:
            fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:  # held by another run
            handle.close()
            continue
        try:
            yield domain
        finally:
            fcntl.flock(handle, fcntl.LOCK_UN)
            handle.close()
        return
    raise RuntimeError(f'every ROS domain id in {ids} is held by another test run '
                       f'(lock files kpi_calib_ros_domain_*.lock in {lock_dir})')


@contextlib.contextmanager
def ros_environment(domain: int) -> Iterator[None]:
    """ROS_DOMAIN_ID and localhost-only discovery for this process and its children."""
    keys = ('ROS_DOMAIN_ID', 'ROS_AUTOMATIC_DISCOVERY_RANGE')
    saved = {k: os.environ.get(k) for k in keys}
    os.environ.update(ROS_DOMAIN_ID=str(domain), ROS_AUTOMATIC_DISCOVERY_RANGE='LOCALHOST')
    try:
        yield
    finally:
        for key, value in saved.items():
            if value is None:
                os.environ.pop(key, None)
            else:
                os.environ[key] = value


class Client:
    """Test-side ROS participant: private context, own executor, records what arrives."""

    def __init__(self, domain: int) -> None:
        self.context = Context()
        rclpy.init(context=self.context, domain_id=domain)
        self.node = rclpy.create_node('kpi_calib_test_client', context=self.context)
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)
        self.received: dict[str, list] = defaultdict(list)
        for topic, kind in (('measurement_poses', JointTrajectory), ('calibration', String),
                            ('tcp', PoseWithCovarianceStamped), ('markers', MarkerArray),
                            ('robot_description_calibrated', String), ('diagnosis', String)):
            self.node.create_subscription(kind, f'{NS}/{topic}', self._recorder(topic), LATCHED)
        self.node.create_subscription(DiagnosticArray, '/diagnostics',
                                      self._recorder('diagnostics'), 50)
        self.description = self.node.create_publisher(String, '/robot_description', LATCHED)
        # Made once, before any node starts (one made just before a burst counts the node's
        # subscription at once, while the node may not have matched it yet).
        burst = QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE)
        self.joints = self.node.create_publisher(JointState, '/joint_states', burst)
        self.points = self.node.create_publisher(PointStamped, '/laser_tracker/point', burst)
        self.clients: dict[str, Any] = {}

    def _recorder(self, topic: str) -> Callable[[Any], None]:
        def record(msg: Any) -> None:
            if topic == 'calibration':
                msg = yaml.safe_load(msg.data)
            elif topic == 'diagnostics':
                if not msg.status or not msg.status[0].name.startswith('kpi_calib_node'):
                    return
                msg = (msg.status[0].level, cv.diagnostic_values(msg))
            self.received[topic].append(msg)
        return record

    def spin_until(self, condition: Callable[[], Any], timeout: float, what: str) -> None:
        deadline = time.monotonic() + timeout
        while not condition():
            assert time.monotonic() < deadline, (
                f'timed out after {timeout} s waiting for {what}; the node\'s last '
                f'diagnostics: {self.diagnostics()}')
            self.executor.spin_once(timeout_sec=0.05)

    def diagnostics(self) -> dict[str, str]:
        return self.received['diagnostics'][-1][1] if self.received['diagnostics'] else {}

    def count(self, key: str) -> int:
        return int(self.diagnostics().get(key, -1))

    def call_async(self, service: str, timeout: float = 20.0):
        if service not in self.clients:
            self.clients[service] = self.node.create_client(Trigger, f'{NS}/{service}')
        client = self.clients[service]
        assert client.wait_for_service(timeout_sec=timeout), f'{NS}/{service} not available'
        return client.call_async(Trigger.Request())

    def call(self, service: str, timeout: float = 60.0) -> Trigger.Response:
        future = self.call_async(service)
        self.executor.spin_until_future_complete(future, timeout_sec=timeout)
        assert future.done(), f'{NS}/{service} did not answer within {timeout} s'
        return future.result()

    def publish_measurements(self, q: Any, joint_names: Any, eta: Any, frame: str,
                             accepted: int, timeout: float = 60.0,
                             edit: Callable[[list], list] | None = None,
                             start_ns: int = 1_700_000_000_000_000_000) -> None:
        """Publish static poses ``q`` with their points ``eta`` as a robot and a tracker
        would (joint states at 20 Hz, a point while each pose is held) on the node's
        measurement topics, and wait until it has accepted ``accepted`` measurements.
        ``edit`` changes the joint samples before they are sent (e.g. adds joints);
        ``start_ns`` stamps the first (a later campaign of one run starts later).

        Faster than real time, in chunks of :data:`CHUNK_S` of stream time, each received
        whole by the node before the next is sent: the node pairs a point with the last
        STREAM_BUFFER_S of joint states, so the points must never trail the joint states
        by more stream time than that. Sent unpaced, 80 s of stream took well under a
        second: one topic's first messages arriving 3 s late came after all of the
        other's, and the first point was rejected (no_joint_state).
        """
        joints, points = synthesize_streams(q, joint_names, eta, frame, rate_hz=20.0,
                                            move_time_s=0.2, hold_time_s=0.6,
                                            start_ns=start_ns)
        if edit is not None:  # the joint states as a particular driver sends them
            joints = edit(joints)
        stream = sorted([(s.stamp_ns, 0, cv.joint_state_msg(s)) for s in joints]
                        + [(s.stamp_ns, 1, cv.point_stamped_msg(s)) for s in points],
                        key=lambda item: item[:2])
        publishers = (self.joints, self.points)
        self.spin_until(lambda: all(p.get_subscription_count() for p in publishers), 20,
                        'the node on the measurement topics')
        keys = ('received.joint_states', 'received.points')
        sent = [self.count(key) for key in keys]  # what the node had received before

        def received() -> bool:
            return all(self.count(key) >= n for key, n in zip(keys, sent))

        chunk_start = stream[0][0]
        for stamp, kind, msg in stream:
            if stamp - chunk_start > CHUNK_S * 1e9:
                self.spin_until(received, timeout, f'the node to receive {sent} messages')
                chunk_start = stamp
            publishers[kind].publish(msg)
            sent[kind] += 1
        self.spin_until(lambda: self.count('accepted') == accepted, timeout,
                        f'{accepted} accepted measurements')

    def close(self) -> None:
        self.executor.shutdown()
        self.node.destroy_node()
        rclpy.shutdown(context=self.context)


class SpinThread(threading.Thread):
    """``executor`` spun in a thread of its own until :meth:`stop`.

    It spins one callback at a time with a short wait, so a stop is seen between waits, and
    :meth:`stop` shuts the executor down from the caller's thread only once the spin has
    ended: an ``Executor.shutdown`` from another thread while ``spin`` waits races the
    executor's wait set (ros2/rclpy#968) and left an exception in the spin thread of
    one full run in about ten.
    """

    def __init__(self, executor: SingleThreadedExecutor) -> None:
        super().__init__(daemon=True)
        self.executor = executor
        self._stopped = threading.Event()

    def run(self) -> None:
        while not self._stopped.is_set() and self.executor.context.ok():
            self.executor.spin_once(timeout_sec=0.05)

    def stop(self) -> None:
        """End the spin, wait for it, then shut the executor down."""
        self._stopped.set()
        if self.is_alive():
            self.join(timeout=10)
        assert not self.is_alive(), 'the spin thread did not end within 10 s'
        self.executor.shutdown()


class NodeProcess:
    """kpi_calib_node started as a cell controller would, output kept in a file."""

    def __init__(self, data_dir: Path, log: Path, *overrides: str) -> None:
        args = [str(BIN / 'kpi_calib_node'), '--ros-args', '--params-file', str(PARAMS_FILE),
                '-p', f'data_dir:={data_dir}']
        for override in overrides:
            args += ['-p', override]
        self.log = log
        self._out = open(log, 'w')
        self.process = subprocess.Popen(args, stdout=self._out, stderr=subprocess.STDOUT)

    def output(self) -> str:
        if not self._out.closed:
            self._out.flush()
        return self.log.read_text()

    def stop(self, sig: int = signal.SIGINT, timeout: float = 20.0) -> int:
        """Send ``sig`` and return the exit code (killed if it does not exit in time)."""
        if self.process.poll() is None:
            self.process.send_signal(sig)
        try:
            return self.process.wait(timeout=timeout)
        finally:
            if self.process.poll() is None:
                self.process.kill()
                self.process.wait()
            self._out.close()


class Spawner:
    """Starts node and replay processes in ``log_dir``; :meth:`kill_all` ends what is
    still running (a failed test must not leave a node behind)."""

    def __init__(self, log_dir: Path) -> None:
        self.log_dir = log_dir
        self.started: list[NodeProcess | subprocess.Popen] = []

    def __call__(self, data_dir: Path, log_name: str, *overrides: str) -> NodeProcess:
        self.started.append(NodeProcess(data_dir, self.log_dir / log_name, *overrides))
        return self.started[-1]

    def replay(self, bag: Path, rate: float = RATE) -> subprocess.Popen:
        self.started.append(subprocess.Popen(
            [str(BIN / 'kpi-calib'), 'replay', str(bag), '--rate', str(rate)],
            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True))
        return self.started[-1]

    def kill_all(self) -> None:
        """Kill what still runs and close every log and pipe (unclosed: a ResourceWarning)."""
        for item in self.started:
            process = item.process if isinstance(item, NodeProcess) else item
            if process.poll() is None:
                process.kill()
                process.wait()
            if isinstance(item, NodeProcess):
                item._out.close()
            elif process.stdout is not None:
                process.stdout.close()


def tcp_of(msg: PoseWithCovarianceStamped) -> tuple[Any, Any]:
    """The position (3,) and position covariance (3, 3) of a ~/tcp_corrected answer."""
    p = msg.pose.pose.position
    return np.array([p.x, p.y, p.z]), np.reshape(msg.pose.covariance, (6, 6))[:3, :3]


class Queries:
    """~/tcp_query from the test client, answers on ~/tcp_corrected by query stamp.

    ``names``: the joint names the queries give, in their order (default the chain's);
    ``extra``: the values of those not on the chain (e.g. gripper fingers).
    """

    def __init__(self, client: Client, cm: Any, depth: int = 10,
                 names: list[str] | None = None, extra: dict[str, float] | None = None
                 ) -> None:
        self.client, self.cm, self.answers = client, cm, {}
        self.names = list(names or cm.joint_names)
        self.extra = dict(extra or {})
        self.publisher = client.node.create_publisher(JointState, f'{NS}/tcp_query', depth)
        self.subscription = client.node.create_subscription(
            PoseWithCovarianceStamped, f'{NS}/tcp_corrected',
            lambda m: self.answers.setdefault(
                m.header.stamp.sec * 10 ** 9 + m.header.stamp.nanosec, m), depth)

    def message(self, q: Any, stamp: int) -> JointState:
        chain = list(self.cm.joint_names)
        msg = JointState(name=self.names, position=[
            float(q[chain.index(n)]) if n in chain else self.extra[n] for n in self.names])
        msg.header.stamp = time_msg(stamp)
        return msg

    def connected(self) -> bool:
        return bool(self.publisher.get_subscription_count()
                    and self.subscription.get_publisher_count())

    def ready(self) -> None:
        self.client.spin_until(self.connected, 30, 'the TCP query topics')

    def ask(self, poses: Any, first_stamp: int, timeout: float = 10.0
            ) -> list[tuple[Any, Any]]:
        """The answers at ``poses``, one query at a time."""
        out = []
        for i, q in enumerate(poses):
            stamp = first_stamp + i
            self.publisher.publish(self.message(q, stamp))
            self.client.spin_until(lambda s=stamp: s in self.answers, timeout, f'answer {i}')
            out.append(tcp_of(self.answers[stamp]))
        return out

    def unanswered(self, node: NodeProcess, q: Any) -> None:
        """Sent until the node logs that it has no calibration to answer with."""
        msg = self.message(q, 7)
        self.client.spin_until(lambda: (self.publisher.publish(msg),
                                        'TCP query dropped: no calibration yet'
                                        in node.output())[1], 20, 'the query dropped')
        assert 7 not in self.answers


def run_job(node: CalibrationNode, executor: SingleThreadedExecutor, name: str,
            work: Callable[[], Any], timeout: float) -> Any:
    """Run the node's job ``work`` on ``executor`` (as its service would) to its answer,
    within ``timeout`` s."""
    assert node._claim_job(name)
    task = executor.create_task(node._run_job, name, work)
    done = threading.Event()
    task.add_done_callback(lambda _: done.set())
    assert done.wait(timeout=timeout), f'{name} did not finish'
    return task.result()


def start_error(data_dir: Path, domain: int, *overrides: Parameter) -> ConfigError:
    """The ConfigError a node started in process with ``overrides`` stops with."""
    context = Context()
    rclpy.init(context=context, domain_id=domain)
    try:
        with pytest.raises(ConfigError) as info:
            CalibrationNode(context=context, parameter_overrides=[
                Parameter('robot_description', value=KR15_URDF),
                Parameter('data_dir', value=str(data_dir)), *overrides])
    finally:
        rclpy.shutdown(context=context)
    return info.value


def finish(replay: subprocess.Popen, client: Client, timeout: float = 60.0) -> str:
    """Spin ``client`` until ``replay`` exits; its output (asserted rc 0)."""
    client.spin_until(lambda: replay.poll() is not None, timeout, 'the replay to finish')
    output = replay.stdout.read()
    assert replay.returncode == 0, output
    return output
