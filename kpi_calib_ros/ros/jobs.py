"""What the node's jobs do in a worker thread: compute, write the result files, make the
messages' text. Plain inputs in, values out; nothing here sees the node, so these run
beside the executor without sharing its state (see :mod:`kpi_calib_ros.ros.node`).

Messages and their text are made here too: a YAML dump of a calibration takes ~0.1 s,
long enough to hold up pairing if the executor did it.
"""
from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
import yaml
from geometry_msgs.msg import PoseWithCovarianceStamped

from kpi_calib_ros.app.design import design_cell_model
from kpi_calib_ros.core.design import DesignResult
from kpi_calib_ros.core.estimation import CalibrationResult
from kpi_calib_ros.core.measurement import Measurements
from kpi_calib_ros.core.pairing import PairingResult
from kpi_calib_ros.io.cell import CellModel
from kpi_calib_ros.io.design_io import write_design
from kpi_calib_ros.app.diagnose import diagnose_cell
from kpi_calib_ros.app.validate import validate_report
from kpi_calib_ros.io.report import diagnosis_to_dict, write_report
from kpi_calib_ros.io.results import write_atomic, write_calibration
from kpi_calib_ros.io.urdf_export import calibrated_urdf
from kpi_calib_ros.app.identify import calibration_document, identify_cell
from kpi_calib_ros.io.names import (CALIBRATED_URDF_FILE, DESIGN_FILE, DIAGNOSIS_DIR,
                                    VALIDATION_DIR)
from kpi_calib_ros.ros import conversions as cv
from kpi_calib_ros.ros.parameters import NodeSettings



def design_work(cm: CellModel, settings: NodeSettings,
                data_dir: Path) -> tuple[DesignResult, np.ndarray, Path]:
    """Design ``settings.num_measurements`` poses and write ``design.yaml``.

    Returns
    -------
    design : DesignResult
    points : ndarray, shape (N, 3)
        Nominal reflector positions (m, tracker frame) of the designed poses.
    path : Path
        The written design file.
    """
    design = design_cell_model(cm, settings.num_measurements, settings.criterion,
                               settings.design_seed)
    path = write_design(data_dir / DESIGN_FILE, design)
    points = cm.model.predict(cm.model.params.nominal, design.configurations)
    return design, points, path


def identify_work(cm: CellModel, data: Measurements, pairing: PairingResult, data_dir: Path
                  ) -> tuple[CalibrationResult, str, str, list[PoseWithCovarianceStamped]]:
    """Identify from ``data`` as ``kpi-calib identify`` does and write the calibration and
    the calibrated URDF atomically.

    Returns
    -------
    result : CalibrationResult
    calibration : str
        ``calibration.yaml`` exactly as written.
    urdf : str
        The calibrated robot description, as written.
    tcp : list of PoseWithCovarianceStamped
        One per working pose, stamped with the last measurement.
    """
    result = identify_cell(cm, data)
    doc = calibration_document(cm, result, pairing)
    urdf = calibrated_urdf(cm.cell.urdf_xml, cm.robot, dict(zip(result.names, result.values)))
    calibration = write_calibration(data_dir, doc).read_text()  # published as written
    write_atomic(data_dir / CALIBRATED_URDF_FILE, urdf)
    tcp = cv.tcp_pose_msgs(result.tcp, result.tcp_covariance, cm.cell.tracker_frame,
                           int(data.stamps_ns[-1]))
    return result, calibration, urdf, tcp


def validate_work(cm: CellModel, calibration: str, data: Measurements,
                  data_dir: Path) -> tuple[dict[str, Any], str]:
    """Validate the calibration (the YAML text the node published) on new measurements,
    as ``kpi-calib validate`` does; writes ``data_dir/validation/``.

    Returns
    -------
    doc : dict
        ``validation.json``'s document; ``text`` : str, it as JSON.
    """
    doc = validate_report(cm, yaml.safe_load(calibration), data, data_dir / VALIDATION_DIR)
    return doc, json.dumps(doc)


def diagnose_work(cm: CellModel, data: Measurements,
                  data_dir: Path) -> tuple[dict[str, Any], str, str, Path]:
    """Diagnose the model on ``data`` as ``kpi-calib diagnose`` does; write the report.

    Returns
    -------
    doc : dict
        ``diagnosis.json``'s document; ``text`` : str, it as JSON; ``verdict`` : str;
        ``report`` : Path, the written ``report.md``.
    """
    cd = diagnose_cell(cm, data)
    report = write_report(data_dir / DIAGNOSIS_DIR, cd)
    doc = diagnosis_to_dict(cd)
    return doc, json.dumps(doc), cd.diagnosis.verdict, report


__all__ = ['design_work', 'diagnose_work', 'identify_work', 'validate_work']
