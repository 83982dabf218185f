"""The node's measured inputs, end to end (kpi_calib_node in its own process, real rclpy and
Fast DDS): an inclinometer published as geometry_msgs/Vector3Stamped on a topic of the cell's
``inputs.sources`` is logged with the measurements and paired to them by time; the node's
~/identify recovers the gains of the column's measured tilt within 3σ, and the same readings
come back from its measurement log. A reading that is not finite is counted, never used as a
value: logged as a reading without one, it voids the measurement it falls among."""
from __future__ import annotations

import numpy as np
import pytest
import yaml
from geometry_msgs.msg import Vector3, Vector3Stamped
from rclpy.qos import QoSProfile
from std_msgs.msg import Header, String

from kpi_calib_ros.app.cell_model import build_cell_model
from kpi_calib_ros.app.measurements import measurements_from_bag
from kpi_calib_ros.core.acquisition.streams import synthesize_streams
from kpi_calib_ros.core.simulation import random_configurations, true_parameters
from kpi_calib_ros.io.cell import DEFAULT_CELL, load_cell
from kpi_calib_ros.io.measurement_log import MeasurementLog
from kpi_calib_ros.io.ros_messages import time_msg

from ros_helpers import KR15_URDF, Client, Spawner

pytestmark = pytest.mark.slow
SPEC = 'measured_tilt:joint_2:column'
TOPIC = '/column_tilt'
N = 30


def _cell(tmp_path):
    doc = yaml.safe_load(DEFAULT_CELL.read_text())
    doc['robot']['urdf'] = str((DEFAULT_CELL.parent / doc['robot']['urdf']).resolve())
    doc['effects'] = [SPEC]
    doc.setdefault('identification', {})['model'] = 'geometric'
    doc['inputs'] = {'max_gap': 1.0, 'sources': [
        {'topic': TOPIC, 'type': 'geometry_msgs/msg/Vector3Stamped',
         'fields': {'tilt.column.x': 'vector.x', 'tilt.column.y': 'vector.y'}}]}
    path = tmp_path / 'cell.yaml'
    path.write_text(yaml.safe_dump(doc))
    return path


def test_the_node_logs_and_pairs_an_inclinometer_topic(tmp_path, ros_domain):
    cell = _cell(tmp_path)
    cm = build_cell_model(load_cell(cell))
    rng = np.random.default_rng(11)
    truth = cm.model  # the cell's model carries the tilt effect
    p_true = true_parameters(cm.model.params, rng)
    p_true[cm.model.params.indices(['measured_tilt.joint_2.column.gx',
                                    'measured_tilt.joint_2.column.gy'])] = 1.0
    q = random_configurations(cm.model, cm.model.params.nominal, N, rng)
    tilt = rng.uniform(-2e-3, 2e-3, (N, 2))
    eta = truth.predict(p_true, q, covariates={'tilt.column.x': tilt[:, 0],
                                               'tilt.column.y': tilt[:, 1]})
    eta = eta + rng.normal(0.0, 20e-6, eta.shape)
    # the point stamps publish_measurements will send (same stream parameters)
    _, points = synthesize_streams(q, cm.joint_names, eta, cm.cell.tracker_frame, rate_hz=20.0,
                                   move_time_s=0.2, hold_time_s=0.6)
    spawn = Spawner(tmp_path)
    client = Client(ros_domain)
    client.description.publish(String(data=KR15_URDF))
    try:
        node = spawn(tmp_path / 'data', 'node.log', f'cell_file:={cell}',
                     f'min_measurements:={10 * N}')
        inclinometer = client.node.create_publisher(Vector3Stamped, TOPIC,
                                                    QoSProfile(depth=1000))
        client.spin_until(lambda: inclinometer.get_subscription_count() > 0, 30,
                          f'the node on {TOPIC}')
        sent = 0
        for i, p in enumerate(points):
            for dt in (-100_000_000, 100_000_000):  # readings 0.1 s before and after
                inclinometer.publish(Vector3Stamped(
                    header=Header(stamp=time_msg(p.stamp_ns + dt), frame_id='column'),
                    vector=Vector3(x=float(tilt[i, 0]), y=float(tilt[i, 1]), z=0.0)))
                sent += 1
        inclinometer.publish(Vector3Stamped(header=Header(stamp=time_msg(points[0].stamp_ns),
                                                          frame_id='column'),
                                            vector=Vector3(x=float('nan'), y=float('inf'), z=0.0)))
        client.spin_until(lambda: client.count('received.inputs') >= sent + 1, 60,
                          f'{sent + 1} inclinometer readings')
        assert client.count('rejected_inputs') == 2
        client.publish_measurements(q, cm.joint_names, eta, cm.cell.tracker_frame, accepted=N)
        answer = client.call('identify', timeout=120.0)
        assert answer.success, answer.message
        # the published URDF holds the geometry only: the node says what it leaves out
        assert ('robot_description_calibrated: the calibrated URDF holds the geometry only: '
                f'the effects {SPEC} move the point by up to') in answer.message, answer.message
        client.spin_until(lambda: client.received['calibration'], 30, 'a calibration')
        doc = client.received['calibration'][-1]
        gains = {p['name']: p for p in doc['parameters']
                 if p['name'].startswith('measured_tilt')}
        assert len(gains) == 2
        for p in gains.values():
            assert abs(p['value'] - 1.0) < 3 * p['std'], p
        assert node.stop() == 0
    finally:
        spawn.kill_all()
        client.close()
    # logged durably beside the measurements, and paired offline from the log as in the node
    logged = MeasurementLog.load_inputs(tmp_path / 'data', cm.cell.inputs.topic)
    assert len(logged) == 2 * sent + 2
    assert sum(not np.isfinite(s.value) for s in logged) == 2
    log = sorted((tmp_path / 'data').glob('measurements_*.mcap'))[0]
    with pytest.warns(UserWarning) as caught:
        data, _ = measurements_from_bag(cm, log)
    text = ' '.join(str(w.message) for w in caught)
    assert '2 measured input reading(s) not finite' in text
    assert '1 of 30 measurement rows refused' in text, text
    # the measurement at the reading without a value is refused, not given its neighbours'
    order = [i for i in np.argsort([p.stamp_ns for p in points]) if i != 0]
    assert points[0].stamp_ns not in set(data.stamps_ns.tolist())
    np.testing.assert_allclose(data.covariates['tilt.column.x'], tilt[order, 0], rtol=1e-12)
