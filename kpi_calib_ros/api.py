"""The Python front door: load a cell, simulate or read its measurements, calibrate,
diagnose, design and validate, each in one call.

The command line (``kpi-calib``) and the node run the same jobs; this module gives them
to a script without its reader having to know where each concept lives. A first
calibration on the built-in simulated cell, the TCP compared with the simulated truth:

>>> import numpy as np
>>> from kpi_calib_ros import api
>>> cell = api.load_cell()                      # the built-in KR15-class cell
>>> campaign = api.simulate(cell, 60, seed=7)   # 60 measurable poses of a "true" robot
>>> cal = api.calibrate(cell, campaign.data)    # constrained least squares, eq. (19)
>>> cal.valid
True
>>> error = cal.result.tcp - campaign.true_tcp  # (working poses, 3) m
>>> std = np.sqrt(np.diagonal(cal.result.tcp_covariance, axis1=1, axis2=2))
>>> bool(np.all(np.abs(error) < 4 * std))        # the TCP error within its predicted std
True

Its check on new poses of the same robot:

>>> fresh = api.simulate(cell, 40, seed=8, truth=campaign)
>>> api.validate(cell, cal, fresh.data).holds
True

Every function takes the cell model :func:`load_cell` returns (a
:class:`~kpi_calib_ros.app.cell_model.CellModel`: robot, tracker, working poses, settings) and
measurements as :class:`~kpi_calib_ros.core.measurement.data.Measurements` (joint
readings in rad, tracker points in m); :func:`read_bag` makes them from a recording.
"""
from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

from kpi_calib_ros.app.calibration_document import (
    CellCalibration,
    add_robust_sections,
    calibration_document,
    with_recording_names,
)
from kpi_calib_ros.app.campaign import (
    campaign_context,
    new_campaign,
    simulate_sequential,
)
from kpi_calib_ros.app.cell_model import CellModel, build_cell_model
from kpi_calib_ros.app.design import design_cell_model
from kpi_calib_ros.app.diagnose import CellDiagnosis, diagnose_cell
from kpi_calib_ros.app.identify import calibrate_cell
from kpi_calib_ros.app.learned_residual import choose_residual
from kpi_calib_ros.app.measurements import measurements_from_bag, with_recordings
from kpi_calib_ros.app.reidentify import Reidentification, cycle_prior, reidentify
from kpi_calib_ros.app.simulate import simulate_campaign
from kpi_calib_ros.app.validate import (
    calibrated_model,
    parameter_vector,
    read_calibration,
    validate_calibration,
)
from kpi_calib_ros.core.campaigns.settings import CampaignSettings, SimulatedRun
from kpi_calib_ros.core.design.optimum import DesignResult
from kpi_calib_ros.core.diagnosis.learned_residual import ResidualChoice
from kpi_calib_ros.core.diagnosis.validation import Validation
from kpi_calib_ros.core.measurement.data import Measurements
from kpi_calib_ros.core.measurement.recordings import Recording, combine
from kpi_calib_ros.core.simulation import (
    random_configurations,
    simulate_measurements,
    true_parameters,
)
from kpi_calib_ros.io.cell import DEFAULT_CELL
from kpi_calib_ros.io.cell import load_cell as _read_cell

__all__ = ['Campaign', 'calibrate', 'design', 'diagnose', 'learn_residual', 'load_cell',
           'read_bag', 'recalibrate', 'sequential_campaign', 'simulate', 'validate', 'write_bag']


@dataclass(frozen=True)
class Campaign:
    """A simulated measurement campaign and the robot that produced it.

    Attributes
    ----------
    data : Measurements
        The simulated joint readings (rad) and tracker points (m).
    model : CellModel
        The true robot's cell model (the cell's, plus the hidden effects).
    true_values : (P,) ndarray
        The true robot's parameters, in the order of ``model.model.params``.
    true_tcp : (T, 3) ndarray
        The true TCP at the cell's working poses, tracker frame (m).
    """

    data: Measurements
    model: CellModel
    true_values: np.ndarray
    true_tcp: np.ndarray


def load_cell(path: str | Path | None = None, effects: str = '',
              allow_code_effects: bool = False) -> CellModel:
    """The cell model of a cell file (default: the built-in simulated KR15-class cell).

    ``effects``: extra effects to identify, as for ``--effects``
    (``'joint_compliance:joint_2,joint_play:joint_3'``). Every key of the file is checked;
    a bad one raises :class:`~kpi_calib_ros.core.errors.ConfigError` naming it.

    >>> from kpi_calib_ros import api
    >>> cell = api.load_cell(effects='joint_compliance:joint_2')
    >>> [e.name for e in cell.model.effects]
    ['joint_compliance:joint_2']
    """
    cell = _read_cell(DEFAULT_CELL if path is None else path,
                      allow_code_effects=allow_code_effects)
    cm = build_cell_model(cell)
    if not effects:
        return cm
    return build_cell_model(cell, effects=_specs(effects))


def _specs(text: str) -> tuple[str, ...]:
    """Effect specs of a comma-separated list (``--effects``)."""
    return tuple(s.strip() for s in text.split(',') if s.strip())


