"""Simulated cell: a "true" robot, measurable poses and noisy tracker data.

The true robot is the nominal model plus random geometric errors of realistic
size (0.1-1 mm, 0.01-0.1°), a tracker pose a few mm / tenths of a degree off
nominal and a reflector a few mm off. Poses are drawn uniformly in the joint
ranges and kept only where the tracker can see the reflector (incidence angle)
and where an optional extra check (collisions) passes.
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Callable, Mapping, Sequence

import numpy as np

from kpi_calib_ros.core.errors import ConfigError
from kpi_calib_ros.core.measurement.covariates import (
    REFERENCE_TEMPERATURE_C,
    TemperatureSample,
    shift_temperature,
    temperature_covariates,
)
from kpi_calib_ros.core.measurement.data import Measurements
from kpi_calib_ros.core.measurement.pose import noisy_rotations
from kpi_calib_ros.core.measurement.tracker import MeasurementModel
from kpi_calib_ros.core.model.parameters import ParameterSet
from kpi_calib_ros.core.model.robot import Payload, RobotModel

__all__ = [
    'ErrorMagnitudes', 'true_parameters', 'sampling_bounds', 'random_configurations',
    'measurable_batch', 'one_joint_at_a_time', 'simulate_measurements',
    'simulate_pose_measurements', 'equivalent_parameters', 'smooth_joint_map',
    'sensor_temperatures', 'simulate_two_sensor_shift', 'held_deflection',
]

_DEG = np.pi / 180.0


@dataclass(frozen=True)
class ErrorMagnitudes:
    """Ranges [low, high] of |error| drawn uniformly with a random sign (m or rad)."""

    placement_translation: tuple[float, float] = (1e-4, 1e-3)
    placement_rotation: tuple[float, float] = (0.01 * _DEG, 0.1 * _DEG)
    joint_offset: tuple[float, float] = (0.01 * _DEG, 0.1 * _DEG)
    base_translation: tuple[float, float] = (1e-3, 5e-3)
    base_rotation: tuple[float, float] = (0.1 * _DEG, 0.5 * _DEG)
    reflector: tuple[float, float] = (1e-3, 3e-3)


def _range_for(name: str, mag: ErrorMagnitudes) -> tuple[float, float] | None:
    if name.startswith('base.'):
        return mag.base_translation if name[5:] in ('x', 'y', 'z') else mag.base_rotation
    if name.startswith('reflector.'):
        # a tracked body's identified orientation (reflector.<name>.rx/ry/rz, rad) is off by
        # a mounting's rotation, its offset (m) by a few millimetres
        return mag.base_rotation if name.endswith(('.rx', '.ry', '.rz')) else mag.reflector
    if '.placement.t' in name:
        return mag.placement_translation
    if '.placement.r' in name:
        return mag.placement_rotation
    if name.endswith('.offset'):
        return mag.joint_offset
    return None


def true_parameters(params: ParameterSet, rng: np.random.Generator,
                    magnitudes: ErrorMagnitudes = ErrorMagnitudes(),
                    overrides: dict[str, float] | None = None) -> np.ndarray:
    """Nominal values plus random errors for every geometric parameter.

    Parameters without a range (effect parameters) keep their nominal value
    unless given in ``overrides`` (name -> true value).
    """
    p = params.nominal.copy()
    for i, name in enumerate(params.names):
        bounds = _range_for(name, magnitudes)
        if bounds is not None:
            p[i] += rng.choice([-1.0, 1.0]) * rng.uniform(*bounds)
    for name, value in (overrides or {}).items():
        p[params.index(name)] = value
    return p


def sampling_bounds(model: MeasurementModel) -> tuple[np.ndarray, np.ndarray]:
    """Joint ranges to sample from: limits, with continuous joints on [-π, π]."""
    lower = np.where(np.isfinite(model.robot.lower), model.robot.lower, -np.pi)
    upper = np.where(np.isfinite(model.robot.upper), model.robot.upper, np.pi)
    return lower, upper


def random_configurations(model: MeasurementModel, p: np.ndarray, n: int,
                          rng: np.random.Generator, max_incidence: float = 30 * _DEG,
                          accept: Callable[[np.ndarray], np.ndarray] | None = None,
                          max_draws: int = 2_000_000) -> np.ndarray:
    """``n`` configurations uniform in the joint ranges that the tracker can measure.

    Parameters
    ----------
    model : MeasurementModel
    p : (n_p,) ndarray
        Parameters used to evaluate the incidence angle (nominal for planning).
    max_incidence : float
        Largest angle between reflector axis and beam, rad (eq. 4).
    accept : callable, optional
        Extra filter: (M, n) configurations -> (M,) bool (e.g. collision-free).

    Raises
    ------
    ConfigError
        If fewer than ``n`` feasible poses are found in ``max_draws`` draws.
    """
    found: list[np.ndarray] = []
    count, drawn = 0, 0
    batch = max(256, 8 * n)
    cos_limit = np.cos(max_incidence)
    while count < n:
        if drawn >= max_draws:
            raise ConfigError('tracker.base_in_tracker',
                              f'only {count} of {n} measurable poses in {drawn} random draws; '
                              'check the tracker pose, reflector.axis, reflector.max_incidence, '
                              'the joint limits and collision.ignore_pairs')
        cand = measurable_batch(model, p, rng, batch, cos_limit)
        drawn += batch
        if accept is not None and len(cand):
            cand = cand[accept(cand)]
        found.append(cand)
        count += len(cand)
    return np.vstack(found)[:n]


def measurable_batch(model: MeasurementModel, p: np.ndarray, rng: np.random.Generator,
                     batch: int, cos_limit: float) -> np.ndarray:
    """Return the measurable ones among ``batch`` uniform draws in the joint ranges.

    Draws (batch, n) configurations uniformly within :func:`sampling_bounds` and
    keeps those whose incidence cosine at parameters ``p`` is ``>= cos_limit``
    (eq. 4). The one sampler of the simulator, the design candidates and the
    collision-pair screening.
    """
    q = model.robot.sample_configurations(rng, batch)  # mimic joints follow their masters
    return q[model.incidence_cos(p, q) >= cos_limit]


def one_joint_at_a_time(model: MeasurementModel, home: np.ndarray, per_joint: int,
                        rng: np.random.Generator | None = None, span: float = 1.0,
                        p: np.ndarray | None = None, max_incidence: float | None = None,
                        max_draws: int = 100_000) -> np.ndarray:
    """Draw a one-joint-at-a-time campaign (the circle point method).

    Each joint is swept alone from ``home``, the other joints held at their home values.

    Parameters
    ----------
    model : MeasurementModel
    home : (n,) ndarray
        Home configuration, rad (m for prismatic joints).
    per_joint : int
        Poses per joint.
    rng : numpy.random.Generator, optional
        Draw each joint's values uniformly over its sweep; without it they are evenly
        spaced over the sweep (end points included).
    span : float
        The sweep of joint j is ``span`` × its range (:func:`sampling_bounds`), centred
        on its home value and shifted inside the limits; 1: the whole range.
    p, max_incidence : ndarray, float, optional
        With both, keep only poses the tracker can measure at parameters ``p`` (eq. 4,
        rad); default every pose (a reflector seen from every side, as several
        reflectors or an active target give).

    Returns
    -------
    (n * per_joint, n) ndarray
        Joint 0's poses first, then joint 1's, ...

    Raises
    ------
    ConfigError
        A joint has fewer than ``per_joint`` measurable poses in its sweep.
    """
    home = np.asarray(home, float)
    if per_joint < 1 or not 0 < span <= 1:
        raise ValueError(f'per_joint must be >= 1 and span in (0, 1], got {per_joint}, {span}')
    lower, upper = sampling_bounds(model)
    cos_limit = None if p is None or max_incidence is None else float(np.cos(max_incidence))
    check = cos_limit is not None
    rows = []
    for j in range(len(home)):
        width = span * (upper[j] - lower[j])
        lo = min(max(lower[j], home[j] - width / 2), upper[j] - width)
        count = per_joint if not check else min(max_draws, 64 * per_joint)
        values = (np.linspace(lo, lo + width, count) if rng is None
                  else rng.uniform(lo, lo + width, count))
        q = np.repeat(home[None, :], count, axis=0)
        q[:, j] = values
        if p is not None and cos_limit is not None:
            q = q[model.incidence_cos(p, q) >= cos_limit]
            if len(q) < per_joint:
                raise ConfigError('reflector.max_incidence',
                                  f'only {len(q)} measurable poses of joint {j} swept alone '
                                  f'from the home pose {np.round(home, 3).tolist()}; choose '
                                  'another home pose or allow a larger incidence')
            q = q[np.round(np.linspace(0, len(q) - 1, per_joint)).astype(int)]
        rows.append(q)
    return np.vstack(rows)


def simulate_measurements(model: MeasurementModel, p_true: np.ndarray, q: np.ndarray,
                          sigma: float | np.ndarray, rng: np.random.Generator,
                          joint_sigma: float | np.ndarray | None = None,
                          covariates: Mapping[str, np.ndarray] | None = None,
                          stamps_ns: np.ndarray | None = None) -> Measurements:
    """Tracker points h(p_true, q) + N(0, σ²) per axis.

    With ``joint_sigma`` (rad, scalar or (n,) in chain order, or a (n, k) noise map S as
    :class:`MeasurementModel` keeps it) the joint readings are not exact: the measurements
    carry the readings q + N(0, joint_sigma²) (q + S ε) of the true joints q
    (drawn after the tracker noise, so the points are the same as without it).
    ``covariates`` (name -> (N,), e.g. a temperature ramp over a shift,
    :func:`kpi_calib_ros.core.measurement.covariates.shift_temperature`) drive the true model's
    effects that read them (a hidden thermal effect) and are recorded with the rows, as are
    ``stamps_ns`` (N,).
    """
    q = np.atleast_2d(q)
    clean = model.predict(p_true, q, covariates=covariates)
    noise = rng.normal(size=clean.shape) * np.broadcast_to(np.asarray(sigma, float), (3,))
    recorded = None if covariates is None else {k: np.asarray(v, float).copy()
                                                for k, v in covariates.items()}
    if joint_sigma is not None:
        given = np.asarray(joint_sigma, float)
        if given.ndim == 2:  # a noise map (MeasurementModel's): q + S ε
            q = q + rng.normal(size=(len(q), given.shape[1])) @ given.T
        else:
            q = q + rng.normal(size=q.shape) * np.broadcast_to(given, (q.shape[1],))
    return Measurements(q=q, eta=clean + noise, stamps_ns=stamps_ns, covariates=recorded)


def sensor_temperatures(stamps_ns: np.ndarray, celsius: Mapping[str, np.ndarray],
                        reference_c: float = REFERENCE_TEMPERATURE_C) -> dict[str, np.ndarray]:
    """Return the covariates of rows stamped ``stamps_ns`` (N,) from several sensors' readings.

    ``celsius`` maps each sensor's frame id to its reading at every stamp, °C (N,) (e.g.
    :func:`~kpi_calib_ros.core.measurement.covariates.shift_temperature` with a rise of its
    own per link). The readings go through
    :func:`~kpi_calib_ros.core.measurement.covariates.temperature_covariates` as recorded
    samples at the rows' stamps, so the covariates are those a recording of the same readings
    gives: ``temperature.<frame_id>``, each sensor's ``delta_temperature.<frame_id>`` and their
    mean ``delta_temperature`` (K). Readings of one sensor at one stamp are averaged.
    Pass them as ``covariates`` to :func:`simulate_measurements`.

    Raises
    ------
    ValueError
        A reading array of another length than the stamps, or not finite.
    """
    stamps = np.asarray(stamps_ns, dtype=np.int64).reshape(-1)
    samples = []
    for frame_id, values in celsius.items():
        values = np.asarray(values, float).reshape(-1)
        if values.shape != stamps.shape or not np.all(np.isfinite(values)):
            raise ValueError(f'sensor {frame_id!r} needs {len(stamps)} finite readings (°C), '
                             f'one per stamp, got {values.shape}')
        samples += [TemperatureSample(int(t), frame_id, float(c)) for t, c in zip(stamps, values)]
    return temperature_covariates(stamps, samples, tuple(celsius), reference_c)


def simulate_two_sensor_shift(model: MeasurementModel, p_true: np.ndarray, n: int,
                              sigma: float | np.ndarray,
                              rng: np.random.Generator) -> Measurements:
    """Simulate ``n`` random poses measured over an 8 h shift in which two links warm differently.

    The poses are drawn by :func:`random_configurations` (at ``model``'s nominal
    parameters) and stamped at uniform random times of the shift (ns from its start,
    sorted). A sensor per link reads its temperature (°C): ``upper_arm`` warms from
    20 °C by 10 K, 95 % of it after 4 h
    (:func:`~kpi_calib_ros.core.measurement.covariates.shift_temperature`); ``forearm``
    swings ±3 K around 20 °C once over the shift and warms by 2 K, 95 % of it after
    1 h. Their covariates (:func:`sensor_temperatures`: ``temperature.<frame_id>``,
    ``delta_temperature.<frame_id>`` and the mean ``delta_temperature``, K) drive the
    effects of ``model`` that read them and are recorded with the rows
    (:func:`simulate_measurements`). The scenario of the thermal link growth read per
    sensor against the mean of the sensors (``bench/thermal_sensors.py`` and its test).

    Parameters
    ----------
    model : MeasurementModel
        The true model (geometry and effects).
    p_true : (n_p,) ndarray
        Its true parameters.
    n : int
        Number of poses.
    sigma : float or (3,) ndarray
        Tracker σ per axis, m.
    rng : numpy.random.Generator
        Drawn from in order: poses, stamps, tracker noise.

    Returns
    -------
    Measurements
        ``n`` rows with their stamps and temperature covariates.
    """
    q = random_configurations(model, model.params.nominal, n, rng)
    stamps = (np.sort(rng.uniform(0, 8, n)) * 3600 * 10**9).astype(np.int64)
    hours = stamps / 3.6e12
    upper = shift_temperature(stamps, 20.0, 10.0, 4.0, start_ns=0)
    fore = (20.0 + 3.0 * np.sin(2 * np.pi * hours / 8.0)
            + shift_temperature(stamps, 0.0, 2.0, 1.0, start_ns=0))
    cov = sensor_temperatures(stamps, {'upper_arm': upper, 'forearm': fore})
    return simulate_measurements(model, p_true, q, sigma, rng, covariates=cov,
                                 stamps_ns=stamps)


def simulate_pose_measurements(model: MeasurementModel, p_true: np.ndarray, q: np.ndarray,
                               sigma: float | np.ndarray, sigma_rotation: float,
                               rng: np.random.Generator) -> Measurements:
    """Simulate every row measuring the poses ``q`` (N, n) gives, with noise.

    The rows are those of :meth:`MeasurementModel.pose_measurements`: each reflector's point
    ``h(p_true, q) + N(0, σ²)`` per axis, each tracked body's rotation ``R · exp(ω)``,
    ``ω ~ N(0, σ_rot² I)`` (rad) in the body frame. For one reflector the same draws as
    :func:`simulate_measurements`.
    """
    rows = model.pose_measurements(p_true, q)
    points = np.asarray(rows.reflector) < model.n_reflectors
    eta = rows.eta.copy()
    eta[points] += (rng.normal(size=(int(points.sum()), 3))
                    * np.broadcast_to(np.asarray(sigma, float), (3,)))
    rotation = rows.rotation
    if rotation is not None and not points.all():
        rotation = rotation.copy()
        rotation[~points] = noisy_rotations(rotation[~points], sigma_rotation, rng)
        eta[~points] = 0.0
    return dataclasses.replace(rows, eta=eta, rotation=rotation)


def equivalent_parameters(model: MeasurementModel, p_true: np.ndarray, kept: tuple[str, ...],
                          p_start: np.ndarray, q_samples: np.ndarray,
                          iterations: int = 20) -> tuple[np.ndarray, float]:
    """Express the true robot in an identified (reduced) parameterisation.

    Dropped parameters stay at ``p_start``; the kept ones absorb the true
    errors of the dropped ones. This is the truth an estimate of the kept
    parameters should be compared with. Found by a noiseless Gauss-Newton fit
    of the reduced model to ``h(p_true, q_samples)``.

    Returns
    -------
    p_equiv : (n_p,) ndarray
    max_residual_m : float
        Largest remaining point error of the fit: how exactly the reduced model
        reproduces the true robot (nonlinear effects of the dropped errors).
    """
    idx = model.params.indices(kept)
    target = model.predict(p_true, q_samples)
    p = np.array(p_start, dtype=float)
    for _ in range(iterations):
        pred, jac = model.jacobian(p, q_samples)
        r = (target - pred).ravel()
        f = jac.reshape(-1, len(p))[:, idx]
        scale = np.linalg.norm(f, axis=0)
        step, *_ = np.linalg.lstsq(f / scale, r, rcond=None)
        p[idx] += step / scale
        if np.max(np.abs(step)) < 1e-15:
            break
    residual = target - model.predict(p, q_samples)
    return p, float(np.max(np.linalg.norm(residual, axis=1)))


def smooth_joint_map(q: np.ndarray, joints: tuple[int, int], amplitude_m: float,
                     phase: np.ndarray) -> np.ndarray:
    """Return a smooth tool displacement (N, 3) (m, tracker frame) that no library effect describes.

    It depends on two joints only: each axis a product of sines of the two angles,
    ``amplitude_m`` its largest size, ``phase`` (6,) rad.

    The unknown misfit the learned residual (:mod:`kpi_calib_ros.core.diagnosis.learned_residual`)
    is tested on.
    """
    q = np.atleast_2d(np.asarray(q, float))
    a, b = q[:, joints[0]], q[:, joints[1]]
    phase = np.asarray(phase, float).reshape(3, 2)
    return amplitude_m * np.column_stack([np.sin(1.3 * a + ph[0]) * np.cos(1.1 * b + ph[1])
                                          for ph in phase])


def held_deflection(robot: RobotModel, compliance: np.ndarray, q: np.ndarray,
                    payloads: Sequence[Payload] | None = None
                    ) -> tuple[np.ndarray, np.ndarray]:
    """Return the deflection δ = c·τ(q + δ) a joint of compliance ``c`` (n,) holds, exactly.

    By fixed point on the robot's gravity torques (Pinocchio, each row with its
    ``payloads``, None: the cell's) to 1e-14 rad: a truth independent of the model's
    linearised torque at the deflected configuration
    (:mod:`kpi_calib_ros.core.measurement.deflection`). Returns δ (N, n) and the torques
    there (N, n), to give a model as measured ones.
    """
    q = np.atleast_2d(np.asarray(q, float))
    c = np.asarray(compliance, float)
    d = np.zeros_like(q)
    for _ in range(100):
        bent = c * np.atleast_2d(robot.gravity_torques(q + d, payloads))
        if np.max(np.abs(bent - d)) < 1e-14:
            d = bent
            break
        d = bent
    return d, np.atleast_2d(robot.gravity_torques(q + d, payloads))
