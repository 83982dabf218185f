"""Validation of a calibration on new measurements.

Do the new points fall within the errors the calibration itself predicts?

A new point ``η_i`` is predicted as ``h(p̂, q_i)``; its error is the measurement noise
plus the propagated uncertainty of the identified parameters,

    C_i = Σ + J_i C_p J_iᵀ        (J_i = ∂h/∂p of the identified parameters at q_i),

plus J_q Σ_q J_qᵀ when the model states joint-reading noise,

per point. The new points' noise is independent of the fit, but every new point carries
the same error of the identified parameters, so the points are not independent of each
other: χ² is ``eᵀ V⁻¹ e``, ``e`` every residual stacked (3N) and
``V = blockdiag(C_i − J_i C_p J_iᵀ) + J C_p Jᵀ`` their joint covariance (the noise per point
plus the shared parameters' part), which follows χ²(3N) when the calibration holds. Summed
point by point (``Σ_i r_iᵀ C_i⁻¹ r_i``) it would not: a calibration from few poses, or
validated far from them, would fail on many new points for no fault of its own.

Σ is the noise the calibration showed: the stated σ, or
σ̂ = σ·√(χ²/dof) when its model was not adequate and its covariance was scaled by that
(:mod:`kpi_calib_ros.core.estimation.precision`), as its predicted out-of-sample error
(:mod:`kpi_calib_ros.core.diagnosis.out_of_sample`) and a re-identification from it take it. The
verdict is this test at the adequacy level.

The new poses fall in three groups, reported apart (the groups of a held-out protocol):
*outside* the joint ranges the calibration was identified on, beyond a reading's
tolerance (:func:`range_tolerance`: a joint held at one angle reads a little differently each
time) (extrapolation, where a geometric model fails first); *repeated*, inside them and the
same pose as a training pose
(:func:`~kpi_calib_ros.core.measurement.replicates.same_pose`: the same configuration measured
again: their error is the calibration's misfit at a pose it was fitted to plus the robot's and
the instrument's repeatability between the campaigns, no floor: on the real UR10's Series D
split in halves, 25 points repeated 0.352 mm from the half the calibration was fitted to,
while the two measurements of those poses differ by 0.079 mm); *new* poses inside the ranges
(generalisation).

A validation recording is usually made with the tracker (or the probe) set up again, so
its points are in another tracker frame. With ``registered`` the base pose (and, if
named, the reflector offsets) are re-fitted on the new recording alone
(:func:`kpi_calib_ros.core.estimation.registration.reregister`, least squares with the other
values held: the residuals and rms reported). The calibration's uncertainty of those
parameters is absorbed by the fit, that of the others is common to every new point, and
χ² is the minimum over them of ``eᵀ V⁻¹ e`` with the full covariance V
(noise plus ``J_u C_u J_uᵀ`` across all points), which follows χ²(3N − r), r the rank
of the re-fitted parameters' Jacobian: the degrees of freedom the registration costs.
The per-point distances keep the per-point ``C_i`` of the other parameters.

*The estimable combination.* Position data cannot separate every parameter: identify held
some fixed (``dropped_parameters``, a choice of gauge) and ``C_p`` is that of the others. The
same fit in another gauge (other parameters held) predicts the training points alike, but a
new point's ``J_i C_p J_iᵀ`` is the same in every gauge only for the part of its gradient
(over every free parameter, the held ones too) in the row space of the training Jacobian F
(:mod:`kpi_calib_ros.core.estimation.estimability`). With the training poses known
(``free`` and ``training_q`` of :func:`validate`, :func:`training_row_space`) the gradient
is projected on that row space first and only the projection enters ``C_i``: a joint read
1e-4 rad off its training value gives no gauge a lever on the prediction (one fit gave 1.58
and 81.9 mm of predicted std in two gauges). A point whose gradient leaves the row space by
more than :data:`PREDICTION_TOLERANCE` (relative) is *not determined* by the training poses: the
calibration does not predict it, it gets no predicted std and no part in χ², and is
counted apart.
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np
import scipy.stats

from kpi_calib_ros.core.errors import DataError
from kpi_calib_ros.core.estimation.identifiability import DEFAULT_TOLERANCE
from kpi_calib_ros.core.estimation.registration import Reregistration, horn, reregister
from kpi_calib_ros.core.estimation.residuals import ADEQUACY_ALPHA
from kpi_calib_ros.core.measurement.data import Measurements, row_sigma
from kpi_calib_ros.core.measurement.payload import gravity_input
from kpi_calib_ros.core.measurement.replicates import (
    SAME_POSE_TOLERANCE,
    same_pose,
    same_turn,
)
from kpi_calib_ros.core.measurement.tracker import MeasurementModel
from kpi_calib_ros.core.measurement.weighting import row_torques

__all__ = ['PREDICTION_TOLERANCE', 'TrainingSpan', 'Validation', 'range_tolerance',
           'shared_chi2', 'training_row_space', 'validate', 'set_up_moved',
           'SET_UP_MOVED_FRACTION', 'NominalOnNew', 'against_nominal_on_new', 'corrected_rms',
           'HARM_Z', 'nominal_validation']

# Largest relative part of a new point's gradient outside the training row space
# (column-equilibrated, as core.estimation.estimability) for its prediction to count as
# determined. A joint read 1e-4 rad from its training value leaves ~1e-4 (estimable: the
# calibration was made there);
# a motion no training pose made (a joint held in training) leaves O(0.1-1).
PREDICTION_TOLERANCE = 1e-3


@dataclass(frozen=True)
class TrainingSpan:
    """The row space of a calibration's training Jacobian over its free parameters.

    free : (f,) int ndarray, parameter indices (the identified ones and those held by the
    identifiability selection); scale : (f,) column norms of the training Jacobian (the
    equilibration); basis : (r, f) orthonormal rows spanning its row space in equilibrated
    coordinates.
    """

    free: np.ndarray
    scale: np.ndarray
    basis: np.ndarray

    def project(self, jac: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Split new points' Jacobians (N, 3, n_p) into the estimable part and a verdict.

        Returns the (N, 3, n_p) Jacobian whose free columns are projected on the row space
        (other columns unchanged: fixed parameters carry no covariance), and per point the
        largest relative residual (N,) of its three rows.
        """
        g = jac[:, :, self.free] / self.scale
        inside = (g @ self.basis.T) @ self.basis
        norms = np.linalg.norm(g, axis=2)
        rel = np.linalg.norm(g - inside, axis=2) / np.where(norms > 0, norms, 1.0)
        out = np.array(jac, dtype=float, copy=True)
        out[:, :, self.free] = inside * self.scale
        return out, rel.max(axis=1)


