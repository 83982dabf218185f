"""What the node's jobs do in a worker thread: compute, write the result files, make the
messages' text. Plain inputs in, values out; nothing here sees the node, so these run
beside the executor without sharing its state (see :mod:`kpi_calib_ros.ros.node`).

Messages and their text are made here too: a YAML dump of a calibration takes ~0.1 s,
long enough to hold up pairing if the executor did it.
"""
from __future__ import annotations

import dataclasses
import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Sequence

import numpy as np
import yaml
from geometry_msgs.msg import PoseWithCovarianceStamped

from kpi_calib_ros.app.calibration_document import (
    CellCalibration,
    add_placement_jumps,
    add_robust_sections,
    calibration_document,
    name_excluded,
    recordings_section,
    recordings_text,
    urdf_omission,
    with_recording_names,
)
from kpi_calib_ros.app.campaign import campaign_calibration, campaign_context, new_campaign
from kpi_calib_ros.app.cell_model import CellModel, build_cell_model
from kpi_calib_ros.app.design import (
    controller_design,
    design_cell_model,
    design_estimability,
    design_free,
    design_point,
    drawn_robots_section,
    prior_cell_model,
    prior_design,
)
from kpi_calib_ros.app.diagnose import diagnose_and_report
from kpi_calib_ros.app.finish import finish_calibration
from kpi_calib_ros.app.identify import add_prior_and_comparison, calibrate_cell
from kpi_calib_ros.app.learned_residual import learned_residual_section
from kpi_calib_ros.app.reidentify import (
    cycle_prior,
    read_prior_calibration,
    reidentification_document,
    reidentify,
)
from kpi_calib_ros.app.validate import (
    calibrated_model,
    recording_calibration,
    validate_report,
)
from kpi_calib_ros.core.acquisition.outcomes import PairingResult
from kpi_calib_ros.core.campaigns.change_detection import ChangeTest
from kpi_calib_ros.core.campaigns.sequential import SequentialCampaign
from kpi_calib_ros.core.campaigns.settings import MODEL_INADEQUATE, CampaignSettings, CampaignStatus
from kpi_calib_ros.core.design.optimum import DesignResult
from kpi_calib_ros.core.errors import DataError, KpiCalibError
from kpi_calib_ros.core.estimation.drift_state import DriftSwing
from kpi_calib_ros.core.measurement.data import Measurements
from kpi_calib_ros.core.measurement.recordings import Recording
from kpi_calib_ros.core.model.parameters import BASE_COMPONENTS
from kpi_calib_ros.io.calibration_file import calibration_recordings
from kpi_calib_ros.io.campaign_io import CampaignState, write_campaign_state, write_plan
from kpi_calib_ros.io.design_io import write_design
from kpi_calib_ros.io.names import (
    CALIBRATED_URDF_TOPIC,
    CALIBRATIONS_DIR,
    CAMPAIGN_PLAN_FILE,
    CAMPAIGN_PRIOR_FILE,
    CAMPAIGN_STATE_FILE,
    DESIGN_FILE,
    DIAGNOSIS_DIR,
    LEARNED_RESIDUAL_FILE,
    VALIDATION_DIR,
)
from kpi_calib_ros.io.report import diagnosis_to_dict
from kpi_calib_ros.io.results import write_atomic
from kpi_calib_ros.io.yaml_bounded import SAFE_LOADER, dump_yaml
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


