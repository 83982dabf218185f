"""Identification: from recorded or live samples to a calibration, the one path every
front end uses.

The CLI (`kpi-calib identify`), the ROS node and the demo all call these
functions, so a bag replayed into the node and the same bag identified offline
give the same numbers.
"""
from __future__ import annotations

import dataclasses
import sys
from pathlib import Path
from typing import Any, Iterable

import numpy as np

from kpi_calib_ros.core.dh import dh_table
from kpi_calib_ros.core.diagnosis import augmented_model, compare_models
from kpi_calib_ros.core.effects import parse_effect_spec, split_specs
from kpi_calib_ros.core.errors import DataError
from kpi_calib_ros.core.estimation import CalibrationResult, identify
from kpi_calib_ros.core.measurement import MeasurementModel, Measurements
from kpi_calib_ros.core.pairing import PairingResult, pair_measurements
from kpi_calib_ros.core.streams import JointSample, PointSample
from kpi_calib_ros.io.bag import read_for_pairing
from kpi_calib_ros.io.cell import CellModel, build_cell_model, load_cell
from kpi_calib_ros.io.measurement_log import stored_pairing
from kpi_calib_ros.io.names import DEFAULT_JOINT_TOPIC, DEFAULT_POINT_TOPIC
from kpi_calib_ros.io.report import comparison_text, comparison_to_dict
from kpi_calib_ros.io.results import (calibration_to_dict, summary_text, writable_folder,
                                      write_calibration)


def measurements_from_samples(cm: CellModel, joint_samples: Iterable[JointSample],
                              point_samples: Iterable[PointSample],
                              **pairer_options) -> tuple[Measurements, PairingResult]:
    """Pair tracker points with still joint states, matching joints by name.

    Raises
    ------
    DataError
        When no point could be paired because the joint states lack the
        chain's joints (wrong robot or renamed joints): names both sets.
    """
    joint_samples = list(joint_samples)
    pairing = pair_measurements(joint_samples, point_samples, cm.joint_names,
                                cm.cell.tracker_frame, **pairer_options)
    if len(pairing) == 0 and pairing.rejections.get('missing_joints'):
        seen = sorted({n for s in joint_samples for n in s.names})
        raise DataError(f'the joint states name joints {seen}, but the robot chain needs '
                        f'{cm.joint_names}; record the right robot or fix the URDF joint names')
    return Measurements(q=pairing.q, eta=pairing.eta, stamps_ns=pairing.stamps_ns), pairing


def measurements_from_bag(cm: CellModel, path: str | Path,
                          joint_topic: str = DEFAULT_JOINT_TOPIC,
                          point_topic: str = DEFAULT_POINT_TOPIC,
                          **pairer_options) -> tuple[Measurements, PairingResult]:
    """Measurements from a recording (paired here) or from the node's measurement log
    (paired when stored), reading only the joint states pairing needs."""
    contents = read_for_pairing(path, joint_topic, point_topic,
                                window_ns=pairer_options.get('window_ns'))
    if contents.measurement_log:
        pairing = stored_pairing(zip(contents.joints, contents.points), list(cm.joint_names),
                                 cm.cell.tracker_frame)
        return Measurements(q=pairing.q, eta=pairing.eta, stamps_ns=pairing.stamps_ns), pairing
    return measurements_from_samples(cm, contents.joints, contents.points, **pairer_options)


def identify_cell(cm: CellModel, data: Measurements, p0: np.ndarray | None = None,
                  free: list[str] | None = None) -> CalibrationResult:
    """Identify the cell's parameters from paired measurements (σ and poses from the cell)."""
    if len(data) == 0:
        raise DataError('no accepted measurement to identify from')
    return identify(cm.model, data, cm.cell.sigma, cm.q_work, list(cm.working_pose_names),
                    p0=p0, free=free, identifiability_method=cm.cell.identification_method,
                    priority=list(cm.cell.identification_priority) or None)


def calibration_document(cm: CellModel, result: CalibrationResult,
                         pairing: PairingResult | None = None) -> dict:
    """The calibration.yaml document: the result plus the DH/Hayati view of its axes."""
    doc = calibration_to_dict(result, pairing)
    doc['dh_hayati'] = dh_table(cm.robot, cm.geometric, cm.geometric.nominal,
                                result.values[:len(cm.geometric)])
    return doc


def geometric_only(cm: CellModel) -> CellModel:
    """``cm`` with the geometric model only (no effects)."""
    return dataclasses.replace(cm, model=MeasurementModel(cm.robot, cm.geometric, (),
                                                          cm.cell.reflector_axis))


def with_effects(cm: CellModel, effects: tuple) -> CellModel:
    """``cm`` with ``effects`` (specs or bound effects) appended to its model."""
    bound = tuple(parse_effect_spec(e, cm.robot) if isinstance(e, str) else e for e in effects)
    return dataclasses.replace(cm, model=augmented_model(cm.model, bound))


def add_effect_comparison(doc: dict[str, Any], cm: CellModel, data: Measurements,
                          result: CalibrationResult, folds: int = 5) -> str:
    """Compare ``result`` (model with effects) with the geometric model on the same data.

    Adds ``effects_comparison`` to the calibration document ``doc`` and returns
    the readable summary.
    """
    base = geometric_only(cm)
    before = identify_cell(base, data)
    cmp = compare_models((base.model, before), (cm.model, result), data, folds=folds)
    doc['effects_comparison'] = comparison_to_dict(cmp)
    return comparison_text(cmp)


def load_measurements(cell_path: str | Path, bag_path: str | Path, effects: str = '',
                      joint_topic: str | None = None, point_topic: str | None = None,
                      allow_code_effects: bool = False
                      ) -> tuple[CellModel, Measurements, PairingResult]:
    """Cell model (with the extra ``effects`` specs, comma-separated) and the paired
    measurements of a bag; rejections are reported on stderr.

    ``joint_topic`` / ``point_topic`` (``--joint-topic`` / ``--point-topic``) override
    the cell's ``topics:``; ``allow_code_effects`` lets effects name Python code.
    """
    cell = load_cell(cell_path, allow_code_effects=allow_code_effects)
    cm = build_cell_model(cell, effects=tuple(split_specs(effects)))
    data, pairing = measurements_from_bag(cm, bag_path, joint_topic or cell.joint_topic,
                                          point_topic or cell.point_topic)
    for reason, count in sorted(pairing.rejections.items()):
        print(f'rejected {count} sample(s): {reason}', file=sys.stderr)
    return cm, data, pairing


def run_identify(cell_path: str | Path, bag_path: str | Path, out_dir: str | Path,
                 effects: str = '', **options: Any) -> int:
    """``kpi-calib identify``: calibration.yaml in ``out_dir`` and a summary on stdout;
    ``options`` as for :func:`load_measurements`. ``out_dir`` is checked first.

    Returns 0 when the identification converged, else 1.
    """
    writable_folder(out_dir, '--out')
    cm, data, pairing = load_measurements(cell_path, bag_path, effects, **options)
    result = identify_cell(cm, data)
    doc = calibration_document(cm, result, pairing)
    comparison = add_effect_comparison(doc, cm, data, result) if cm.model.effects else ''
    path = write_calibration(out_dir, doc)
    print(summary_text(doc))
    if comparison:
        print(comparison)
    print(f'written: {path}')
    return 0 if result.converged else 1