def training_row_space(model: MeasurementModel, p: np.ndarray, q: np.ndarray,
                       free: np.ndarray,
                       rank_tolerance: float = DEFAULT_TOLERANCE) -> TrainingSpan | None:
    """Return the :class:`TrainingSpan` of training poses ``q`` (M, n) at ``p`` over ``free``.

    Every reflector is taken at every pose (the calibration file keeps the poses, not which
    reflector each point was): a row space at least as wide as the training's. None when the
    model's effects read covariates or it measures orientations (the training's covariate
    values and rotations are not kept), or no pose is given.
    """
    q = np.atleast_2d(np.asarray(q, float))
    if not q.size or model.inputs or model.orientations:
        return None
    n_ref = max(model.n_reflectors, 1)
    poses = np.repeat(q, n_ref, axis=0)
    reflector = np.tile(np.arange(n_ref), len(q))
    tau = gravity_input(model.robot, poses) if model.uses_torque else None
    _, jac = model.jacobian(np.asarray(p, float), poses, tau, reflector)
    free = np.asarray(free, dtype=int)
    f = jac[:, :, free].reshape(-1, len(free))
    col = np.linalg.norm(f, axis=0)
    scale = np.where(col > 0, col, 1.0)
    _, sv, vt = np.linalg.svd(f / scale, full_matrices=False)
    basis = vt[sv > rank_tolerance * sv[0]] if len(sv) and sv[0] > 0 else vt[:0]
    return TrainingSpan(free, scale, basis)