def station_design_work(cm: CellModel, settings: NodeSettings, data_dir: Path,
                        calibration: str, station: str
                        ) -> tuple[DesignResult, np.ndarray, Path, str, str]:
    """Design ``settings.num_measurements`` poses for ``station`` with the calibration the
    node published (its YAML text, several stations identified together) as prior, and
    write ``design.yaml``; as ``kpi-calib design --prior`` does for a station's cell file.

    The calibration seen from ``station``
    (:func:`~kpi_calib_ros.app.validate.recording_calibration`): its base pose in the
    tracker frame places the design (the tracker's line of sight and incidence from where
    that station stands, the KPI linearised there), with its covariance and the robot's
    in the prior (:func:`~kpi_calib_ros.app.reidentify.cycle_prior`, no drift: the same
    campaign); the other stations' placements are marginalised out. The predicted TCP
    covariance is that of identifying everything measured and these poses together.

    Returns
    -------
    design, points, path, estimability
        As :func:`design_work` (``points`` where the calibration places them).
    description : str
        The prior, in words.
    """
    stored = yaml.load(calibration, Loader=SAFE_LOADER)  # the node's own text
    at_station, _, cp = _station_prior(cm, stored, station)
    weighted, design, p = prior_design(at_station, cp, settings.num_measurements,
                                       settings.criterion, settings.design_seed)
    points = weighted.model.predict(p, design.configurations)
    estimability = design_estimability(weighted, design.configurations, cp.prior, p,
                                       cp.allowed)
    description = (f'designed for station {station!r} with the calibration of stations '
                   f"{', '.join(r.name for r in calibration_recordings(stored, 'calibration'))}"
                   f' as prior: {cp.description}')
    design = controller_design(weighted, design)
    path = write_design(data_dir / DESIGN_FILE, design, extra={
        'geometry': weighted.robot_geometry().summary(),
        'prior': {'source': 'the calibration the node published', 'station': station,
                  'description': description}})
    return (design, points, path,
            '' if estimability.all_estimable else estimability.summary(), description)


def _station_prior(cm: CellModel, stored: dict[str, Any], station: str
                   ) -> tuple[CellModel, tuple[float, ...], Any]:
    """The cell model placed where the calibration document ``stored`` (several stations)
    places ``station``, that base pose, and the calibration seen from the station as prior
    (:func:`~kpi_calib_ros.app.validate.recording_calibration`; the other stations'
    placements marginalised, no drift: the same campaign;
    :func:`~kpi_calib_ros.app.reidentify.cycle_prior`)."""
    placed, _ = calibrated_model(cm.cell, stored)
    seen = recording_calibration(placed, stored, station)
    values = {e['name']: float(e['value']) for e in seen['parameters']}
    base = tuple(values[f'base.{c}'] for c in BASE_COMPONENTS)
    at_station = at_placement(cm, base, tuple(stored.get('effects') or ()))
    return at_station, base, cycle_prior(at_station, seen, None, keep_placement=True,
                                         hours=0.0)


def at_placement(cm: CellModel, base: Sequence[float], effects: tuple = ()) -> CellModel:
    """``cm`` with the robot's base at ``base`` in the tracker frame (a station's; () keeps
    the cell file's) and ``effects`` added."""
    if not len(base) and not effects:
        return cm
    cell = cm.cell if not len(base) else dataclasses.replace(
        cm.cell, base_in_tracker=np.asarray(base, float), base_in_tracker_given=True)
    return build_cell_model(cell, effects=effects)


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
            return path, read_prior_calibration(path, 'prior calibration'), notes
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


@dataclass(frozen=True)
class IdentifyOutput:
    """What ``~/identify`` gives the node to publish (:func:`identify_work`).

    calibration : CellCalibration or None
        None when a change was detected (nothing blended).
    text : str
        The document exactly as written.
    urdf : str
        The calibrated robot description, as written ('' when invalid).
    tcp : tuple of PoseWithCovarianceStamped
        One per working pose, stamped with the last measurement (empty when invalid).
    change : ChangeTest or None
        The innovation test against the prior (None without a prior).
    prior : str
        The prior calibration's path ('' without).
    notes : tuple of str
        With ``with_prior``: archived files skipped, why no prior was used, and the
        prior's drift-time warnings (clocks that disagree).
    learned : (str, str)
        With ``learned_residual`` and a valid calibration: the outcome (``chosen`` with the
        file written, ``not chosen``, ``not fitted`` with a prior) and the choice in words
        with its figures, the CLI's summary lines; ('', '') otherwise.
    """

    calibration: CellCalibration | None
    text: str
    urdf: str = ''
    tcp: tuple[PoseWithCovarianceStamped, ...] = ()
    change: ChangeTest | None = None
    prior: str = ''
    notes: tuple[str, ...] = ()
    learned: tuple[str, str] = ('', '')
    stations: str = ''


