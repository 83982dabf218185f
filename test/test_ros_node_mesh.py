"""The node with a stock mesh robot description (UR10 from example-robot-data, package://
meshes as robot_state_publisher publishes them) and a cell with no placement: it builds the
model without touching the meshes, identifies (registering the placement from the data) as
`kpi-calib identify` does, and after a design draws the fitted capsules in ``~/markers``.
In process, with a private context."""
from __future__ import annotations

import threading
from pathlib import Path

import numpy as np
import pytest
import rclpy
import yaml
from rclpy.context import Context
from rclpy.executors import SingleThreadedExecutor
from rclpy.parameter import Parameter
from visualization_msgs.msg import MarkerArray

from kpi_calib_ros.app.cell_model import build_cell_model
from kpi_calib_ros.app.identify import identify_cell
from kpi_calib_ros.core.acquisition.streams import synthesize_streams
from kpi_calib_ros.core.simulation import (
    random_configurations,
    simulate_measurements,
    true_parameters,
)
from kpi_calib_ros.io.cell import load_cell
from kpi_calib_ros.io.resources import resolve_uri
from kpi_calib_ros.ros import conversions as cv
from kpi_calib_ros.ros.node import CalibrationNode

from ros_helpers import LATCHED, SpinThread, run_job

DATA = Path(__file__).resolve().parent / 'data'
UR10 = 'package://example-robot-data/robots/ur_description/urdf/ur10_robot.urdf'
SIGMA = 2.0e-5



@pytest.mark.slow
def test_node_identifies_from_a_stock_mesh_urdf_with_unknown_placement(tmp_path, ros_domain):
    doc = yaml.safe_load((DATA / 'ur10_mesh_cell.yaml').read_text())
    truth_cell = tmp_path / 'truth.yaml'
    truth_cell.write_text(yaml.safe_dump(doc))
    del doc['tracker']['base_in_tracker'], doc['reflector']['offset']
    cell = tmp_path / 'cell.yaml'
    cell.write_text(yaml.safe_dump(doc))
    urdf = resolve_uri(UR10).read_text()  # package:// URIs left as they are
    assert 'package://example-robot-data' in urdf

    truth = build_cell_model(load_cell(truth_cell))
    rng = np.random.default_rng(12)
    p_true = true_parameters(truth.model.params, rng)
    q = random_configurations(truth.model, p_true, 30, rng)
    data = simulate_measurements(truth.model, p_true, q, SIGMA, rng)
    joints, points = synthesize_streams(q, truth.joint_names, data.eta, 'laser_tracker',
                                        joint_noise_rad=0.0, rng=rng)

    context = Context()
    rclpy.init(context=context, domain_id=ros_domain)
    node = executor = spinner = None
    try:
        node = CalibrationNode(context=context, parameter_overrides=[
            Parameter('robot_description', value=urdf), Parameter('cell_file', value=str(cell)),
            Parameter('auto_identify', value=False), Parameter('num_measurements', value=16),
            Parameter('data_dir', value=str(tmp_path / 'data'))])
        assert node.status()[2]['state'] == 'idle'
        # Until a design builds the robot capsules, only obstacle capsules are drawn.
        assert all(c.frame == 'base' for c in node._capsules)
        samples = sorted([(s.stamp_ns, 0, s) for s in joints] + [(s.stamp_ns, 1, s)
                                                                  for s in points],
                         key=lambda t: t[:2])
        for _, kind, sample in samples:  # arrival order, on this (the executor's) thread
            if kind == 0:
                node._on_joint_state(cv.joint_state_msg(sample), {})
            else:
                node._on_point(cv.point_stamped_msg(sample), {})
        assert len(node.store) == 30

        executor = SingleThreadedExecutor(context=context)
        executor.add_node(node)
        spinner = SpinThread(executor)
        spinner.start()
        ok, message = run_job(node, executor, 'identifying', node._identify, 300)
        assert ok, message
        # The same numbers as the offline path on the paired campaign.
        paired, _ = node.store.measurements(node._cm.joint_names, 'laser_tracker')
        offline = identify_cell(build_cell_model(load_cell(cell)), paired)
        np.testing.assert_allclose(node._run.result.values, offline.values, rtol=0, atol=1e-12)
        # The registered start led to the true robot: TCP within 5 σ of its prediction.
        tcp_true = truth.model.predict(p_true, truth.q_work)
        err = np.linalg.norm(node._run.result.tcp - tcp_true, axis=1)
        std = np.sqrt(np.trace(node._run.result.tcp_covariance, axis1=1, axis2=2))
        print(f'node: TCP error {np.round(err * 1e6, 2).tolist()} µm, std '
              f'{np.round(std * 1e6, 2).tolist()} µm, rms {node._run.result.rms_m * 1e6:.2f} µm')
        assert np.all(err < 5 * std)

        # Without a tracker pose a design cannot know where the tracker is: it says so.
        ok, message = run_job(node, executor, 'designing', node._design, 300)
        assert not ok and 'tracker.base_in_tracker' in message
    finally:
        if spinner is not None:
            spinner.stop()
        elif executor is not None:
            executor.shutdown()
        if node is not None:
            node.destroy_node()
        rclpy.shutdown(context=context)


