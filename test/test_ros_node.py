"""kpi_calib_node end to end: real rclpy and Fast DDS, the node as a separate process.

The node runs exactly as a cell controller starts it (the installed executable with
the package's params file via --ros-args) on a ROS domain of its own, discovery
limited to localhost. A test client with a private context publishes the robot
description, calls the services and listens; `kpi-calib replay` plays simulated bags.
"""
from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
import xml.etree.ElementTree as ET
from collections import defaultdict
from pathlib import Path

import numpy as np
import pytest
import rclpy
import yaml
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from geometry_msgs.msg import Point, PointStamped, PoseWithCovarianceStamped
from rclpy.context import Context
from rclpy.executors import SingleThreadedExecutor
from rclpy.parameter import Parameter
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import JointState
from std_msgs.msg import Header, String
from std_srvs.srv import Trigger
from trajectory_msgs.msg import JointTrajectory
from visualization_msgs.msg import MarkerArray

from kpi_calib_ros import cli
from kpi_calib_ros.core.errors import ConfigError
from kpi_calib_ros.core.streams import synthesize_streams
from kpi_calib_ros.io.bag import read_bag, write_bag
from kpi_calib_ros.io.measurement_log import MeasurementLog
from kpi_calib_ros.io.cell import DEFAULT_CELL, build_cell_model, load_cell
from kpi_calib_ros.app.simulate import simulate_campaign
from kpi_calib_ros.ros import conversions as cv
from kpi_calib_ros.ros.node import CalibrationNode
from kpi_calib_ros.ros.parameters import PARAMETERS, settings_from_parameters

REPO = Path(__file__).resolve().parents[1]
BIN = Path(sys.executable).parent
PARAMS_FILE = REPO / 'config' / 'kpi_calib.params.yaml'
KR15_URDF = (DEFAULT_CELL.parent.parent / 'robots' / 'kr15_class.urdf').read_text()
NS = '/kpi_calib_node'
N_POSES = 30
RATE = 20.0
LATCHED = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE,
                     durability=DurabilityPolicy.TRANSIENT_LOCAL)


@pytest.fixture(scope='module')
def ros_domain():
    """A ROS domain of this test run's own, discovery on localhost only."""
    domain = 10 + os.getpid() % 80
    saved = {k: os.environ.get(k) for k in ('ROS_DOMAIN_ID', 'ROS_AUTOMATIC_DISCOVERY_RANGE')}
    os.environ.update(ROS_DOMAIN_ID=str(domain), ROS_AUTOMATIC_DISCOVERY_RANGE='LOCALHOST')
    yield domain
    for key, value in saved.items():
        if value is None:
            os.environ.pop(key, None)
        else:
            os.environ[key] = value


@pytest.fixture(scope='module')
def campaign(tmp_path_factory):
    """A simulated 30-pose bag and what `kpi-calib identify` and `kpi-calib diagnose`
    make of it offline."""
    folder = tmp_path_factory.mktemp('campaign')
    bag = folder / 'run.mcap'
    simulate_campaign(DEFAULT_CELL, N_POSES, bag, seed=21)
    assert cli.main(['identify', '--cell', str(DEFAULT_CELL), '--bag', str(bag),
                     '--out', str(folder / 'offline')]) == 0
    assert cli.main(['diagnose', '--cell', str(DEFAULT_CELL), '--bag', str(bag),
                     '--out', str(folder / 'diagnosis')]) == 0
    offline = yaml.safe_load((folder / 'offline' / 'calibration.yaml').read_text())
    diagnosis = json.loads((folder / 'diagnosis' / 'diagnosis.json').read_text())
    joints, points = read_bag(bag)
    return {'bag': bag, 'offline': offline, 'offline_diagnosis': diagnosis, 'joints': joints,
            'points': points}


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
        self.joints = self.node.create_publisher(JointState, '/joint_states', 100)
        self.points = self.node.create_publisher(PointStamped, '/laser_tracker/point', 100)
        self.clients = {}

    def _recorder(self, topic: str):
        def record(msg) -> None:
            if topic == 'calibration':
                msg = yaml.safe_load(msg.data)
            elif topic == 'diagnostics':
                if not msg.status or not msg.status[0].name.startswith('kpi_calib_node'):
                    return
                msg = (msg.status[0].level, cv.diagnostic_values(msg))
            self.received[topic].append(msg)
        return record

    def spin_until(self, condition, timeout: float, what: str) -> None:
        deadline = time.monotonic() + timeout
        while not condition():
            assert time.monotonic() < deadline, f'timed out after {timeout} s waiting for {what}'
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

    def close(self) -> None:
        self.executor.shutdown()
        self.node.destroy_node()
        rclpy.shutdown(context=self.context)


