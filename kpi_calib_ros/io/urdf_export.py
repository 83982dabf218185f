"""The calibrated robot as a URDF: identified joint errors folded into the joint origins.

The calibrated chain is, per chain joint i (see :mod:`kpi_calib_ros.core.model.kinematics`),

    M_i · Trans(t_i) · error_rotation(axis_i, rx_i, ry_i, rz_i) · Motion_i(q_i + o_i)

where ``M_i`` ends with the joint's own URDF ``<origin>``. Because a motion about
(along) a fixed axis composes as ``Motion(q + o) = Motion(o) · Motion(q)``, the URDF
origin ``O_i`` is replaced by ``O_i · Trans(t_i) · error_rotation(...) · Motion_i(o_i)``
and the joint keeps its axis, type and limits: the same joint readings then give the
calibrated link poses in any URDF consumer (robot_state_publisher, MoveIt, RViz).

Limits of the representation
----------------------------
* URDF has no joint zero offset: ``<joint>.offset`` is folded into the origin (a
  rotation about the axis, or a translation along it for prismatic joints). Joint
  limits stay in reading units and are not shifted.
* A mimic joint (``<mimic joint=... multiplier=... offset=...>``) keeps its tag: its
  ``<joint>.offset`` is added to the tag's ``offset`` (the relation's calibrated zero),
  not folded into the origin; the multiplier is the URDF's (not calibrated).
* The robot base pose in the tracker frame (``base.*``) is a property of the cell, not
  of the robot; publish it as a static transform tracker -> base from the calibration.
* The reflector offset (``reflector.*``) belongs to the tool, not to the URDF.
* Non-geometric effect parameters (compliance, gear errors) have no URDF form.
"""
from __future__ import annotations

import xml.etree.ElementTree as ET
from typing import Mapping

import casadi as ca
import numpy as np
import pinocchio as pin

from kpi_calib_ros.core.model.kinematics import axis_rotation, error_rotation, homogeneous, pose6
from kpi_calib_ros.core.model.parameters import PLACEMENT_COMPONENTS
from kpi_calib_ros.core.model.robot import RobotModel


def _numbers(text: str | None, default: tuple[float, float, float]) -> np.ndarray:
    if text is None:
        return np.array(default, dtype=float)
    values = np.array([float(v) for v in text.split()], dtype=float)
    if values.shape != (3,):
        raise ValueError(f'expected 3 numbers, got {text!r}')
    return values


def rpy_from_matrix(rotation: np.ndarray) -> np.ndarray:
    """URDF roll, pitch, yaw (rad) of a rotation matrix (3, 3), R = Rz(y) Ry(p) Rx(r).

    Pinocchio's ``rpy.matrixToRpy``: accurate to round-off in the reconstructed
    matrix even next to pitch = ±π/2 (checked in the tests).
    """
    return np.asarray(pin.rpy.matrixToRpy(np.asarray(rotation, dtype=float)), dtype=float)


def _joint_of(name: str) -> str | None:
    """The joint a ``<joint>.placement.<c>`` or ``<joint>.offset`` name refers to."""
    head, sep, component = name.rpartition('.placement.')
    if sep and component in PLACEMENT_COMPONENTS:
        return head
    head, sep, component = name.rpartition('.')
    return head if sep and component == 'offset' else None


def _format(values: np.ndarray) -> str:
    # repr gives the shortest string that parses back to the same double.
    return ' '.join(repr(float(v) + 0.0) for v in values)


def calibrated_urdf(urdf_xml: str, robot: RobotModel, parameters: Mapping[str, float]) -> str:
    """The URDF whose chain-joint origins reproduce the calibrated kinematics.

    Parameters
    ----------
    urdf_xml : str
        The original URDF document (the one ``robot`` was built from).
    robot : RobotModel
        The calibrated chain (base frame to tip frame) of ``urdf_xml``.
    parameters : mapping of str to float
        Identified values by stable name: ``<joint>.placement.{tx,ty,tz}`` (m),
        ``<joint>.placement.{rx,ry,rz}`` (rad), ``<joint>.offset`` (rad, or m for
        prismatic joints). Missing names count as zero error; ``base.*``,
        ``reflector.*`` and effect parameters are not part of a robot URDF and are
        ignored (see the module docstring).

    Returns
    -------
    str
        The URDF document with the chain joints' ``<origin xyz rpy>`` replaced;
        everything else (links, meshes, limits, other joints, comments) unchanged.

    Raises
    ------
    ValueError
        ``parameters`` names a joint that is not on the chain, a value is not
        finite, or ``urdf_xml`` lacks a chain joint.
    """
    root = ET.fromstring(urdf_xml, parser=ET.XMLParser(
        target=ET.TreeBuilder(insert_comments=True)))
    # Only the <robot>'s own <joint> children are joints: a <transmission> has <joint>
    # elements too (the actuated joint's name, no origin), and iter() would find them.
    elements = {e.get('name'): e for e in root.findall('joint')}
    chain = {j.name for j in robot.joints}
    for name, value in parameters.items():
        if not np.isfinite(value):
            raise ValueError(f'parameters[{name!r}] = {value!r} is not finite')
        joint_name = _joint_of(name)
        if joint_name in elements and joint_name not in chain:
            raise ValueError(f'parameters[{name!r}]: joint {joint_name!r} is not on the chain '
                             f'{robot.joint_names}')
    for joint in robot.joints:
        element = elements.get(joint.name)
        if element is None:
            raise ValueError(f'urdf_xml has no <joint name={joint.name!r}>')
        origin = element.find('origin')
        if origin is None:
            origin = ET.SubElement(element, 'origin')
        nominal = np.array(ca.DM(pose6(ca.DM(np.concatenate([
            _numbers(origin.get('xyz'), (0.0, 0.0, 0.0)),
            _numbers(origin.get('rpy'), (0.0, 0.0, 0.0))])))))
        e = [float(parameters.get(f'{joint.name}.placement.{c}', 0.0))
             for c in PLACEMENT_COMPONENTS]
        error = np.array(ca.DM(homogeneous(error_rotation(joint.axis, e[3], e[4], e[5]),
                                           ca.DM(e[:3]))))
        offset = float(parameters.get(f'{joint.name}.offset', 0.0))
        mimic = element.find('mimic')
        if joint.mimic is not None and mimic is not None:
            # A mimic joint's value is m · q_master + o: its calibrated zero is the
            # relation's offset, written there (the tag stays, the origin takes no motion).
            mimic.set('offset', repr(joint.mimic.offset + offset + 0.0))
            offset = 0.0
        if joint.kind == 'prismatic':
            motion = np.eye(4)
            motion[:3, 3] = joint.axis * offset
        else:
            motion = np.eye(4)
            motion[:3, :3] = np.array(ca.DM(axis_rotation(joint.axis, offset)))
        calibrated = nominal @ error @ motion
        origin.set('xyz', _format(calibrated[:3, 3]))
        origin.set('rpy', _format(rpy_from_matrix(calibrated[:3, :3])))
    text = ET.tostring(root, encoding='unicode')
    return '<?xml version="1.0"?>\n' + text + '\n'


__all__ = ['calibrated_urdf', 'rpy_from_matrix']