@dataclass(frozen=True)
class Validation:
    """Prediction of new measurements by a calibration.

    Attributes
    ----------
    residuals : (N, 3) ndarray
        η − h(p̂, q) per new measurement, tracker frame (m).
    predicted_std : (N,) ndarray
        sqrt(trace C_i / 3): the calibration's own predicted error per axis (m).
    mahalanobis : (N,) ndarray
        sqrt(r_iᵀ C_i⁻¹ r_i) per point.
    outside : (N,) bool ndarray
        Pose beyond the training joint range of some joint.
    repeated : (N,) bool ndarray
        Pose inside the ranges and the same pose as a training pose
        (:func:`~kpi_calib_ros.core.measurement.replicates.same_pose`; all False when the training
        poses are not known).
    chi2, dof, p_value : float, int, float
        dof is 3N less the degrees of freedom the re-registration took; with none left
        (a re-registration as large as the recording) p_value is NaN: the test cannot be
        made (``tested`` False).
    holds : bool
        Tested and p_value >= alpha.
    registration : Reregistration or None
        The placement re-fitted on the new recording (``registered`` of :func:`validate`).
    identical : (N,) bool ndarray or None
        The pose's joint readings equal a training pose's bit for bit: no encoder reads a
        pose measured again so, these are the training measurements themselves.
    determined : (N,) bool ndarray
        The point's prediction is determined by the training poses (module text, the
        estimable combination); an undetermined point has NaN ``predicted_std`` and
        ``mahalanobis`` and no part in χ². All True without the training poses.
    noise_ratio : float
        sqrt(Σ r_iᵀ N_i⁻¹ r_i / dof), N_i the point's stated noise alone (the tracker's and
        the joint readings', without ``noise_scale`` and the parameters' part): how many
        times the stated noise the residuals are (NaN without dof). χ²/dof cannot say it: its
        covariance holds the noise the calibration showed (σ·√scale) and the parameters'
        part too.
    """

    residuals: np.ndarray
    predicted_std: np.ndarray
    mahalanobis: np.ndarray
    outside: np.ndarray
    repeated: np.ndarray
    chi2: float
    dof: int
    p_value: float
    alpha: float
    registration: Reregistration | None = None
    noise_ratio: float = float('nan')
    determined: np.ndarray | None = None
    identical: np.ndarray | None = None

    @property
    def tested(self) -> bool:
        """Whether the χ² test could be made.

        It needs degrees of freedom left after the re-registration (with none, the re-fit
        absorbs every residual and χ² = 0 says nothing about the calibration) and a point
        the training determines.
        """
        return bool(self.dof > 0 and np.isfinite(self.p_value))

    @property
    def holds(self) -> bool:
        """Whether the calibration passes: tested, p-value at least ``alpha``."""
        return bool(self.tested and self.p_value >= self.alpha)

    @property
    def rms_m(self) -> float:
        """sqrt(mean ‖r_i‖²) over every new point (m)."""
        return _rms(self.residuals)

    def rms_where(self, mask: np.ndarray) -> float:
        """Root mean square (m) over the points of ``mask`` (NaN when there are none)."""
        return _rms(self.residuals[mask]) if np.any(mask) else float('nan')


def range_tolerance(model: MeasurementModel) -> np.ndarray:
    """(n,) how far (rad, m) beyond a training joint range a reading still lies inside it.

    A joint read again at the same angle differs by the reading's own scatter (encoder
    counts, servo settling): a joint held at 0 in training reads 1e-4 rad in the new
    recording and is not outside. The tolerance of a reading is that of the same pose
    (:data:`~kpi_calib_ros.core.measurement.replicates.SAME_POSE_TOLERANCE`), or three
    times the joint's stated reading noise (``noise.joint_sigma``) when that is larger.
    """
    tol = np.full(model.robot.n_joints, SAME_POSE_TOLERANCE)
    if model.joint_sigma is not None:
        tol = np.maximum(tol, 3.0 * model.joint_sigma)
    return tol


def _rms(r: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.sum(r ** 2, axis=1))))


