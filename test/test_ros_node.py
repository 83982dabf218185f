"""kpi_calib_node: end to end with real rclpy and Fast DDS, and in process.

End to end (marked slow), the node runs exactly as a cell controller starts it (the
installed executable with the package's params file via --ros-args) on a ROS domain
of the test run's own (``ros_helpers``). A test client with a private context
publishes the robot description, calls the services and listens; `kpi-calib replay`
plays simulated bags. The replayed campaign (kill, restart, results) is in
test_ros_node_campaign.py. In process, with a private context: parameters and the
executor/worker hand-over.
"""
from __future__ import annotations

import dataclasses
import threading
import time
from pathlib import Path

import numpy as np
import pytest
import rclpy
import yaml
from geometry_msgs.msg import PointStamped
from rclpy.context import Context
from rclpy.executors import SingleThreadedExecutor
from rclpy.parameter import Parameter
from rclpy.qos import QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import JointState
from std_msgs.msg import String

from kpi_calib_ros.app.cell_model import build_cell_model
from kpi_calib_ros.core.acquisition.streams import synthesize_streams
from kpi_calib_ros.core.errors import ConfigError
from kpi_calib_ros.io.bag import write_bag
from kpi_calib_ros.io.cell import DEFAULT_CELL, load_cell
from kpi_calib_ros.ros import conversions as cv
from kpi_calib_ros.ros.node import CalibrationNode
from kpi_calib_ros.ros.parameters import PARAMETERS, settings_from_parameters

from ros_helpers import KR15_URDF, SpinThread, finish, run_job, start_error


@pytest.mark.slow
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


@pytest.mark.slow
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


@pytest.mark.slow
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
    ({'joint_states_topic': '/joint states'}, 'joint_states_topic'),
    ({'point_topic': 'tracker/point!'}, 'point_topic'),
    ({'robot_description_topic': ''}, 'robot_description_topic'),
    ({'auto_identify': 'maybe'}, 'auto_identify'),
    ({'drift_velocity': [5.0]}, 'drift_velocity'),
    ({'drift_velocity': [5.0, -1e-5]}, 'drift_velocity'),
    ({'drift_velocity': [5.0, 5e-5, 0.0]}, 'drift_velocity'),
    ({'drift_velocity': ['warm', 'cold']}, 'drift_velocity'),
    ({'allow_code_effects': 'yes'}, 'allow_code_effects'),
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


def _start_error(tmp_path, ros_domain, *overrides: Parameter) -> ConfigError:
    """The ConfigError a node started with ``overrides`` stops with."""
    return start_error(tmp_path / 'data', ros_domain, *overrides)


@pytest.mark.parametrize('name, value, words', [
    ('auto_identify', 'maybe', 'true or false'),     # -p auto_identify:=maybe: a string
    ('num_measurements', 1.5, 'an integer'),
    ('design_seed', 'one', 'an integer'),
    ('working_poses', 'up', 'a list of numbers'),
    ('joint_states_topic', '/joint states', 'not a valid ROS topic name'),
])
def test_a_start_up_value_of_the_wrong_kind_names_the_parameter(tmp_path, ros_domain, name,
                                                                 value, words):
    error = _start_error(tmp_path, ros_domain, Parameter(name, value=value))
    assert error.key == name and words in str(error) and repr(value) in str(error)


def test_an_unusable_data_dir_is_a_config_error(tmp_path, ros_domain):
    blocker = tmp_path / 'a_file'
    blocker.write_text('in the way')
    for data_dir in (blocker, blocker / 'data', Path('/proc/kpi_calib_data')):
        error = _start_error(tmp_path, ros_domain, Parameter('data_dir', value=str(data_dir)))
        assert error.key == 'data_dir' and str(data_dir) in str(error)


