"""kpi_calib_node on a robot description with mimic joints, end to end (real rclpy and Fast
DDS, the node as a separate process): the stock UR5 on a two-stage lifting column whose
stages mimic its drive (``mimic_column``), published on /robot_description.

The robot's driver first publishes the actuated joints only (the drive ``lift`` and the
arm), then the stages too, as ros2_control publishes mimic joints; both are accepted. Joint
states in which a stage does not follow its drive are rejected rows, counted under
``mimic_mismatch``. ~/identify calibrates from the accepted rows, its result agrees with
the truth within the stated TCP uncertainty, and the calibrated description it publishes
keeps the mimic tags.
"""
from __future__ import annotations

import xml.etree.ElementTree as ET

import numpy as np
import pytest
import scipy.stats
import yaml
from std_msgs.msg import String

from kpi_calib_ros.app.cell_model import build_cell_model
from kpi_calib_ros.core.acquisition.streams import JointSample
from kpi_calib_ros.core.simulation import (
    random_configurations,
    simulate_measurements,
    true_parameters,
)
from kpi_calib_ros.io.cell import load_cell

from mimic_column import STAGES, column_urdf, write_cell
from ros_helpers import Client

N_PLAIN, N_STAGES, N_BAD = 25, 25, 3
SEED = 7


def with_stages(cm, error: float = 0.0):
    """An edit of joint samples: each carries the stages' readings too (stage 2 ``error``
    (m) off its relation)."""
    def edit(joints: list[JointSample]) -> list[JointSample]:
        out = []
        for s in joints:
            stages = cm.joint_coupling.to_urdf(np.asarray(s.positions))[:2] + [0.0, error]
            out.append(JointSample(s.stamp_ns, (*s.names, *STAGES), np.r_[s.positions, stages],
                                   None if s.velocities is None
                                   else np.r_[s.velocities, 0.0, 0.0]))
        return out
    return edit


@pytest.mark.slow
def test_node_pairs_joint_states_with_and_without_mimic_joints_and_identifies(
        ros_domain, spawn, tmp_path):
    cell = write_cell(tmp_path)
    cm = build_cell_model(load_cell(cell))
    rng = np.random.default_rng(SEED)
    p_true = true_parameters(cm.model.params, rng)
    n = N_PLAIN + N_STAGES + N_BAD
    # An active target (seen from every side): the poses cover the joint ranges.
    q = random_configurations(cm.model, cm.model.params.nominal, n, rng, max_incidence=np.pi)
    eta = simulate_measurements(cm.model, p_true, q, cm.cell.sigma, rng).eta
    x = cm.joint_coupling.to_controller(q)  # what the driver reports: lift and the arm
    frame = cm.cell.tracker_frame
    data_dir = tmp_path / 'data'
    client = Client(ros_domain)
    urdf = column_urdf()
    client.description.publish(String(data=urdf))
    node = spawn(data_dir, 'node.log', 'auto_identify:=false', f'cell_file:={cell}')
    try:
        client.spin_until(lambda: client.diagnostics().get('state') == 'idle', 60,
                          'the robot model from /robot_description')
        plain, staged = slice(0, N_PLAIN), slice(N_PLAIN, N_PLAIN + N_STAGES)
        client.publish_measurements(x[plain], cm.joint_names, eta[plain], frame, N_PLAIN)
        later = 1_700_000_000_000_000_000 + 3_600 * 10 ** 9  # an hour on, then another
        client.publish_measurements(x[staged], cm.joint_names, eta[staged], frame,
                                    N_PLAIN + N_STAGES, edit=with_stages(cm), start_ns=later)
        bad = slice(N_PLAIN + N_STAGES, n)
        client.publish_measurements(x[bad], cm.joint_names, eta[bad], frame,
                                    N_PLAIN + N_STAGES, edit=with_stages(cm, 1e-3),
                                    start_ns=later + 3_600 * 10 ** 9)
        client.spin_until(lambda: client.count('rejected.mimic_mismatch') == N_BAD, 30,
                          f'{N_BAD} rows rejected as mimic_mismatch')
        assert client.count('accepted') == N_PLAIN + N_STAGES
        assert 'mimic_mismatch' in node.output()

        done = client.call('identify', timeout=180)
        print('identify:', done.message)
        assert done.success, done.message
        doc = yaml.safe_load((data_dir / 'calibration.yaml').read_text())
        assert doc['valid'] is True and doc['pairing']['accepted'] == N_PLAIN + N_STAGES
        assert doc['training_configurations']['joints'] == cm.robot.joint_names
        error = np.array(doc['tcp'][0]['position']) - cm.model.predict(p_true, cm.q_work)[0]
        cov = np.array(doc['tcp'][0]['covariance'], float)
        mahalanobis = float(np.sqrt(error @ np.linalg.solve(cov, error)))
        print(f'TCP error {error * 1e6} µm, Mahalanobis {mahalanobis:.2f}')
        assert mahalanobis < np.sqrt(scipy.stats.chi2.ppf(0.999, 3))
        client.spin_until(lambda: client.received['robot_description_calibrated'], 20,
                          'the calibrated robot description')
        written = client.received['robot_description_calibrated'][-1].data
        tags = {e.get('name'): e.find('mimic') for e in ET.fromstring(written).findall('joint')}
        assert all(tags[s] is not None and tags[s].get('joint') == 'lift' for s in STAGES)
    finally:
        client.close()
        assert node.stop() == 0, node.output()
