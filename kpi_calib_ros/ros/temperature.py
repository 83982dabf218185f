"""The node's temperature input: the cell's ``sensor_msgs/Temperature`` topic, logged with
the measurements and paired to them by time when a job takes the campaign's data.

Readings go to the :class:`~kpi_calib_ros.ros.measurement_store.MeasurementStore` (durably
logged before they are kept); a job pairs them with the accepted measurements as a bag's are
paired (:func:`kpi_calib_ros.ros.stored_measurements.with_temperature_readings`): interpolated at
each point's stamp, a point outside the readings refused with a warning.
"""
from __future__ import annotations

from typing import Any

from rclpy.node import Node
from rclpy.qos import QoSProfile
from sensor_msgs.msg import Temperature

from kpi_calib_ros.io.ros_messages import temperature_sample_from_message
from kpi_calib_ros.ros.measurement_store import MeasurementStore

TEMPERATURE_DEPTH = 100  # readings come at ~1 Hz: a buffer of minutes


def subscribe_temperature(node: Node, store: MeasurementStore, callback_group: Any = None) -> Any:
    """Subscribe ``node`` to the store's temperature topic (None when it has none); each
    reading is logged and kept, a reading that cannot be stored is logged as an error, one
    outside the cell's ``temperature.valid_range`` as a warning (counted in /diagnostics as
    ``rejected_temperatures``, never stored)."""
    topic = store.temperature_topic
    if topic is None:
        return None

    def on_temperature(message: Temperature) -> None:
        try:
            refused = store.receive_temperature(temperature_sample_from_message(message))
        except (OSError, ValueError) as exc:
            node.get_logger().error(f'temperature reading not stored: {exc}')
            return
        if refused:
            node.get_logger().warning(refused, throttle_duration_sec=5.0)

    return node.create_subscription(Temperature, topic, on_temperature,
                                     QoSProfile(depth=TEMPERATURE_DEPTH),
                                     callback_group=callback_group)