def test_the_node_runs_no_code_named_by_the_cell_without_the_opt_in(tmp_path, ros_domain):
    marker = tmp_path / 'ran.marker'
    (tmp_path / 'evil.py').write_text(
        f'from pathlib import Path\nPath({str(marker)!r}).write_text("ran")\n')
    doc = yaml.safe_load(DEFAULT_CELL.read_text())
    doc['robot']['urdf'] = str((DEFAULT_CELL.parent / doc['robot']['urdf']).resolve())
    doc['effects'] = ['evil.py:SAG:joint_2']
    cell = tmp_path / 'cell.yaml'
    cell.write_text(yaml.safe_dump(doc))
    error = _start_error(tmp_path, ros_domain, Parameter('cell_file', value=str(cell)))
    assert error.key == 'effects[0]' and 'allow_code_effects' in str(error)
    assert not marker.exists()
    # With the opt-in the file runs (and is then refused: it defines no SAG).
    error = _start_error(tmp_path, ros_domain, Parameter('cell_file', value=str(cell)),
                         Parameter('allow_code_effects', value=True))
    assert marker.exists() and 'SAG' in str(error)


def test_a_control_character_in_the_cell_file_is_a_config_error_naming_it(tmp_path,
                                                                          ros_domain):
    text = DEFAULT_CELL.read_text()
    cell = tmp_path / 'cell.yaml'
    cell.write_text(text[:100] + '\x00' + text[100:])
    error = _start_error(tmp_path, ros_domain, Parameter('cell_file', value=str(cell)))
    assert error.key == 'cell' and f'{cell} holds a character YAML does not allow' \
        in str(error), str(error)


@pytest.mark.slow
def test_bad_command_line_parameters_exit_2_naming_them(spawn, tmp_path, ros_domain):
    blocker = tmp_path / 'a_file'
    blocker.write_text('in the way')
    for i, (override, name) in enumerate([('auto_identify:=maybe', 'auto_identify'),
                                          ('num_measurements:=1.5', 'num_measurements'),
                                          ('point_topic:=/tracker point', 'point_topic'),
                                          (f'data_dir:={blocker}/data', 'data_dir')]):
        node = spawn(tmp_path / 'data', f'node{i}.log', override)
        try:
            code = node.process.wait(timeout=60)
        finally:
            node.stop()
        assert code == 2, node.output()
        assert f'error: {name}' in node.output() and 'Traceback' not in node.output()


@pytest.fixture
def in_process(tmp_path, ros_domain):
    """A CalibrationNode in this process (private context) with its robot model."""
    context = Context()
    rclpy.init(context=context, domain_id=ros_domain)
    node = None
    try:
        node = CalibrationNode(context=context, parameter_overrides=[
            Parameter('robot_description', value=KR15_URDF),
            Parameter('data_dir', value=str(tmp_path))])
        yield node
    finally:
        if node is not None:
            node.destroy_node()
        rclpy.shutdown(context=context)


def test_a_rejected_parameter_change_leaves_every_setting_as_it_was(in_process):
    """Validation (on-set) has no side effect; only an accepted change is applied (post-set)."""
    node = in_process
    before = node.settings
    result = node.set_parameters([Parameter('num_measurements', value=12),
                                  Parameter('criterion', value='best')])
    assert [r.successful for r in result] == [True, False]  # applied one at a time
    assert 'criterion' in result[1].reason
    assert node.settings == dataclasses.replace(before, num_measurements=12)
    atomic = node.set_parameters_atomically([Parameter('num_measurements', value=7),
                                             Parameter('min_measurements', value=0)])
    assert not atomic.successful and 'min_measurements' in atomic.reason
    assert node.settings.num_measurements == 12 and node.get_parameter(
        'num_measurements').value == 12
    assert node.set_parameters([Parameter('auto_identify', value=False)])[0].successful
    assert node.settings.auto_identify is False


