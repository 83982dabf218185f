"""Whether a screened candidate effect is physically plausible on this data.

Beside values beyond the effect's bounds
(:func:`~kpi_calib_ros.core.effects.registry.implausible`), three reasons it is not: a
backlash whose joint's torque stays where it acts as a compliance (:func:`backlash_unloaded`),
an effect its data do not determine (:func:`effect_undetermined`), and one that leaves an
identified geometric parameter undetermined (:func:`geometry_undetermined`).
"""
from __future__ import annotations

from typing import Mapping

import numpy as np

from kpi_calib_ros.core.diagnosis.candidate_fit import CandidateFit
from kpi_calib_ros.core.diagnosis.effect_signature import effect_columns
from kpi_calib_ros.core.effects.library import BACKLASH_TORQUE_SCALE
from kpi_calib_ros.core.effects.registry import BoundEffect, effect_bounds
from kpi_calib_ros.core.estimation.least_squares import CalibrationResult
from kpi_calib_ros.core.estimation.plausibility import Tolerances
from kpi_calib_ros.core.estimation.precision import chi2_scale
from kpi_calib_ros.core.estimation.residuals import LinearizedFit, orthonormal_basis
from kpi_calib_ros.core.measurement.tracker import MeasurementModel

__all__ = ['backlash_unloaded', 'effect_undetermined', 'geometry_undetermined']


def backlash_unloaded(effect: BoundEffect, tau: np.ndarray) -> str:
    """Return why ``joint_backlash`` is no backlash on this data, or ''.

    With the joint's gravity torques ``tau`` (N, n) below its torque scale τ_b
    (:data:`~kpi_calib_ros.core.effects.library.BACKLASH_TORQUE_SCALE`), its b·tanh(τ/τ_b) is
    (b/τ_b)·τ there: a compliance of the joint, never a step. A torque of exactly 0
    everywhere is left to the no-effect test.
    """
    if effect.kind.name != 'joint_backlash' or effect.joint_index is None:
        return ''
    top = float(np.max(np.abs(np.asarray(tau)[:, effect.joint_index]), initial=0.0))
    if top == 0.0 or top >= BACKLASH_TORQUE_SCALE:
        return ''
    return (f'not a backlash with this data: the gravity torque of {effect.joint} stays below '
            f'{top:.2g} N m, under the backlash\'s torque scale τ_b = '
            f'{BACKLASH_TORQUE_SCALE:g} N m, where b·tanh(τ/τ_b) is (b/τ_b)·τ, a compliance '
            f'(joint_compliance:{effect.joint} is its candidate). To see it: '
            f'{effect.hint()}.')


def effect_undetermined(effect: BoundEffect, std: np.ndarray,
                        bounds: Mapping[str, tuple[float, ...]]) -> str:
    """Why a screened effect is undetermined (a std above its bound), '' when it is not.

    An infinite std (not determined at all) is above every bound; NaN is a shape parameter
    held at its grid value (no std).
    """
    loose = [f'{n} std {v:.3g} {u} > its bound {b:.3g}' for n, v, u, b in
             zip(effect.parameter_names, std, effect.units, effect_bounds(effect, bounds))
             if not np.isnan(v) and v > b]
    return ('undetermined: ' + '; '.join(loose) + f' (to determine it: {effect.hint()})'
            if loose else '')


def geometry_undetermined(model: MeasurementModel, sys_: LinearizedFit,
                          result: CalibrationResult, fit: CandidateFit, q: np.ndarray,
                          tau: np.ndarray, tolerances: Tolerances) -> str:
    """Which identified geometric parameters a candidate leaves undetermined, '' for none.

    With the candidate's columns beside the geometry, the std of each identified geometric
    parameter is that of the fit [J E] (Schur complement, at the candidate's χ²/dof); one above
    its tolerance (m or rad, :class:`~kpi_calib_ros.core.estimation.plausibility.Tolerances`)
    that was within it without the candidate is undetermined by the effect: the data cannot
    tell the effect from that direction of the geometry (link bending turning a column's
    placement by 0.2 rad).
    """
    k = len(fit.effect.parameter_names) - fit.effect.kind.n_shape
    shape = tuple(fit.theta[k:]) if fit.effect.kind.n_shape else ()
    cols, _ = effect_columns(model, sys_, fit.effect, q, tau, shape)
    basis = orthonormal_basis(cols)
    perp = sys_.jac - basis @ (basis.T @ sys_.jac)
    scale = chi2_scale(fit.chi2, fit.dof)
    with np.errstate(divide='ignore', invalid='ignore'):
        std = np.sqrt(np.abs(np.diag(np.linalg.pinv(perp.T @ perp, hermitian=True))) * scale)
    before = dict(zip(result.estimated, result.std))
    units = dict(zip(model.params.names, model.params.units))
    out = []
    for name, s in zip(result.estimated, std):
        if name not in units or not _is_geometric(name):
            continue
        tol = _tolerance_of(name, units[name], tolerances)
        if s > tol >= before.get(name, 0.0):
            out.append(f'{name} std {s:.3g} {units[name]} > its tolerance {tol:g}')
    return ('it leaves the geometry undetermined: ' + '; '.join(out[:4])
            + (f' and {len(out) - 4} more' if len(out) > 4 else '')
            + ' (the data cannot tell the effect from these directions)') if out else ''


def _is_geometric(name: str) -> bool:
    return name.startswith(('base.', 'reflector.')) or '.placement.' in name \
        or (name.endswith('.offset') and name.count('.') == 1)


def _tolerance_of(name: str, unit: str, tolerances: Tolerances) -> float:
    if name.startswith('reflector.'):
        # an offset (m), or the identified orientation of a tracked body (rad)
        return tolerances.reflector_offset if unit == 'm' else tolerances.rotation
    if name.endswith('.offset'):
        return tolerances.offset
    prefix = 'base_' if name.startswith('base.') else ''
    return getattr(tolerances, prefix + ('translation' if unit == 'm' else 'rotation'))
