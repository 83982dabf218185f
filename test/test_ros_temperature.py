"""The node's temperature input (in process, private context, real rclpy): readings
published as sensor_msgs/Temperature on the cell's topic are logged durably, reloaded by a
new campaign in the same folder, and paired to the accepted measurements exactly as a bag's
are (linear in time), with a point beyond the readings refused."""
from __future__ import annotations

import time

import numpy as np
import pytest
import rclpy
import yaml
from rclpy.context import Context
from rclpy.executors import SingleThreadedExecutor
from rclpy.parameter import Parameter
from rclpy.qos import QoSProfile
from sensor_msgs.msg import Temperature
from std_msgs.msg import Header

from kpi_calib_ros.core.measurement.covariates import DELTA_TEMPERATURE
from kpi_calib_ros.core.measurement.data import Measurements
from kpi_calib_ros.io.cell import DEFAULT_CELL
from kpi_calib_ros.io.measurement_log import MeasurementLog
from kpi_calib_ros.io.ros_messages import time_msg
from kpi_calib_ros.ros.measurement_store import MeasurementStore
from kpi_calib_ros.ros.node import CalibrationNode
from kpi_calib_ros.ros.stored_measurements import with_temperature_readings

from ros_helpers import KR15_URDF

FIRST_NS = 1_700_000_000_000_000_000
S = 10**9
TOPIC = '/arm/temperature'


def _cell(tmp_path):
    doc = yaml.safe_load(DEFAULT_CELL.read_text())
    doc['temperature'] = {'topic': TOPIC, 'sensors': ['upper_arm'], 'reference': 21.0,
                          'max_gap': 30.0}
    path = tmp_path / 'cell.yaml'
    path.write_text(yaml.safe_dump(doc))
    return path


def test_published_temperatures_are_logged_and_paired_to_the_points(tmp_path, ros_domain):
    context = Context()
    rclpy.init(context=context, domain_id=ros_domain)
    executor = SingleThreadedExecutor(context=context)
    node = source = None
    try:
        node = CalibrationNode(context=context, parameter_overrides=[
            Parameter('robot_description', value=KR15_URDF),
            Parameter('cell_file', value=str(_cell(tmp_path))),
            Parameter('data_dir', value=str(tmp_path / 'data'))])
        source = rclpy.create_node('thermometer', context=context)
        publisher = source.create_publisher(Temperature, TOPIC, QoSProfile(depth=100))
        executor.add_node(node)
        executor.add_node(source)
        deadline = time.monotonic() + 20
        while publisher.get_subscription_count() < 1 and time.monotonic() < deadline:
            executor.spin_once(timeout_sec=0.05)
        assert publisher.get_subscription_count() == 1
        readings = [(FIRST_NS + k * 10 * S, 22.0 + 0.05 * k * 10) for k in range(13)]  # 2 min
        for stamp, celsius in readings:
            publisher.publish(Temperature(header=Header(stamp=time_msg(stamp),
                                                        frame_id='upper_arm'),
                                          temperature=celsius, variance=0.0))
        # a sensor fault: counted in /diagnostics, never kept nor logged
        publisher.publish(Temperature(header=Header(stamp=time_msg(FIRST_NS + 5 * S),
                                                    frame_id='upper_arm'),
                                      temperature=1e300, variance=0.0))
        while node.store.counts()['received.temperatures'] < len(readings) + 1 \
                and time.monotonic() < deadline:
            executor.spin_once(timeout_sec=0.05)
        got = node.store.temperatures()
        assert [(s.stamp_ns, s.celsius) for s in got] == readings
        assert node.status()[2]['rejected_temperatures'] == 1
        # durably logged: a new campaign in the same folder reloads them
        assert [(s.stamp_ns, s.celsius) for s in MeasurementLog.load_temperatures(
            tmp_path / 'data', TOPIC)] == readings
        again = MeasurementStore(tmp_path / 'data', temperature_topic=TOPIC)
        assert len(again.temperatures()) == len(readings)
        again.close()
        # paired to the measurements by time: exact for a linear rise; the last point is
        # 60 s after the last reading (max_gap 30 s): refused
        offsets_s = np.array([3.0, 47.5, 119.0, 180.0])
        stamps = FIRST_NS + (offsets_s * S).astype(np.int64)
        data = Measurements(q=np.zeros((4, 6)), eta=np.zeros((4, 3)), stamps_ns=stamps)
        with pytest.warns(UserWarning, match='1 of 4 measurement rows refused'):
            paired = with_temperature_readings(node.store, node._cm, data)
        assert len(paired) == 3
        np.testing.assert_allclose(paired.covariates['temperature.upper_arm'],
                                   22.0 + 0.05 * offsets_s[:3], atol=1e-12)
        np.testing.assert_allclose(paired.covariates[DELTA_TEMPERATURE],
                                   1.0 + 0.05 * offsets_s[:3], atol=1e-12)
    finally:
        executor.shutdown()
        for made in (node, source):
            if made is not None:
                made.destroy_node()
        rclpy.shutdown(context=context)


