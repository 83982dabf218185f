"""Robot base in the tracker frame and reflector on the tip, registered from a campaign's points.

Model (eq. 3 with nominal kinematics): ``η_i = R (R_i o + p_i) + t``, with
``(R_i, p_i)`` the nominal tip pose of posture ``i`` in the base frame, ``o``
the reflector centre in the tip frame and ``(R, t)`` the base pose in the
tracker frame. Given ``o`` the base pose is the closed-form Horn/Umeyama
(SVD) fit of the points ``R_i o + p_i`` onto ``η_i``; given ``(R, t)`` the offset
is linear least squares in ``o``. The two alternate from ``o = 0`` (no start
needed for the base pose: the closed form has none), then Gauss-Newton on all
nine unknowns polishes the joint minimum. Identification then starts from the
result instead of hand-measured placements.

Several reflectors (mocap markers) on one tool: row ``i`` measured reflector
``k_i`` with its own offset ``o_k``; the base pose and every offset are registered
jointly (Horn on all rows, one linear least squares per reflector, Gauss-Newton
on 6 + 3R unknowns).

A calibrated model is re-registered on a recording made with the tracker (or the probe)
set up again (:func:`reregister`): the same closed-form start on the calibration's
predicted points, then Gauss-Newton on the base pose (and the reflector offsets) with the
calibration's other parameters held, as ``validate --register`` needs.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import pinocchio as pin

from kpi_calib_ros.core.errors import DataError
from kpi_calib_ros.core.measurement.data import Measurements
from kpi_calib_ros.core.measurement.tracker import MeasurementModel
from kpi_calib_ros.core.measurement.weighting import weighted_rows

__all__ = [
    'TRIM_FACTOR', 'TRIM_FLOOR_M', 'MAX_TRIM_ROUNDS', 'MIN_KEPT_FRACTION', 'Registration', 'horn',
    'register', 'RANK_TOLERANCE', 'Reregistration', 'reregister',
]

# A point set whose second principal spread is below this fraction of the first
# is a line: the rotation about it is undetermined.
_COLLINEAR = 1e-3
# Trimmed registration: a point missing by more than TRIM_FACTOR x the median miss (and
# more than TRIM_FLOOR_M) is left out and the rest registered again, at most
# MAX_TRIM_ROUNDS times, keeping at least MIN_KEPT_FRACTION of the points.
TRIM_FACTOR = 10.0
TRIM_FLOOR_M = 0.01
MAX_TRIM_ROUNDS = 5
MIN_KEPT_FRACTION = 0.7


@dataclass(frozen=True)
class Registration:
    """Base pose and reflector offset that best map nominal points onto measured ones.

    Attributes
    ----------
    base_in_tracker : (6,) ndarray
        [x, y, z, roll, pitch, yaw] of the base frame in the tracker frame (m, rad),
        URDF convention R = Rz(yaw) Ry(pitch) Rx(roll).
    reflector_offset : (3,) ndarray
        Reflector centre in the tip frame (m).
    residuals_m : (N,) ndarray
        Distance between each measured point and its registered nominal point (m).
    iterations : int
        Alternations plus Gauss-Newton steps taken.
    reflector_offsets : (R, 3) ndarray
        Every reflector's centre in the tip frame (m); row 0 is ``reflector_offset``.
    trimmed : tuple of int
        Points left out of the final registration because they missed by far more than
        the others (see :func:`register`); their residuals are still in ``residuals_m``.
    offset_std_m : (R, 3) ndarray or None
        Std of every registered offset component (m) at the noise the registered miss
        shows; 0 where the offsets were held (the cell states them), inf along a direction
        the postures cannot tell from the base position (the tool never turns about it).
    """

    base_in_tracker: np.ndarray
    reflector_offset: np.ndarray
    residuals_m: np.ndarray
    iterations: int
    reflector_offsets: np.ndarray | None = None
    trimmed: tuple[int, ...] = ()
    offset_std_m: np.ndarray | None = None

    @property
    def rms_m(self) -> float:
        """Root mean square of :attr:`residuals_m` over the points not trimmed (m)."""
        kept = np.ones(len(self.residuals_m), bool)
        kept[list(self.trimmed)] = False
        return float(np.sqrt(np.mean(self.residuals_m[kept] ** 2)))

    @property
    def transform(self) -> np.ndarray:
        """Base pose in the tracker frame as a (4, 4) homogeneous matrix."""
        out = np.eye(4)
        out[:3, :3] = pin.rpy.rpyToMatrix(*self.base_in_tracker[3:])
        out[:3, 3] = self.base_in_tracker[:3]
        return out


def horn(source: np.ndarray, target: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rotation R (3, 3), translation t (3,) minimising Σ‖R x_i + t − y_i‖² (Umeyama 1991).

    Parameters
    ----------
    source, target : (N, 3) ndarray
        Corresponding points ``x_i`` and ``y_i`` (m).
    """
    mx, my = source.mean(axis=0), target.mean(axis=0)
    u, _, vt = np.linalg.svd((target - my).T @ (source - mx))
    # The sign fix keeps a proper rotation when the best orthogonal map is a reflection.
    d = np.diag([1.0, 1.0, np.sign(np.linalg.det(u @ vt)) or 1.0])
    rot = u @ d @ vt
    return rot, my - rot @ mx