def read_bag(cell: CellModel, path: str | Path, joint_topic: str | None = None,
             point_topic: str | None = None, pose_topic: str | None = None) -> Measurements:
    """The measurements of an MCAP recording: tracker points paired with still joint
    states, joints matched by name; topics default to the cell's ``topics:``."""
    return measurements_from_bag(cell, path, joint_topic, point_topic, pose_topic)[0]


def write_bag(campaign: Campaign, path: str | Path, seed: int = 0) -> str:
    """Record ``campaign``'s poses as an MCAP bag, as ``kpi-calib simulate`` does: joint
    states held still around each tracker point (new tracker noise, seeded), the truth
    beside it (``<bag>.truth.yaml``). Returns the summary line."""
    q = campaign.data.q
    return simulate_campaign('', len(q), path, seed, poses=(campaign.model.joint_names, q),
                             cm=campaign.model, p_true=campaign.true_values)


def simulate(cell: CellModel, n: int, seed: int = 0, hidden: str = '',
             values: dict[str, float] | None = None,
             truth: Campaign | None = None,
             inputs: Mapping[str, float | np.ndarray] | None = None) -> Campaign:
    """``n`` measurable poses of a robot drawn near the cell's nominal one, measured with
    the cell's noise.

    ``hidden``: effects the true robot has and ``cell`` may lack (an effect spec, as
    ``--effects``), ``values`` the true values of some parameters (name -> SI value;
    the others drawn from the cell's simulated error magnitudes). ``truth``: measure
    the robot of an earlier campaign again (new poses, same robot). ``inputs``: the
    measured inputs of every row (name -> value or (n,) values in SI, e.g.
    ``{'payload.mass': 5.0}``), which drive the true robot's effects and are recorded
    with the rows, as the cell's ``inputs:`` or a manifest's ``covariates`` record them.

    >>> from kpi_calib_ros import api
    >>> cell = api.load_cell()
    >>> bent = api.simulate(cell, 60, seed=3, hidden='joint_compliance:joint_2',
    ...                     values={'joint_compliance.joint_2.c': -1e-6})
    >>> bent.data.q.shape, bent.data.eta.shape
    ((60, 6), (60, 3))
    """
    rng = np.random.default_rng(seed)
    if truth is None:
        specs = _specs(hidden)
        model = build_cell_model(cell.cell, effects=tuple(cell.model.effects) + specs) \
            if specs else cell
        p_true = true_parameters(model.model.params, rng, overrides=values)
    else:
        model, p_true = truth.model, truth.true_values
    q = random_configurations(model.model, model.model.params.nominal, n, rng,
                              cell.cell.max_incidence)
    covariates = None if inputs is None else {
        name: np.broadcast_to(np.asarray(v, float), (n,)).copy() for name, v in inputs.items()}
    data = simulate_measurements(model.model, p_true, q, cell.cell.sigma, rng,
                                 covariates=covariates)
    return Campaign(data, model, p_true, model.model.predict(p_true, model.q_work))


def calibrate(cell: CellModel, data: Measurements | Mapping[str, Measurements],
              model: str | None = None, remounted: Sequence[str] = ()) -> CellCalibration:
    """Identify the robot from ``data`` as ``kpi-calib identify`` does: placement
    registered, outliers that are faults excluded, the model level ``model`` (or the
    cell's ``identification.model``; ``'auto'`` adds the effects that predict new poses
    better), the TCP covariance of eq. (19) and its estimability.

    ``.valid`` says whether it may be published, ``.problems`` why not;
    ``.result`` holds the parameters, their std, the TCP and its covariance.

    ``data`` may be several recordings (tracker set-ups), ``{name: Measurements}`` in
    order, as ``identify --bag a.mcap --bag b.mcap``: the robot shared, every recording
    after the first with its own base pose ``recording.<name>.base.*`` (and, named in
    ``remounted``, its own reflector offsets); ``.cell`` is then the model of them all.

    >>> from kpi_calib_ros import api
    >>> cell = api.load_cell()
    >>> a = api.simulate(cell, 30, seed=1)
    >>> b = api.simulate(cell, 30, seed=2, truth=a)   # the same robot, another set-up
    >>> cal = api.calibrate(cell, {'a': a.data, 'b': b.data}, model='geometric')
    >>> [n for n in cal.result.estimated if n.startswith('recording.')][:2]
    ['recording.b.base.x', 'recording.b.base.y']
    """
    if isinstance(data, Measurements):
        return calibrate_cell(cell, data, model)
    if not data:
        raise ValueError('calibrate: no recording given')
    recordings = [Recording(name, name in remounted) for name in data]
    unknown = sorted(set(remounted) - set(data))
    if unknown:
        raise ValueError(f'calibrate: remounted names no recording: {unknown}')
    return with_recording_names(calibrate_cell(
        with_recordings(cell, recordings), combine(list(data.values()), recordings), model),
        recordings)


