"""``kpi-calib replay`` stopped by Ctrl-C ends with exit code 130, whatever it is taking.

The replay reads the node's counts on /diagnostics while it plays. A SIGINT that arrives
while rclpy takes a message there raised KeyboardInterrupt inside the message constructor
rclpy calls, which pybind11 turned into ``RuntimeError: Unable to convert call argument
'0' to Python object``: a traceback and exit code 1 instead of 130. Large diagnostics
from the test client flood /diagnostics so that most signals arrive during a take.
"""
from __future__ import annotations

import signal
import subprocess
import time

import pytest
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from geometry_msgs.msg import PointStamped, PoseStamped
from rclpy.serialization import serialize_message
from sensor_msgs.msg import JointState

from kpi_calib_ros.app.simulate import simulate_campaign
from kpi_calib_ros.io.cell import DEFAULT_CELL
from kpi_calib_ros.io.names import DEFAULT_JOINT_TOPIC, DEFAULT_POINT_TOPIC, DEFAULT_POSE_TOPIC

STOPS = 4
# ~0.4 MB per array (under Fast DDS's shared-memory segment): milliseconds to build one.
VALUES = 12_000


@pytest.mark.slow
def test_ctrl_c_during_a_flood_of_diagnostics_ends_the_replay_with_130(client, spawn,
                                                                      tmp_path):
    bag = tmp_path / 'run.mcap'
    simulate_campaign(DEFAULT_CELL, 20, bag, seed=5)
    # Subscribers on the replayed topics, so the replay starts at once and then spins
    # /diagnostics for the node's counts (none come: no node).
    for msg_type, topic in ((JointState, DEFAULT_JOINT_TOPIC),
                            (PointStamped, DEFAULT_POINT_TOPIC),
                            (PoseStamped, DEFAULT_POSE_TOPIC)):
        client.node.create_subscription(msg_type, topic, lambda _: None, 10)
    status = DiagnosticStatus(name='someone_else', values=[
        KeyValue(key=f'k{i}', value='v') for i in range(VALUES)])
    flood = serialize_message(DiagnosticArray(status=[status]))
    publisher = client.node.create_publisher(DiagnosticArray, '/diagnostics', 10)
    others = publisher.get_subscription_count()  # the test client's own
    for i in range(STOPS):
        client.spin_until(lambda: publisher.get_subscription_count() == others, 30,
                          'the last replay gone from /diagnostics')
        replay = spawn.replay(bag, 0.05)  # slow: it is still playing when stopped
        client.spin_until(lambda: publisher.get_subscription_count() > others, 30,
                          'the replay on /diagnostics')
        flood_end = time.monotonic() + 1.0
        while time.monotonic() < flood_end:
            publisher.publish(flood)
        replay.send_signal(signal.SIGINT)
        deadline = time.monotonic() + 20
        while replay.poll() is None and time.monotonic() < deadline:
            publisher.publish(flood)  # still flooding while it stops
        try:
            output, _ = replay.communicate(timeout=10)
        except subprocess.TimeoutExpired:
            replay.kill()
            output, _ = replay.communicate()
        assert replay.returncode == 130 and 'Traceback' not in output, (
            f'stop {i}: exit code {replay.returncode}\n{output}')
