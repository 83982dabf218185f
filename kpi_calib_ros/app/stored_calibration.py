"""A calibration.yaml read back for the cell it is to serve: the node's last valid
calibration after a restart.

:func:`read_stored_calibration` reads the document as ``kpi-calib validate`` does
(:func:`~kpi_calib_ros.app.validate.read_calibration`: bounded, every field checked) and
rebuilds its model with its effects (the cell's and those ``identification.model: auto``
added, :func:`~kpi_calib_ros.app.validate.calibrated_model`). It is used only when it
says it is valid and fits the current cell: the same effects, parameter names, joints
and working poses, and the robot description it was identified on (its DH/Hayati table,
nominal and calibrated, computed again on this robot). Anything else is a
:class:`~kpi_calib_ros.core.errors.DataError` naming the file and why.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from kpi_calib_ros.app.cell_model import CellModel
from kpi_calib_ros.app.validate import calibrated_model, read_calibration
from kpi_calib_ros.core.errors import DataError, KpiCalibError
from kpi_calib_ros.core.model.dh import dh_table
from kpi_calib_ros.io.urdf_export import calibrated_urdf

# DH/Hayati values (m, rad) of the robot computed again must equal the written ones to
# this: the same URDF and values give them to round-off; another robot differs by far more.
ROBOT_TOLERANCE = 1e-9
# The written TCP computed again from the written parameters at the cell's working poses
# (m): the same poses and payloads give it to round-off; a working pose whose joints or
# payload changed since the calibration moves it by far more.
TCP_TOLERANCE = 1e-7


@dataclass(frozen=True)
class StoredCalibration:
    """A valid calibration.yaml that fits the cell, ready to serve.

    Attributes
    ----------
    path : Path
        The file it was read from.
    text : str
        The document exactly as written (what ``~/calibration`` publishes).
    doc : dict
        The checked document.
    cell : CellModel
        The cell model with the calibration's effects.
    values : (n_p,) ndarray
        Every parameter of ``cell.model``, in vector order.
    estimated : tuple of str
        The identified parameters.
    covariance : (k, k) ndarray
        Their covariance (m, rad).
    tcp : (t, 3) ndarray
        KPI points at the working poses (m, tracker frame), as written.
    tcp_covariance : (t, 3, 3) ndarray
        Their covariance (m²).
    urdf : str
        The calibrated robot description of ``values`` on the current URDF.
    """

    path: Path
    text: str
    doc: dict[str, Any]
    cell: CellModel
    values: np.ndarray
    estimated: tuple[str, ...]
    covariance: np.ndarray
    tcp: np.ndarray
    tcp_covariance: np.ndarray
    urdf: str

    @property
    def identified_at_ns(self) -> int | None:
        """Stamp (ns) of the last measurement of the calibration; None if not written."""
        stamp = self.doc.get('identified_at_ns')
        return None if stamp is None else int(stamp)

    @property
    def measurements(self) -> int:
        return int(self.doc.get('measurements', 0))

    @property
    def rms_m(self) -> float | None:
        rms = self.doc.get('rms_m')
        return None if rms is None else float(rms)

    @property
    def p_value(self) -> float | None:
        p = (self.doc.get('model_adequacy') or {}).get('p_value')
        return None if p is None else float(p)

    def summary(self) -> str:
        """'restored from <path>, identified at <stamp> ns'."""
        stamp = self.identified_at_ns
        return (f'restored from {self.path}, identified at '
                + ('an unknown time' if stamp is None else f'{stamp} ns'))


def read_stored_calibration(cm: CellModel, path: str | Path) -> StoredCalibration:
    """The calibration.yaml at ``path`` for the cell model ``cm`` (the cell's own effects,
    the current robot description and working poses).

    Raises
    ------
    DataError
        The file is missing, damaged or edited, not a valid calibration, or one of
        another cell or robot; the message names the file and why.
    """
    path = Path(path)
    try:
        text = path.read_text()
        doc = read_calibration(path)
    except (OSError, UnicodeDecodeError, KpiCalibError) as exc:
        raise _refused(path, f'not readable: {exc}') from None
    if doc.get('valid') is not True:
        reasons = ' | '.join(str(r) for r in doc.get('invalid_reasons') or ()) or (
            'it does not say valid: true')
        raise _refused(path, f'not a valid calibration ({reasons})')
    joints = list((doc.get('training_configurations') or {}).get('joints') or ())
    if joints and sorted(joints) != sorted(cm.robot.joint_names):
        raise _refused(path, f'identified for the joints {joints}; this robot has '
                       f'{list(cm.robot.joint_names)}')
    try:
        cal_cm, values = calibrated_model(cm.cell, doc)
    except KpiCalibError as exc:  # an effect or parameter this cell's robot lacks
        raise _refused(path, f'its model does not fit this cell: {exc}') from None
    written = [str(e) for e in doc.get('effects') or ()]
    effects = [e.name for e in cal_cm.model.effects]
    if effects != written:
        raise _refused(path, f'its effects {written} are not this cell\'s ({effects} with '
                       'the calibration\'s): identified for another cell')
    names = [str(p['name']) for p in doc['parameters']]
    if names != list(cal_cm.model.params.names):
        extra = [n for n in names if n not in cal_cm.model.params.names]
        raise _refused(path, f'its parameters are not those of this cell\'s model '
                       f'(unknown here: {extra[:5]}): identified for another cell or robot')
    _check_robot(path, cal_cm, values, doc)
    tcp, tcp_covariance = _tcp(path, cal_cm, doc)
    _check_working_poses(path, cal_cm, values, tcp)
    cov = doc['parameter_covariance']
    estimated = tuple(str(n) for n in cov['names'])
    return StoredCalibration(
        path, text, doc, cal_cm, values, estimated,
        np.array(cov['matrix'], dtype=float).reshape(len(estimated), len(estimated)),
        tcp, tcp_covariance,
        calibrated_urdf(cal_cm.cell.urdf_xml, cal_cm.robot, dict(zip(names, values))))


def _refused(path: Path, why: str) -> DataError:
    return DataError(f"{path} not used: {why}")


def _check_robot(path: Path, cm: CellModel, values: np.ndarray, doc: dict[str, Any]) -> None:
    """The DH/Hayati table written with the calibration equals the one of this robot
    description: the same nominal geometry and the same calibrated one."""
    written = doc.get('dh_hayati')
    if written is None:
        raise _refused(path, 'no dh_hayati table to check the robot description against; '
                       'identify again with this version')
    here = dh_table(cm.robot, cm.geometric, cm.geometric.nominal, values[:len(cm.geometric)])
    if not isinstance(written, list) or len(written) != len(here):
        raise _refused(path, f'its dh_hayati table has {_count(written)} rows, this robot '
                       f'{len(here)}: identified for another robot')
    for old, new in zip(written, here):
        if not isinstance(old, dict) or old.get('joints') != new['joints'] \
                or old.get('convention') != new['convention']:
            raise _refused(path, f"dh_hayati row {new['joints']} ({new['convention']}) is "
                           f'{old!r} in the file: identified for another robot')
        for column in ('nominal', 'calibrated'):
            for key, value in new[column].items():
                try:
                    difference = abs(float(old[column][key]) - value)
                except (KeyError, TypeError, ValueError):
                    difference = float('inf')
                if not difference <= ROBOT_TOLERANCE:
                    raise _refused(path, f"dh_hayati {new['joints']} {column} {key} differs "
                                   f'from this robot description\'s by {difference:.3g}: '
                                   'identified on another robot description')


def _check_working_poses(path: Path, cm: CellModel, values: np.ndarray,
                         tcp: np.ndarray) -> None:
    """The written TCP is where the written parameters put the cell's working poses now
    (their joints and payloads): a working pose changed since the calibration would be
    published at its former place, with its former covariance."""
    now = np.asarray(cm.model.jacobian(values, cm.q_work, cm.tau_work)[0],
                     float).reshape(-1, 3)
    moved = np.linalg.norm(now - tcp, axis=1)
    if not np.all(moved <= TCP_TOLERANCE):
        i = int(np.argmax(np.where(np.isfinite(moved), moved, np.inf)))
        raise _refused(path, f'its TCP at working pose {cm.working_pose_names[i]!r} is '
                       f'{moved[i] * 1e3:.4g} mm from where its parameters put that pose now: '
                       'the working pose (its joints or payload) changed since the '
                       'calibration; identify again for the working poses as they are')


def _count(rows: Any) -> int | str:
    return len(rows) if isinstance(rows, list) else 'no'


def _tcp(path: Path, cm: CellModel, doc: dict[str, Any]) -> tuple[np.ndarray, np.ndarray]:
    """The written TCP at the cell's working poses, in their order."""
    entries = doc.get('tcp')
    if not isinstance(entries, list) or not all(isinstance(e, dict) for e in entries):
        raise _refused(path, 'tcp must be a list of working poses')
    written = [e.get('name') for e in entries]
    if sorted(map(str, written)) != sorted(cm.working_pose_names):
        raise _refused(path, f'its TCP is for the working poses {written}, the node\'s are '
                       f'{list(cm.working_pose_names)}')
    by_name = {str(e['name']): e for e in entries}
    try:
        position = np.array([by_name[n]['position'] for n in cm.working_pose_names],
                            dtype=float).reshape(-1, 3)
        covariance = np.array([by_name[n]['covariance'] for n in cm.working_pose_names],
                              dtype=float).reshape(-1, 3, 3)
    except (KeyError, TypeError, ValueError):
        raise _refused(path, 'a tcp entry lacks its position or covariance (3 and 3 x 3 '
                       'numbers)') from None
    if not (np.all(np.isfinite(position)) and np.all(np.isfinite(covariance))):
        raise _refused(path, 'a tcp position or covariance is not finite')
    return position, covariance


__all__ = ['ROBOT_TOLERANCE', 'TCP_TOLERANCE', 'StoredCalibration', 'read_stored_calibration']
