"""Finishing a calibration, the one way every front end does it: ``kpi-calib identify``,
``identify --prior``, the node's ``~/identify`` and its sequential campaign.

A valid calibration is a set of files -- calibration.yaml, the calibrated URDF,
learned_residual.yaml when one was chosen and, for the node, the archived copy
``calibrations/<identified_at_ns>.yaml`` -- written as one unit
(:func:`kpi_calib_ros.io.result_set.write_result_set`): after any failure the folder holds
the complete new set or the complete old one. A new set without a learned residual
removes the old learned_residual.yaml with it, so that file never corrects a calibration
it was not fitted to. An invalid calibration (not converged, TCP not estimable, a change
beyond the drift model) is written to calibration.failed.yaml alone; the last good set
stays as it was.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

from kpi_calib_ros.app.calibration_document import calibrated_robot_description
from kpi_calib_ros.app.cell_model import CellModel
from kpi_calib_ros.core.estimation.least_squares import CalibrationResult
from kpi_calib_ros.io.names import (
    CALIBRATED_URDF_FILE,
    CALIBRATION_FILE,
    CALIBRATIONS_DIR,
    FAILED_CALIBRATION_FILE,
    LEARNED_RESIDUAL_FILE,
)
from kpi_calib_ros.io.result_set import write_result_set
from kpi_calib_ros.io.yaml_bounded import dump_yaml


@dataclass(frozen=True)
class FinishedCalibration:
    """The files a finished calibration wrote.

    path : calibration.yaml, or calibration.failed.yaml when invalid; text : the document
    as written; urdf_path / urdf : the calibrated URDF and its text (None / '' when
    invalid); learned_path : learned_residual.yaml (None when none was chosen: an old one
    was removed); archived : ``calibrations/<identified_at_ns>.yaml`` (None when not
    archived); files : the set's members, relative to the folder, in the order they were
    moved into place (a member without a file was removed).
    """

    valid: bool
    path: Path
    text: str
    urdf_path: Path | None = None
    urdf: str = ''
    learned_path: Path | None = None
    archived: Path | None = None
    files: tuple[str, ...] = ()


def result_set(doc: dict[str, Any], text: str, urdf: str, learned: str | None,
               archive: bool) -> dict[str, str | None]:
    """The files of a calibration document ``doc`` (its YAML ``text``), relative to the
    results folder, in the order they are moved into place, calibration.yaml last; None:
    a member this calibration does not have (removed)."""
    if not doc.get('valid', True):
        return {FAILED_CALIBRATION_FILE: text}
    files: dict[str, str | None] = {}
    stamp = doc.get('identified_at_ns')
    if archive and stamp is not None:
        files[f'{CALIBRATIONS_DIR}/{int(stamp)}.yaml'] = text
    files[LEARNED_RESIDUAL_FILE] = learned
    files[CALIBRATED_URDF_FILE] = urdf
    files[CALIBRATION_FILE] = text
    return files


def finish_calibration(cm: CellModel, result: CalibrationResult, doc: dict[str, Any],
                       out_dir: str | Path, learned: str | None = None,
                       archive: bool = False, key: str = '--out') -> FinishedCalibration:
    """Write the calibration ``doc`` of ``result`` in ``out_dir`` as one set of files.

    Parameters
    ----------
    cm : CellModel
        The cell model of the calibration (the calibrated URDF is made from its URDF).
    result : CalibrationResult
        The identification ``doc`` describes.
    doc : dict
        calibration.yaml's document; ``valid`` false writes calibration.failed.yaml only.
    out_dir : path
        The results folder (``--out``, the node's ``data_dir``).
    learned : str or None
        learned_residual.yaml's text when one was chosen
        (:func:`kpi_calib_ros.app.learned_residual.learned_residual_section`); None
        removes an old one with the new set.
    archive : bool
        Also keep the valid document as ``calibrations/<identified_at_ns>.yaml`` (the
        node's archive of priors), in the same set.
    key : str
        The option or parameter that named ``out_dir``, for the error.

    Raises
    ------
    ConfigError
        A file could not be written (a full disk): names the folder; the previous set is
        intact.
    """
    out_dir = Path(out_dir)
    valid = bool(doc.get('valid', True))
    text = dump_yaml(doc)
    urdf = calibrated_robot_description(cm, result) if valid else ''
    files = result_set(doc, text, urdf, learned, archive)
    written = write_result_set(out_dir, files, key)
    if not valid:
        return FinishedCalibration(False, written[FAILED_CALIBRATION_FILE], text,
                                   files=tuple(files))
    archived = next((written[n] for n in files if n.startswith(f'{CALIBRATIONS_DIR}/')), None)
    return FinishedCalibration(True, written[CALIBRATION_FILE], text,
                               written[CALIBRATED_URDF_FILE], urdf,
                               written.get(LEARNED_RESIDUAL_FILE), archived, tuple(files))


__all__ = ['FinishedCalibration', 'finish_calibration', 'result_set']
