"""The stock UR5 (example-robot-data) on a two-stage lifting column of mimic joints, built
at test time from the installed description, and its tracker cell."""
from __future__ import annotations

from pathlib import Path

import yaml

from kpi_calib_ros.core.model.robot_library import with_lifting_column
from kpi_calib_ros.io.arm_cell import arm_cell_document
from kpi_calib_ros.io.resources import resolve_uri

UR5 = 'package://example-robot-data/robots/ur_description/urdf/ur5_robot.urdf'
ARM = ('shoulder_pan_joint', 'shoulder_lift_joint', 'elbow_joint', 'wrist_1_joint',
       'wrist_2_joint', 'wrist_3_joint')
STAGES = ('stage_1', 'stage_2')
SIGMA = 2e-5
REACH = {'lift': 0.3, 'shoulder_pan_joint': 0.0, 'shoulder_lift_joint': -1.2,
         'elbow_joint': 1.4, 'wrist_1_joint': -1.0, 'wrist_2_joint': -1.5, 'wrist_3_joint': 0.0}


def column_urdf() -> str:
    """The UR5 with its base_link on the column: each stage 0.5 · lift − 0.1 (m)."""
    return with_lifting_column(resolve_uri(UR5).read_text(), 'base_link')


def write_cell(directory: Path, **extra) -> Path:
    """The column UR5 2.5 m from a tracker, one working pose; ``extra`` top-level keys."""
    urdf = directory / 'column_ur5.urdf'
    urdf.write_text(column_urdf())
    doc = arm_cell_document(str(urdf), 'column_base', 'tool0', SIGMA)
    doc['working_poses'] = [{'name': 'reach', 'joints': dict(REACH)}]
    doc.update(extra)
    path = directory / f'cell_{len(extra)}.yaml'
    path.write_text(yaml.safe_dump(doc))
    return path