@pytest.fixture
def client(ros_domain):
    c = Client(ros_domain)
    c.description.publish(String(data=KR15_URDF))  # as robot_state_publisher does
    try:
        yield c
    finally:
        c.close()


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


@pytest.fixture
def spawn(tmp_path):
    """Start node and replay processes; whatever a test leaves running is killed."""
    started: list = []

    def node(data_dir: Path, log_name: str, *overrides: str) -> NodeProcess:
        started.append(NodeProcess(data_dir, tmp_path / log_name, *overrides))
        return started[-1]

    def replay(bag: Path, rate: float = RATE) -> subprocess.Popen:
        started.append(subprocess.Popen(
            [str(BIN / 'kpi-calib'), 'replay', str(bag), '--rate', str(rate)],
            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True))
        return started[-1]

    node.replay = replay
    yield node
    for item in started:
        process = item.process if isinstance(item, NodeProcess) else item
        if process.poll() is None:
            process.kill()
            process.wait()


def finish(replay: subprocess.Popen, client: Client, timeout: float = 60.0) -> str:
    client.spin_until(lambda: replay.poll() is not None, timeout, 'the replay to finish')
    output = replay.stdout.read()
    assert replay.returncode == 0, output
    return output


def test_design_service_publishes_the_poses_and_a_second_call_is_busy(client, spawn, tmp_path):
    started = time.monotonic()
    node = spawn(tmp_path / 'data', 'node.log', 'num_measurements:=12')
    try:
        client.spin_until(lambda: client.diagnostics().get('state') == 'idle', 30,
                          'the robot model from /robot_description')
        first = client.call_async('design')
        second = client.call_async('design')
        for future in (first, second):
            client.executor.spin_until_future_complete(future, timeout_sec=120)
            assert future.done(), node.output()
        answers = sorted([first.result(), second.result()],
                         key=lambda r: r.message.startswith('busy'))
        print('design answers:', [(r.success, r.message) for r in answers])
        assert answers[0].success, answers[0].message
        assert not answers[1].success and answers[1].message == 'busy: designing'
        client.spin_until(lambda: client.received['measurement_poses'], 10, 'measurement poses')
        names, q = cv.configurations_from_trajectory(client.received['measurement_poses'][-1])
        cm = build_cell_model(load_cell(DEFAULT_CELL))
        assert names == cm.joint_names and q.shape == (12, 6)
        written = yaml.safe_load((tmp_path / 'data' / 'design.yaml').read_text())
        np.testing.assert_array_equal(written['configurations'], q)
        assert written['verification']['ok']
        assert cm.robot.within_limits(q).all()
        # The design is drawn in RViz along with the capsules of the cell.
        client.spin_until(lambda: client.received['markers'], 10, 'markers')
        spaces = {m.ns for m in client.received['markers'][-1].markers}
        assert {'design_poses', 'capsules'} <= spaces
        # Idle again: the next call is served.
        assert client.call('reset').success
    finally:
        assert node.stop() == 0, node.output()
    print(f'design test: {time.monotonic() - started:.1f} s')