def identify_work(cm: CellModel, data: Measurements, pairing: PairingResult, data_dir: Path,
                  with_prior: bool = False, swing: DriftSwing | None = None,
                  archive: bool = True, learned_residual: bool = False,
                  stations: Sequence[Recording] = ()) -> IdentifyOutput:
    """Identify from ``data`` as ``kpi-calib identify`` does and finish the calibration as
    it does (:func:`~kpi_calib_ros.app.finish.finish_calibration`): calibration.yaml, the
    calibrated URDF, learned_residual.yaml when chosen and the archived copy
    ``data_dir/calibrations/<identified_at_ns>.yaml`` written as one set, so a full disk
    leaves the previous set whole (ConfigError naming ``data_dir``). An invalid
    calibration (not converged, TCP not estimable) is written to calibration.failed.yaml
    only: the last good set stays, and nothing is returned to publish but its text.

    ``with_prior``: the last archived calibration of an earlier cycle
    (:func:`previous_calibration`) is the prior (``identify --prior``, default drift;
    ``swing``: the daily swing of its drift state, ``--drift-velocity``);
    a change beyond the drift model returns no calibration, the change test and the
    failed document's text (written to calibration.failed.yaml). ``archive`` false: a
    valid calibration is written and returned but not archived (never the next cycle's
    prior), e.g. from a campaign that stopped as model inadequate.

    ``learned_residual``: the learned residual is chosen on the measurements the valid
    calibration kept, as ``kpi-calib identify --learned-residual`` does
    (:func:`~kpi_calib_ros.app.learned_residual.learned_residual_section`): written as
    learned_residual.yaml in ``data_dir`` when chosen, its section in the document either
    way. Not with a prior (as ``--learned-residual`` is not with ``--prior``). A valid
    calibration without one removes an older learned_residual.yaml with its set, so the
    file never corrects a calibration it was not fitted to.

    ``stations``: the tracker stations of ``data``'s rows as recordings (``cm`` and ``data``
    from :func:`~kpi_calib_ros.ros.stored_measurements.station_measurements`); with several,
    each has its own placement, the document states what each contributed
    (``recordings:``, as ``identify --bag a --bag b``) and no prior is used (a prior
    calibration places one station).
    """
    if data.stamps_ns is None:
        raise ValueError('data.stamps_ns is None: the TCP poses are stamped with the last '
                         'measurement')
    several = len(stations) > 1
    source, old, notes = (previous_calibration(data_dir, int(np.min(data.stamps_ns)))
                          if with_prior and len(data) and not several else (None, None, []))
    if with_prior and several:
        notes = [f'no prior: measurements from {len(stations)} stations '
                 f"({', '.join(r.name for r in stations)}) are identified together, each "
                 'with its own placement, without a prior']
    change = None
    if source is None:
        cal: CellCalibration | None = with_recording_names(calibrate_cell(cm, data), stations)
        assert cal is not None
        cm = cal.cell or cm  # with the effects identification.model auto added
        doc = add_robust_sections(calibration_document(cm, cal.result, pairing), cal)
        add_prior_and_comparison(doc, cm, data, cal)
        result = cal.result
        notes += add_placement_jumps(doc, cm, data, cal,
                                     [r.name for r in stations] or ['station'])
        if several and cal.valid:
            doc['recordings'] = recordings_section(
                cm, data, cal, stations, [f'{data_dir} station {r.name}' for r in stations])
            name_excluded(doc, data, stations)
    else:
        assert old is not None
        cp = cycle_prior(cm, old, data, swing=swing)
        notes += list(cp.warnings)
        out = reidentify(cm, data, cp)
        cal, change = out.calibration, out.change
        doc = reidentification_document(cm, out, cp, str(source), pairing)
        result = cal.result if cal is not None else out.fit
    learned, content = ('', ''), None
    if cal is not None and cal.valid:
        if learned_residual and source is not None:
            learned = ('not fitted', f'learned residual not fitted: identified with the prior '
                       f'{source} (identify --learned-residual is not available with --prior '
                       'either); set reidentify_with_prior:=false to learn it')
        elif learned_residual:
            text, content = learned_residual_section(doc, cm, data.subset(cal.robust.kept),
                                                     result)
            learned = ('not chosen', text) if content is None else (
                'chosen', f'{text}\nwritten: {data_dir / LEARNED_RESIDUAL_FILE}')
    done = finish_calibration(cm, result, doc, data_dir, content, archive, key='data_dir')
    if cal is None or not cal.valid:
        return IdentifyOutput(cal, done.text, change=change, prior=str(source or ''),
                              notes=tuple(notes))
    tcp = cv.tcp_pose_msgs(result.tcp, result.tcp_covariance, cm.cell.tracker_frame,
                           int(data.stamps_ns[-1]))
    omitted = urdf_omission(cal.cell or cm, result, data.subset(cal.robust.kept))
    notes = [*notes, f'{CALIBRATED_URDF_TOPIC}: {omitted}'] if omitted else notes
    return IdentifyOutput(cal, done.text, done.urdf, tuple(tcp), change, str(source or ''),
                          tuple(notes), learned,
                          recordings_text(doc['recordings']) if 'recordings' in doc else '')