def _skew(v: np.ndarray) -> np.ndarray:
    """(N, 3, 3) cross-product matrices of the rows of ``v`` (N, 3)."""
    z = np.zeros(len(v))
    return np.stack([np.stack([z, -v[:, 2], v[:, 1]], -1),
                     np.stack([v[:, 2], z, -v[:, 0]], -1),
                     np.stack([-v[:, 1], v[:, 0], z], -1)], axis=1)


def _check_geometry(eta: np.ndarray, rotations: np.ndarray) -> None:
    spread = np.linalg.svd(eta - eta.mean(axis=0), compute_uv=False)
    if spread[1] < _COLLINEAR * spread[0] or spread[1] < 1e-6:
        raise DataError(f'registration: the {len(eta)} measured points are nearly collinear '
                        f'(principal spreads {spread.round(6).tolist()} m); the rotation about '
                        'their line is undetermined. Measure postures that span a plane or a '
                        'volume')
    mean = rotations.mean(axis=0)
    sv = np.linalg.svd((rotations - mean).reshape(-1, 3), compute_uv=False)
    if sv[-1] < _COLLINEAR * max(sv[0], 1e-12) or sv[-1] < 1e-6:
        raise DataError('registration: the tip orientations hardly vary (singular values '
                        f'{sv.round(6).tolist()}), so the reflector offset cannot be told '
                        'from the base position. Measure postures with different tip '
                        'orientations about all three axes')