def test_a_new_robot_description_keeps_the_tcp_publisher(in_process):
    """~/tcp is made once: a new robot description with the same working poses reuses it,
    so a worker-era publisher is never destroyed under a publish."""
    node = in_process
    publisher = node._pub_tcp
    depth = len(node._cm.working_pose_names)
    assert publisher is not None and publisher.qos_profile.depth == depth
    node._on_robot_description(String(data=KR15_URDF + '<!-- re-sent -->'))
    assert node._model_error == '' and node._urdf.endswith('<!-- re-sent -->')
    assert node._pub_tcp is publisher
    assert node.count_publishers(node.resolve_topic_name('~/tcp')) == 1
    # A model with another number of working poses: replaced (on the executor), still one.
    replaced = node._tcp_publisher(depth + 3)
    assert replaced is not publisher and replaced.qos_profile.depth == depth + 3
    assert node._tcp_publisher(depth + 3) is replaced
    assert node.count_publishers(node.resolve_topic_name('~/tcp')) == 1


def test_jobs_compute_in_a_worker_and_touch_the_node_on_the_executor(in_process):
    """The hand-over the node relies on: a job's code before and after ``await _offload``
    runs on the executor thread, the offloaded function in another thread, and while
    it runs the executor keeps serving and a second job is refused as busy."""
    node = in_process
    executor = SingleThreadedExecutor(context=node.context)
    executor.add_node(node)
    spinner = SpinThread(executor)
    release, threads, seen = threading.Event(), {}, {}

    def compute(x: float) -> float:
        threads['worker'] = threading.get_ident()
        assert release.wait(timeout=30)
        return 2 * x

    async def job() -> tuple[bool, str]:
        threads['before'] = threading.get_ident()
        value = await node._offload(compute, 21.0)
        threads['after'] = threading.get_ident()
        return True, f'{value:g}'

    def second_claim() -> None:  # a callback that arrives while the job runs
        seen['busy'] = not node._claim_job('other')
        seen['state'] = node.status()[2]['state']
        release.set()

    spinner.start()
    try:
        assert node._claim_job('testing')
        task = executor.create_task(node._run_job, 'test job', job)
        timer = node.create_timer(0.01, lambda: 'worker' in threads and not release.is_set()
                                  and second_claim())
        finished = threading.Event()
        task.add_done_callback(lambda _: finished.set())
        assert finished.wait(timeout=60), 'the job did not finish'
        node.destroy_timer(timer)
        assert task.result() == (True, '42')
        assert seen == {'busy': True, 'state': 'testing'}
        assert threads['before'] == threads['after'] == spinner.ident != threads['worker']
        assert node._claim_job('next')  # freed after the job
    finally:
        spinner.stop()


def test_an_invalid_identification_keeps_the_last_good_calibration(in_process, monkeypatch):
    """A campaign whose KPI is not estimable (60 points from one pose) is never published:
    the previous calibration stays (topics, calibration.yaml) and /diagnostics says ERROR
    with the reason."""
    from kpi_calib_ros.core.measurement.data import Measurements
    from kpi_calib_ros.core.simulation import (
        random_configurations,
        simulate_measurements,
        true_parameters,
    )
    node = in_process
    cm = node._cm
    rng = np.random.default_rng(21)
    p_true = true_parameters(cm.model.params, rng)
    q = random_configurations(cm.model, cm.model.params.nominal, 40, rng)
    campaigns = {'good': q, 'one_pose': np.repeat(q[:1], 60, axis=0)}
    chosen = {}

    def measurements(*_args, **_kwargs):
        data = simulate_measurements(cm.model, p_true, campaigns[chosen['name']], 2e-5, rng)
        stamps = 10 ** 9 * (np.arange(len(data)) + 1)
        return Measurements(q=data.q, eta=data.eta, stamps_ns=stamps), None

    monkeypatch.setattr(node.store, 'measurements', measurements)
    executor = SingleThreadedExecutor(context=node.context)
    executor.add_node(node)
    spinner = SpinThread(executor)
    spinner.start()

    def run(name: str) -> tuple[bool, str]:
        chosen['name'] = name
        return run_job(node, executor, 'identifying', node._identify, 120)

    try:
        ok, message = run('good')
        assert ok, message
        good, written = node._run.result, (node.data_dir / 'calibration.yaml').read_text()
        assert node.status()[0] in ('OK', 'WARN')
        ok, message = run('one_pose')
        assert not ok and 'not estimable' in message.lower()
        assert node._run.result is good
        assert (node.data_dir / 'calibration.yaml').read_text() == written
        level, text, _ = node.status()
        assert level == 'ERROR' and 'calibration not published' in text
    finally:
        spinner.stop()