def validate_work(cm: CellModel, calibration: str, data: Measurements,
                  data_dir: Path, register: str | None = None,
                  station: str = '') -> tuple[dict[str, Any], str]:
    """Validate the calibration (the YAML text the node published) on new measurements,
    as ``kpi-calib validate`` (``--register register``) does; writes ``data_dir/validation/``.

    ``cm``: the cell's model of one station; the calibration's model is built from it with
    the calibration's effects (those ``identification.model: auto`` added) and its further
    stations, placed as it placed them (:func:`~kpi_calib_ros.app.validate.calibrated_model`).
    ``station``:
    the station ``data`` was measured from; one the calibration holds places them as it
    did (``validate --recording``), another (or the first) by ``base.*``.

    Returns
    -------
    doc : dict
        ``validation.json``'s document; ``text`` : str, it as JSON.
    """
    learned = data_dir / LEARNED_RESIDUAL_FILE
    stored = yaml.load(calibration, Loader=SAFE_LOADER)  # the node's own text
    recordings = calibration_recordings(stored, 'the calibration')
    known = [r.name for r in recordings]
    # the calibration's own model: the effects identification.model auto added, its stations
    doc = validate_report(calibrated_model(cm.cell, stored)[0], stored, data,
                          data_dir / VALIDATION_DIR, register,
                          learned if learned.is_file() else None,
                          station if station in known else None)
    return doc, json.dumps(doc, allow_nan=False)


def diagnose_work(cm: CellModel, data: Measurements,
                  data_dir: Path) -> tuple[dict[str, Any], str, str, Path]:
    """Diagnose the model on ``data`` as ``kpi-calib diagnose`` does (the learned residual
    one more remedy when the model is not adequate); write the report and its plots.

    Returns
    -------
    doc : dict
        ``diagnosis.json``'s document; ``text`` : str, it as JSON; ``verdict`` : str, with
        the learned residual's decision when it was asked; ``report`` : Path, the written
        ``report.md``.
    """
    cd, choice, refused, report = diagnose_and_report(cm, data, data_dir / DIAGNOSIS_DIR)
    doc = diagnosis_to_dict(cd)
    verdict = ' '.join(t for t in (cd.diagnosis.verdict, refused,
                                   choice.reason if choice is not None else '') if t)
    return doc, json.dumps(doc, allow_nan=False), verdict, report


def campaign_settings(settings: NodeSettings) -> CampaignSettings:
    """The campaign settings the node's parameters give."""
    return CampaignSettings(target_std=settings.target_tcp_std,
                            max_measurements=settings.max_measurements)


def station_campaign(cm: CellModel, calibration: str, station: str
                     ) -> tuple[CellModel, tuple[float, ...], Any]:
    """The cell model a sequential campaign at ``station`` plans and identifies in, where
    the calibration the node published (its YAML text, several stations) places it, and
    that calibration as its prior, seen from the station (the other stations' placements
    marginalised, no drift: the same campaign;
    :func:`~kpi_calib_ros.app.reidentify.cycle_prior`), the new points weighted at the
    noise it showed (:func:`~kpi_calib_ros.app.design.prior_cell_model`)."""
    at_station, base, cp = _station_prior(cm, yaml.load(calibration, Loader=SAFE_LOADER),
                                          station)
    weighted, _ = prior_cell_model(at_station, cp)
    return weighted, base, cp


