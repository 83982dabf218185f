"""kpi_calib_node stops with exit code 0 on SIGINT or SIGTERM, whatever it is taking.

A signal that arrives while rclpy takes a message must not end the node with a
traceback (ros/stop_request.py): with Python's KeyboardInterrupt it did, as
``RuntimeError: Unable to convert call argument '0' to Python object``. Large queries
flood ``~/tcp_query`` from the test client so that the node spends most of its time
taking them and most signals arrive during a take; each stop is a new node process.
"""
from __future__ import annotations

import signal
import time

import pytest
from rclpy.serialization import serialize_message
from sensor_msgs.msg import JointState

from ros_helpers import NS

STOPS = (signal.SIGINT,) * 4 + (signal.SIGTERM,)
# 0.42 MB per query (under Fast DDS's 0.5 MB shared-memory segment, so they arrive fast);
# rclpy takes milliseconds to build one.
QUERY_JOINTS = 35_000
FLOOD_S = 0.3  # queries before the signal, once the node is seen dropping them


@pytest.mark.slow
def test_a_stop_signal_during_a_flood_of_queries_ends_the_node_cleanly(client, spawn,
                                                                       tmp_path):
    # Serialized once: the client publishes faster than the node can take.
    query = serialize_message(JointState(name=[f'j{i}' for i in range(QUERY_JOINTS)]))
    publisher = client.node.create_publisher(JointState, f'{NS}/tcp_query', 10)
    for i, sig in enumerate(STOPS):
        # No robot description on this topic: every query is taken, then dropped.
        node = spawn(tmp_path / 'data', f'node_{i}.log',
                     'robot_description_topic:=/kpi_calib_test/no_description')
        client.spin_until(publisher.get_subscription_count, 30, 'the node on ~/tcp_query')
        deadline = time.monotonic() + 30
        while 'TCP query dropped: no robot model yet' not in node.output():
            assert time.monotonic() < deadline, f'no query taken:\n{node.output()}'
            for _ in range(20):
                publisher.publish(query)
        flood_end = time.monotonic() + FLOOD_S
        while time.monotonic() < flood_end:
            publisher.publish(query)
        node.process.send_signal(sig)
        deadline = time.monotonic() + 20
        while node.process.poll() is None and time.monotonic() < deadline:
            publisher.publish(query)  # still flooding while it stops
        code = node.stop()
        output = node.output()
        assert code == 0 and 'Traceback' not in output, (
            f'stop {i} ({signal.Signals(sig).name}): exit code {code}\n{output}')
