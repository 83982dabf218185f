"""Predicted out-of-sample error of a calibration, from the fit itself (no refits).

A new measurement at a fresh pose q misses the calibrated prediction by the tracker noise
(and the joint-reading noise carried to the point, tr(J_q Σ_q J_qᵀ), when the model states
it) plus the error of the identified parameters carried to that pose. To first order, with
C the covariance of the identified parameters (eq. (19)-style, from the stated σ) and
J(q) the point Jacobian of the identified parameters::

    E‖η(q) − h(p̂, q)‖² = s · tr(J(q) C Jᵀ(q)) + Σ_axes σ̂_a²

where σ̂_a² = s σ_a² is the noise estimated from the residuals, s = χ²/dof with the
effective degrees of freedom of the fit (3N − k, or 3N − k_eff with a prior). The
predicted rms over a domain of fresh poses is the square root of the mean over its poses.
Nothing is refitted, so a design in which every parameter is excited only by a few poses
(one joint at a time, the circle point method) is judged by the model actually
identified, not by weaker refits that lose a joint's excitation.

Three domains of fresh poses:

* ``like_measured`` -- the measured configurations measured again (new noise), or for a
  one-joint-at-a-time campaign (the circle point method) new poses along the same sweeps:
  the error a user sees when the robot works where and how it was measured;
* ``within_measured_ranges`` -- configurations uniform in the box of joint values the
  campaign spanned (every joint between its smallest and largest measured value);
* ``over_joint_ranges`` -- configurations uniform within the joint limits.

A domain whose poses need a parameter direction the data did not determine (the gradient
of a fresh prediction w.r.t. every free parameter outside the row space of the data
Jacobian, :func:`kpi_calib_ros.core.estimation.estimability.kpi_estimability`) has no number: it is
"not estimable from this design", with the parameters it misses.

Interval: where the error this one calibration will show is expected to lie (95 %): the
parameter part varies from calibration to calibration (a χ² mixture, most where few
parameter directions dominate, far from the measured poses) and σ̂ is itself uncertain
(s · dof ~ χ²(dof)); the interval combines both, conservatively, and does not cover a
systematic misfit.

Known bias: with an effect the model lacks, the fit absorbs part of the misfit at the
measured poses and the estimate is low. √(3N/dof), the factor a noise-like misfit would
give, is not a bound for a systematic one: a hidden joint compliance on a circle-point
campaign gave 0.56-1.27x the truth like measured and 0.18-0.37x over the joint ranges,
where the misfit grows (bench/results/one_joint_oos.md). When χ² rejects the model the
figures are therefore marked as lower bounds.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.stats

from kpi_calib_ros.core.estimation.estimability import information_rows, kpi_estimability
from kpi_calib_ros.core.estimation.folds import campaign_home, moved_joints
from kpi_calib_ros.core.estimation.least_squares import CalibrationResult, point_sigma_squares
from kpi_calib_ros.core.estimation.prior import Prior
from kpi_calib_ros.core.estimation.residuals import is_adequate
from kpi_calib_ros.core.measurement.data import Measurements
from kpi_calib_ros.core.measurement.tracker import MeasurementModel
from kpi_calib_ros.core.model.robot import RobotModel

DOMAINS = ('like_measured', 'within_measured_ranges', 'over_joint_ranges')
DOMAIN_TEXT = {'like_measured': 'like measured (the measured poses or sweeps)',
               'within_measured_ranges': 'within the measured joint ranges',
               'over_joint_ranges': 'over the joint ranges (limits)'}
NOT_ESTIMABLE = 'not estimable from this design'
LOWER_BOUND = ('the model is not adequate (χ² rejects it): a systematic misfit is predicted '
               'only as noise, so these figures are lower bounds, most of all away from the '
               'measured poses')
FRESH_POSES = 400      # random configurations per sampled domain
INTERVAL_LEVEL = 0.95
METHOD = ('predicted from the fit, no refits: s·J C Jᵀ + σ̂² at fresh poses, '
          'σ̂² = σ² χ²/dof (effective dof)')


@dataclass(frozen=True)
class DomainError:
    """Predicted rms error (m) of new measurements in one domain of fresh poses.

    ``rms_m`` and the interval are NaN when not estimable; ``not_determined`` then names
    the free parameters (at most 5) the domain needs and the data did not determine.
    ``parameter_rms_m`` is the part from the parameter uncertainty alone (no noise).
    """

    domain: str
    estimable: bool
    rms_m: float
    interval_m: tuple[float, float]
    parameter_rms_m: float
    poses: int
    not_determined: tuple[str, ...] = ()

    def text(self) -> str:
        """One line: the predicted rms (µm) with its interval, or why it is not estimable."""
        head = f'{DOMAIN_TEXT[self.domain]}: '
        if not self.estimable:
            return head + NOT_ESTIMABLE + (f' (not determined: {", ".join(self.not_determined)})'
                                           if self.not_determined else '')
        lo, hi = self.interval_m
        return (f'{head}{self.rms_m * 1e6:.1f} µm ({INTERVAL_LEVEL:.0%} interval '
                f'{lo * 1e6:.1f}-{hi * 1e6:.1f} µm; parameters alone '
                f'{self.parameter_rms_m * 1e6:.1f} µm)')

    def to_dict(self) -> dict:
        """YAML-ready form (m); the figures are None when not estimable."""
        ok = self.estimable
        return {'estimable': ok, 'rms_m': float(self.rms_m) if ok else None,
                'interval_m': [float(v) for v in self.interval_m] if ok else None,
                'parameter_rms_m': float(self.parameter_rms_m) if ok else None,
                'poses': int(self.poses),
                'not_determined': list(self.not_determined),
                'text': self.text()}


@dataclass(frozen=True)
class OutOfSample:
    """Predicted out-of-sample error in every domain (see the module docstring).

    ``sigma_hat_m`` (3,) is σ̂ per axis, ``scale`` s = χ²/dof, ``dof`` the effective
    degrees of freedom it rests on.
    """

    domains: dict[str, DomainError]
    sigma_hat_m: np.ndarray
    scale: float
    dof: int
    adequate: bool = True
    method: str = METHOD

    @property
    def caveat(self) -> str:
        """'' when χ² accepts the model; else why the figures are lower bounds."""
        return '' if self.adequate else LOWER_BOUND

    def to_dict(self) -> dict:
        """YAML-ready form: σ̂ (m), the χ² figures and every domain's prediction."""
        return {'method': self.method, 'sigma_hat_m': [float(v) for v in self.sigma_hat_m],
                'chi2_per_dof': float(self.scale), 'dof': int(self.dof),
                'interval_level': INTERVAL_LEVEL, 'model_adequate': bool(self.adequate),
                'caveat': self.caveat,
                **{name: d.to_dict() for name, d in self.domains.items()}}

    def text(self) -> str:
        """Several lines: every domain's prediction, then the caveat if any."""
        return '\n'.join(['predicted out-of-sample error (' + self.method + '):']
                         + [f'  {d.text()}' for d in self.domains.values()]
                         + ([f'  WARNING: {self.caveat}'] if self.caveat else []))