def sequential_start_work(cm: CellModel, settings: CampaignSettings, design_seed: int,
                          data_dir: Path, station: str = '',
                          base: Sequence[float] = (), cp: Any = None,
                          calibration: str = '') -> tuple[SequentialCampaign, np.ndarray,
                                                          np.ndarray, Path]:
    """A sequential campaign for the cell and its initial design; writes the plan and the
    campaign state (no step yet), so a restarted node resumes it. ``cm``: the cell model
    at ``station``'s placement ``base`` (() : the cell file's), which the state keeps;
    ``cp`` its prior (:func:`station_campaign`) from ``calibration``, kept in
    ``data_dir/campaign_prior.yaml`` for the resume.

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
    campaign, q = new_sequential(cm, settings, design_seed, cp)
    points = cm.model.predict(campaign.start, q)
    controller = cm.joint_coupling.to_controller(q)
    if cp is not None:
        write_atomic(data_dir / CAMPAIGN_PRIOR_FILE, calibration)
    path = write_plan(data_dir / CAMPAIGN_PLAN_FILE, cm.joint_names, controller,
                      campaign.settings)
    write_campaign_state(data_dir / CAMPAIGN_STATE_FILE, CampaignState(
        settings, design_seed, station=station, base_in_tracker=tuple(float(v) for v in base)))
    return campaign, controller, points, path


def new_sequential(cm: CellModel, settings: CampaignSettings, design_seed: int,
                    cp: Any = None) -> tuple[SequentialCampaign, np.ndarray]:
    """The campaign and its initial design (URDF joint values): the same for the same
    cell, settings, seed and prior ``cp``."""
    if cp is None:
        cell, ctx = campaign_context(cm, design_seed)
        campaign = new_campaign(cm, cell, ctx, settings, design_seed)
    else:
        p, free = design_point(cm, cp), design_free(cm, cp.allowed)
        cell, ctx = campaign_context(cm, design_seed, prior=cp.prior, p=p, free=free)
        campaign = new_campaign(cm, cell, ctx, settings, design_seed, prior=cp.prior,
                                start=p, free=free)
    return campaign, ctx.candidates.configurations[campaign.initial_design()]


@dataclass(frozen=True)
class StepOutput:
    """What a campaign step gives the node to publish.

    status : the campaign's status; plan : (m, n) controller values, next pose first;
    text : ``~/campaign_status`` (YAML); state : the campaign state as written;
    calibration : (text, urdf, tcp messages) of a stopped campaign's calibration, None
    while it runs or when it stopped as model inadequate (nothing published, nothing
    archived as a prior); result : that calibration; refused : why a stopped campaign's
    calibration is not valid and not published ('' otherwise).
    """

    status: CampaignStatus
    plan: np.ndarray
    text: str
    state: CampaignState
    calibration: tuple[str, str, list[PoseWithCovarianceStamped]] | None = None
    result: CellCalibration | None = None
    refused: str = ''


def sequential_step_work(campaign: SequentialCampaign, cm: CellModel, data: Measurements,
                         state: CampaignState, data_dir: Path,
                         pairing: PairingResult | None = None,
                         extra: dict[str, Any] | None = None) -> StepOutput:
    """Add the measurements ``data`` (URDF joint values, stamped) to ``campaign``:
    re-identify, re-plan, write the campaign state with this step; once the campaign
    stopped (target met or cap), write, archive and return its calibration
    (:func:`~kpi_calib_ros.app.campaign.campaign_calibration`). ``extra`` is added to the
    status text (e.g. ``resumed``)."""
    status = campaign.add(data.q, data.eta, -1, data.reflector, data.rotation,
                          stamps_ns=data.stamps_ns)
    # A pose's rows (reflectors, rotation rows) may share a stamp: stored once.
    stamps = tuple(dict.fromkeys(int(t) for t in np.asarray(data.stamps_ns).ravel()))
    return _step_output(campaign, cm, dataclasses.replace(
        state, steps=state.steps + (stamps,),
        status=status.to_dict(cm.working_pose_names)), data_dir, pairing, extra)


def _step_output(campaign: SequentialCampaign, cm: CellModel, state: CampaignState,
                 data_dir: Path, pairing: PairingResult | None,
                 extra: dict[str, Any] | None, publish: bool = True) -> StepOutput:
    status = campaign.status
    assert status is not None
    doc = {**status.to_dict(cm.working_pose_names), **(extra or {})}
    plan = cm.joint_coupling.to_controller(status.next_configurations) if len(
        status.next_configurations) else status.next_configurations
    calibration, result, refused = None, None, ''
    # The calibration is on disk before the state says the campaign stopped: a node
    # killed in between repeats this step on restart and writes it again.
    if publish and status.stopped and status.stop_reason != MODEL_INADEQUATE:
        cal, cal_doc = campaign_calibration(cm, campaign, pairing)
        done = finish_calibration(cm, cal.result, cal_doc, data_dir, archive=True,
                                  key='data_dir')
        if cal.valid:
            stamp = int(np.max(campaign.stamps)) if len(campaign.stamps) else 0
            calibration = (done.text, done.urdf, cv.tcp_pose_msgs(
                cal.result.tcp, cal.result.tcp_covariance, cm.cell.tracker_frame, stamp))
            result = cal
        else:
            # Stopped, and its calibration is not valid: said in the status, not left to a
            # calibration.failed.yaml nobody is told of.
            refused = ' | '.join(cal.problems) or 'not valid'
            doc['calibration_not_published'] = refused
    text = dump_yaml(doc)
    state = dataclasses.replace(state, status=doc)
    write_campaign_state(data_dir / CAMPAIGN_STATE_FILE, state)
    return StepOutput(status, plan, text, state, calibration, result, refused)


def sequential_resume_work(cm: CellModel, state: CampaignState, data: Measurements,
                           data_dir: Path, cp: Any = None
                           ) -> tuple[SequentialCampaign, np.ndarray, StepOutput | None]:
    """Rebuild the campaign of ``state`` after a restart: the same initial design, then
    every step added again with the same stored measurements (found by stamp in
    ``data``, URDF joint values), so the status and the plan are the ones the campaign
    had (the core is deterministic); ``cm`` and ``cp`` as it started with them
    (:func:`station_campaign`). Nothing is published as a calibration here: a
    campaign that had stopped published its calibration then.

    Returns the campaign, its initial design (controller values) and the last step's
    output (None before the first step).

    Raises
    ------
    DataError
        A stored step's measurement is not among the restored ones (the logs and the
        state file disagree).
    """
    stamps = np.asarray(data.stamps_ns, dtype=np.int64).ravel()
    known = set(int(t) for t in stamps)
    missing = [t for step in state.steps for t in step if t not in known]
    if missing:
        raise DataError(f'{data_dir / CAMPAIGN_STATE_FILE}: steps: measurement stamp '
                        f'{missing[0]} is not in the restored measurement logs; call '
                        '~/reset to archive the campaign and start a new one')
    campaign, q = new_sequential(cm, state.settings, state.design_seed, cp)
    for step in state.steps:
        # Every row with a stamp of the step (a pose's reflectors and rotation rows).
        rows = data.subset(np.isin(stamps, np.asarray(step, np.int64)))
        campaign.add(rows.q, rows.eta, -1, rows.reflector, rows.rotation,
                     stamps_ns=rows.stamps_ns)
    controller = cm.joint_coupling.to_controller(q)
    if not state.steps:
        return campaign, controller, None
    return campaign, controller, _step_output(campaign, cm, state, data_dir, None,
                                              {'resumed': True}, publish=False)


__all__ = ['IdentifyOutput', 'StepOutput', 'at_placement', 'campaign_settings', 'design_work',
           'diagnose_work', 'identify_work', 'new_sequential', 'previous_calibration',
           'sequential_resume_work', 'sequential_start_work', 'sequential_step_work',
           'station_campaign', 'station_design_work', 'validate_work']
