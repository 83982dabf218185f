"""A learned residual: the last layer when the physical model is exhausted.

What the physical model (geometry and the effects it carries) leaves of the measured
points is learned as a smooth function of the joint values by a Gaussian process
(fitted by scikit-learn's :class:`~sklearn.gaussian_process.GaussianProcessRegressor`;
a :class:`LearnedResidual` rebuilt from its numbers factors its kernel matrix once and
predicts with that factor): ``δ(q)``, a translation of the tool in the tracker frame (m),
added to every point the physical model predicts at ``q``, the TCP included.

Why a translation of the tool: the reflectors and the TCP are different points of one
rigid tool, so only the part of the misfit that moves the whole tool transfers from the
measured reflectors to the TCP. With several reflectors per pose every reflector's
residual is one sample of δ(q) (the part that differs between them, a rotation of the
tool, shows as noise); tracked rotations are not used.

The kernel is ``(c · RBF(ℓ_1 … ℓ_n) + w) · A``: one length scale per joint (a long one says
the misfit does not depend on that joint), the signal variance c (m²) and a white noise
w (m², per axis), all by maximum likelihood, and the output shape A, a 3 × 3 matrix of mean
eigenvalue 1 shared by the field and the noise (an intrinsic coregionalisation model): the
shape of the residuals' second moment. A misfit is rarely isotropic (it lies along the
directions the joints move the point, and a tracker's range noise differs from its angle
noise); the outputs are whitened by A before the fit, and the field's covariance carries A.
The noise a measurement carries is stated with its own shape N, that of what the field leaves
at the training rows. The prior mean is 0: the physical model.
Far from the training poses the correction returns to 0 and its variance grows to c,
so nothing is extrapolated silently; every prediction also states its distance to the
nearest training pose in length-scale units and whether that is inside the fitted
region (:data:`INSIDE_DISTANCE`). The length scales are bounded by
:data:`SPAN_FACTOR` × each joint's training span, so even a joint the misfit does not
depend on is not trusted beyond the range it was measured over.

The learned residual is chosen only when it predicts held-out regions of joint space
better: cross-validation over folds that hold out whole k-means blocks of poses in
normalised joint space (:func:`~kpi_calib_ros.core.estimation.folds.region_fold_ids`;
a pose's rows stay together) of the whole Gaussian process (its hyperparameters
refitted in every fold) against the physical model's residuals, with a one-sided paired
t-test over the held-out poses (:data:`CHOICE_ALPHA`) and a least gain
(:data:`MIN_GAIN`), so data the physical model explains add nothing.

The predicted TCP then carries two independent parts of uncertainty: the physical
parameters' (their covariance, with the noise the Gaussian process leaves, see
:func:`residual_noise_scale`; far from the training poses their covariance under the
learned misfit field, :func:`field_parameter_covariance`) and the Gaussian process's latent
variance at that pose (:mod:`kpi_calib_ros.core.diagnosis.corrected_tcp`).
"""
from __future__ import annotations

import warnings
from dataclasses import dataclass, field

import numpy as np
import scipy.linalg
import scipy.spatial.distance
import scipy.stats
from sklearn.exceptions import ConvergenceWarning
from sklearn.gaussian_process import GaussianProcessRegressor
from sklearn.gaussian_process.kernels import RBF, ConstantKernel, Kernel, WhiteKernel

from kpi_calib_ros.core.estimation.folds import pose_index, region_fold_ids