def test_replayed_campaign_survives_a_kill_and_matches_offline(client, campaign, spawn,
                                                               tmp_path):
    """Kill the node mid-replay, restart it, replay the whole recording again: every
    measurement accepted before the kill is kept, none is counted twice, and the
    result equals `kpi-calib identify` on the same bag."""
    started = time.monotonic()
    data_dir = tmp_path / 'data'
    first = spawn(data_dir, 'node_1.log')
    replay = spawn.replay(campaign['bag'])
    try:
        client.spin_until(lambda: client.count('accepted') >= 8, 60, '8 accepted measurements')
        reported = client.count('accepted')
        first.process.kill()                        # SIGKILL: no chance to clean up
        assert first.stop() == -signal.SIGKILL
    finally:
        replay.kill()
        replay.wait()
    logged = MeasurementLog.load_all(data_dir)
    point_stamps = {p.stamp_ns for p in campaign['points']}
    assert len(logged) >= reported and {p.stamp_ns for _, p in logged} <= point_stamps
    print(f'killed after {reported} reported accepted, {len(logged)} on disk')

    client.received.clear()
    second = spawn(data_dir, 'node_2.log')
    try:
        client.spin_until(lambda: client.count('restored') == len(logged), 30, 'restore')
        output = finish(spawn.replay(campaign['bag']), client)
        print(output.strip())
        client.spin_until(lambda: any(d['measurements'] == N_POSES
                                      for d in client.received['calibration']),
                          60, f'a calibration from {N_POSES} measurements')
        doc = next(d for d in client.received['calibration'] if d['measurements'] == N_POSES)
        client.spin_until(lambda: client.count('identified_with') == N_POSES, 10, 'diagnostics')
        values = client.diagnostics()
        assert int(values['accepted']) == N_POSES
        assert int(values['rejected.duplicate_stamp']) == len(logged)  # re-sent, not re-counted
        assert int(values['rejected']) == len(logged)

        # The same document, with the same numbers, as the offline identification.
        offline = campaign['offline']
        assert list(doc) == list(offline)
        assert doc['measurements'] == offline['measurements'] == N_POSES
        assert [p['name'] for p in doc['parameters']] == [p['name'] for p in offline['parameters']]
        node_values = np.array([p['value'] for p in doc['parameters']])
        offline_values = np.array([p['value'] for p in offline['parameters']])
        print(f'max |node - offline| parameter difference: '
              f'{np.abs(node_values - offline_values).max():.2e}; rms node '
              f'{doc["rms_m"] * 1e6:.3f} µm, offline {offline["rms_m"] * 1e6:.3f} µm')
        np.testing.assert_allclose(node_values, offline_values, rtol=1e-9, atol=1e-12)
        assert doc['rms_m'] == pytest.approx(offline['rms_m'], rel=1e-9)
        assert doc['model_adequacy']['p_value'] == pytest.approx(
            offline['model_adequacy']['p_value'], rel=1e-6, abs=1e-9)

        client.spin_until(lambda: client.received['tcp'], 10, 'tcp')
        tcp = client.received['tcp'][-1]
        expected = offline['tcp'][0]
        assert tcp.header.frame_id == 'laser_tracker'
        p = tcp.pose.pose.position
        np.testing.assert_allclose([p.x, p.y, p.z], expected['position'], rtol=0, atol=1e-10)
        np.testing.assert_allclose(np.reshape(tcp.pose.covariance, (6, 6))[:3, :3],
                                   expected['covariance'], rtol=1e-6, atol=1e-18)

        # Results on disk, written atomically, equal what was published.
        assert yaml.safe_load((data_dir / 'calibration.yaml').read_text()) == doc
        client.spin_until(lambda: client.received['robot_description_calibrated'], 10, 'urdf')
        urdf = client.received['robot_description_calibrated'][-1].data
        assert (data_dir / 'robot_description_calibrated.urdf').read_text() == urdf
        assert {j.get('name') for j in ET.fromstring(urdf).iter('joint')} == \
            {j.get('name') for j in ET.fromstring(KR15_URDF).iter('joint')}
        client.spin_until(lambda: any(m.ns == 'residuals' for a in client.received['markers']
                                      for m in a.markers), 10, 'residual markers')
        markers = [m for m in client.received['markers'][-1].markers]
        assert sum(m.ns == 'residuals' for m in markers) == N_POSES
        assert sum(m.ns == 'tcp_ellipsoids' for m in markers) == 1

        reject_malformed_messages(client, campaign)
        assert second.process.poll() is None, second.output()
        answer = client.call('identify')
        print('identify after malformed input:', answer.message)
        assert answer.success and f'from {N_POSES} measurements' in answer.message

        # ~/diagnose gives what `kpi-calib diagnose` gives on the same bag.
        answer = client.call('diagnose')
        print('diagnose:', answer.message)
        assert answer.success, answer.message
        client.spin_until(lambda: client.received['diagnosis'], 10, 'diagnosis')
        diagnosis = json.loads(client.received['diagnosis'][-1].data)
        offline = campaign['offline_diagnosis']
        assert diagnosis['verdict'] == offline['verdict']
        assert diagnosis['model_adequate'] == offline['model_adequate']
        assert diagnosis['rms_m'] == pytest.approx(offline['rms_m'], rel=1e-9)
        assert [c['spec'] for c in diagnosis['candidates']] == \
            [c['spec'] for c in offline['candidates']]
        assert (data_dir / 'diagnosis' / 'report.md').is_file()
        client.spin_until(lambda: 'model_adequate' in client.diagnostics(), 10, 'diagnostics')
    finally:
        code = second.stop()
    assert code == 0, second.output()
    # A clean stop finalises the log: every measurement is there, once.
    stamps = [p.stamp_ns for _, p in MeasurementLog.load_all(data_dir)]
    assert sorted(stamps) == sorted(point_stamps) and len(stamps) == N_POSES
    print(f'campaign test: {time.monotonic() - started:.1f} s')