def learn_residual(cell: CellModel, calibration: CellCalibration, data: Measurements,
                   seed: int = 0) -> ResidualChoice:
    """Fit a learned residual (a Gaussian process over the joints) to what
    ``calibration`` leaves of ``data`` and decide, by cross-validation over poses, whether
    it predicts held-out poses better (``.chosen``, ``.reason``, ``.cv_rms_physical_m``,
    ``.cv_rms_learned_m``), as ``identify --learned-residual`` does; ``.model.predict(q)``
    is the correction at new joint values (tracker frame, m)."""
    rows = data.subset(np.asarray(calibration.robust.kept, bool))
    return choose_residual(calibration.cell or cell, rows, calibration.result, seed=seed)


def sequential_campaign(cell: CellModel, target_std: float, truth: Campaign,
                        seed: int = 0, candidates: int = 400,
                        max_measurements: int = 200) -> SimulatedRun:
    """Measure ``truth``'s robot pose by pose until the largest TCP std at the working
    poses is below ``target_std`` (m, at the upper confidence limit of the noise) or
    ``max_measurements`` are taken, as ``kpi-calib campaign --simulate`` does: an initial
    KPI design, then each next pose the one that lowers the KPI most among ``candidates``
    feasible ones. ``.history[-1]`` holds the final status (``stop_reason``,
    ``tcp_std``, ``measurements``), ``.tcp_estimated`` / ``.tcp_true`` the TCP."""
    design_cell, ctx = campaign_context(cell, seed, candidates)
    settings = CampaignSettings(target_std=target_std, max_measurements=max_measurements)
    campaign = new_campaign(cell, design_cell, ctx, settings, seed)
    return simulate_sequential(campaign, truth.model, truth.true_values,
                               float(np.max(cell.cell.sigma)), np.random.default_rng(seed))


def diagnose(cell: CellModel, data: Measurements) -> CellDiagnosis:
    """Calibrate, test the model's adequacy, rank the effects it may miss and, when one is
    significant, add the best and refit (``.diagnosis.best``, ``.after``), as
    ``kpi-calib diagnose`` does."""
    return diagnose_cell(cell, data)


def design(cell: CellModel, n: int, criterion: str = 'kpi', seed: int = 0,
           candidates: int | None = None, refine: bool | None = None) -> DesignResult:
    """``n`` measurement poses optimal for ``criterion`` (``'kpi'``: the TCP covariance at
    the working poses, eq. (24); ``'A'``, ``'D'``, ``'random'`` …) under the cell's joint
    limits, incidence and collision constraints, checked on the meshes.

    ``candidates`` and ``refine`` (the IPOPT refinement) override the cell's ``design:``
    settings; fewer candidates and no refinement take seconds, not minutes.

    >>> from kpi_calib_ros import api
    >>> cell = api.load_cell()
    >>> poses = api.design(cell, 20, candidates=300, refine=False)
    >>> poses.configurations.shape
    (20, 6)
    """
    settings = dict(cell.cell.design)
    if candidates is not None:
        settings['candidates'] = candidates
    if refine is not None:
        settings['nlp'] = refine
    return design_cell_model(replace(cell, cell=replace(cell.cell, design=settings)), n,
                             criterion, seed)


def validate(cell: CellModel, calibration: CellCalibration | str | Path,
             data: Measurements, register: str | None = None) -> Validation:
    """Predict new measurements with a calibration and test them against its own
    statement of precision (``.holds``, ``.p_value``, ``.residuals``), as
    ``kpi-calib validate`` does.

    ``calibration``: what :func:`calibrate` returned, or a calibration.yaml.
    ``register`` (``'base'``, ``'base+reflector'`` or ``'reflector'``): re-fit the placement on
    the new recording first, for a tracker (or probe) set up again.
    """
    cm, doc = _document(cell, calibration)
    p = (calibration.result.values if isinstance(calibration, CellCalibration)
         else parameter_vector(cm, doc))
    return validate_calibration(cm, p, doc, data, register)


def recalibrate(cell: CellModel, previous: CellCalibration | str | Path, data: Measurements,
                hours: float | None = None) -> Reidentification:
    """A work cycle, as ``identify --prior``: the ``previous`` calibration (what
    :func:`calibrate` returned, or a calibration.yaml) as Gaussian prior, widened by the
    default drift model over ``hours`` (default: from its ``identified_at_ns`` to the
    first stamp of ``data``); the change test first (``.change.consistent``, ``.change.moved``
    largest likelihood ratio first), then, when the new points agree with the prior, the
    calibration identified with it (``.calibration``; None when a change was found:
    nothing is blended)."""
    cm, doc = _document(cell, previous)
    return reidentify(cm, data, cycle_prior(cm, doc, data, hours=hours))


def _document(cell: CellModel, calibration: CellCalibration | str | Path
              ) -> tuple[CellModel, dict[str, Any]]:
    """The cell model and calibration.yaml document of ``calibration``."""
    if isinstance(calibration, CellCalibration):
        cm = calibration.cell or cell
        return cm, add_robust_sections(calibration_document(cm, calibration.result),
                                       calibration)
    doc = read_calibration(calibration)
    return calibrated_model(cell.cell, doc)[0], doc
