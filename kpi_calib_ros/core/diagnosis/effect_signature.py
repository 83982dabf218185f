"""An effect beside the geometric fit: the augmented model and the effect's signature.

The signature of an effect is the part of the measurements it moves: its weighted Jacobian
columns at the converged geometric solution (effect size 0). The screen
(:mod:`kpi_calib_ros.core.diagnosis.screening`) asks how much of it the geometric parameters
reproduce (:func:`absorbed_by` names them). The columns are exact (CasADi, from the augmented
measurement model), and the augmented model of one base model and effect is built once.
"""
from __future__ import annotations

import weakref

import numpy as np

from kpi_calib_ros.core.effects.registry import BoundEffect
from kpi_calib_ros.core.estimation.least_squares import CalibrationResult
from kpi_calib_ros.core.estimation.residuals import LinearizedFit
from kpi_calib_ros.core.measurement.tracker import MeasurementModel
from kpi_calib_ros.core.measurement.weighting import weighted_rows

__all__ = ['absorbed_by', 'augmented_model', 'effect_columns', 'effect_std']


def augmented_model(model: MeasurementModel, effects: tuple) -> MeasurementModel:
    """``model`` with ``effects`` appended (their parameters after the existing ones)."""
    return MeasurementModel(model.robot, model.geometric, model.effects + tuple(effects),
                            model.reflector_axis, model.orientations, model.rotation_scale,
                            model.joint_noise_map, model.joint_temperatures)


# Candidate models of a base model, by effect name: the screen builds one per candidate
# (the CasADi expressions and their Jacobians, most of a screen's time), and one base model
# is screened again for every campaign, seed or round.
_CANDIDATE_MODELS: weakref.WeakKeyDictionary[MeasurementModel, dict[str, MeasurementModel]] = \
    weakref.WeakKeyDictionary()


def _candidate_model(model: MeasurementModel, effect: BoundEffect) -> MeasurementModel:
    """Return ``model`` with ``effect`` appended, built once per base model and effect."""
    built = _CANDIDATE_MODELS.setdefault(model, {})
    aug = built.get(effect.name)
    if aug is None or aug.effects[-1] != effect:
        aug = augmented_model(model, (effect,))
        built[effect.name] = aug
    return aug


def effect_columns(model: MeasurementModel, sys_: LinearizedFit, effect: BoundEffect,
                   q: np.ndarray, tau: np.ndarray,
                   shape: tuple[float, ...] = ()) -> tuple[np.ndarray, float]:
    """Weighted Jacobian columns (3N, k) of the size parameters at size 0, and the largest shift.

    The columns are the effect's size parameters; shape parameters, the last ``len(shape)``, are
    held at ``shape``. The shift is the largest point displacement (m) a typical-size effect
    causes.
    """
    aug = _candidate_model(model, effect)
    k = len(effect.parameter_names) - len(shape)
    p = np.concatenate([sys_.p, np.zeros(k), shape])
    _, jac = aug.jacobian(p, q, tau, sys_.reflector, sys_.rotation, sys_.covariates)
    cols = jac[:, :, len(sys_.p):len(sys_.p) + k]
    disp = float(np.max(np.linalg.norm(cols @ np.asarray(effect.typical[:k]), axis=1)))
    return weighted_rows(cols, sys_.w), disp


def effect_std(model: MeasurementModel, sys_: LinearizedFit, effect: BoundEffect,
               q: np.ndarray, tau: np.ndarray, theta: np.ndarray) -> np.ndarray:
    """Return the std (k,) of every parameter of ``effect`` at its screened values ``theta``.

    The geometry free, at the stated σ: the shape parameters too, which the screen holds at
    a grid value. Held, a joint play's transition was "best of its grid" and its size b = −0.041 ±
    0.0016 rad looked determined, where the fit that frees the transition (identify) found
    b and u undetermined (std 4.2e4 rad and 5.1e3). Inf where a parameter has no
    direction of its own.
    """
    aug = _candidate_model(model, effect)
    p = np.concatenate([sys_.p, theta])
    _, jac = aug.jacobian(p, q, tau, sys_.reflector, sys_.rotation, sys_.covariates)
    cols = weighted_rows(jac[:, :, len(sys_.p):], sys_.w)
    unique = cols - sys_.basis @ (sys_.basis.T @ cols)
    info = unique.T @ unique
    try:
        cov = np.linalg.inv(info)
    except np.linalg.LinAlgError:
        return np.full(len(theta), np.inf)
    diag = np.diag(cov)
    return np.where(np.isfinite(diag) & (diag > 0), np.sqrt(np.abs(diag)), np.inf)


def absorbed_by(model: MeasurementModel, result: CalibrationResult, sys_: LinearizedFit,
                unit: np.ndarray) -> dict[str, float]:
    """Return the identified parameters that reproduce a signature, with their coefficients.

    ``unit`` (3N, k): the effect's weighted columns scaled to unit length; its first column is
    expressed in the fit's columns (each scaled to unit length), and the parameters of the
    (at most four) largest coefficients above 1e-3 are returned, by name.
    """
    norms = np.linalg.norm(sys_.jac, axis=0)
    ok = norms > 0
    coef, *_ = np.linalg.lstsq(sys_.jac[:, ok] / norms[ok], unit[:, 0], rcond=None)
    names = [n for n, keep in zip(result.estimated, ok) if keep]
    top = np.argsort(-np.abs(coef))[:4]
    return {names[t]: float(coef[t]) for t in top if abs(coef[t]) > 1e-3}