@pytest.mark.slow
def test_node_draws_the_fitted_capsules_after_a_design(tmp_path, ros_domain):
    urdf = resolve_uri(UR10).read_text()
    context = Context()
    rclpy.init(context=context, domain_id=ros_domain)
    node = executor = spinner = None
    try:
        node = CalibrationNode(context=context, parameter_overrides=[
            Parameter('robot_description', value=urdf),
            Parameter('cell_file', value=str(DATA / 'ur10_mesh_cell.yaml')),
            Parameter('num_measurements', value=12),
            Parameter('data_dir', value=str(tmp_path / 'data'))])
        markers: list[MarkerArray] = []
        node.create_subscription(MarkerArray, '~/markers', markers.append, LATCHED)
        executor = SingleThreadedExecutor(context=context)
        executor.add_node(node)
        spinner = SpinThread(executor)
        spinner.start()
        ok, message = run_job(node, executor, 'designing', node._design, 300)
        assert ok, message
        written = yaml.safe_load((tmp_path / 'data' / 'design.yaml').read_text())
        assert written['verification']['ok']
        assert {c['link'] for c in written['geometry']['capsules']} == set(
            node._cm.robot.link_names)
        links = node._cm.robot.link_names
        fitted = node._cm.robot_geometry().capsules
        assert {c.frame for c in fitted} == set(links)
        done = threading.Event()
        node.create_timer(0.05, lambda: markers and done.set())
        assert done.wait(timeout=30), 'no markers'
        capsules = [m for m in markers[-1].markers if m.ns == 'capsules']
        assert {m.header.frame_id for m in capsules} >= set(links)
        # Two spheres per capsule (a cylinder too when it has a length).
        assert sum(m.type == m.SPHERE for m in capsules) == 2 * len(fitted)
    finally:
        if spinner is not None:
            spinner.stop()
        elif executor is not None:
            executor.shutdown()
        if node is not None:
            node.destroy_node()
        rclpy.shutdown(context=context)


def test_node_accepts_a_description_whose_meshes_cannot_be_found(tmp_path, ros_domain):
    """Identification needs the chain only: the model is ready; a design says what is missing."""
    missing_mesh_urdf = (DATA / 'missing_mesh_arm.urdf').read_text()
    cell = tmp_path / 'cell.yaml'
    cell.write_text(yaml.safe_dump({
        'robot': {'urdf': 'unused.urdf', 'base_frame': 'base', 'tip_frame': 'tip'},
        'tracker': {'base_in_tracker': [2.0, 0.0, 0.0, 0.0, 0.0, 3.0]},
        'noise': {'sigma': SIGMA}, 'working_poses': [[0.5, 0.3]]}))
    context = Context()
    rclpy.init(context=context, domain_id=ros_domain)
    node = executor = spinner = None
    try:
        node = CalibrationNode(context=context, parameter_overrides=[
            Parameter('robot_description', value=missing_mesh_urdf),
            Parameter('cell_file', value=str(cell)),
            Parameter('data_dir', value=str(tmp_path / 'data'))])
        assert node.status()[2]['state'] == 'idle' and node._cm.joint_names == ['j1', 'j2']
        executor = SingleThreadedExecutor(context=context)
        executor.add_node(node)
        spinner = SpinThread(executor)
        spinner.start()
        ok, message = run_job(node, executor, 'designing', node._design, 300)
        assert not ok and 'package://no_such_pkg/meshes/base.stl' in message
        assert 'tried' in message
    finally:
        if spinner is not None:
            spinner.stop()
        elif executor is not None:
            executor.shutdown()
        if node is not None:
            node.destroy_node()
        rclpy.shutdown(context=context)