def test_measured_inputs_that_cannot_be_paired_fail_the_identification_loudly(in_process,
                                                                           monkeypatch):
    """Pairing the measured inputs is part of ~/identify: an input the cell expects
    (``inputs.expect``) that never arrived refuses the identification and /diagnostics says
    ERROR with the reason. The refusal came before the job's error handling and
    /diagnostics stayed OK."""
    from kpi_calib_ros.core.errors import DataError
    from kpi_calib_ros.ros import calibration_jobs
    node = in_process

    def unpaired(*_args, **_kwargs):
        raise DataError("the node's measured inputs: no finite reading of the measured "
                        "input(s) ['payload.mass']")

    monkeypatch.setattr(calibration_jobs, 'station_measurements', unpaired)
    executor = SingleThreadedExecutor(context=node.context)
    executor.add_node(node)
    spinner = SpinThread(executor)
    spinner.start()
    try:
        ok, message = run_job(node, executor, 'identifying', node._identify, 60)
        assert not ok and 'payload.mass' in message
        level, text, _ = node.status()
        assert level == 'ERROR' and 'identification failed' in text and 'payload.mass' in text
    finally:
        spinner.stop()


def test_heavy_jobs_compute_in_a_child_process_that_holds_no_gil_of_the_node(in_process,
                                                                            tmp_path):
    """``child=True``: the function runs in another process (its own interpreter and GIL),
    sees the inputs without pickling them, writes files the node then reads, and its
    value or its error (ConfigError included) comes back to the job on the executor."""
    import os

    from kpi_calib_ros.core.errors import KpiCalibError
    node = in_process
    executor = SingleThreadedExecutor(context=node.context)
    executor.add_node(node)
    unpicklable = threading.Lock()  # an input that could not be sent to a spawned process

    def compute(lock, path):
        path.write_text(str(os.getpid()))
        return os.getpid(), lock.locked()

    def refuse():
        raise ConfigError('some.key', 'a reason')

    async def job():
        pid, locked = await node._offload(compute, unpicklable, tmp_path / 'pid', child=True)
        try:
            await node._offload(refuse, child=True)
        except KpiCalibError as exc:
            return pid, locked, str(exc)
        return pid, locked, ''

    try:
        task = executor.create_task(job)
        executor.spin_until_future_complete(task, timeout_sec=60)
        pid, locked, error = task.result()
    finally:
        executor.shutdown()
    assert pid != os.getpid() and (tmp_path / 'pid').read_text() == str(pid)
    assert locked is False and error == 'some.key: a reason'


def test_joint_states_lost_before_the_node_read_them_are_counted_and_reported(in_process):
    """DDS numbers each message of a publisher; a gap is messages the queue dropped."""
    node = in_process
    sequence = node._sequences['joint_states']
    for number in (1, 2, 3, 7, 8, 20, 1, 2):  # 3 + 11 lost; 1 again: a new publisher
        sequence.see({'publication_sequence_number': number})
    level, message, values = node.status()
    assert values['lost.joint_states'] == 14 and values['lost.points'] == 0
    assert level == 'WARN' and '14 joint states' in message


