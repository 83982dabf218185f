"""Shared by the live-node benches: kpi_calib_node as a process on a ROS domain of its
own (localhost only), and a client that gives it the robot model and reads its
/diagnostics. Not a bench itself."""
from __future__ import annotations

import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import rclpy
from diagnostic_msgs.msg import DiagnosticArray
from rclpy.context import Context
from rclpy.executors import SingleThreadedExecutor
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from std_msgs.msg import String

from kpi_calib_ros.io.cell import DEFAULT_CELL
from kpi_calib_ros.ros.conversions import diagnostic_values

REPO = Path(__file__).resolve().parents[1]
BIN = Path(sys.executable).parent
PARAMS_FILE = REPO / 'config' / 'kpi_calib.params.yaml'
KR15_URDF = (DEFAULT_CELL.parent.parent / 'robots' / 'kr15_class.urdf').read_text()
LATCHED = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                     durability=DurabilityPolicy.TRANSIENT_LOCAL)


def private_domain() -> int:
    domain = 110 + os.getpid() % 100
    os.environ.update(ROS_DOMAIN_ID=str(domain), ROS_AUTOMATIC_DISCOVERY_RANGE='LOCALHOST')
    return domain


class LiveNode:
    """The node process, and a client with the robot model and the node's diagnostics."""

    def __init__(self, *overrides: str) -> None:
        self.domain = private_domain()
        self.folder = Path(tempfile.mkdtemp(prefix='kpi_bench_'))
        args = [str(BIN / 'kpi_calib_node'), '--ros-args', '--params-file', str(PARAMS_FILE),
                '-p', f'data_dir:={self.folder / "data"}']
        for override in overrides:
            args += ['-p', override]
        self.log = open(self.folder / 'node.log', 'w')
        self.process = subprocess.Popen(args, stdout=self.log, stderr=subprocess.STDOUT)
        self.context = Context()
        rclpy.init(context=self.context, domain_id=self.domain)
        self.node = rclpy.create_node('kpi_calib_bench_client', context=self.context)
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)
        self.values: dict[str, str] = {}
        self.node.create_subscription(DiagnosticArray, '/diagnostics', self._on_diagnostics, 50)
        self.description = self.node.create_publisher(String, '/robot_description', LATCHED)
        self.description.publish(String(data=KR15_URDF))
        self.spin_until(lambda: self.values.get('state') == 'idle', 60, 'the robot model')

    def _on_diagnostics(self, msg: DiagnosticArray) -> None:
        if msg.status and msg.status[0].name.startswith('kpi_calib_node'):
            self.values = diagnostic_values(msg)

    def count(self, key: str) -> int:
        return int(self.values.get(key, -1))

    def spin_until(self, condition, timeout: float, what: str) -> bool:
        deadline = time.monotonic() + timeout
        while not condition():
            if time.monotonic() > deadline:
                if what:
                    print(f'  (gave up after {timeout} s waiting for {what})')
                return False
            self.executor.spin_once(timeout_sec=0.05)
        return True

    def rss_kb(self) -> tuple[int, int]:
        """(VmRSS, VmHWM) of the node process in kB."""
        status = Path(f'/proc/{self.process.pid}/status').read_text().splitlines()
        fields = dict(line.split(':', 1) for line in status if ':' in line)
        return int(fields['VmRSS'].split()[0]), int(fields['VmHWM'].split()[0])

    def close(self) -> int:
        self.executor.shutdown()
        self.node.destroy_node()
        rclpy.shutdown(context=self.context)
        self.process.send_signal(2)
        try:
            return self.process.wait(timeout=30)
        finally:
            if self.process.poll() is None:
                self.process.kill()
                self.process.wait()
            self.log.close()