def shared_chi2(residuals: np.ndarray, jacobian: np.ndarray, covariance: np.ndarray,
                noise: np.ndarray) -> float:
    """Return ``eᵀ V⁻¹ e`` of points that share the parameters' error.

    ``V = blockdiag(noise_i) + J C Jᵀ``; computed as the least-squares minimum over a
    correction ``δ = R u`` of the parameters (``C = R Rᵀ``) of
    ``Σ_i ‖L_i⁻¹ (e_i − J_i R u)‖² + ‖u‖²`` (``noise_i = L_i L_iᵀ``), which equals it
    without forming V.

    Parameters
    ----------
    residuals : (N, 3) ndarray
        e_i, m.
    jacobian : (N, 3, k) ndarray
        J_i of the k identified parameters.
    covariance : (k, k) ndarray
        C, their covariance.
    noise : (N, 3, 3) ndarray
        Each point's own noise covariance, m².
    """
    e = np.asarray(residuals, float).reshape(-1, 3)
    jac = np.asarray(jacobian, float).reshape(len(e), 3, -1)
    eig, vec = np.linalg.eigh(0.5 * (covariance + np.transpose(covariance)))
    root = vec * np.sqrt(np.clip(eig, 0.0, None))
    whiten = np.linalg.inv(np.linalg.cholesky(noise))
    rows = np.einsum('nab,nbk->nak', whiten, jac @ root).reshape(3 * len(e), -1)
    rhs = np.einsum('nab,nb->na', whiten, e).reshape(-1)
    k = rows.shape[1]
    system = np.vstack([rows, np.eye(k)])
    target = np.concatenate([rhs, np.zeros(k)])
    step = np.linalg.lstsq(system, target, rcond=None)[0]
    return float(np.sum((target - system @ step) ** 2))


def _off_placement(j: np.ndarray, placement: np.ndarray, sigma_rows: np.ndarray
                   ) -> np.ndarray:
    """Return ``j`` (N, 3, k) less its least-squares fit by ``placement``'s columns (N, 3, r).

    Rows whitened by ``sigma_rows`` (N, 3) for the fit, as the re-registration weighs them.
    """
    n, _, k = j.shape
    w = 1.0 / np.asarray(sigma_rows, float).reshape(-1)
    a = placement.reshape(3 * n, -1) * w[:, None]
    b = j.reshape(3 * n, k) * w[:, None]
    scale = np.linalg.norm(a, axis=0)
    scale[scale == 0.0] = 1.0
    coef, *_ = np.linalg.lstsq(a / scale, b, rcond=1e-10)
    return ((b - (a / scale) @ coef) / w[:, None]).reshape(n, 3, k)