def measured_box(q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Smallest and largest measured value of every joint (n,), (n,)."""
    q = np.atleast_2d(q)
    return q.min(axis=0), q.max(axis=0)


SWEEP_ATOL = 1e-6   # rad (m): a joint within this of its home value has not moved


def joint_sweeps(q: np.ndarray) -> tuple[np.ndarray, dict[int, int]] | None:
    """Return a one-joint-at-a-time campaign's home configuration and poses per swept joint.

    The home configuration as :func:`~kpi_calib_ros.core.estimation.folds.campaign_home`
    finds it and, per swept joint, its number of poses; None when some pose moves more than one
    joint from the home.
    """
    q = np.atleast_2d(q)
    moved = moved_joints(q, SWEEP_ATOL)
    if len(q) < 2 or np.any(moved.sum(axis=1) > 1) or not moved.any():
        return None
    joints, counts = np.unique(np.argmax(moved[moved.any(axis=1)], axis=1), return_counts=True)
    return campaign_home(q, SWEEP_ATOL), {int(j): int(c) for j, c in zip(joints, counts)}


def _fresh_conditions(model: MeasurementModel, data: Measurements, domain: str,
                      configs: np.ndarray, rng: np.random.Generator
                      ) -> tuple[np.ndarray, dict[str, np.ndarray] | None]:
    """Fresh poses under the campaign's conditions, for a model whose effects read covariates.

    The covariates are :attr:`MeasurementModel.inputs`. ``like_measured`` (not a sweep) measures
    every measured row again at its own covariates; every other domain draws each fresh pose's
    covariates from a random measured row. None (the reference condition) when the model reads
    none or the data carry none.
    """
    if not model.inputs or data.covariates is None:
        return configs, None
    values = {name: np.asarray(data.covariates[name], float) for name in model.inputs}
    if domain == 'like_measured' and joint_sweeps(np.atleast_2d(data.q)) is None:
        return np.atleast_2d(data.q), values
    pick = rng.integers(len(data), size=len(configs))
    return configs, {name: v[pick] for name, v in values.items()}


def domain_configurations(model: MeasurementModel, q: np.ndarray, domain: str,
                          rng: np.random.Generator, n: int = FRESH_POSES) -> np.ndarray:
    """Fresh configurations (M, n_joints) of ``domain`` for a campaign measured at ``q``.

    ``like_measured``: a one-joint-at-a-time campaign (:func:`joint_sweeps`) is resampled
    along its sweeps (each swept joint uniform over the values it was measured at, the
    others at home, about ``n`` poses shared as the measured ones are); any other campaign
    gives its distinct measured configurations. ``within_measured_ranges`` /
    ``over_joint_ranges``: ``n`` uniform draws in the measured box / in the joint limits
    (continuous joints on [-π, π]).
    """
    # Drawn in the actuated joints: mimic joints follow their masters.
    robot = model.robot
    return robot.chain_values(_actuated_configurations(
        robot, robot.actuated_values(np.atleast_2d(q)), domain, rng, n))


def _actuated_configurations(robot: RobotModel, q: np.ndarray, domain: str,
                             rng: np.random.Generator, n: int) -> np.ndarray:
    """:func:`domain_configurations` in the actuated joints ``q`` (N, m)."""
    if domain == 'like_measured':
        sweeps = joint_sweeps(q)
        if sweeps is None:
            return np.unique(q, axis=0)
        home, groups = sweeps
        rows = []
        for j, count in groups.items():
            lo, hi = q[:, j][np.abs(q[:, j] - home[j]) > SWEEP_ATOL].min(), \
                q[:, j][np.abs(q[:, j] - home[j]) > SWEEP_ATOL].max()
            lo, hi = min(lo, home[j]), max(hi, home[j])
            block = np.repeat(home[None, :], max(1, round(n * count / len(q))), axis=0)
            block[:, j] = rng.uniform(lo, hi, len(block))
            rows.append(block)
        return np.vstack(rows)
    if domain == 'within_measured_ranges':
        lower, upper = measured_box(q)
    elif domain == 'over_joint_ranges':
        lower, upper = robot.sampling_bounds()
    else:
        raise ValueError(f'domain must be one of {DOMAINS}, got {domain!r}')
    return rng.uniform(lower, upper, size=(n, len(lower)))


def _interval(c0: np.ndarray, m: np.ndarray, noise_ms: float, scale: float,
              dof: int) -> tuple[float, float]:
    """INTERVAL_LEVEL interval (m²) of the mean square error this calibration will show.

    The parameter part δpᵀ M δp, δp ~ N(0, s C), is Σ λ_i χ²₁ with λ the eigenvalues of
    C^½ M C^½: it varies from calibration to calibration around its mean s Σλ, most where
    few parameter directions dominate (far from the measured poses). Its quantiles come
    from the two-moment (Satterthwaite) χ² match; s, from χ²(dof), at its own bounds
    (conservative). The noise part is its expectation (many fresh measurements).
    """
    w, v = np.linalg.eigh((c0 + c0.T) / 2)
    root = v * np.sqrt(np.clip(w, 0.0, None))
    lam = np.clip(np.linalg.eigvalsh(root.T @ m @ root), 0.0, None)
    tail = (1 - INTERVAL_LEVEL) / 2
    s_lo = scale * dof / scipy.stats.chi2.ppf(1 - tail, dof)
    s_hi = scale * dof / scipy.stats.chi2.ppf(tail, dof)
    total, square = float(lam.sum()), float(np.sum(lam ** 2))
    if total <= 0:
        return s_lo * noise_ms, s_hi * noise_ms
    nu, g = total ** 2 / square, square / total
    p_lo = g * scipy.stats.chi2.ppf(tail, nu)
    p_hi = g * scipy.stats.chi2.ppf(1 - tail, nu)
    return s_lo * (noise_ms + p_lo), s_hi * (noise_ms + p_hi)


def out_of_sample_error(model: MeasurementModel, data: Measurements,
                        result: CalibrationResult, free: list[str] | tuple[str, ...] | None = None,
                        prior: Prior | None = None, seed: int = 0,
                        fresh_poses: int = FRESH_POSES,
                        domains: tuple[str, ...] = DOMAINS) -> OutOfSample:
    """Predicted rms error of new measurements at fresh poses, per domain.

    Parameters
    ----------
    model : MeasurementModel
        The model ``result`` was identified with.
    data : Measurements
        The measurements it was identified from (q (N, n) rad; reflector rows).
    result : CalibrationResult
        Its ``covariance`` (identified parameters), ``chi2`` and ``dof``.
    free : sequence of str, optional
        Every free parameter of the fit (identified and dropped; default those of
        ``result.identifiability``): the estimability test uses all of them.
    prior : Prior, optional
        The prior of the fit: its rows count as information in the estimability test.
    seed : int
        Seed of the random fresh configurations.
    fresh_poses : int
        Random configurations per sampled domain.
    """
    q = np.atleast_2d(data.q)
    p = np.asarray(result.values, float)
    sigma = np.broadcast_to(np.asarray(result.sigma, float), (3,))
    if free is None:
        free = list(result.identifiability.kept) + [d.name for d in
                                                    result.identifiability.dropped]
    free = [n for n in model.params.names if n in set(free)]  # vector order
    free_idx = model.params.indices(free)
    est_idx = model.params.indices(result.estimated)
    dof = int(result.dof)
    scale = float(result.chi2 / dof) if dof > 0 else float('nan')
    c0 = np.asarray(result.covariance, float) / float(result.covariance_scale)
    data_jac = information_rows(model, p, q, sigma, free_idx, prior, data.reflector,
                                data.rotation, data.covariates)
    # Fresh poses are predicted as points: rotation rows of tracked bodies (channels from
    # model.n_reflectors on) need a measured rotation and are no length.
    reflectors = (np.array([0]) if data.reflector is None
                  else np.unique(np.asarray(data.reflector, int)))
    reflectors = reflectors[reflectors < model.n_reflectors]
    rng = np.random.default_rng(seed)
    out: dict[str, DomainError] = {}
    for domain in domains:
        configs = domain_configurations(model, q, domain, rng, fresh_poses)
        configs, fresh_z = _fresh_conditions(model, data, domain, configs, rng)
        rows_q = np.repeat(configs, len(reflectors), axis=0)
        ref = np.tile(reflectors, len(configs))
        rows_z = None if fresh_z is None else {k: np.repeat(v, len(reflectors))
                                                for k, v in fresh_z.items()}
        _, jn = model.jacobian(p, rows_q, None, None if data.reflector is None else ref,
                               covariates=rows_z)
        flat = jn.reshape(-1, jn.shape[2])
        if not np.isfinite(scale):
            out[domain] = DomainError(domain, False, float('nan'), (float('nan'),) * 2,
                                      float('nan'), len(configs),
                                      ('no degrees of freedom left for σ̂',))
            continue
        check = kpi_estimability(data_jac, flat[:, free_idx], free,
                                 [str(i) for i in range(len(rows_q))])
        if not check.all_estimable:
            missing: dict[str, int] = {}
            for names in check.missing:
                for name in names:
                    missing[name] = missing.get(name, 0) + 1
            top = tuple(sorted(missing, key=lambda n: -missing[n])[:5])
            out[domain] = DomainError(domain, False, float('nan'), (float('nan'),) * 2,
                                      float('nan'), len(configs), top)
            continue
        je = flat[:, est_idx]                        # (3M, k), m per unit
        # C = (FᵀF)⁻¹ with F weighted by 1/σ: parameter units, J C Jᵀ in m² at the stated σ.
        # Mean over the fresh rows of ‖J δp‖² = δpᵀ M δp, M = mean JᵀJ (per pose: 3 rows).
        m = je.T @ je / (len(je) / 3)
        param_ms = float(np.trace(c0 @ m))
        # A fresh pose's tracker noise: the mean over the measured points of their σ.
        noise_ms = float(np.mean(point_sigma_squares(result, data.reflector,
                                                     model.n_reflectors)))
        if model.joint_sigma is not None:
            # Joint-reading noise at the fresh poses: mean tr(J_q Σ_q J_qᵀ) per point.
            jq = model.joint_jacobian(p, rows_q, None, None if data.reflector is None else ref,
                                      covariates=rows_z)
            noise_ms += float(np.mean(np.sum((jq @ model.joint_noise_map) ** 2, axis=(1, 2))))
        ms_unit = param_ms + noise_ms                # mean square at s = 1
        lo, hi = _interval(c0, m, noise_ms, scale, dof)
        out[domain] = DomainError(domain, True, float(np.sqrt(scale * ms_unit)),
                                  (float(np.sqrt(lo)), float(np.sqrt(hi))),
                                  float(np.sqrt(scale * param_ms)), len(configs))
    if result.point_sigma is not None:
        sigma = np.sqrt(np.mean(np.asarray(result.point_sigma) ** 2, axis=0))
    return OutOfSample(out, sigma * np.sqrt(scale) if np.isfinite(scale) else
                       np.full(3, np.nan), scale, dof, is_adequate(result.p_value))


__all__ = ['DOMAINS', 'DomainError', 'NOT_ESTIMABLE', 'OutOfSample', 'domain_configurations',
           'measured_box', 'out_of_sample_error']