def reject_malformed_messages(client: Client, campaign) -> None:
    """NaN, wrong frame, wrong joint names, wrong array lengths: each is rejected with its
    reason and counted; nothing is accepted. (Duplicates: the second replay above.)"""
    before = client.diagnostics()
    names = list(campaign['joints'][0].names)
    end = campaign['joints'][-1].stamp_ns + 60_000_000_000

    def joint_state(stamp, joint_names, positions, velocities=()):
        return JointState(header=Header(stamp=cv.time_msg(stamp)), name=joint_names,
                          position=positions, velocity=list(velocities))

    def point(stamp, frame='laser_tracker', xyz=(1.0, 0.5, 0.2)):
        x, y, z = xyz
        return PointStamped(header=Header(stamp=cv.time_msg(stamp), frame_id=frame),
                            point=Point(x=x, y=y, z=z))

    # Malformed points: NaN coordinates, a frame other than the tracker's.
    client.points.publish(point(end, xyz=(float('nan'), 0.0, 0.0)))
    client.points.publish(point(end + 1, frame='world'))
    # Malformed joint states: a NaN position, positions shorter than the names.
    client.joints.publish(joint_state(end, names, [0.0, float('nan'), 0, 0, 0, 0]))
    client.joints.publish(joint_state(end + 1, names, [0.0, 0.1]))
    # Another robot's joint names around a point.
    point_stamp = end + 1_000_000_000
    for dt in (-100_000_000, 100_000_000, 300_000_000):
        client.joints.publish(joint_state(point_stamp + dt, ['axis_a', 'axis_b'], [0.0, 0.0]))
    client.points.publish(point(point_stamp))

    expected = {'rejected.non_finite_point': 1,
                'rejected.wrong_frame': 1, 'rejected.non_finite_joint_state': 2,
                'rejected.missing_joints': 1}

    def counted() -> bool:
        now = client.diagnostics()
        return all(int(now[k]) - int(before[k]) == v for k, v in expected.items())
    client.spin_until(counted, 20, f'rejections {expected}')
    after = client.diagnostics()
    print('rejections after malformed input:',
          {k: v for k, v in after.items() if k.startswith('rejected')})
    assert after['accepted'] == before['accepted']
    assert int(after['ignored_joint_samples']) - int(before['ignored_joint_samples']) == 3
    assert client.received['diagnostics'][-1][0] == DiagnosticStatus.WARN