@pytest.mark.slow
def test_joint_states_at_1khz_all_arrive_while_the_node_identifies(client, spawn, tmp_path):
    """A driver streams 1 kHz joint states, unpaced by the node, while the node identifies
    again after every new measurement: every joint state is received, none counted lost,
    every point accepted. (Jobs in a thread of the node lost 37 % of them:
    bench/node_load.py.)"""
    from kpi_calib_ros.core.simulation import (
        random_configurations,
        simulate_measurements,
        true_parameters,
    )
    cm = build_cell_model(load_cell(DEFAULT_CELL))
    rng = np.random.default_rng(4)
    q = random_configurations(cm.model, cm.model.params.nominal, 16, rng)
    data = simulate_measurements(cm.model, true_parameters(cm.model.params, rng), q,
                                 cm.cell.sigma, rng)
    joints, points = synthesize_streams(q, cm.joint_names, data.eta, cm.cell.tracker_frame,
                                        rate_hz=1000.0, move_time_s=1.0, hold_time_s=1.0,
                                        rng=rng)
    stream = sorted([(s.stamp_ns, 0, cv.joint_state_msg(s)) for s in joints]
                    + [(p.stamp_ns, 1, cv.point_stamped_msg(p)) for p in points],
                    key=lambda item: item[:2])
    node = spawn(tmp_path / 'data', 'node.log', 'auto_identify:=true', 'min_measurements:=10')
    client.spin_until(lambda: client.diagnostics().get('state') == 'idle', 60, 'the model')
    publishers = (client.joints, client.points)
    start, first = time.monotonic(), stream[0][0]
    for i, (stamp, kind, msg) in enumerate(stream):
        delay = start + (stamp - first) * 1e-9 - time.monotonic()
        if delay > 0:
            time.sleep(delay)  # the driver's clock: pacing, not synchronisation
        publishers[kind].publish(msg)
        if not i % 500:
            client.executor.spin_once(timeout_sec=0.0)
    client.spin_until(lambda: client.count('identified_with') == len(points)
                      and client.count('received.joint_states') >= len(joints)
                      and client.diagnostics().get('state') == 'idle', 180, 'the last job')
    counts = client.diagnostics()
    node.stop()
    assert int(counts['received.joint_states']) == len(joints)
    assert int(counts['lost.joint_states']) == 0 and int(counts['lost.points']) == 0
    assert int(counts['accepted']) == len(points) and int(counts['rejected']) == 0
    assert int(counts['identifications']) >= 2  # jobs ran while the stream went on


def _with_a_campaign(context, executor, overrides):
    """An in-process node with ``overrides`` and a caller on ``executor``; ~/design started
    its sequential campaign. Returns (node, caller)."""
    from std_srvs.srv import Trigger
    node = CalibrationNode(context=context, parameter_overrides=overrides)
    caller = rclpy.create_node('caller', context=context)
    executor.add_node(node)
    executor.add_node(caller)
    design = caller.create_client(Trigger, '/kpi_calib_node/design')
    assert design.wait_for_service(timeout_sec=10)
    future = design.call_async(Trigger.Request())
    executor.spin_until_future_complete(future, timeout_sec=120)
    assert future.done() and future.result().success, future.result()
    return node, caller


@pytest.mark.slow
def test_a_station_change_stops_a_running_sequential_campaign(tmp_path, ros_domain):
    """The tracker moved under a running campaign (lost line of sight): the station change
    was refused, and the campaign could go on only after ~/reset archived its measurements.
    It is now accepted and stops the campaign (it plans from one placement): stop_reason
    'station changed' in /diagnostics and campaign_state.yaml, its plan withdrawn,
    ~/identify no longer refused; a restart does not resume it."""
    import yaml
    from std_srvs.srv import Trigger

    from kpi_calib_ros.core.campaigns.settings import STATION_CHANGED
    from kpi_calib_ros.io.names import CAMPAIGN_STATE_FILE
    context = Context()
    rclpy.init(context=context, domain_id=ros_domain)
    node = caller = again = None
    executor = SingleThreadedExecutor(context=context)
    overrides = [Parameter('robot_description', value=KR15_URDF),
                 Parameter('data_dir', value=str(tmp_path)),
                 Parameter('campaign', value='sequential'), Parameter('station', value='near')]
    try:
        node, caller = _with_a_campaign(context, executor, overrides)
        assert node.status()[2]['campaign.stop_reason'] == 'running'
        result = node.set_parameters([Parameter('station', value='far')])[0]
        assert result.successful, result.reason
        assert node.status()[2]['campaign.stop_reason'] == STATION_CHANGED
        state = yaml.safe_load((tmp_path / CAMPAIGN_STATE_FILE).read_text())
        assert state['status']['stop_reason'] == STATION_CHANGED
        assert state['status']['station_changed'] == {'from': 'near', 'to': 'far',
                                                      'probe_remounted': False}
        identify = caller.create_client(Trigger, '/kpi_calib_node/identify')
        assert identify.wait_for_service(timeout_sec=10)
        future = identify.call_async(Trigger.Request())
        executor.spin_until_future_complete(future, timeout_sec=60)
        assert 'sequential campaign is running' not in future.result().message
        executor.remove_node(node)
        node.destroy_node()
        node = None
        again = CalibrationNode(context=context, parameter_overrides=overrides)
        assert not again._run.resume_pending
        assert again.status()[2]['campaign.stop_reason'] == STATION_CHANGED
    finally:
        executor.shutdown()
        for n in (caller, node, again):
            if n is not None:
                n.destroy_node()
        rclpy.shutdown(context=context)