def validate(model: MeasurementModel, p: np.ndarray, estimated: np.ndarray,
             covariance: np.ndarray, sigma: np.ndarray, data: Measurements,
             lower: np.ndarray, upper: np.ndarray,
             alpha: float = ADEQUACY_ALPHA,
             training_q: np.ndarray | None = None,
             noise_scale: float = 1.0,
             registered: np.ndarray | None = None,
             free: np.ndarray | None = None) -> Validation:
    """Predict ``data`` with the calibration ``p`` and test the residuals.

    Parameters
    ----------
    model : MeasurementModel
        The calibrated model (effects included).
    p : (n_p,) ndarray
        Calibrated parameter values.
    estimated : (k,) int ndarray
        Indices in ``p`` of the identified parameters, ordered as ``covariance``.
    covariance : (k, k) ndarray
        C_p of the identified parameters.
    sigma : (3,) ndarray
        Noise std per axis (m) of a new point about the calibrated prediction; a row of
        ``data`` with its own stated σ (``data.sigma``) takes that one, times
        √``noise_scale``.
    data : Measurements
        New (pose, reflector) rows.
    lower, upper : (n,) ndarray
        Training joint ranges; a pose with any joint outside is marked.
    training_q : (M, n) ndarray, optional
        The training poses (chain order): a pose inside the ranges near one is marked
        repeated.
    registered : (r,) int ndarray, optional
        Indices in ``p`` re-fitted on ``data`` first (the tracker set up again: the
        ``base.*`` parameters, optionally the reflector offsets). The re-registration's
        own χ² holds the tracker noise and the parameters' share, not the joint-reading
        noise.
    noise_scale : float
        The factor ``sigma`` was scaled by (χ²/dof of a calibration whose model was not
        adequate); the joint-reading noise of the model, ``J_q Σ_q J_qᵀ`` per point, is
        added scaled by it as well.
    free : (f,) int ndarray, optional
        Indices in ``p`` of the calibration's free parameters: the identified ones and
        those it held for identifiability. With ``training_q`` the predicted error is that
        of the estimable combination (:func:`training_row_space` of the training poses at
        the final ``p``, the re-registered one too: estimability does not depend on where
        the tracker stands), and points the training does not determine are marked (module
        text). Without them every point is taken as determined.
    """
    q = np.atleast_2d(data.q)
    tau = row_torques(model, data)
    estimated = np.asarray(estimated, dtype=int)
    covariance = np.asarray(covariance, dtype=float)
    keep = ~np.isin(estimated, [] if registered is None else registered)
    estimated, covariance = estimated[keep], covariance[np.ix_(keep, keep)]

    stated = None if data.sigma is None else np.asarray(data.sigma, float) * np.sqrt(noise_scale)
    try:
        sigma_rows = row_sigma(sigma, stated, len(q))
    except ValueError as exc:
        raise DataError(f'{exc}; the per-point sigma of the validation data') from None

    def noise_covariance(p_now: np.ndarray) -> np.ndarray:
        """(N, 3, 3) each point's own noise: the tracker's and the joint readings'."""
        noise = sigma_rows[:, :, None] ** 2 * np.eye(3)
        if model.joint_sigma is not None:
            jq = (model.joint_jacobian(p_now, q, tau, data.reflector, data.rotation,
                                       data.covariates)
                  @ model.joint_noise_map)
            noise = noise + noise_scale * np.einsum('nak,nbk->nab', jq, jq)
        return noise

    registration = None
    if registered is not None and len(registered):
        registration = reregister(model, p, dataclasses.replace(data, tau=tau), registered,
                                  sigma_rows, estimated, covariance)
        p = registration.p
    pred, jac = model.jacobian(p, q, tau, data.reflector, data.rotation, data.covariates)
    residuals = np.atleast_2d(data.eta) - pred
    determined = np.ones(len(q), dtype=bool)
    training = (None if free is None or training_q is None
                else training_row_space(model, p, training_q, free))
    if training is not None:
        # Only the estimable combination has a gauge-free covariance (module text).
        jac, leaving = training.project(jac)
        determined = leaving < PREDICTION_TOLERANCE
    j = jac[:, :, estimated]
    if registration is not None:
        # The re-fitted placement takes up whatever of the calibration's error looks like
        # it over these poses: the error that remains is the part off the placement's
        # columns (whitened by the rows' noise). A joint placement nearly redundant with
        # the base (a measured tilt keeps both) was otherwise predicted at its marginal
        # std, millimetres, where the re-registered prediction misses by micrometres.
        j = _off_placement(j, jac[:, :, registration.index], sigma_rows)
    noise = noise_covariance(p)
    cov = np.einsum('nak,kl,nbl->nab', j, covariance, j) + noise
    solved = np.linalg.solve(cov, residuals[:, :, None])[:, :, 0]
    d2 = np.where(determined, np.sum(residuals * solved, axis=1), np.nan)
    tested = determined if registration is None else np.ones(len(q), dtype=bool)
    chi2 = (registration.chi2 if registration is not None
            else shared_chi2(residuals[tested], j[tested], covariance, noise[tested])
            if tested.any() else 0.0)
    dof = 3 * int(tested.sum()) - (registration.dof if registration is not None else 0)
    tol = range_tolerance(model)
    turns = np.array([j.kind == 'continuous' for j in model.robot.joints])
    turned = same_turn(q, lower, upper, turns)
    outside = np.any((turned < np.asarray(lower) - tol) | (turned > np.asarray(upper) + tol),
                     axis=1)
    repeated = identical = np.zeros(len(q), dtype=bool)
    if training_q is not None and len(training_q):
        trained = same_turn(np.asarray(training_q, float), lower, upper, turns)
        repeated = same_pose(turned, trained) & ~outside
        identical = same_pose(q, np.asarray(training_q, float), 0.0)
    p_value = float(scipy.stats.chi2.sf(chi2, dof)) if dof > 0 else float('nan')
    noise_d2 = np.sum((residuals * np.linalg.solve(noise, residuals[:, :, None])[:, :, 0])[tested])
    # Against the stated noise: ``noise`` holds it times noise_scale.
    noise_ratio = float(np.sqrt(noise_d2 * noise_scale / dof)) if dof > 0 else float('nan')
    std = np.where(determined, np.sqrt(np.trace(cov, axis1=1, axis2=2) / 3), np.nan)
    return Validation(residuals, std, np.sqrt(d2), outside, repeated, chi2, dof, p_value,
                      alpha, registration, noise_ratio, determined, identical)


