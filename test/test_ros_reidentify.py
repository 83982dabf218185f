"""kpi_calib_node over two work cycles, the node as a process (real rclpy and Fast DDS):
the second cycle is identified with the first cycle's calibration as prior, the calibration
topic is updated and the first calibration stays in data_dir/calibrations/."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import yaml
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from std_msgs.msg import String

from kpi_calib_ros.core.acquisition.streams import synthesize_streams
from kpi_calib_ros.core.simulation import (
    random_configurations,
    simulate_measurements,
    true_parameters,
)
from kpi_calib_ros.io.bag_writing import write_bag

from ros_helpers import finish

pytestmark = pytest.mark.slow
START_NS = 1_700_000_000_000_000_000
HOUR_NS = 3_600_000_000_000


def _cycle_bag(path: Path, cm, p_true, n: int, start_ns: int, seed: int) -> Path:
    rng = np.random.default_rng(seed)
    q = random_configurations(cm.model, cm.model.params.nominal, n, rng)
    eta = simulate_measurements(cm.model, p_true, q, cm.cell.sigma, rng).eta
    joints, points = synthesize_streams(q, cm.joint_names, eta, cm.cell.tracker_frame,
                                        start_ns=start_ns, rng=rng)
    write_bag(path, joints, points)
    return path


def test_second_cycle_is_identified_with_the_first_as_prior(tmp_path, client, spawn, cm):
    p_true = true_parameters(cm.model.params, np.random.default_rng(31))
    first = _cycle_bag(tmp_path / 'cycle1.mcap', cm, p_true, 30, START_NS, 1)
    # Two hours later, the same robot: 12 poses, fewer than the 30 of a full campaign.
    second = _cycle_bag(tmp_path / 'cycle2.mcap', cm, p_true, 12, START_NS + 2 * HOUR_NS, 2)
    changes: list[dict] = []
    client.node.create_subscription(
        String, '/kpi_calib_node/change_test', lambda m: changes.append(json.loads(m.data)),
        QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                   durability=DurabilityPolicy.TRANSIENT_LOCAL))
    data_dir = tmp_path / 'data'
    # With the drift state (a daily swing): the second calibration carries it onward.
    node = spawn(data_dir, 'node.log', 'min_measurements:=30',
                 'drift_velocity:=[5.0, 5.0e-5]')
    finish(spawn.replay(first), client)
    client.spin_until(lambda: any(d['measurements'] == 30
                                  for d in client.received['calibration']),
                      90, 'the first cycle calibration')
    one = next(d for d in client.received['calibration'] if d['measurements'] == 30)
    assert one['valid'] and 'prior' not in one
    archived = data_dir / 'calibrations' / f"{one['identified_at_ns']}.yaml"
    assert archived.is_file()
    answer = client.call('reset')  # a new cycle: the log and results go to archive/
    assert answer.success, answer.message
    finish(spawn.replay(second), client)
    client.spin_until(lambda: client.count('accepted') == 12, 30, '12 accepted')
    answer = client.call('identify', timeout=120)
    assert answer.success, answer.message
    assert f'prior {archived}' in answer.message
    assert 'expected TCP error <=' in answer.message
    client.spin_until(lambda: any(d['measurements'] == 12
                                  for d in client.received['calibration']),
                      30, 'the second cycle calibration on ~/calibration')
    two = next(d for d in client.received['calibration'] if d['measurements'] == 12)
    assert two['valid'] and two['prior']['source'] == str(archived)
    # Both TCP figures by working pose: the parameter part and with the misfit.
    assert set(two['precision']['expected_tcp_error_m']) == set(two['precision']['tcp_std_m'])
    assert two['change_test']['consistent'] is True
    assert 'no drift_state in it: stationary' in two['prior']['description']
    state = two['drift_state']
    assert state['swing'] == {'temperature_k': 5.0, 'offset_rad': 5e-5, 'period_hours': 24.0}
    assert len(state['values']) == 2 * len(state['names']) > 0
    client.spin_until(lambda: changes, 10, '~/change_test')
    assert changes[-1]['consistent'] is True and changes[-1]['prior'] == str(archived)
    # The identified TCP agrees with the truth within 4 of its predicted std.
    truth = cm.model.predict(p_true, cm.q_work)[0]
    tcp = two['tcp'][0]
    assert np.linalg.norm(np.array(tcp['position']) - truth) < 4 * np.sqrt(tcp['trace_m2'])
    # Both cycles are kept; the first file is unchanged.
    files = sorted((data_dir / 'calibrations').glob('*.yaml'))
    assert [f.name for f in files] == sorted([archived.name,
                                             f"{two['identified_at_ns']}.yaml"])
    assert yaml.safe_load(archived.read_text())['measurements'] == 30
    kept = yaml.safe_load((data_dir / 'calibrations' / f"{two['identified_at_ns']}.yaml")
                          .read_text())
    assert kept['drift_state']['names'] == state['names']
    assert node.stop() == 0