@pytest.mark.slow
def test_campaign_parameters_are_refused_while_a_sequential_campaign_runs(tmp_path,
                                                                          ros_domain):
    """A running campaign keeps its target and cap: a change is refused with the reason, so
    the parameter, ~/campaign_status and /diagnostics all keep stating the one target the
    campaign works to; other parameters still change. ~/identify is refused too."""
    from std_srvs.srv import Trigger
    context = Context()
    rclpy.init(context=context, domain_id=ros_domain)
    node = caller = None
    executor = SingleThreadedExecutor(context=context)
    try:
        node, caller = _with_a_campaign(context, executor, [
            Parameter('robot_description', value=KR15_URDF),
            Parameter('data_dir', value=str(tmp_path)),
            Parameter('campaign', value='sequential'),
            Parameter('target_tcp_std', value=12e-6)])
        for name, value in (('target_tcp_std', 2e-5), ('max_measurements', 30)):
            result = node.set_parameters([Parameter(name, value=value)])[0]
            assert not result.successful
            assert name in result.reason and 'campaign is running' in result.reason
        assert node.get_parameter('target_tcp_std').value == 12e-6
        _, _, values = node.status()
        assert values['campaign.target_um'] == pytest.approx(12.0)
        assert values['campaign.max_measurements'] == 200
        assert node.set_parameters([Parameter('num_measurements', value=12)])[0].successful
        # Nor is a calibration of part of the campaign published.
        identify = caller.create_client(Trigger, '/kpi_calib_node/identify')
        assert identify.wait_for_service(timeout_sec=10)
        future = identify.call_async(Trigger.Request())
        executor.spin_until_future_complete(future, timeout_sec=60)
        answer = future.result()
        assert not answer.success and 'sequential campaign is running' in answer.message
    finally:
        executor.shutdown()
        for n in (caller, node):
            if n is not None:
                n.destroy_node()
        rclpy.shutdown(context=context)


def test_a_pose_read_beyond_the_joint_limits_is_rejected_and_named(in_process):
    """A still pose whose reading lies beyond a joint's URDF limits (a wrong joint order,
    unit or zero) is a rejected row, counted and named, as the TCP query refuses it; the
    node accepted such rows silently and fitted them, stating training joint ranges beyond
    the robot's."""
    node = in_process
    cm = node._cm
    q = np.repeat(cm.q_work[:1], 3, axis=0)
    q[1, 1] = cm.robot.upper[1] + 0.2  # joint_2 0.2 rad beyond its upper limit
    q[2, 2] = cm.robot.lower[2] - 0.02  # joint_3 just beyond, beyond the 0.01 rad tolerance
    joints, points = synthesize_streams(cm.joint_coupling.to_controller(q), cm.joint_names,
                                        np.zeros((3, 3)), cm.cell.tracker_frame)
    stream = sorted([(s.stamp_ns, 0, s) for s in joints] + [(p.stamp_ns, 1, p) for p in points],
                    key=lambda item: item[:2])
    for _, kind, sample in stream:
        if kind == 0:
            node._on_joint_state(cv.joint_state_msg(sample), {})
        else:
            node._on_point(cv.point_stamped_msg(sample), {})
    counts = node.store.counts()
    assert counts['accepted'] == 1 and counts['rejected.outside_joint_limits'] == 2
