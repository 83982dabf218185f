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

from kpi_calib_ros.app.campaign import campaign_context, new_campaign
from kpi_calib_ros.app.design import (controller_design, design_cell_model, design_estimability,
                                      drawn_robots_section)
from kpi_calib_ros.core.design import DesignResult
from kpi_calib_ros.core.measurement import Measurements
from kpi_calib_ros.core.pairing import PairingResult
from kpi_calib_ros.core.sequential import CampaignSettings, CampaignStatus, SequentialCampaign
from kpi_calib_ros.io.campaign_io import write_plan
from kpi_calib_ros.io.cell import CellModel
from kpi_calib_ros.io.design_io import write_design
from kpi_calib_ros.app.diagnose import diagnose_cell
from kpi_calib_ros.app.validate import validate_report
from kpi_calib_ros.io.report import diagnosis_to_dict, write_report
from kpi_calib_ros.app.identify import (CellCalibration, add_robust_sections,
                                        calibrate_cell, calibration_document, write_results)
from kpi_calib_ros.app.reidentify import cycle_prior, reidentification_document, reidentify
from kpi_calib_ros.core.prior import DriftSwing
from kpi_calib_ros.core.change_detection import ChangeTest
from kpi_calib_ros.core.errors import KpiCalibError
from kpi_calib_ros.io.names import (CALIBRATIONS_DIR, CAMPAIGN_PLAN_FILE, DESIGN_FILE,
                                    DIAGNOSIS_DIR, VALIDATION_DIR)
from kpi_calib_ros.io.calibration_file import read_calibration_document
from kpi_calib_ros.io.results import write_atomic
from kpi_calib_ros.ros import conversions as cv
from kpi_calib_ros.ros.parameters import NodeSettings



def design_work(cm: CellModel, settings: NodeSettings,
                data_dir: Path) -> tuple[DesignResult, np.ndarray, Path, str]:
    """Design ``settings.num_measurements`` poses and write ``design.yaml``.

    Returns
    -------
    design : DesignResult
        Configurations in the controller's joint values (``robot.joint_coupling``).
    points : ndarray, shape (N, 3)
        Nominal reflector positions (m, tracker frame) of the designed poses.
    path : Path
        The written design file.
    estimability : str
        '' when the design determines the TCP at every working pose, else why not.
    """
    design = design_cell_model(cm, settings.num_measurements, settings.criterion,
                               settings.design_seed)
    points = cm.model.predict(cm.model.params.nominal, design.configurations)
    estimability = design_estimability(cm, design.configurations)
    drawn, _ = drawn_robots_section(cm, design, settings.design_seed)
    design = controller_design(cm, design)  # the robot program gets controller values
    # The capsules and skipped pairs the design used (built by it, cached); the mesh
    # check's findings are in the design's verification.
    path = write_design(data_dir / DESIGN_FILE, design,
                        extra={'geometry': cm.robot_geometry().summary(),
                               'drawn_robots': drawn})
    return design, points, path, '' if estimability.all_estimable else estimability.summary()


def previous_calibration(data_dir: Path, first_stamp_ns: int
                         ) -> tuple[Path | None, dict[str, Any] | None, list[str]]:
    """The newest archived calibration (``data_dir/calibrations/<identified_at_ns>.yaml``)
    identified before ``first_stamp_ns``: the last cycle's, never one fitted to any of
    the current measurements. A file that is not a readable calibration (damaged, edited,
    not one) is skipped with a warning and the next older one is tried.

    Returns
    -------
    path, doc : Path and dict, or None and None
        The prior calibration and its checked document; None when there is none.
    notes : list of str
        The files skipped and, without a prior, why none was used.
    """
    folder = data_dir / CALIBRATIONS_DIR
    dated: list[tuple[int, Path]] = []
    notes: list[str] = []
    for path in sorted(folder.glob('*.yaml')):
        try:
            dated.append((int(path.stem), path))
        except ValueError:
            notes.append(f'{path} skipped: not named <identified_at_ns>.yaml')
    before = sorted((d for d in dated if d[0] < first_stamp_ns), reverse=True)
    for _, path in before:
        try:
            return path, read_calibration_document(path, 'prior calibration'), notes
        except KpiCalibError as exc:
            notes.append(f'{path} skipped: {exc}')
    after = len(dated) - len(before)
    if after:
        newest = max(d[0] for d in dated)
        notes.append(f'no prior: {after} archived calibration(s) in {folder} dated at or '
                     f'after the first measurement (identified_at_ns up to {newest}, first '
                     f'measurement stamped {int(first_stamp_ns)}, '
                     f'{(newest - int(first_stamp_ns)) / 3.6e12:.3g} h later): the clock that '
                     'stamps the measurements was set back, or they are from another cycle; '
                     'identified without a prior')
    elif not before:
        notes.append(f'no prior: no archived calibration in {folder}; identified without '
                     'a prior')
    else:
        notes.append('no prior: no archived calibration could be read; identified without '
                     'a prior')
    return None, None, notes


def archive_calibration(data_dir: Path, doc: dict[str, Any], text: str) -> Path | None:
    """Keep a valid calibration as ``data_dir/calibrations/<identified_at_ns>.yaml``."""
    stamp = doc.get('identified_at_ns')
    if stamp is None:
        return None
    return write_atomic(data_dir / CALIBRATIONS_DIR / f'{int(stamp)}.yaml', text)


