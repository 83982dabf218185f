"""The node's ~/identify on a real full file system (a small tmpfs as data_dir, in
process, private context): the identification fails with an ERROR on /diagnostics that
names data_dir and the full disk, the previous calibration's set stays whole on disk,
~/calibration and ~/tcp_query go on serving that calibration and its learned residual
(the old code left the new learned_residual.yaml beside the old calibration.yaml, and
~/tcp_query followed the failed fit), and the node identifies again once there is room."""
from __future__ import annotations

import threading

import numpy as np
import pytest
import rclpy
from rclpy.context import Context
from rclpy.executors import SingleThreadedExecutor
from rclpy.parameter import Parameter
from sensor_msgs.msg import JointState

from kpi_calib_ros.core.measurement.data import Measurements
from kpi_calib_ros.core.simulation import (
    random_configurations,
    simulate_measurements,
    smooth_joint_map,
    true_parameters,
)
from kpi_calib_ros.io.names import CALIBRATION_FILE, LEARNED_RESIDUAL_FILE
from kpi_calib_ros.ros.node import CalibrationNode

from full_disk import fill, small_tmpfs, snapshot
from ros_helpers import KR15_URDF, SpinThread

FIRST_NS = 1_700_000_000_000_000_000
N_POSES = 100


@pytest.fixture
def disk(tmp_path):
    with small_tmpfs(tmp_path / 'disk', '24m') as mounted:
        yield mounted


@pytest.fixture
def node(disk, ros_domain, monkeypatch):
    """A node with data_dir on the tmpfs that learns the residual; its accepted
    measurements are ``node.cycle`` (0 or 1): 100 simulated points of a robot with a
    smooth map its model lacks, each cycle other poses."""
    context = Context()
    rclpy.init(context=context, domain_id=ros_domain)
    made = spinner = None
    executor = SingleThreadedExecutor(context=context)
    try:
        made = CalibrationNode(context=context, parameter_overrides=[
            Parameter('robot_description', value=KR15_URDF),
            Parameter('data_dir', value=str(disk / 'data')),
            Parameter('identify_learned_residual', value=True)])
        cm = made._cm
        rng = np.random.default_rng(3)
        p_true = true_parameters(cm.model.params, rng)
        phase = rng.uniform(0, 2 * np.pi, 6)
        cycles = []
        for k in range(2):
            q = random_configurations(cm.model, p_true, N_POSES, rng)
            eta = simulate_measurements(cm.model, p_true, q, cm.cell.sigma, rng).eta
            eta = eta + smooth_joint_map(q, (1, 2), 2e-4, phase)
            stamps = FIRST_NS + 3_600_000_000_000 * k + 10 ** 9 * np.arange(N_POSES)
            cycles.append(Measurements(q=q, eta=eta, stamps_ns=stamps))
        made.cycle = 0
        monkeypatch.setattr(made.store, 'measurements',
                            lambda *a, **k: (cycles[made.cycle], None))
        executor.add_node(made)
        spinner = SpinThread(executor)
        spinner.start()

        def run(work, *args):
            task = executor.create_task(work, *args)
            finished = threading.Event()
            task.add_done_callback(lambda _: finished.set())
            assert finished.wait(timeout=180), f'{work} did not finish'
            return task.result()

        def identify() -> tuple[bool, str]:
            assert made._claim_job('identifying')
            return run(made._run_job, 'identify', made._identify)

        def tcp_query(q: np.ndarray) -> np.ndarray:
            answers = []
            monkeypatch.setattr(made.tcp_query.publisher, 'publish', answers.append)
            run(made.tcp_query.answer, JointState(name=list(cm.joint_names),
                                                  position=[float(x) for x in q]))
            assert len(answers) == 1
            p = answers[0].pose.pose.position
            return np.array([p.x, p.y, p.z])
        made.identify, made.tcp_query_at = identify, tcp_query
        yield made
    finally:
        if spinner is not None:
            spinner.stop()
        else:
            executor.shutdown()
        if made is not None:
            made.destroy_node()
        rclpy.shutdown(context=context)


@pytest.mark.slow
def test_a_full_disk_keeps_the_old_calibration_served_whole(node, disk):
    data_dir = node.data_dir
    ok, message = node.identify()
    assert ok and 'learned residual chosen' in message, message
    before = snapshot(data_dir)
    assert {CALIBRATION_FILE, LEARNED_RESIDUAL_FILE} <= set(before)
    served = node._calibration_text
    assert served == before[CALIBRATION_FILE].decode()
    q = np.array([0.3, -1.1, 1.0, 0.2, 0.6, -0.4])  # inside the KR15's joint limits
    tcp = node.tcp_query_at(q)
    # Room for little more than a new learned residual once the old one is gone.
    filler = fill(disk, 32 * 1024)
    node.cycle = 1
    ok, message = node.identify()
    assert not ok
    assert snapshot(data_dir) == before
    assert node._calibration_text == served
    assert np.array_equal(node.tcp_query_at(q), tcp)
    assert 'No space left on device' in message and str(data_dir) in message, message
    assert 'intact' in message, message
    level, text, _ = node.status()
    assert level == 'ERROR' and 'No space left on device' in text and str(data_dir) in text
    # Room again: the next ~/identify writes the new set and clears the ERROR.
    filler.unlink()
    ok, message = node.identify()
    assert ok, message
    assert node.status()[0] != 'ERROR'
    assert (data_dir / CALIBRATION_FILE).read_text() == node._calibration_text != served
    assert not np.array_equal(node.tcp_query_at(q), tcp)