def register(eta: np.ndarray, tip_poses: np.ndarray, max_rms: float = 0.02,
             alternations: int = 50, gauss_newton: int = 20, tol: float = 1e-12,
             reflector: np.ndarray | None = None,
             offsets: np.ndarray | None = None) -> Registration:
    """Estimate base pose in the tracker frame and reflector offset on the tip from one campaign.

    Parameters
    ----------
    eta : (N, 3) array_like
        Measured reflector centres in the tracker frame (m), N >= 4.
    tip_poses : (N, 4, 4) array_like
        Nominal tip poses in the robot base frame at the measured joint values (m).
    max_rms : float
        Refuse when the registered points still miss by more than this rms (m): the
        nominal model then cannot explain the data (units, joint order, tip frame).
    alternations, gauss_newton : int
        Most Horn / least-squares alternations, then most Gauss-Newton steps.
    tol : float
        Stop when a step changes the unknowns by less than this (m, rad).
    reflector : (N,) int array_like, optional
        Reflector index of every row (several reflectors on the tool, each with its
        own offset); None: one reflector.
    offsets : (R, 3) array_like, optional
        Reflector offsets the cell states (m): held, and only the base pose registered. A
        stated offset is a prior, not a start to throw away: postures that never turn the
        tool cannot tell an offset from the base position, and registering it there moves
        it anywhere (metres) with the base moved to match.

    Returns
    -------
    Registration

    Raises
    ------
    ValueError
        Shapes or non-finite values.
    DataError
        Degenerate postures (collinear points, one tip orientation) or a miss above
        ``max_rms``, with the distances and the likely causes.
    """
    eta = np.asarray(eta, dtype=float)
    poses = np.asarray(tip_poses, dtype=float)
    if eta.ndim != 2 or eta.shape[1] != 3 or poses.shape != (len(eta), 4, 4):
        raise ValueError(f'eta must be (N, 3) and tip_poses (N, 4, 4); got {eta.shape} and '
                         f'{poses.shape}')
    if len(eta) < 4:
        raise ValueError(f'eta: registration needs at least 4 points, got {len(eta)}')
    if not (np.all(np.isfinite(eta)) and np.all(np.isfinite(poses))):
        raise ValueError('eta and tip_poses must be finite')
    ref = (np.zeros(len(eta), dtype=int) if reflector is None
           else np.asarray(reflector, dtype=int).reshape(-1))
    if len(ref) != len(eta) or ref.min() < 0:
        raise ValueError(f'reflector must hold one index >= 0 per point ({len(eta)})')
    n_ref = int(ref.max()) + 1
    held = None if offsets is None else np.asarray(offsets, dtype=float).reshape(-1, 3)
    if held is not None and (len(held) < n_ref or not np.all(np.isfinite(held))):
        raise ValueError(f'offsets must hold a finite offset for each of the {n_ref} reflectors')
    rotations, positions = poses[:, :3, :3], poses[:, :3, 3]
    for k in range(n_ref):
        if np.count_nonzero(ref == k) < 2:
            raise ValueError(f'reflector: index {k} has fewer than 2 points; every reflector '
                             'needs several postures to register its offset')
        if held is None:
            _check_geometry(eta[ref == k], rotations[ref == k])

    # A gross point (a reflector lost mid-shot, a wrong pairing) drags the closed form;
    # register again without the points that miss by far more than the median (trimmed
    # registration), so a few of them cannot spoil the start. They stay in the data: the
    # identification's own outlier screening decides on them.
    kept = np.ones(len(eta), bool)
    for _ in range(MAX_TRIM_ROUNDS):
        result = _fit(eta[kept], rotations[kept], positions[kept], ref[kept], n_ref,
                      alternations, gauss_newton, tol, held)
        residuals = _residuals(result, eta, rotations, positions, ref)
        far = residuals > max(TRIM_FACTOR * float(np.median(residuals[kept])), TRIM_FLOOR_M)
        enough = all(np.count_nonzero(~far & (ref == k)) >= 2 for k in range(n_ref))
        if (not np.any(far & kept) or not enough
                or np.sum(~far) < max(4, MIN_KEPT_FRACTION * len(eta))):
            break
        kept = ~far
    result = Registration(result.base_in_tracker, result.reflector_offset, residuals,
                          result.iterations, result.reflector_offsets,
                          tuple(int(i) for i in np.flatnonzero(~kept)), result.offset_std_m)
    if result.rms_m > max_rms:
        raise DataError(_miss_message(result, eta, positions, max_rms))
    return result


def _fit(eta: np.ndarray, rotations: np.ndarray, positions: np.ndarray, ref: np.ndarray,
         n_ref: int, alternations: int, gauss_newton: int, tol: float,
         held: np.ndarray | None = None) -> Registration:
    """Solve in closed form (Horn) alternating with the offsets, then Gauss-Newton, on the rows.

    ``held`` (R, 3): offsets held at these values, only the base pose fitted.
    """
    offsets = np.zeros((n_ref, 3)) if held is None else held[:n_ref].copy()
    rows = [np.flatnonzero(ref == k) for k in range(n_ref)]
    steps = 0
    for _ in range(alternations if held is None else 1):
        steps += 1
        rot, trans = horn(np.einsum('nij,nj->ni', rotations, offsets[ref]) + positions, eta)
        if held is not None:
            break
        # R^T (η_i - t) - p_i = R_i o_k, stacked over the rows of reflector k: linear in o_k.
        rhs = (eta - trans) @ rot - positions
        new = np.array([np.linalg.lstsq(rotations[r].reshape(-1, 3), rhs[r].reshape(-1),
                                        rcond=None)[0] for r in rows])
        change = float(np.linalg.norm(new - offsets))
        offsets = new
        if change < tol:
            break
    free = 6 + (0 if held is not None else 3 * n_ref)
    for _ in range(gauss_newton):
        residual, jac = _gauss_newton_rows(rot, trans, offsets, eta, rotations, positions,
                                           ref, rows)
        step = np.linalg.lstsq(jac[:, :free], -residual, rcond=None)[0]
        step = np.concatenate([step, np.zeros(6 + 3 * n_ref - free)])
        rot = pin.exp3(step[:3]) @ rot
        trans, offsets = trans + step[3:6], offsets + step[6:].reshape(n_ref, 3)
        steps += 1
        if np.linalg.norm(step) < tol:
            break
    points = np.einsum('nij,nj->ni', rotations, offsets[ref]) + positions
    residuals = np.linalg.norm(points @ rot.T + trans - eta, axis=1)
    return Registration(np.concatenate([trans, pin.rpy.matrixToRpy(rot)]), offsets[0],
                        residuals, steps, offsets,
                        offset_std_m=(np.zeros((n_ref, 3)) if held is not None else
                                      _offset_std(rot, trans, offsets, eta, rotations,
                                                  positions, ref, rows)))


