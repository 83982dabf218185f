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
:class:`~kpi_calib_ros.io.cell.CellModel`: robot, tracker, working poses, settings) and
measurements as :class:`~kpi_calib_ros.core.measurement.data.Measurements` (joint
readings in rad, tracker points in m); :func:`read_bag` makes them from a recording.
"""
from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

from kpi_calib_ros.app.calibration_document import (
    CellCalibration,
    add_robust_sections,
    calibration_document,
)
from kpi_calib_ros.app.design import design_cell_model
from kpi_calib_ros.app.diagnose import CellDiagnosis, diagnose_cell
from kpi_calib_ros.app.identify import calibrate_cell
from kpi_calib_ros.app.measurements import measurements_from_bag
from kpi_calib_ros.app.validate import (
    calibrated_model,
    parameter_vector,
    read_calibration,
    validate_calibration,
)
from kpi_calib_ros.core.design.optimum import DesignResult
from kpi_calib_ros.core.diagnosis.validation import Validation
from kpi_calib_ros.core.measurement.data import Measurements
from kpi_calib_ros.core.simulation import (
    random_configurations,
    simulate_measurements,
    true_parameters,
)
from kpi_calib_ros.io.cell import DEFAULT_CELL, CellModel, build_cell_model
from kpi_calib_ros.io.cell import load_cell as _read_cell

__all__ = ['Campaign', 'calibrate', 'design', 'diagnose', 'load_cell', 'read_bag',
           'simulate', 'validate']


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


def simulate(cell: CellModel, n: int, seed: int = 0, hidden: str = '',
             values: dict[str, float] | None = None,
             truth: Campaign | None = None) -> Campaign:
    """``n`` measurable poses of a robot drawn near the cell's nominal one, measured with
    the cell's noise.

    ``hidden``: effects the true robot has and ``cell`` may lack (an effect spec, as
    ``--effects``), ``values`` the true values of some parameters (name -> SI value;
    the others drawn from the cell's simulated error magnitudes). ``truth``: measure
    the robot of an earlier campaign again (new poses, same robot).

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
    data = simulate_measurements(model.model, p_true, q, cell.cell.sigma, rng)
    return Campaign(data, model, p_true, model.model.predict(p_true, model.q_work))


def calibrate(cell: CellModel, data: Measurements, model: str | None = None
              ) -> CellCalibration:
    """Identify the robot from ``data`` as ``kpi-calib identify`` does: placement
    registered, outliers that are faults excluded, the model level ``model`` (or the
    cell's ``identification.model``; ``'auto'`` adds the effects that predict new poses
    better), the TCP covariance of eq. (19) and its estimability.

    ``.valid`` says whether it may be published, ``.problems`` why not;
    ``.result`` holds the parameters, their std, the TCP and its covariance.
    """
    return calibrate_cell(cell, data, model)


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
    settings = cell.cell.design
    if candidates is not None:
        settings = replace(settings, candidates=candidates)
    if refine is not None:
        settings = replace(settings, nlp=refine)
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
    doc: dict[str, Any]
    if isinstance(calibration, CellCalibration):
        cm = calibration.cell or cell
        doc = add_robust_sections(calibration_document(cm, calibration.result), calibration)
        p = calibration.result.values
    else:
        doc = read_calibration(calibration)
        cm, _ = calibrated_model(cell.cell, doc)
        p = parameter_vector(cm, doc)
    return validate_calibration(cm, p, doc, data, register)