# Length scales are bounded above by this factor times each joint's training span
# (span at least MIN_SPAN): beyond its range a joint is not trusted.
SPAN_FACTOR = 2.0
MIN_SPAN = 0.1  # rad (m for a prismatic joint)
# ... and below by this fraction of the upper bound.
MIN_LENGTH_FRACTION = 0.01
# A query within this distance (length-scale units) of a training pose is inside the
# fitted region: the kernel still correlates it with that pose by exp(-1/2) or more.
INSIDE_DISTANCE = 1.0
# Choice: one-sided paired t-test over held-out poses, and a least relative drop of the
# held-out mean square.
CHOICE_ALPHA = 0.01
MIN_GAIN = 0.05
DEFAULT_FOLDS = 5
MIN_POSES = 10  # fewer: no cross-validated choice, never chosen
# The white noise is not allowed below this fraction of the stated σ² (per axis): a
# Gaussian process that explains the noise itself would promise more than the tracker.
MIN_NOISE_FRACTION = 0.25
MAX_VARIANCE_M2 = 1e-2  # (0.1 m)²: bound of the signal and noise variances
# The output shape's eigenvalues are held above this fraction of the largest.
MIN_SHAPE = 0.01
MIN_VARIANCE_M2 = 1e-16
# Added to the kernel matrix's diagonal, as scikit-learn's GaussianProcessRegressor does
# (its ``alpha``) in the fit that chose the hyperparameters: the same posterior.
FIT_JITTER_M2 = 1e-10
# The most training rows a learned residual is fitted on and read back with: a campaign of
# 1000 poses with three reflectors. Fitting costs m³ per likelihood step (1000 rows: ~16 s
# in all, so 3000 some 27 times that) and m² × (number of hyperparameters) memory for its
# gradient (3000 rows, seven joints: 0.6 GiB); reading one back factors its m × m kernel
# matrix once (3000 rows: 69 MiB). Above it identify fits none and says why, so the bound
# covers every file identify writes.
MAX_TRAINING_ROWS = 3000


@dataclass(frozen=True)
class ResidualPrediction:
    """The learned correction at query poses.

    Attributes
    ----------
    mean : (M, 3) ndarray
        δ(q), tracker frame, m.
    covariance : (M, 3, 3) ndarray
        Latent variance of δ(q) times the output shape A (m²): the uncertainty of the
        correction itself,
        without the noise of a measurement.
    distance : (M,) ndarray
        Distance to the nearest training pose in length-scale units.
    inside : (M,) ndarray of bool
        ``distance <= INSIDE_DISTANCE``.
    """

    mean: np.ndarray
    covariance: np.ndarray
    distance: np.ndarray
    inside: np.ndarray


class SingularKernelError(ValueError):
    """The kernel matrix of a learned residual's training rows is not positive definite."""