def _gauss_newton_rows(rot: np.ndarray, trans: np.ndarray, offsets: np.ndarray,
                       eta: np.ndarray, rotations: np.ndarray, positions: np.ndarray,
                       ref: np.ndarray, rows: list[np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """Stacked residual (3N,) and Jacobian (3N, 6 + 3R) over [rotation, translation, offsets]."""
    n_ref = len(offsets)
    points = np.einsum('nij,nj->ni', rotations, offsets[ref]) + positions
    world = points @ rot.T
    residual = (world + trans - eta).reshape(-1)
    jac = np.zeros((len(eta), 3, 6 + 3 * n_ref))
    jac[:, :, :3] = -_skew(world)
    jac[:, :, 3:6] = np.eye(3)
    for k, r in enumerate(rows):
        jac[r, :, 6 + 3 * k:9 + 3 * k] = rot @ rotations[r]
    return residual, jac.reshape(-1, 6 + 3 * n_ref)


def _offset_std(rot: np.ndarray, trans: np.ndarray, offsets: np.ndarray, eta: np.ndarray,
                rotations: np.ndarray, positions: np.ndarray, ref: np.ndarray,
                rows: list[np.ndarray]) -> np.ndarray:
    """(R, 3) std of the registered offsets (m).

    The noise per axis taken from the registered miss (nominal kinematics: the robot's errors
    count as noise); inf along a direction the postures cannot tell from the base (a singular
    value below 1e-9 of the largest).
    """
    residual, jac = _gauss_newton_rows(rot, trans, offsets, eta, rotations, positions, ref, rows)
    dof = max(len(residual) - jac.shape[1], 1)
    scale = float(residual @ residual) / dof
    _, sv, vt = np.linalg.svd(jac, full_matrices=False)
    weak = sv < 1e-9 * sv[0]
    inverse = np.where(weak, 0.0, 1.0 / np.where(weak, 1.0, sv) ** 2)
    var = scale * (vt.T ** 2) @ inverse
    var[np.any(np.abs(vt[weak]) > 1e-6, axis=0)] = np.inf
    return np.sqrt(var[6:]).reshape(-1, 3)


def _residuals(result: Registration, eta: np.ndarray, rotations: np.ndarray,
               positions: np.ndarray, ref: np.ndarray) -> np.ndarray:
    """Distance of every measured point from its registered nominal point (m)."""
    rot, trans = result.transform[:3, :3], result.transform[:3, 3]
    offsets = np.asarray(result.reflector_offsets)
    points = np.einsum('nij,nj->ni', rotations, offsets[ref]) + positions
    return np.linalg.norm(points @ rot.T + trans - eta, axis=1)


def _miss_message(result: Registration, eta: np.ndarray, positions: np.ndarray,
                  max_rms: float) -> str:
    """Why registered nominal points still miss: figures first, then the likely causes."""
    r = result.residuals_m
    worst = np.argsort(r)[::-1][:3]
    scale = float(np.sqrt(np.sum(np.var(eta, axis=0)) / max(np.sum(np.var(positions, axis=0)),
                                                            1e-30)))
    causes = ['joint values in the wrong order or units (degrees given as radians)',
              'the wrong tip frame (robot.tip_frame) or base frame',
              'points paired with the wrong postures']
    if not 0.5 < scale < 2.0:
        causes.insert(0, f'units: the measured points spread {scale:.3g} times as far as the '
                         'nominal tip positions (mm given as m?)')
    return (f'registration: the nominal model misses the measured points by {result.rms_m:.4g} m '
            f'rms (max {r.max():.4g} m at points {worst.tolist()}, median {np.median(r):.4g} m; '
            f'limit {max_rms} m). Likely causes: ' + '; '.join(causes))


# Re-registration of a calibrated model on a new recording: a registration direction whose
# scaled singular value is below this fraction of the largest is not determined by the new
# poses (it costs no degree of freedom and is left at the calibration's value).
RANK_TOLERANCE = 1e-8


@dataclass(frozen=True)
class Reregistration:
    """A calibrated model's placement re-fitted on a new recording alone.

    Attributes
    ----------
    p : (n_p,) ndarray
        The calibration's values with the re-fitted ones replaced.
    index : (r,) int ndarray
        Positions in ``p`` of the re-fitted parameters.
    dof : int
        Degrees of freedom the fit takes from the new recording: the rank of its
        Jacobian (r when the new poses determine every re-fitted parameter).
    chi2 : float
        The minimum ``eᵀ V⁻¹ e`` (see :func:`reregister`), χ²(3N − dof) when the
        calibration holds.
    iterations : int
        Gauss-Newton steps taken after the closed-form start.
    std : (r,) ndarray
        Each re-fitted parameter's std from the new recording alone (the calibration held),
        the noise as stated; inf for one the new poses do not determine (a part of it lies
        in a direction below :data:`RANK_TOLERANCE`). Empty when not computed.
    """

    p: np.ndarray
    index: np.ndarray
    dof: int
    chi2: float
    iterations: int
    std: np.ndarray = field(default_factory=lambda: np.zeros(0))


def reregister(model: MeasurementModel, p: np.ndarray, data: Measurements, index: np.ndarray,
               sigma: np.ndarray, uncertain: np.ndarray, covariance: np.ndarray,
               iterations: int = 30, tol: float = 1e-9) -> Reregistration:
    """Re-fit the parameters ``index`` of the calibrated model on ``data``, the rest fixed.

    The new recording's tracker (or probe) was set up again: its base pose in the
    tracker frame (``base.*``) and possibly the reflector offsets changed, nothing else.
    When every ``base.*`` is re-fitted, the start is the closed-form (Horn) fit of the
    calibration's predicted points onto the measured ones, composed with the calibrated
    base pose, so a tracker moved by metres and turned by any angle needs no start.

    Gauss-Newton then fits the re-fitted parameters by least squares with the
    calibration's other values held: the placement, and the residuals the user compares.
    The χ² of the test is the minimum over them of ``eᵀ V⁻¹ e``, with ``e`` every row's
    residual stacked (3N) and ``V = Σ ⊗ I + J_u C_u J_uᵀ`` its covariance: the noise plus
    the calibration's uncertainty of the other parameters, which is common to all rows.
    It is a least-squares problem that also fits a correction ``δ`` of the uncertain
    parameters under the prior ``δ ~ N(0, C_u)`` (profiled out, never applied), so V is
    never formed. The minimum is χ²(3N − r), r the rank. The two fits coincide when the
    calibration is precise; where a re-fitted parameter is nearly redundant with
    uncertain ones (a reflector offset along the tool axis), the χ² fit may move it
    where δ explains the miss, which is no placement to report.

    Parameters
    ----------
    model : MeasurementModel
    p : (n_p,) ndarray
        Calibrated parameter values.
    data : Measurements
        The new recording (point rows, and rotation rows of tracked bodies).
    index : (r,) int ndarray
        Parameters to re-fit (positions in ``p``).
    sigma : (3,) or (N, 3) ndarray
        Noise std per axis of a row about the calibrated prediction (m), or per row.
    uncertain : (k,) int ndarray
        Positions in ``p`` of the other identified parameters, ordered as ``covariance``.
    covariance : (k, k) ndarray
        C_u, their covariance from the calibration.
    iterations : int
        Most Gauss-Newton steps.
    tol : float
        Stop when a step moves the whitened residuals by less than this (units of their
        std).

    Raises
    ------
    DataError
        Fewer than 3 point rows to place the base on.
    """
    index = np.asarray(index, dtype=int)
    uncertain = np.asarray(uncertain, dtype=int)
    p = np.asarray(p, dtype=float).copy()
    q = np.atleast_2d(data.q)
    eta = np.atleast_2d(data.eta)
    base = model.params.indices([f'base.{c}' for c in ('x', 'y', 'z', 'roll', 'pitch', 'yaw')])
    if set(base.tolist()) <= set(index.tolist()):
        ref = (np.zeros(len(q), dtype=int) if data.reflector is None
               else np.asarray(data.reflector, dtype=int))
        points = ref < model.n_reflectors
        if np.count_nonzero(points) < 3:
            raise DataError(f're-registration needs at least 3 measured points, got '
                            f'{np.count_nonzero(points)}')
        pred = model.predict(p, q[points], None if data.tau is None else data.tau[points],
                             ref[points], covariates=data.subset(points).covariates)
        rot, trans = horn(pred, eta[points])
        old = pin.rpy.rpyToMatrix(*p[base[3:]])
        p[base[:3]] = rot @ p[base[:3]] + trans
        p[base[3:]] = pin.rpy.matrixToRpy(rot @ old)
    weight = 1.0 / np.asarray(sigma, dtype=float)
    k = len(uncertain)
    # Prior rows L⁻¹ δ with C_u = L Lᵀ (C_u⁻¹ = L⁻ᵀ L⁻¹).
    prior = np.linalg.inv(np.linalg.cholesky(covariance)) if k else np.zeros((0, 0))
    # The placement is the least-squares fit with the calibration held (the miss the user
    # sees); the χ² is the minimum with its uncertainty free (the test), from there.
    p, _, _, steps = _refit(model, p, data, index, weight, np.zeros(0, int),
                            np.zeros((0, 0)), iterations, tol)
    _, chi2, rank, more = _refit(model, p, data, index, weight, uncertain, prior,
                                 iterations, tol)
    return Reregistration(p, index, rank - k, chi2, steps + more,
                          _refitted_std(model, p, data, index, weight))


def _refitted_std(model: MeasurementModel, p: np.ndarray, data: Measurements,
                  index: np.ndarray, weight: np.ndarray) -> np.ndarray:
    """Return the (r,) std of ``p[index]`` fitted on ``data`` alone, the rest held.

    The square root of the diagonal of ``(Jᵀ W² J)⁺``; inf where a direction the data do
    not determine (singular value below :data:`RANK_TOLERANCE` of the largest, columns
    scaled) enters.
    """
    _, jac = model.jacobian(p, np.atleast_2d(data.q), data.tau, data.reflector, data.rotation,
                            data.covariates)
    rows = weighted_rows(jac, weight, index)
    scale = np.linalg.norm(rows, axis=0)
    scale[scale == 0.0] = 1.0
    _, s, vt = np.linalg.svd(rows / scale, full_matrices=True)
    s = np.concatenate([s, np.zeros(len(vt) - len(s))])  # fewer rows than parameters
    kept = s > RANK_TOLERANCE * (s[0] if len(s) else 0.0)
    s = np.where(kept, s, 1.0)
    var = np.sum((vt[kept] / s[kept, None]) ** 2, axis=0)
    # A parameter with a part in a left-out direction is not determined, whatever its size.
    lost = np.sum(vt[~kept] ** 2, axis=0) > 1e-6
    return np.where(lost, np.inf, np.sqrt(var) / scale)


def _refit(model: MeasurementModel, p: np.ndarray, data: Measurements, index: np.ndarray,
           weight: np.ndarray, uncertain: np.ndarray, prior: np.ndarray, iterations: int,
           tol: float) -> tuple[np.ndarray, float, int, int]:
    """Gauss-Newton on ``p[index]`` minimising ``‖W (η − h)‖²``, with a profiled prior correction.

    With ``uncertain`` parameters, a correction ``δ`` of them under the prior rows ``prior`` is
    added to the minimisation (profiled out, never applied). Returns the values, the minimum,
    the rank of the system and the steps.
    """
    p = p.copy()
    q, eta = np.atleast_2d(data.q), np.atleast_2d(data.eta)
    k, r = len(uncertain), len(index)
    steps, rank, chi2 = 0, 0, float('nan')
    while steps < iterations:
        steps += 1
        pred, jac = model.jacobian(p, q, data.tau, data.reflector, data.rotation,
                                   data.covariates)
        rows = np.vstack([
            np.hstack([weighted_rows(jac, weight, index), weighted_rows(jac, weight, uncertain)]),
            np.hstack([np.zeros((k, r)), prior])])
        rhs = np.concatenate([((eta - pred) * weight).reshape(-1), np.zeros(k)])
        scale = np.linalg.norm(rows, axis=0)
        scale[scale == 0.0] = 1.0
        step, _, rank, _ = np.linalg.lstsq(rows / scale, rhs, rcond=RANK_TOLERANCE)
        chi2 = float(np.sum((rhs - (rows / scale) @ step) ** 2))
        p[index] += step[:r] / scale[:r]
        if np.linalg.norm(step[:r]) < tol:
            break
    return p, chi2, int(rank), steps
