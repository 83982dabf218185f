"""Shared fixtures: a deliberately awkward URDF chain for generality tests, and the ROS
domain every ROS test runs on."""
from __future__ import annotations

from collections import Counter

import pytest

import kpi_calib_ros  # noqa: F401  (single-threaded BLAS before any test imports numpy)

ODD_ARM_URDF = """<?xml version="1.0"?>
<robot name="odd_arm">
  <link name="world"/>
  <link name="mount"/>
  <link name="base"/>
  <link name="l1"><inertial><mass value="3"/><origin xyz="0 0 0.1"/>
    <inertia ixx="0.1" iyy="0.1" izz="0.1" ixy="0" ixz="0" iyz="0"/></inertial></link>
  <link name="l2"><inertial><mass value="2"/><origin xyz="0.2 0 0"/>
    <inertia ixx="0.1" iyy="0.1" izz="0.1" ixy="0" ixz="0" iyz="0"/></inertial></link>
  <link name="l2_cover"/>
  <link name="l3"><inertial><mass value="1.5"/><origin xyz="0.1 0 0"/>
    <inertia ixx="0.1" iyy="0.1" izz="0.1" ixy="0" ixz="0" iyz="0"/></inertial></link>
  <link name="l4"><inertial><mass value="1"/><origin xyz="0 0 0.05"/>
    <inertia ixx="0.05" iyy="0.05" izz="0.05" ixy="0" ixz="0" iyz="0"/></inertial></link>
  <link name="l5"><inertial><mass value="0.5"/><origin xyz="0 0 0.02"/>
    <inertia ixx="0.01" iyy="0.01" izz="0.01" ixy="0" ixz="0" iyz="0"/></inertial></link>
  <link name="flange"/>
  <link name="finger"><inertial><mass value="0.1"/>
    <inertia ixx="0.001" iyy="0.001" izz="0.001" ixy="0" ixz="0" iyz="0"/></inertial></link>
  <joint name="world_to_mount" type="fixed"><parent link="world"/><child link="mount"/>
    <origin xyz="0.3 -0.2 0.1" rpy="0 0 0.4"/></joint>
  <joint name="mount_to_base" type="fixed"><parent link="mount"/><child link="base"/>
    <origin xyz="0 0 0.05" rpy="0.01 -0.02 0.3"/></joint>
  <joint name="swing" type="revolute"><parent link="base"/><child link="l1"/>
    <origin xyz="0 0 0.3" rpy="0 0 0"/><axis xyz="0 0 1"/>
    <limit lower="-2.5" upper="2.5" effort="100" velocity="1"/></joint>
  <joint name="lift" type="revolute"><parent link="l1"/><child link="l2"/>
    <origin xyz="0.05 0 0.2" rpy="0.1 0 0"/><axis xyz="0 0.6 0.8"/>
    <limit lower="-1.5" upper="1.5" effort="100" velocity="1"/></joint>
  <joint name="cover" type="fixed"><parent link="l2"/><child link="l2_cover"/>
    <origin xyz="0.4 0 0" rpy="0 0.2 0"/></joint>
  <joint name="telescope" type="prismatic"><parent link="l2_cover"/><child link="l3"/>
    <origin xyz="0.02 0 0" rpy="0 0 0"/><axis xyz="1 0 0"/>
    <limit lower="0.0" upper="0.3" effort="100" velocity="1"/></joint>
  <joint name="wrist" type="continuous"><parent link="l3"/><child link="l4"/>
    <origin xyz="0.3 0 0" rpy="0 1.5707963 0"/><axis xyz="0 0 -1"/></joint>
  <joint name="tilt" type="revolute"><parent link="l4"/><child link="l5"/>
    <origin xyz="0 0 0.1" rpy="0 0 0"/><axis xyz="0 1 0"/>
    <limit lower="-2" upper="2" effort="10" velocity="1"/></joint>
  <joint name="to_flange" type="fixed"><parent link="l5"/><child link="flange"/>
    <origin xyz="0 0.01 0.08" rpy="0.3 0 0"/></joint>
  <joint name="gripper" type="prismatic"><parent link="l5"/><child link="finger"/>
    <origin xyz="0 0 0.05"/><axis xyz="0 1 0"/>
    <limit lower="0" upper="0.04" effort="10" velocity="1"/></joint>
</robot>
"""


@pytest.hookimpl(trylast=True)
def pytest_collection_modifyitems(items):
    """The modules with the most tests marked slow first, each module's tests kept together
    and in order (its module fixtures are built once per worker): with pytest-xdist handing
    out two tests at a time (Makefile), the long ones start early on every worker and the
    short ones fill in at the end, so the workers finish together."""
    slow = Counter(item.module.__name__ for item in items if item.get_closest_marker('slow'))
    items.sort(key=lambda item: -slow[item.module.__name__])


@pytest.fixture(scope='session')
def cm():
    """The built-in simulated cell's model (KR15-class), built once for the whole run and
    shared: a frozen CellModel that no test changes (a variant is a new model)."""
    from kpi_calib_ros.app.cell_model import build_cell_model
    from kpi_calib_ros.io.cell import DEFAULT_CELL, load_cell
    return build_cell_model(load_cell(DEFAULT_CELL))


@pytest.fixture(scope='session')
def cell(cm):
    """The same shared model under the name the ROS and joint-noise tests use."""
    return cm


@pytest.fixture
def odd_arm_urdf() -> str:
    return ODD_ARM_URDF


@pytest.fixture(scope='session')
def ros_domain():
    """A ROS domain id held by this test run alone (see ros_helpers.exclusive_ros_domain)
    for the whole session, discovery on localhost, in this process and its children."""
    from ros_helpers import exclusive_ros_domain, ros_environment  # rclpy only when needed
    with exclusive_ros_domain() as domain, ros_environment(domain):
        yield domain


@pytest.fixture
def client(ros_domain):
    """A test-side ROS participant on the run's domain; the robot description published
    latched, as robot_state_publisher does."""
    from std_msgs.msg import String

    from ros_helpers import KR15_URDF, Client
    c = Client(ros_domain)
    c.description.publish(String(data=KR15_URDF))
    try:
        yield c
    finally:
        c.close()


@pytest.fixture
def spawn(tmp_path):
    """Start node and replay processes; whatever a test leaves running is killed."""
    from ros_helpers import Spawner
    spawner = Spawner(tmp_path)
    yield spawner
    spawner.kill_all()