# A miss a rigid move of the points explains to this fraction of its rms is a set-up moved.
SET_UP_MOVED_FRACTION = 0.1


def set_up_moved(v: Validation, data: Measurements, points: np.ndarray
                 ) -> dict[str, float] | None:
    """Return the rigid move of the tracker frame that explains a validation's miss, or None.

    Without ``--register``, a miss that one rotation and translation of the new points
    takes to below :data:`SET_UP_MOVED_FRACTION` of its rms, beyond 10× the predicted std,
    is the tracker (or robot) set up again since the calibration, not the robot's error:
    {'translation_m', 'rotation_rad', 'rms_before_m', 'rms_after_m'}.
    """
    if v.registration is not None or v.holds or np.count_nonzero(points) < 4:
        return None
    eta = np.atleast_2d(data.eta)[points]
    predicted = eta - v.residuals[points]
    rot, trans = horn(predicted, eta)
    after = eta - (predicted @ rot.T + trans)
    before_rms = float(np.sqrt(np.mean(np.sum(v.residuals[points] ** 2, axis=1))))
    after_rms = float(np.sqrt(np.mean(np.sum(after ** 2, axis=1))))
    std = v.predicted_std[points]
    scale = float(np.nanmedian(std)) if np.isfinite(std).any() else 0.0
    if not (after_rms < SET_UP_MOVED_FRACTION * before_rms and before_rms > 10 * scale):
        return None
    angle = float(np.arccos(np.clip((np.trace(rot) - 1.0) / 2.0, -1.0, 1.0)))
    return {'translation_m': float(np.linalg.norm(trans)), 'rotation_rad': angle,
            'rms_before_m': before_rms, 'rms_after_m': after_rms}


@dataclass(frozen=True)
class NominalOnNew:
    """A calibrated robot against the nominal robot on new measurements.

    The calibrated robot and the nominal robot (every parameter at its URDF value) each
    have their placement registered on the new points themselves, so the robots are
    compared, not the placements. Each rms is over the point rows and corrected for the
    degrees of freedom its placement took from them, rms·√(3n / (3n − k)): a placement
    fitted to the points it is scored on makes them look better than new ones by that
    factor (the unbiased residual variance of least squares).

    The verdict is a paired test over the new poses: each pose's squared miss by the
    calibration less the nominal robot's (its points summed), their mean over its standard
    error, ``z``; worse when ``z`` > :data:`HARM_Z` (one-sided, 1 %). The scatter of the
    poses, not the stated noise, sets the margin: on a real UR10 with a misfit 15 times
    the stated σ, a calibration 0.5 % worse over 632 poses of Series D (0.778 against
    0.774 mm, z = 0.23) is not worse beyond what those poses can say (the stated noise
    called it harmful); over 1500 poses of other regions of Series A, 22 % worse (0.998
    against 0.815 mm, z = 14.15), it is.

    Attributes
    ----------
    rms_m, nominal_rms_m : float
        The calibration's and the registered nominal robot's corrected rms (m).
    dof, nominal_dof : int
        Degrees of freedom each took from the new points (k).
    points : int
        Point rows compared (n).
    poses : int
        Poses they were measured at (the paired test's count).
    z : float
        Mean of the per-pose differences of squared misses over its standard error
        (positive: the calibration misses more); NaN with fewer than 2 poses.
    """

    rms_m: float
    nominal_rms_m: float
    dof: int
    nominal_dof: int
    points: int
    poses: int
    z: float

    @property
    def worse(self) -> bool:
        """Whether the calibrated robot predicts the new points worse than nominal.

        Worse than the nominal robot, both registered on them, beyond what the poses'
        scatter can do (``z`` > :data:`HARM_Z`): the calibration does harm where these
        poses were taken.
        """
        return bool(np.isfinite(self.z) and self.z > HARM_Z)

    def to_dict(self) -> dict[str, float | int | bool | None]:
        """JSON-ready figures and the verdict (``worse_than_nominal``)."""
        return {'rms_m': self.rms_m, 'nominal_rms_m': self.nominal_rms_m,
                'dof': self.dof, 'nominal_dof': self.nominal_dof, 'points': self.points,
                'poses': self.poses, 'z': float(self.z) if np.isfinite(self.z) else None,
                'z_needed': HARM_Z, 'worse_than_nominal': self.worse}