def test_a_cell_without_temperature_reads_none(tmp_path):
    campaign = MeasurementStore(tmp_path)
    try:
        assert campaign.temperature_topic is None and campaign.temperatures() == []
        with pytest.raises(ValueError, match='no temperature'):
            campaign.log.append_temperature(None)  # type: ignore[arg-type]
    finally:
        campaign.close()


def test_an_implausible_reading_is_counted_not_logged_and_one_in_an_old_log_is_set_aside(
        tmp_path):
    from kpi_calib_ros.app.cell_model import build_cell_model
    from kpi_calib_ros.core.measurement.covariates import TemperatureSample
    from kpi_calib_ros.io.cell import load_cell
    cm = build_cell_model(load_cell(_cell(tmp_path), urdf_xml=KR15_URDF))
    good = [TemperatureSample(FIRST_NS + k * 10 * S, 'upper_arm', 22.0 + 0.5 * k)
            for k in range(7)]
    campaign = MeasurementStore(tmp_path / 'data', temperature_topic=TOPIC,
                        temperature_range_c=cm.cell.temperature.valid_range_c)
    try:
        for sample in good[:3]:
            assert campaign.receive_temperature(sample) == ''
        refused = campaign.receive_temperature(TemperatureSample(FIRST_NS + 25 * S,
                                                                 'upper_arm', -500.0))
        assert refused == (f"{TOPIC}: reading -500 °C of sensor 'upper_arm' (stamp "
                           f'{FIRST_NS + 25 * S} ns) outside temperature.valid_range '
                           '[-50, 150] °C: not used (1 so far); check the sensor')
        assert campaign.counts()['rejected_temperatures'] == 1
        assert [s.celsius for s in campaign.temperatures()] == [22.0, 22.5, 23.0]
        # an older log that stored a fault (written before readings were checked)
        campaign.log.append_temperature(TemperatureSample(FIRST_NS + 35 * S, 'upper_arm',
                                                          1e300))
        for sample in good[3:]:
            campaign.receive_temperature(sample)
    finally:
        campaign.close()
    assert len(MeasurementLog.load_temperatures(tmp_path / 'data', TOPIC)) == 8
    again = MeasurementStore(tmp_path / 'data', temperature_topic=TOPIC,
                     temperature_range_c=cm.cell.temperature.valid_range_c)
    try:
        stamps = FIRST_NS + np.array([5, 33, 38, 55]) * S
        data = Measurements(q=np.zeros((4, 6)), eta=np.zeros((4, 3)), stamps_ns=stamps)
        with pytest.warns(UserWarning, match=r'1 temperature reading\(s\) outside '):
            paired = with_temperature_readings(again, cm, data)
        np.testing.assert_allclose(paired.covariates['temperature.upper_arm'],
                                   22.0 + 0.05 * np.array([5, 33, 38, 55]), atol=1e-12)
    finally:
        again.close()