@dataclass(frozen=True, eq=False)
class LearnedResidual:
    """A fitted Gaussian process of the physical model's residuals over joint space.

    Rebuilt exactly from these fields (the kernel's hyperparameters held fixed), so it
    can be stored as plain numbers and read back without pickle.

    Attributes
    ----------
    joint_names : tuple of str
        The columns of ``q`` (URDF chain order).
    q : (m, n) ndarray
        Joint values of the training rows (rad, m for prismatic joints).
    residual_m : (m, 3) ndarray
        Physical model's residuals η − h(p̂, q) of those rows, tracker frame, m.
    amplitude_m2 : float
        Signal variance c of the kernel: the prior variance of δ far from data, m².
    length_scales : (n,) ndarray
        ARD length scale of each joint (rad, m).
    noise_m2 : float
        White noise variance w per axis (mean over the axes), m².
    output_shape : (3, 3) ndarray, optional
        A, symmetric positive definite with mean eigenvalue 1: the field's covariance is
        c · k · A, and the fit takes the noise's as w · A. Default the identity (isotropic).
    noise_shape : (3, 3) ndarray, optional
        N, the same kind of matrix: the shape of what the fitted field leaves at the
        training rows, so the noise a measurement carries is stated as w · N (a tracker's
        noise and a misfit need not share a shape). Default ``output_shape``.
    """

    joint_names: tuple[str, ...]
    q: np.ndarray
    residual_m: np.ndarray
    amplitude_m2: float
    length_scales: np.ndarray
    noise_m2: float
    output_shape: np.ndarray | None = None
    noise_shape: np.ndarray | None = None
    _factor: np.ndarray = field(init=False, repr=False, compare=False)  # Cholesky, lower
    _weights: np.ndarray = field(init=False, repr=False, compare=False)  # K⁻¹ y, whitened
    _colour: np.ndarray = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        """Check the fields and factor the kernel matrix of the training rows (Cholesky).

        :class:`SingularKernelError` when it is not positive definite, ValueError for
        fields of the wrong shape or range or more than :data:`MAX_TRAINING_ROWS` rows.
        """
        q = np.atleast_2d(np.asarray(self.q, float))
        y = np.asarray(self.residual_m, float).reshape(-1, 3)
        ell = np.asarray(self.length_scales, float).reshape(-1)
        if len(q) != len(y) or q.shape[1] != len(ell) or len(ell) != len(self.joint_names):
            raise ValueError(f'shapes do not fit: q {q.shape}, residual_m {y.shape}, '
                             f'length_scales {ell.shape}, {len(self.joint_names)} joint names')
        if not (np.all(np.isfinite(q)) and np.all(np.isfinite(y))):
            raise ValueError('q and residual_m must be finite')
        if not (self.amplitude_m2 > 0 and self.noise_m2 > 0 and np.all(ell > 0)
                and np.all(np.isfinite(ell))):
            raise ValueError('amplitude_m2, noise_m2 and length_scales must be positive '
                             f'and finite, got {self.amplitude_m2}, {self.noise_m2}, {ell}')
        shape = checked_shape(np.eye(3) if self.output_shape is None else self.output_shape)
        object.__setattr__(self, 'q', q)
        object.__setattr__(self, 'residual_m', y)
        object.__setattr__(self, 'length_scales', ell)
        object.__setattr__(self, 'output_shape', shape)
        object.__setattr__(self, 'noise_shape', shape if self.noise_shape is None
                           else checked_shape(self.noise_shape))
        if len(q) > MAX_TRAINING_ROWS:
            raise ValueError(f'{len(q)} training rows, more than the {MAX_TRAINING_ROWS} a '
                             'learned residual may have')
        whiten, colour = _roots(shape)
        object.__setattr__(self, '_colour', colour)
        # The posterior with the kernel held fixed, as scikit-learn's fit computes it (the
        # same jitter on the diagonal), but the kernel matrix factored once: its fit
        # factors it a second time for the likelihood, which nothing here needs.
        kernel = self.amplitude_m2 * self._correlation(q, q)
        kernel[np.diag_indices_from(kernel)] += self.noise_m2 + FIT_JITTER_M2
        try:
            factor = scipy.linalg.cholesky(kernel, lower=True, check_finite=False)
        except np.linalg.LinAlgError:
            raise SingularKernelError(
                f'the kernel matrix of the {len(q)} training rows is not positive definite '
                f'(amplitude_m2 {self.amplitude_m2:.3g} against noise_m2 '
                f'{self.noise_m2:.3g}: numerically singular)') from None
        del kernel
        object.__setattr__(self, '_factor', factor)
        object.__setattr__(self, '_weights', scipy.linalg.cho_solve(
            (factor, True), y @ whiten, check_finite=False))

    @property
    def noise_covariance_m2(self) -> np.ndarray:
        """(3, 3) covariance of the white noise the learned residual leaves, w · N, m²."""
        return self.noise_m2 * np.asarray(self.noise_shape)

    def predict(self, q: np.ndarray) -> ResidualPrediction:
        """δ(q) with its latent variance, distance and inside flag at (M, n) joint values."""
        q = np.atleast_2d(np.asarray(q, float))
        if q.shape[1] != self.q.shape[1]:
            raise ValueError(f'q must have {self.q.shape[1]} columns '
                             f'({list(self.joint_names)}), got {q.shape}')
        cross = self.amplitude_m2 * self._correlation(q, self.q)  # (M, m)
        v = scipy.linalg.solve_triangular(self._factor, cross.T, lower=True,
                                          check_finite=False)
        latent = np.maximum(self.amplitude_m2 - np.einsum('ij,ij->j', v, v), 0.0)
        distance = self.distance(q)
        return ResidualPrediction((cross @ self._weights) @ self._colour,
                                  latent[:, None, None] * np.asarray(self.output_shape),
                                  distance, distance <= INSIDE_DISTANCE)

    def latent_covariance(self, q: np.ndarray) -> np.ndarray:
        """(M, M) posterior covariance of δ between the queries, per whitened axis.

        The field's covariance between query points i and j is this times the output shape
        A; its diagonal is the latent variance of :meth:`predict`.
        """
        q = np.atleast_2d(np.asarray(q, float))
        v = scipy.linalg.solve_triangular(
            self._factor, self.amplitude_m2 * self._correlation(self.q, q), lower=True,
            check_finite=False)
        cov = self.amplitude_m2 * self._correlation(q, q) - v.T @ v
        np.fill_diagonal(cov, np.maximum(np.diag(cov), 0.0))
        return 0.5 * (cov + cov.T)

    def _correlation(self, a: np.ndarray, b: np.ndarray) -> np.ndarray:
        """(len(a), len(b)) RBF correlation exp(-½ ‖(a_i − b_j)/ℓ‖²) of joint values."""
        return np.exp(-0.5 * scipy.spatial.distance.cdist(
            a / self.length_scales, b / self.length_scales, 'sqeuclidean'))

    def distance(self, q: np.ndarray) -> np.ndarray:
        """Return the (M,) distance of each query to its nearest training pose.

        In length-scale units: ‖(q − q_i)/ℓ‖ minimised over the training poses.
        """
        q = np.atleast_2d(np.asarray(q, float))
        diff = (q[:, None, :] - self.q[None, :, :]) / self.length_scales
        return np.sqrt(np.min(np.sum(diff ** 2, axis=2), axis=1))

    def rotated(self, rotation: np.ndarray) -> LearnedResidual:
        """Return the same field in a tracker frame turned by ``rotation`` (3, 3): R δ(q).

        The field lives in the robot's joint space and moves with the robot; a tracker set up
        again (its base pose re-registered, rotated by R relative to the calibration's) sees
        it turned. Exact: the training residuals turned, the output and noise shapes
        conjugated (R A Rᵀ), so every prediction's mean is R times the old one and its
        covariance R C Rᵀ.
        """
        r = np.asarray(rotation, float).reshape(3, 3)
        if not np.allclose(r @ r.T, np.eye(3), atol=1e-9) or np.linalg.det(r) < 0:
            raise ValueError('rotation must be a proper rotation matrix (3, 3)')
        return LearnedResidual(self.joint_names, self.q, self.residual_m @ r.T,
                               self.amplitude_m2, self.length_scales, self.noise_m2,
                               r @ np.asarray(self.output_shape) @ r.T,
                               r @ np.asarray(self.noise_shape) @ r.T)

    def relevant_joints(self) -> dict[str, float]:
        """Length scale of each joint (rad, m), shortest (most relevant) first."""
        order = np.argsort(self.length_scales)
        return {self.joint_names[i]: float(self.length_scales[i]) for i in order}


