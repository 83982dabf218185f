"""Gaussian prior information on named parameters (maximum a posteriori identification).

A prior p ~ N(m, C) over some of the model's parameters enters
:func:`kpi_calib_ros.core.estimation.least_squares.identify` as extra residual rows L (m − p) with
LᵀL = Λ = C⁻¹, so the Gauss–Newton minimises ½‖W(η − h)‖² + ½(p − m)ᵀ Λ (p − m) and the
KKT covariance of eq. (19) becomes C_p = (FᵀF + Λ)⁻¹. Parameters the prior does not name
are unconstrained.

Two sources:

* :func:`tolerance_prior` -- nominal tolerances: each robot parameter (joint placement
  and joint offset) has a std around its nominal value; base and reflector placements
  stay free (they are measured anew in every cell);
* :func:`kpi_calib_ros.io.calibration_file.prior_from_calibration` -- a previous
  calibration's values and ``parameter_covariance``, widened by :func:`drift_widened`
  for the time since it, and optionally moved along a drift state
  (:mod:`kpi_calib_ros.core.estimation.drift_state`).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Sequence

import numpy as np
import scipy.linalg

from kpi_calib_ros.core.errors import DataError
from kpi_calib_ros.core.model.parameters import ParameterSet

__all__ = [
    'THERMAL_EXPANSION_PER_K', 'KELVIN_PER_SQRT_HOUR', 'DRIFT_LENGTH_PER_SQRT_HOUR',
    'DRIFT_ANGLE_PER_SQRT_HOUR', 'PLACEMENT_PREFIXES', 'Prior', 'tolerance_prior',
    'drift_covariance', 'drift_widened', 'mapped_drift',
]

# Thermal expansion of steel/aluminium-steel arm structures, per metre and kelvin.
THERMAL_EXPANSION_PER_K = 12e-6
# Assumed temperature change of a shop floor: a random walk of 1 K per √hour.
KELVIN_PER_SQRT_HOUR = 1.0
# Default drift rates (random walks, std per √hour): relative length change of a
# placement (thermal growth) and angle drift of joint offsets and placement rotations
# (encoder/reducer settling, 20 µrad ≈ 20 µm at 1 m).
DRIFT_LENGTH_PER_SQRT_HOUR = THERMAL_EXPANSION_PER_K * KELVIN_PER_SQRT_HOUR
DRIFT_ANGLE_PER_SQRT_HOUR = 2e-5
# Placement parameters: the base pose, the reflector offsets and a further recording's.
PLACEMENT_PREFIXES = ('base.', 'reflector.', 'recording.')


@dataclass(frozen=True)
class Prior:
    """Gaussian prior N(mean, covariance) on the parameters ``names`` (SI units).

    Attributes
    ----------
    names : tuple of str
        Parameter names (a subset of the model's, any order).
    mean : (k,) ndarray
    covariance : (k, k) ndarray
        Symmetric positive definite.
    """

    names: tuple[str, ...]
    mean: np.ndarray
    covariance: np.ndarray

    def __post_init__(self) -> None:
        """Check names, shapes, finiteness, symmetry and definiteness; store the arrays."""
        k = len(self.names)
        mean = np.asarray(self.mean, float)
        cov = np.asarray(self.covariance, float)
        if len(set(self.names)) != k or mean.shape != (k,) or cov.shape != (k, k):
            raise DataError(f'prior: {k} unique names need a ({k},) mean and ({k}, {k}) '
                            f'covariance, got {mean.shape} and {cov.shape}')
        if not (np.all(np.isfinite(mean)) and np.all(np.isfinite(cov))):
            raise DataError('prior: mean and covariance must be finite')
        if not np.allclose(cov, cov.T, rtol=1e-9, atol=0.0):
            raise DataError('prior: covariance must be symmetric')
        try:
            np.linalg.cholesky(cov)
        except np.linalg.LinAlgError:
            raise DataError('prior: covariance must be positive definite (a parameter with '
                            'zero prior std is not a prior; fix it by leaving it out of '
                            'the free parameters)') from None
        object.__setattr__(self, 'mean', mean)
        object.__setattr__(self, 'covariance', 0.5 * (cov + cov.T))

    @property
    def std(self) -> np.ndarray:
        """Standard deviations (n,) of the prior, the parameters' units."""
        return np.sqrt(np.diag(self.covariance))

    def rows(self, params: ParameterSet) -> tuple[np.ndarray, np.ndarray]:
        """Square-root information rows over the model's full parameter vector.

        Returns
        -------
        L : (k, n_p) ndarray
            LᵀL = Λ = C⁻¹ in the columns of ``names``, zero elsewhere.
        lm : (k,) ndarray
            L m, so that the prior residual is ``lm − L @ p``.

        Raises
        ------
        DataError
            A prior name is not a parameter of the model.
        """
        unknown = [n for n in self.names if n not in params.names]
        if unknown:
            raise DataError(f'prior names unknown parameter(s) {unknown}; valid names are '
                            f'those of calibration.yaml parameters')
        # C = G Gᵀ (Cholesky), so Λ = G⁻ᵀ G⁻¹ and L = G⁻¹ (whitening rows).
        g = np.linalg.cholesky(self.covariance)
        l_small = scipy.linalg.solve_triangular(g, np.eye(len(self.names)), lower=True)
        full = np.zeros((len(self.names), len(params.names)))
        full[:, params.indices(list(self.names))] = l_small
        return full, l_small @ self.mean


def tolerance_prior(params: ParameterSet, translation: float, rotation: float,
                    offset: float, n_geometric: int | None = None) -> Prior:
    """Independent prior around the nominal values from manufacturing tolerances.

    Parameters
    ----------
    params : ParameterSet
        The model's parameters (geometric first).
    translation, rotation, offset : float
        Std of every joint placement translation (m), placement rotation (rad) and joint
        offset (rad, or m for a prismatic joint).
    n_geometric : int, optional
        Number of geometric parameters; effect parameters after them get no prior.
        Default: all.
    """
    for value, key in ((translation, 'translation'), (rotation, 'rotation'),
                       (offset, 'offset')):
        if not np.isfinite(value) or value <= 0:
            raise DataError(f'prior {key} std must be positive, got {value}')
    n_geo = len(params.names) if n_geometric is None else n_geometric
    names, std = [], []
    for name, unit in zip(params.names[:n_geo], params.units[:n_geo]):
        if name.startswith(PLACEMENT_PREFIXES):
            continue
        names.append(name)
        std.append(offset if name.endswith('.offset')
                   else translation if unit == 'm' else rotation)
    mean = np.array([params.nominal[params.index(n)] for n in names])
    return Prior(tuple(names), mean, np.diag(np.square(std)))


def drift_covariance(names: Sequence[str], lengths: dict[str, float],
                     length_rate: float = DRIFT_LENGTH_PER_SQRT_HOUR,
                     angle_rate: float = DRIFT_ANGLE_PER_SQRT_HOUR,
                     link_vectors: dict[tuple[str, str, str], np.ndarray] | None = None,
                     drifting: Callable[[str], bool] | None = None,
                     rotation_rate: float | None = None) -> np.ndarray:
    """Q (k, k): the covariance the parameters ``names`` gain per hour (random walks).

    A translation parameter named in ``lengths`` (the nominal length, m, of the link its
    placement belongs to) drifts by ``length_rate`` × length per √hour, independently
    per axis (isotropic); every other translation gets no drift; every joint offset
    (rad) drifts by ``angle_rate`` rad per √hour and every placement rotation (joint
    placements, base angles) by ``rotation_rate`` (default: ``angle_rate``); a prismatic
    offset (m) by ``length_rate`` × its length. ``drifting(name)`` false: no drift (e.g.
    effects).

    ``link_vectors`` (thermal model) maps the names of a translation triple (x, y, z) to
    its nominal vector t (m): thermal growth scales a link, δt = α ΔT t, so the triple
    drifts along t only, Q = length_rate² t tᵀ per hour (rank one; the temperature as a
    random walk of ``length_rate`` / α K per √hour). These triples override ``lengths``.
    """
    rotation_rate = angle_rate if rotation_rate is None else rotation_rate
    if length_rate < 0 or angle_rate < 0 or rotation_rate < 0:
        raise DataError('drift rates must be >= 0')
    names = list(names)
    q = np.diag([0.0 if drifting is not None and not drifting(n)
                 else (length_rate * lengths[n]) ** 2 if n in lengths
                 else 0.0 if _is_translation(n)
                 else angle_rate ** 2 if n.endswith('.offset') else rotation_rate ** 2
                 for n in names])
    for triple, vector in (link_vectors or {}).items():
        where = [(names.index(n), float(v)) for n, v in zip(triple, vector) if n in names]
        if not where:
            continue
        idx = np.array([i for i, _ in where])
        t = np.array([v for _, v in where])
        q[idx, idx] = 0.0  # the isotropic terms of these names, replaced
        q[np.ix_(idx, idx)] = length_rate ** 2 * np.outer(t, t)
    return q


def drift_widened(prior: Prior, hours: float, lengths: dict[str, float],
                  length_rate: float = DRIFT_LENGTH_PER_SQRT_HOUR,
                  angle_rate: float = DRIFT_ANGLE_PER_SQRT_HOUR,
                  link_vectors: dict[tuple[str, str, str], np.ndarray] | None = None
                  ) -> Prior:
    """``prior`` after ``hours`` of drift: C + Q·|hours|.

    Q of :func:`drift_covariance` on the prior's own parameters (see :func:`mapped_drift` when
    those are a reduced, identified set).
    """
    if not np.isfinite(hours):
        raise DataError(f'drift time must be finite, got {hours} h')
    q = drift_covariance(prior.names, lengths, length_rate, angle_rate, link_vectors)
    return Prior(prior.names, prior.mean, prior.covariance + q * abs(hours))


def mapped_drift(q_full: np.ndarray, jacobian: np.ndarray,
                 kept: Sequence[int] | np.ndarray) -> np.ndarray:
    """Map the drift Q_full of every parameter onto the identified ones ``kept``.

    Position data cannot separate all parameters: an identification keeps a maximal
    independent set and holds the rest, whose physical drift then shows up in the kept
    ones (the growth of a held link length appears as a change of the kept parameters
    that reproduce it). With J (m, n_p) the Jacobian of the measured points over many
    configurations, the kept parameters' change that reproduces a change δp of all is
    G δp, G = J_k⁺ J (least squares), so the kept set drifts by G Q_full Gᵀ.

    Returns
    -------
    (k, k) ndarray, k = len(kept)
    """
    kept = list(kept)
    g, *_ = np.linalg.lstsq(jacobian[:, kept], jacobian, rcond=None)
    q = g @ q_full @ g.T
    return 0.5 * (q + q.T)


def _is_translation(name: str) -> bool:
    return name.rsplit('.', 1)[-1] in ('x', 'y', 'z', 'tx', 'ty', 'tz')
