"""kpi_calib_node's learned residual on a stock arm whose model ``auto`` augments, end to end
(real rclpy and Fast DDS, the node as a separate process): the Panda of example-robot-data
(package:// meshes, a mimic finger joint) published on /robot_description,
a cell with ``identification.model: auto``, and a true robot whose joint 2 bends under
gravity (a compliance auto adds) and carries a smooth unknown map of joints 2 and 4 that
no effect describes. ~/identify with identify_learned_residual adds the compliance, learns
the rest and writes learned_residual.yaml for the augmented model; ~/tcp_query (joints by
name, in any order, the fingers too) answers at fresh poses in the training region closer
to the truth than the calibration's physical model, the truth inside the stated 95 %
ellipsoid at a plausible share; a node restarted on the same data_dir restores its
calibration (the augmented model) and answers the same;
switched off, the next calibration removes the file and the physical model (with the
compliance) answers."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import scipy.stats
import yaml
from rclpy.parameter import Parameter
from rclpy.parameter_client import AsyncParameterClient
from std_msgs.msg import String

from kpi_calib_ros.app.cell_model import build_cell_model
from kpi_calib_ros.app.learned_residual import predict_stored
from kpi_calib_ros.app.validate import calibrated_model
from kpi_calib_ros.core.diagnosis.effect_signature import augmented_model
from kpi_calib_ros.core.simulation import (
    random_configurations,
    simulate_measurements,
    smooth_joint_map,
    true_parameters,
)
from kpi_calib_ros.io.arm_cell import arm_cell_document
from kpi_calib_ros.io.cell import load_cell
from kpi_calib_ros.io.cell_settings import hidden_effects
from kpi_calib_ros.io.learned_residual_file import read_residual
from kpi_calib_ros.io.resources import resolve_uri

from ros_helpers import Client, Queries

PANDA = 'package://example-robot-data/robots/panda_description/urdf/panda.urdf'
SIGMA = 20e-6
N_POSES = 120
N_FRESH = 25
SEED = 3
COMPLIANCE = 'joint_compliance:panda_joint2'
HIDDEN = {COMPLIANCE: {'c': 5e-6}}  # rad/(N m): ~100 N m swing of gravity torque, ~0.5 mrad
AMPLITUDE_M = 6e-5                  # the map's largest size per axis, 3 σ
JOINTS = (1, 3)                     # the map depends on panda_joint2 and panda_joint4
FINGERS = ('panda_finger_joint1', 'panda_finger_joint2')  # not in the chain


def cell_file(tmp_path: Path) -> Path:
    """The Panda 2.5 m from the tracker, the reflector off the flange axis, ``auto``."""
    doc = arm_cell_document(PANDA, 'panda_link0', 'panda_hand', SIGMA)
    doc['identification'] = {'model': 'auto'}
    doc['working_poses'] = [[0.0, -0.3, 0.0, -2.0, 0.0, 1.7, 0.8]]
    path = tmp_path / 'panda_cell.yaml'
    path.write_text(yaml.safe_dump(doc))
    return path


def robot(cell: Path):
    """The cell model, training poses and their measured points, fresh poses, the truth."""
    cm = build_cell_model(load_cell(cell))
    effects, overrides = hidden_effects(HIDDEN, cm.robot)
    truth = augmented_model(cm.model, effects)
    rng = np.random.default_rng(SEED)
    p = true_parameters(truth.params, rng, overrides=overrides)
    phase = rng.uniform(0, 2 * np.pi, 6)
    # An active target (seen from every side): the poses cover the joint ranges.
    q = random_configurations(cm.model, cm.model.params.nominal, N_POSES + N_FRESH, rng,
                              max_incidence=np.pi)

    def true_tcp(qq: np.ndarray) -> np.ndarray:
        return truth.predict(p, qq) + smooth_joint_map(qq, JOINTS, AMPLITUDE_M, phase)
    eta = simulate_measurements(truth, p, q[:N_POSES], SIGMA, rng).eta
    eta = eta + smooth_joint_map(q[:N_POSES], JOINTS, AMPLITUDE_M, phase)
    return cm, q[:N_POSES], eta, q[N_POSES:], true_tcp


def rms(e: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.sum(e ** 2, axis=1))))


@pytest.mark.slow
def test_auto_effects_and_the_learned_residual_on_a_stock_arm(ros_domain, spawn, tmp_path):
    cell = cell_file(tmp_path)
    cm, q, eta, fresh, true_tcp = robot(cell)
    data_dir = tmp_path / 'data'
    overrides = ('auto_identify:=false', f'cell_file:={cell}', 'identify_learned_residual:=true')
    client = Client(ros_domain)
    # As robot_state_publisher publishes it: package:// meshes, a mimic finger joint.
    urdf = resolve_uri(PANDA).read_text()
    assert 'package://' in urdf and '<mimic' in urdf
    client.description.publish(String(data=urdf))
    node = spawn(data_dir, 'node.log', *overrides)
    # The query names the joints in another order than the chain's, the fingers among them.
    names = [*reversed(cm.joint_names[:4]), FINGERS[0], *cm.joint_names[4:], FINGERS[1]]
    queries = Queries(client, cm, N_FRESH, names, {finger: 0.02 for finger in FINGERS})

    def ask(row: np.ndarray, stamp: int) -> tuple[np.ndarray, np.ndarray]:
        """The node's TCP (m) and its position covariance (m²) at URDF joints ``row``."""
        return queries.ask([row], stamp, timeout=20)[0]

    def ready() -> None:
        client.spin_until(lambda: client.diagnostics().get('state') == 'idle'
                          and queries.connected(), 60, 'the robot model and the TCP query topics')
    try:
        ready()
        client.publish_measurements(q, cm.joint_names, eta, cm.cell.tracker_frame, N_POSES)

        done = client.call('identify', timeout=120)
        print('identify:', done.message)
        assert done.success, done.message
        assert "learned residual chosen: rms" in done.message, done.message
        # auto added the hidden compliance, and calibration.yaml holds the augmented model.
        doc = yaml.safe_load((data_dir / 'calibration.yaml').read_text())
        assert doc['effects'] == [COMPLIANCE], doc['effects']
        assert doc['learned_residual']['chosen'] is True
        cal_cm, values = calibrated_model(load_cell(cell), doc)
        stored = read_residual(data_dir / 'learned_residual.yaml')
        assert stored.names == tuple(cal_cm.model.params.names)
        assert 'joint_compliance.panda_joint2.c' in stored.estimated
        np.testing.assert_allclose(stored.values, values, rtol=0, atol=0)

        stamps = [(i + 1) * 10 ** 6 for i in range(N_FRESH)]
        answered_at = [ask(row, s) for row, s in zip(fresh, stamps)]
        corrected = np.array([a[0] for a in answered_at])
        covariance = np.array([a[1] for a in answered_at])
        expected = predict_stored(cal_cm.model, stored, fresh)
        np.testing.assert_allclose(corrected, expected.position, rtol=0, atol=1e-9)
        np.testing.assert_allclose(covariance, expected.covariance, rtol=1e-9, atol=0)

        # Against the truth: closer than the calibration's physical model (with the
        # compliance), and the truth inside the stated 95 % ellipsoid at a plausible share.
        inside = expected.correction.inside
        truth = true_tcp(fresh)
        physical = cal_cm.model.predict(values, fresh)
        error = corrected - truth
        m2 = np.einsum('mi,mij,mj->m', error, np.linalg.inv(covariance), error)
        covered = m2[inside] <= scipy.stats.chi2.ppf(0.95, 3)
        error_physical, error_learned = rms((physical - truth)[inside]), rms(error[inside])
        print(f'{inside.sum()} of {N_FRESH} fresh poses inside the fitted region: TCP error '
              f'rms {error_physical * 1e6:.1f} um physical (with the compliance), '
              f'{error_learned * 1e6:.1f} um with the learned residual '
              f'({error_learned / error_physical:.2f}x); inside the 95 % ellipsoid '
              f'{covered.mean():.0%}')
        assert inside.sum() >= 20
        assert error_learned <= 0.7 * error_physical
        assert covered.mean() >= 0.8

        # Restarted on the same data_dir (nothing identified since): the same answer.
        assert node.stop() == 0, node.output()
        client.spin_until(lambda: not queries.publisher.get_subscription_count(), 20,
                          'the node gone')
        client.received['diagnostics'].clear()
        node = spawn(data_dir, 'node_restarted.log', *overrides)
        ready()
        # Its calibration, the model auto augmented, is restored with it (ros/restore.py).
        client.spin_until(lambda: 'calibration' in client.diagnostics(), 30, 'the restore')
        assert client.diagnostics()['calibration'].startswith(
            f"restored from {data_dir / 'calibration.yaml'}, identified at"), node.output()
        again = ask(fresh[0], 10 ** 9)
        np.testing.assert_allclose(again[0], corrected[0], rtol=0, atol=1e-9)
        np.testing.assert_allclose(again[1], covariance[0], rtol=1e-9, atol=0)

        # Switched off, a new calibration removes the file: the physical model answers,
        # the calibration's own (with the compliance auto adds again).
        params = AsyncParameterClient(client.node, 'kpi_calib_node')
        assert params.wait_for_services(timeout_sec=10)
        future = params.set_parameters([Parameter('identify_learned_residual', value=False)])
        client.executor.spin_until_future_complete(future, timeout_sec=10)
        assert future.result().results[0].successful, future.result().results[0].reason
        done = client.call('identify', timeout=120)
        assert done.success, done.message
        assert not (data_dir / 'learned_residual.yaml').exists()
        doc = yaml.safe_load((data_dir / 'calibration.yaml').read_text())
        assert doc['effects'] == [COMPLIANCE] and 'learned_residual' not in doc
        cal_cm, values = calibrated_model(load_cell(cell), doc)
        plain = ask(fresh[0], 2 * 10 ** 9)
        np.testing.assert_allclose(plain[0], cal_cm.model.predict(values, fresh[:1])[0],
                                   rtol=0, atol=1e-9)
    finally:
        code = node.stop()
        client.close()
    assert code == 0, node.output()