def checked_shape(shape: np.ndarray) -> np.ndarray:
    """Return the output shape A as a symmetric (3, 3) array; raise if it is not one.

    A must be symmetric positive definite with mean eigenvalue 1 (trace 3).
    """
    a = np.asarray(shape, float)
    if a.shape != (3, 3) or not np.all(np.isfinite(a)):
        raise ValueError(f'output_shape must be a finite 3 x 3 matrix, got shape {a.shape}')
    a = 0.5 * (a + a.T)
    eig = np.linalg.eigvalsh(a)
    if eig[0] <= 0 or abs(np.trace(a) - 3.0) > 1e-6:
        raise ValueError(f'output_shape must be positive definite with trace 3, got '
                         f'eigenvalues {eig}')
    return a


def _roots(shape: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A^(-1/2) and A^(1/2) of a symmetric positive definite A (row vectors: y @ root)."""
    eig, vec = np.linalg.eigh(shape)
    return (vec / np.sqrt(eig)) @ vec.T, (vec * np.sqrt(eig)) @ vec.T


def output_shape(residual_m: np.ndarray) -> np.ndarray:
    """Return A, the shape of the residuals' second moment, scaled to mean eigenvalue 1.

    Its eigenvalues are held above :data:`MIN_SHAPE` of the largest, so that no direction
    is whitened by more than the residuals can show.
    """
    y = np.asarray(residual_m, float).reshape(-1, 3)
    moment = y.T @ y / max(len(y), 1)
    eig, vec = np.linalg.eigh(0.5 * (moment + moment.T))
    if not np.all(np.isfinite(eig)) or eig[-1] <= 0:
        return np.eye(3)
    eig = np.maximum(eig, MIN_SHAPE * eig[-1])
    eig = 3.0 * eig / np.sum(eig)
    return (vec * eig) @ vec.T


def fixed_kernel(amplitude_m2: float, length_scales: np.ndarray, noise_m2: float) -> Kernel:
    """Return the kernel c · RBF(ℓ) + w with every hyperparameter held fixed."""
    return (ConstantKernel(amplitude_m2, 'fixed') * RBF(length_scales, 'fixed')
            + WhiteKernel(noise_m2, 'fixed'))


def _kernel(q: np.ndarray, y: np.ndarray, noise_m2: float) -> Kernel:
    """Return the kernel to optimise, bounded by the training spans and the stated noise."""
    upper = SPAN_FACTOR * np.maximum(np.ptp(q, axis=0), MIN_SPAN)
    lower = MIN_LENGTH_FRACTION * upper
    start = 0.3 * upper
    floor = max(MIN_NOISE_FRACTION * noise_m2, MIN_VARIANCE_M2)
    signal = float(np.clip(np.mean(y ** 2), MIN_VARIANCE_M2 * 10, MAX_VARIANCE_M2 / 10))
    return (ConstantKernel(signal, (MIN_VARIANCE_M2, MAX_VARIANCE_M2))
            * RBF(start, np.column_stack([lower, upper]))
            + WhiteKernel(float(np.clip(noise_m2, floor * 1.01, MAX_VARIANCE_M2 / 10)),
                          (floor, MAX_VARIANCE_M2)))


def _optimised(q: np.ndarray, y: np.ndarray, kernel: Kernel, restarts: int,
               seed: int) -> GaussianProcessRegressor:
    """Maximum-likelihood fit; a hyperparameter at its bound is a result, not a warning."""
    gp = GaussianProcessRegressor(kernel, n_restarts_optimizer=restarts, normalize_y=False,
                                  random_state=seed)
    with warnings.catch_warnings():
        warnings.simplefilter('ignore', ConvergenceWarning)
        return gp.fit(q, y)


def _from_gp(gp: GaussianProcessRegressor, joint_names: tuple[str, ...], q: np.ndarray,
             y: np.ndarray, shape: np.ndarray, noise_shape: np.ndarray) -> LearnedResidual:
    k = gp.kernel_
    return LearnedResidual(joint_names, q, y, float(k.k1.k1.constant_value),
                           np.atleast_1d(np.asarray(k.k1.k2.length_scale, float)),
                           float(k.k2.noise_level), shape, noise_shape)


def _fitted(q: np.ndarray, y: np.ndarray, kernel: Kernel | None, restarts: int, seed: int,
            noise_m2: float = 0.0) -> tuple[GaussianProcessRegressor, Kernel, np.ndarray,
                                               np.ndarray]:
    """Fit the Gaussian process to ``y`` whitened by its output shape A.

    ``kernel`` None: :func:`_kernel` of the whitened rows with the stated noise ``noise_m2``.
    Returns the fitted process, the kernel it started from, A and A^(1/2) (to colour its
    predictions: ``mean @ colour``).
    """
    shape = output_shape(y)
    whiten, colour = _roots(shape)
    white = y @ whiten
    kernel = _kernel(q, white, noise_m2) if kernel is None else kernel
    return _optimised(q, white, kernel, restarts, seed), kernel, shape, colour


@dataclass(frozen=True)
class ResidualChoice:
    """Whether the learned residual predicts held-out poses better, and the model.

    Attributes
    ----------
    chosen : bool
        The cross-validated test passed: the learned residual is to be used.
    model : LearnedResidual
        Fitted on all rows (also when not chosen, for the record).
    cv_rms_physical_m, cv_rms_learned_m : float
        Held-out rms (m, per point) of the physical model's residuals and of what the
        learned residual, fitted without the pose's fold, leaves of them.
    p_value : float
        One-sided paired t-test over held-out poses that the learned residual lowers the
        squared error.
    folds : int
        Folds over poses.
    reason : str
        The decision in words with its figures.
    """

    chosen: bool
    model: LearnedResidual
    cv_rms_physical_m: float
    cv_rms_learned_m: float
    p_value: float
    folds: int
    reason: str

    def to_dict(self) -> dict:
        """YAML-ready summary (m)."""
        return {'chosen': self.chosen, 'cv_rms_physical_m': self.cv_rms_physical_m,
                'cv_rms_learned_m': self.cv_rms_learned_m, 'p_value': self.p_value,
                'folds': self.folds, 'reason': self.reason,
                'amplitude_m': float(np.sqrt(self.model.amplitude_m2)),
                'noise_m': float(np.sqrt(self.model.noise_m2)),
                'length_scales': self.model.relevant_joints()}


def fit_learned_residual(q: np.ndarray, residual_m: np.ndarray, sigma_m: float | np.ndarray,
                         joint_names: tuple[str, ...], folds: int = DEFAULT_FOLDS,
                         seed: int = 0, restarts: int = 1,
                         alpha: float = CHOICE_ALPHA) -> ResidualChoice:
    """Fit the learned residual on a physical model's residuals and decide on it.

    Parameters
    ----------
    q : (m, n) ndarray
        Joint values of the point rows (rad, m); equal rows are one pose (several
        reflectors) and stay in one fold.
    residual_m : (m, 3) ndarray
        η − h(p̂, q) of those rows, tracker frame, m.
    sigma_m : float or (3,) ndarray
        Stated noise σ per axis, m: the white noise is held above
        :data:`MIN_NOISE_FRACTION` of its mean square.
    joint_names : tuple of str
        Names of the columns of ``q``.
    folds : int
        Folds over poses of the cross-validation (fewer poses: one per fold).
    seed : int
        Folds and optimiser restarts.
    restarts : int
        Extra random starts of the likelihood optimisation.
    alpha : float
        Level of the paired test.

    Returns
    -------
    ResidualChoice
    """
    if folds < 2:
        raise ValueError(f'folds must be at least 2, got {folds}')
    q = np.atleast_2d(np.asarray(q, float))
    y = np.asarray(residual_m, float).reshape(-1, 3)
    if len(q) != len(y):
        raise ValueError(f'q has {len(q)} rows, residual_m {len(y)}')
    if len(q) > MAX_TRAINING_ROWS:
        raise ValueError(f'{len(q)} rows, more than the {MAX_TRAINING_ROWS} a learned residual '
                         'is fitted on (MAX_TRAINING_ROWS)')
    noise = float(np.mean(np.broadcast_to(np.asarray(sigma_m, float), (3,)) ** 2))
    full, kernel, shape, colour = _fitted(q, y, None, restarts, seed, noise)
    # What the field leaves at the training rows is the noise; its shape is the noise's.
    left = y - np.asarray(full.predict(q)).reshape(-1, 3) @ colour
    model = _from_gp(full, tuple(joint_names), q, y, shape, output_shape(left))
    poses, pose = pose_index(q)
    n_poses = int(pose.max()) + 1
    if n_poses < MIN_POSES:
        return ResidualChoice(False, model, float('nan'), float('nan'), 1.0, 0,
                              f'learned residual not chosen: {n_poses} poses, fewer than the '
                              f'{MIN_POSES} a cross-validated choice needs')
    k = min(folds, n_poses)
    # Each fold a region of joint space held out whole (k-means blocks): the correction is
    # chosen only when it predicts where no pose was measured, not only between poses.
    fold = region_fold_ids(poses, k, seed)[pose]
    k = int(fold.max()) + 1
    predicted = np.zeros_like(y)
    for f in range(k):
        test = fold == f
        # The shape and the hyperparameters refitted without the fold, from the full
        # fit's optimum.
        gp, _, _, fold_colour = _fitted(q[~test], y[~test], _with_bounds(full.kernel_, kernel),
                                        0, seed)
        predicted[test] = np.asarray(gp.predict(q[test])).reshape(-1, 3) @ fold_colour
    before = np.bincount(pose, np.sum(y ** 2, axis=1), n_poses)
    after = np.bincount(pose, np.sum((y - predicted) ** 2, axis=1), n_poses)
    gain = before - after
    rms_before = float(np.sqrt(np.sum(before) / len(y)))
    rms_after = float(np.sqrt(np.sum(after) / len(y)))
    if np.all(gain == gain[0]):
        p_value = 1.0 if gain[0] <= 0 else 0.0
    else:
        p_value = float(scipy.stats.ttest_1samp(gain, 0.0, alternative='greater').pvalue)
    relative = 1.0 - rms_after ** 2 / rms_before ** 2 if rms_before > 0 else 0.0
    chosen = bool(p_value < alpha and relative >= MIN_GAIN)
    # The physical model's residuals at the poses (its own fit), against what is left
    # when the field, refitted without each region, predicts that region.
    figures = (f'rms {rms_before * 1e6:.1f} um of the physical model\'s residuals -> '
               f'{rms_after * 1e6:.1f} um with the learned residual predicted from the other '
               f'regions ({k} regions of joint space held out in turn over {n_poses} poses), '
               f'paired test p = {p_value:.2g}')
    if chosen:
        reason = f'learned residual chosen: {figures}'
    else:
        why = (f'p >= {alpha}' if p_value >= alpha
               else f'mean square lowered by {relative:.1%} < {MIN_GAIN:.0%}')
        reason = f'learned residual not chosen ({why}): {figures}'
    return ResidualChoice(chosen, model, rms_before, rms_after, p_value, k, reason)


def _with_bounds(fitted: Kernel, bounded: Kernel) -> Kernel:
    """``bounded`` (the kernel with its bounds) started at ``fitted``'s hyperparameters."""
    return bounded.clone_with_theta(fitted.theta)


def residual_noise_scale(model: LearnedResidual, sigma_m: float | np.ndarray) -> float:
    """Return the factor on the parameters' covariance with the learned residual.

    The parameters' covariance from the stated σ is scaled by the white noise the learned
    residual leaves over the stated σ² (mean per axis), at least 1.
    """
    stated = float(np.mean(np.broadcast_to(np.asarray(sigma_m, float), (3,)) ** 2))
    return max(1.0, model.noise_m2 / stated)


def field_parameter_covariance(model: LearnedResidual, q: np.ndarray,
                               precision_jacobian: np.ndarray, covariance: np.ndarray,
                               noise_scale: float = 1.0) -> np.ndarray:
    """Covariance of the estimated parameters when the misfit is the learned field.

    Least squares treats every row's error as independent noise. The misfit the learned
    residual found is not: it is a smooth field δ(q) over joint space, shared by nearby
    poses, and the fit absorbed part of it into the parameters. With the estimate
    p̂ − p = C₀ Fᵀ W ε (C₀ the covariance from the stated σ, F the Jacobian, W the rows'
    weights) and ε the white noise w plus the field of covariance
    c · k(q_i, q_j) I₃ (the fitted kernel), the parameters' covariance is

        C = s C₀ + C₀ (Σ_ij k_ij c H_iᵀ H_j) C₀,   H_i = W_iᵀ W_i J_i,

    s the noise the learned residual leaves over the stated σ²
    (:func:`residual_noise_scale`). Propagated to a pose far from the training poses it
    is what the parameters' error adds there, where the correction has returned to 0.
    With few, widely spread poses it stays near s C₀; with many correlated ones it says
    what the χ² scaling cannot: correlated rows carry less information than their number.

    The field is taken isotropic here, not with the output shape A: A is the shape of the
    residuals, which lack the part of the field the parameters absorbed (the projection
    onto the Jacobian's columns), so it tells nothing of that part's shape; c, the
    field's variance per axis, is kept.

    Parameters
    ----------
    model : LearnedResidual
        The fitted field (its kernel's c and ℓ).
    q : (m, n) ndarray
        Joint values of the point rows the parameters were identified from.
    precision_jacobian : (m, 3, k) ndarray
        W_iᵀ W_i J_i of those rows: the Jacobian of the k estimated parameters times the
        rows' inverse noise covariance (1/m² per unit of each parameter and m).
    covariance : (k, k) ndarray
        C₀ = (Σ J_iᵀ W_iᵀ W_i J_i)⁻¹, the parameters' covariance from the stated σ.
    noise_scale : float
        s.

    Returns
    -------
    (k, k) ndarray
    """
    q = np.atleast_2d(np.asarray(q, float))
    h = np.asarray(precision_jacobian, float).reshape(len(q), 3, -1)
    c0 = np.asarray(covariance, float)
    kq = model.amplitude_m2 * RBF(model.length_scales)(q)
    meat = sum(h[:, a, :].T @ kq @ h[:, a, :] for a in range(3))
    field = c0 @ meat @ c0
    return noise_scale * c0 + 0.5 * (field + field.T)


__all__ = ['CHOICE_ALPHA', 'INSIDE_DISTANCE', 'LearnedResidual', 'MIN_GAIN',
           'MAX_TRAINING_ROWS', 'ResidualChoice', 'ResidualPrediction', 'SingularKernelError',
           'field_parameter_covariance',
           'checked_shape', 'fit_learned_residual', 'fixed_kernel', 'output_shape',
           'residual_noise_scale']