def test_replay_publishes_the_bag_with_its_timing(client, spawn, tmp_path):
    """Every message, unchanged and in order, spread over the recording's duration / rate."""
    rng = np.random.default_rng(8)
    joints, points = synthesize_streams(rng.uniform(-1, 1, (2, 3)), ['a', 'b', 'c'],
                                        rng.uniform(-1, 1, (2, 3)), 'laser_tracker',
                                        joint_noise_rad=1e-5, rng=rng)
    bag = write_bag(tmp_path / 'short.mcap', joints, points)
    arrivals = {'joints': [], 'points': []}
    qos = QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE)
    client.node.create_subscription(JointState, '/joint_states', lambda m: arrivals['joints']
                                    .append((time.monotonic(), m)), qos)
    client.node.create_subscription(PointStamped, '/laser_tracker/point', lambda m: arrivals[
        'points'].append((time.monotonic(), m)), qos)
    rate = 8.0
    finish(spawn.replay(bag, rate), client)
    client.spin_until(lambda: len(arrivals['joints']) == len(joints)
                      and len(arrivals['points']) == len(points), 10, 'every message')
    for (_, msg), sample in zip(arrivals['joints'], joints):
        got = cv.joint_sample_from_msg(msg)
        assert got.stamp_ns == sample.stamp_ns and got.names == sample.names
        np.testing.assert_array_equal(got.positions, sample.positions)
        np.testing.assert_array_equal(got.velocities, sample.velocities)
    for (_, msg), sample in zip(arrivals['points'], points):
        got = cv.point_sample_from_msg(msg)
        assert (got.stamp_ns, got.frame_id) == (sample.stamp_ns, sample.frame_id)
        np.testing.assert_array_equal(got.xyz, sample.xyz)
    recorded_s = (joints[-1].stamp_ns - joints[0].stamp_ns) * 1e-9
    played_s = arrivals['joints'][-1][0] - arrivals['joints'][0][0]
    print(f'replay: {recorded_s:.1f} s recorded, played in {played_s:.2f} s at rate {rate:g}')
    assert played_s >= 0.9 * recorded_s / rate  # paced, not dumped; slower is allowed


def test_invalid_parameters_stop_the_node_with_the_parameter_named(spawn, tmp_path, ros_domain):
    node = spawn(tmp_path / 'data', 'node.log', 'criterion:=best')
    try:
        code = node.process.wait(timeout=60)
    finally:
        node.stop()
    assert code == 2
    assert 'criterion' in node.output() and "'kpi'" in node.output()


# ---------------------------------------------------------------- in-process logic
def defaults(**changes):
    values = {k: ([] if isinstance(v[0], Parameter.Type) else v[0])
              for k, v in PARAMETERS.items()}
    values.update(changes)
    return values


@pytest.mark.parametrize('changes, key', [
    ({'criterion': 'best'}, 'criterion'),
    ({'num_measurements': 0}, 'num_measurements'),
    ({'min_measurements': 1.5}, 'min_measurements'),
    ({'working_poses': [0.0] * 6}, 'working_joint_names'),
    ({'working_poses': [0.0] * 5, 'working_joint_names': ['a', 'b']}, 'working_poses'),
    ({'point_topic': '/joint_states'}, 'point_topic'),
    ({'cell_file': '/no/such/cell.yaml'}, 'cell_file'),
    ({'data_dir': ''}, 'data_dir'),
])
def test_parameters_are_validated_by_name(changes, key):
    with pytest.raises(ConfigError) as info:
        settings_from_parameters(defaults(**changes))
    assert info.value.key == key


def test_working_poses_parameters_override_the_cell(tmp_path, ros_domain):
    context = Context()
    rclpy.init(context=context, domain_id=ros_domain)
    node = None
    try:
        names = ['joint_1', 'joint_2', 'joint_3', 'joint_4', 'joint_5', 'joint_6']
        poses = [0.0, 0.3, -0.2, 0.0, 0.8, 0.0, 0.5, 0.4, -0.3, 0.1, 0.7, -0.2]
        node = CalibrationNode(context=context, parameter_overrides=[
            Parameter('robot_description', value=KR15_URDF),
            Parameter('working_joint_names', value=names),
            Parameter('working_poses', value=poses),
            Parameter('data_dir', value=str(tmp_path))])
        level, message, values = node.status()
        assert (level, values['state']) == ('OK', 'idle')
        np.testing.assert_array_equal(node._cm.q_work, np.reshape(poses, (2, 6)))
        assert node._cm.working_pose_names == ('work_1', 'work_2')
        # Runtime changes are validated too.
        result = node.set_parameters([Parameter('criterion', value='best')])[0]
        assert not result.successful and 'criterion' in result.reason
        assert node.set_parameters([Parameter('min_measurements', value=5)])[0].successful
        assert node.settings.min_measurements == 5
    finally:
        if node is not None:
            node.destroy_node()
        rclpy.shutdown(context=context)
