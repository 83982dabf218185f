"""A simulated campaign on a true robot with hidden effects, calibrated with the
geometric model: the data the diagnosis and general-effect tests look into."""
from __future__ import annotations

from typing import NamedTuple

import numpy as np

from kpi_calib_ros.app.cell_model import CellModel
from kpi_calib_ros.core.diagnosis.effect_signature import augmented_model
from kpi_calib_ros.core.estimation.least_squares import CalibrationResult, identify
from kpi_calib_ros.core.measurement.data import Measurements
from kpi_calib_ros.core.measurement.tracker import MeasurementModel
from kpi_calib_ros.core.simulation import (
    random_configurations,
    simulate_measurements,
    true_parameters,
)
from kpi_calib_ros.io.cell_settings import hidden_effects

SIGMA = 20e-6           # tracker σ per axis, m
FLOOR = SIGMA * np.sqrt(3)  # rms of a fresh point measured by a perfect model, m


class Campaign(NamedTuple):
    """The measurements, the geometric calibration of them, the true parameters and
    model (geometry + hidden effects) and the generator, to draw fresh poses from."""

    data: Measurements
    result: CalibrationResult
    p_true: np.ndarray
    truth: MeasurementModel
    rng: np.random.Generator


def campaign(cm: CellModel, hidden: dict, seed: int, n: int,
             max_incidence: float | None = None) -> Campaign:
    """Simulate a true robot (random geometric errors + ``hidden`` effects, spec ->
    values as in ``simulation.hidden_effects``) measured at ``n`` random poses with σ =
    :data:`SIGMA`, and calibrate it with the geometric model. ``max_incidence`` (rad) of
    the poses drawn: default the simulator's."""
    effects, overrides = hidden_effects(hidden, cm.robot)
    truth = augmented_model(cm.model, effects)
    rng = np.random.default_rng(seed)
    p_true = true_parameters(truth.params, rng, overrides=overrides)
    extra = {} if max_incidence is None else {'max_incidence': max_incidence}
    q = random_configurations(cm.model, cm.model.params.nominal, n, rng, **extra)
    data = simulate_measurements(truth, p_true, q, SIGMA, rng)
    result = identify(cm.model, data, SIGMA, cm.q_work, max_iterations=25)
    return Campaign(data, result, p_true, truth, rng)


def repeated_postures(cm: CellModel, rng: np.random.Generator, postures: int = 40,
                      sessions: int = 3, own_m: float = 2e-4
                      ) -> tuple[Measurements, CalibrationResult, np.ndarray]:
    """``postures`` random postures of a true robot measured in ``sessions`` sessions
    (readings 0.3 mrad apart), each posture with an error of its own (``own_m`` per axis,
    no function of anything), σ = :data:`SIGMA`: the data, their geometric calibration and
    the true parameters."""
    p = true_parameters(cm.model.params, rng)
    q0 = random_configurations(cm.model, p, postures, rng)
    q = np.vstack([q0 + rng.uniform(-3e-4, 3e-4, q0.shape) for _ in range(sessions)])
    own = np.tile(rng.normal(0, own_m, (postures, 3)), (sessions, 1))
    eta = cm.model.predict(p, q) + own + rng.normal(0, SIGMA, (len(q), 3))
    data = Measurements(q=q, eta=eta)
    return data, identify(cm.model, data, SIGMA, cm.q_work, max_iterations=25), p