# One-sided 1 % point of the standard normal: a calibration is called harmful on new
# points when it misses them more than the nominal robot beyond this many standard errors.
HARM_Z = float(scipy.stats.norm.ppf(0.99))
# Mean difference of squared misses below this fraction of their size: the two robots
# predict alike (the placements' fits differ by round-off).
TIE_RELATIVE = 1e-9


def corrected_rms(residuals: np.ndarray, dof: int) -> float:
    """Return the rms of ``residuals`` (n, 3) corrected for the ``dof`` a fit on them took.

    sqrt(Σ‖r_i‖² / (3n − dof)) per axis times √3; NaN when no degree of freedom is left.
    """
    r = np.atleast_2d(residuals)
    left = 3 * len(r) - int(dof)
    if left <= 0:
        return float('nan')
    return float(np.sqrt(3.0 * np.sum(r ** 2) / left))


def against_nominal_on_new(calibration: Validation, nominal: Validation,
                           points: np.ndarray, pose: np.ndarray | None = None
                           ) -> NominalOnNew:
    """Compare a calibration's validation with the nominal robot's on the same points.

    ``calibration``: the calibration's validation with its placement re-registered on the
    new points as the nominal's is. ``nominal``: the nominal robot's validation on the same
    new measurements with its placement re-registered (:func:`validate` with the nominal
    values, nothing estimated, ``registered`` its placement). ``points``: the point rows (a
    tracked body's rotation rows are no length). ``pose``: each row's pose (an index; rows
    of one pose are one term of the paired test), each row its own pose by default.
    """
    points = np.asarray(points, dtype=bool)
    n = int(points.sum())
    taken = calibration.registration.dof if calibration.registration is not None else 0
    taken_nominal = nominal.registration.dof if nominal.registration is not None else 0
    rows = np.flatnonzero(points)
    groups = (np.arange(len(rows)) if pose is None
              else np.unique(np.asarray(pose)[rows], return_inverse=True)[1])
    diff = np.bincount(groups, np.sum(calibration.residuals[rows] ** 2, axis=1)
                       - np.sum(nominal.residuals[rows] ** 2, axis=1))
    z = float('nan')
    if len(diff) >= 2:
        se = float(np.std(diff, ddof=1) / np.sqrt(len(diff)))
        mean = float(np.mean(diff))
        scale = float(np.mean(np.sum(nominal.residuals[rows] ** 2, axis=1)))
        # The same robot (a calibration of the placement alone) differs by the fits'
        # round-off: a tie, not a verdict drawn from it.
        tie = abs(mean) <= TIE_RELATIVE * scale
        z = 0.0 if tie else mean / se if se > 0 else float('inf') if mean > 0 else -np.inf
    return NominalOnNew(corrected_rms(calibration.residuals[points], taken),
                        corrected_rms(nominal.residuals[points], taken_nominal),
                        int(taken), int(taken_nominal), n, len(diff), z)


def nominal_validation(model: MeasurementModel, placed: np.ndarray, registered: np.ndarray,
                       sigma: np.ndarray, data: Measurements,
                       noise_scale: float = 1.0, refit: bool = True) -> Validation | None:
    """Return the nominal robot's validation on ``data``, its placement re-registered.

    Every parameter at its nominal (URDF) value but the placement ``registered``
    (positions), started from ``placed`` and re-fitted on ``data`` (``refit`` False: held
    as ``placed`` gives it, the nominal robot as a user would place it without the points);
    ``sigma`` and ``noise_scale``: the calibration's (its rows weighed as the calibration's
    are, so that the two placements are fitted alike: a tracked body's rotation rows
    against its points). None when the new points cannot place it (fewer than 3, or a
    singular fit).
    """
    registered = np.asarray(registered, dtype=int)
    p = np.array(model.params.nominal, dtype=float)
    p[registered] = np.asarray(placed, dtype=float)[registered]
    n = model.robot.n_joints
    try:
        return validate(model, p, np.zeros(0, dtype=int), np.zeros((0, 0)), sigma, data,
                        np.full(n, -np.inf), np.full(n, np.inf),
                        registered=registered if refit else None, noise_scale=noise_scale)
    except (DataError, np.linalg.LinAlgError):
        return None