def identify_work(cm: CellModel, data: Measurements, pairing: PairingResult, data_dir: Path,
                  with_prior: bool = False, swing: DriftSwing | None = None
                  ) -> tuple[CellCalibration | None, str, str, list[PoseWithCovarianceStamped],
                             ChangeTest | None, str, list[str]]:
    """Identify from ``data`` as ``kpi-calib identify`` does and write the calibration and
    the calibrated URDF atomically. An invalid calibration (not converged, TCP not
    estimable) is written to calibration.failed.yaml only: the last good calibration.yaml
    and URDF stay, and nothing is returned to publish but its text. A valid one is also
    archived as ``data_dir/calibrations/<identified_at_ns>.yaml``.

    ``with_prior``: the last archived calibration of an earlier cycle
    (:func:`previous_calibration`) is the prior (``identify --prior``, default drift;
    ``swing``: the daily swing of its drift state, ``--drift-velocity``);
    a change beyond the drift model returns no calibration, the change test and the
    failed document's text (written to calibration.failed.yaml).

    Returns
    -------
    calibration : CellCalibration or None
        None when a change was detected (nothing blended).
    text : str
        The document exactly as written.
    urdf : str
        The calibrated robot description, as written ('' when invalid).
    tcp : list of PoseWithCovarianceStamped
        One per working pose, stamped with the last measurement (empty when invalid).
    change : ChangeTest or None
        The innovation test against the prior (None without a prior).
    prior : str
        The prior calibration's path ('' without).
    notes : list of str
        With ``with_prior``: archived files skipped, why no prior was used, and the
        prior's drift-time warnings (clocks that disagree).
    """
    if data.stamps_ns is None:
        raise ValueError('data.stamps_ns is None: the TCP poses are stamped with the last '
                         'measurement')
    source, old, notes = (previous_calibration(data_dir, int(np.min(data.stamps_ns)))
                          if with_prior and len(data) else (None, None, []))
    change = None
    if source is None:
        cal: CellCalibration | None = calibrate_cell(cm, data)
        assert cal is not None
        cm = cal.cell or cm  # with the effects identification.model auto added
        doc = add_robust_sections(calibration_document(cm, cal.result, pairing), cal)
        result = cal.result
    else:
        assert old is not None
        cp = cycle_prior(cm, old, data, swing=swing)
        notes += list(cp.warnings)
        out = reidentify(cm, data, cp)
        cal, change = out.calibration, out.change
        doc = reidentification_document(cm, out, cp, str(source), pairing)
        result = cal.result if cal is not None else out.fit
    path, _, urdf = write_results(cm, result, doc, data_dir)
    text = path.read_text()  # published as written
    if cal is None or not cal.valid:
        return cal, text, '', [], change, str(source or ''), notes
    archive_calibration(data_dir, doc, text)
    tcp = cv.tcp_pose_msgs(result.tcp, result.tcp_covariance, cm.cell.tracker_frame,
                           int(data.stamps_ns[-1]))
    return cal, text, urdf, tcp, change, str(source or ''), notes


def validate_work(cm: CellModel, calibration: str, data: Measurements,
                  data_dir: Path, register: str | None = None) -> tuple[dict[str, Any], str]:
    """Validate the calibration (the YAML text the node published) on new measurements,
    as ``kpi-calib validate`` (``--register register``) does; writes ``data_dir/validation/``.

    Returns
    -------
    doc : dict
        ``validation.json``'s document; ``text`` : str, it as JSON.
    """
    doc = validate_report(cm, yaml.safe_load(calibration), data, data_dir / VALIDATION_DIR,
                          register)
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


def sequential_start_work(cm: CellModel, settings: NodeSettings,
                          data_dir: Path) -> tuple[SequentialCampaign, np.ndarray, np.ndarray,
                                                   Path]:
    """A sequential campaign for the cell and its initial design.

    Returns
    -------
    campaign : SequentialCampaign
        Owned by whoever runs the next step (one job at a time).
    initial : ndarray, shape (m, n)
        The initial design in the controller's joint values.
    points : ndarray, shape (m, 3)
        Nominal reflector positions (m, tracker frame) of the initial design.
    path : Path
        ``campaign_plan.yaml``: the initial design, as ``kpi-calib campaign`` writes it.
    """
    cell, ctx = campaign_context(cm, settings.design_seed)
    campaign = new_campaign(cm, cell, ctx, CampaignSettings(
        target_std=settings.target_tcp_std, max_measurements=settings.max_measurements),
        settings.design_seed)
    q = ctx.candidates.configurations[campaign.initial_design()]
    points = cm.model.predict(cm.model.params.nominal, q)
    controller = cm.joint_coupling.to_controller(q)
    path = write_plan(data_dir / CAMPAIGN_PLAN_FILE, cm.joint_names, controller,
                      campaign.settings)
    return campaign, controller, points, path


def sequential_step_work(campaign: SequentialCampaign, cm: CellModel,
                         data: Measurements) -> tuple[CampaignStatus, np.ndarray, str]:
    """Add the measurements ``data`` (URDF joint values) to ``campaign``: re-identify,
    re-plan. Returns the status, the plan in controller values (next pose first) and the
    status as YAML text (``~/campaign_status``)."""
    status = campaign.add(data.q, data.eta, -1, data.reflector, data.rotation)
    plan = cm.joint_coupling.to_controller(status.next_configurations) if len(
        status.next_configurations) else status.next_configurations
    text = yaml.safe_dump(status.to_dict(cm.working_pose_names), sort_keys=False)
    return status, plan, text


__all__ = ['archive_calibration', 'design_work', 'diagnose_work', 'identify_work',
           'previous_calibration', 'sequential_start_work', 'sequential_step_work',
           'validate_work']
