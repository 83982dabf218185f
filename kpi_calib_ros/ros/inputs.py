"""The node's measured inputs: the cell's ``inputs.sources`` topics, each reading logged with
the measurements and paired to them by time when a job takes the stored data.

Each source topic is subscribed with its stated type; every field the cell names becomes one
reading (covariate name, value, the message's header stamp) that goes to the
:class:`~kpi_calib_ros.ros.measurement_store.MeasurementStore` (durably logged on the cell's
``inputs.topic`` before it is kept; a reading that is not finite is counted and warned, never
kept). A job pairs them with the accepted measurements as a bag's are
(:func:`kpi_calib_ros.ros.stored_measurements.with_input_readings`): interpolated at each
point's stamp within ``inputs.max_gap``, a point without a reading refused with a warning.
"""
from __future__ import annotations

import importlib
from typing import Any

from rclpy.node import Node
from rclpy.qos import QoSProfile

from kpi_calib_ros.core.errors import ConfigError
from kpi_calib_ros.io.cell_inputs import InputSource, field_path
from kpi_calib_ros.io.ros_messages import input_samples_from_message, named_values_from_message
from kpi_calib_ros.ros.measurement_store import MeasurementStore

INPUT_DEPTH = 100  # an inclinometer at 10-100 Hz: a buffer of a second or more


def message_class(type_name: str) -> Any:
    """The Python class of ROS message type ``pkg/msg/Type`` (as ``ros2 topic`` finds it)."""
    package, middle, name = type_name.split('/')
    kind = getattr(importlib.import_module(f'{package}.{middle}'), name)
    if not hasattr(kind, '_TYPE_SUPPORT') and not hasattr(kind, 'get_fields_and_field_types'):
        raise ValueError(f'{type_name} is not a message class')
    return kind


def subscribe_inputs(node: Node, store: MeasurementStore, sources: tuple[InputSource, ...],
                     callback_group: Any = None, named_topic: str | None = None) -> list[Any]:
    """Subscribe ``node`` to every input source; returns the subscriptions.

    ``named_topic`` (the cell's ``inputs.topic``): named values (``sensor_msgs/JointState``,
    name = covariate, position = value), as ``identify`` reads them from a bag and a
    replayed bag publishes them (a row's payload from an import, a controller's reading).

    Raises
    ------
    ConfigError
        A source's type is not an installed message type.
    """
    out = []
    if named_topic is not None:
        from sensor_msgs.msg import JointState
        out.append(node.create_subscription(JointState, named_topic,
                                            _named_receiver(node, store, named_topic),
                                            QoSProfile(depth=INPUT_DEPTH),
                                            callback_group=callback_group))
    for i, source in enumerate(sources):
        key = f'inputs.sources[{i}]'
        try:
            kind = message_class(source.type)
        except (AttributeError, ModuleNotFoundError, ValueError) as exc:
            raise ConfigError(f'{key}.type', f'{source.type!r} is not an installed message '
                              f'type ({exc}); give pkg/msg/Type of the topic') from None
        fields = tuple((name, field_path(path, f'{key}.fields.{name}'))
                       for name, path in source.fields)
        out.append(node.create_subscription(kind, source.topic, _receiver(node, store, source,
                                                                           fields),
                                            QoSProfile(depth=INPUT_DEPTH),
                                            callback_group=callback_group))
    return out


def _kept(node: Node, store: MeasurementStore, topic: str, samples: list) -> None:
    """Store ``samples`` read on ``topic``; a failure or a refusal is logged."""
    try:
        refused = store.receive_inputs(samples)
    except (OSError, ValueError) as exc:
        node.get_logger().error(f'measured input on {topic} not stored: {exc}')
        return
    if refused:
        node.get_logger().warning(f'{topic}: {refused}', throttle_duration_sec=5.0)


def _named_receiver(node: Node, store: MeasurementStore, topic: str) -> Any:
    def on_message(message: Any) -> None:
        _kept(node, store, topic, named_values_from_message(message))
    return on_message


def _receiver(node: Node, store: MeasurementStore, source: InputSource, fields: tuple) -> Any:
    def on_message(message: Any) -> None:
        try:
            samples = input_samples_from_message(message, fields)
        except (ValueError, AttributeError) as exc:
            node.get_logger().error(f'{source.topic} ({source.type}): {exc}; fix the field '
                                    "paths of the cell's inputs.sources", throttle_duration_sec=5.0)
            return
        _kept(node, store, source.topic, samples)
    return on_message
