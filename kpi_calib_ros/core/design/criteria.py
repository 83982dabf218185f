"""Design criteria of eq. (24a) for the linearised problem at the nominal parameters.

For the identifiable parameters (QR on a rich random pose set, once per cell)
the covariance is ``C_p = M⁻¹`` with the information ``M = Σ_i J_iᵀ W² J_i``
(W = diag(1/σ)), and the KPI covariance at working pose t is
``C_s,t = J_w,t C_p J_w,tᵀ`` (eq. 19; the KPI point is the reflector centre at
the working pose in the tracker frame, gauge-free). Criteria, all "smaller is
better" except O1:

* ``kpi``  Σ_t ω_t tr(C_s,t) / 3 with weights ω summing to 1 (m²): eq. (24a)
  with P projecting onto the TCP points; the average TCP variance.
* ``A``    tr(S C_p S) / k (m²): the parameter-optimal "state of the art" q_p.
  S_j is the rms length by which a unit change of parameter j moves the
  measured point (1 for a translation, the lever arm for an angle), so every
  term is the point variance that parameter's uncertainty causes: m and rad
  add up, and a parameter the reflector barely feels cannot dominate.
* ``D``    det(S C_p S)^(1/k) (m²).
* ``O1``   Borm-Menq (σ₁⋯σ_k)^(1/k)/√m of the S-scaled Jacobian (larger is better).
* ``cond`` condition number of the S-scaled Jacobian.

Numerics use the column-scaled rows W J D (D equilibrates the columns), so M̃ =
D M D is well conditioned although lengths and angles differ by orders.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Mapping, Sequence

import numpy as np

from kpi_calib_ros.core.design.cell import DesignCell
from kpi_calib_ros.core.design.exchange import (
    ConditionLoss,
    LogDetLoss,
    Loss,
    TraceLoss,
    information,
)
from kpi_calib_ros.core.errors import ConfigError
from kpi_calib_ros.core.estimation.identifiability import select_identifiable
from kpi_calib_ros.core.estimation.prior import Prior
from kpi_calib_ros.core.measurement.tracker import MeasurementModel
from kpi_calib_ros.core.measurement.weighting import weighted_rows

__all__ = ['CRITERIA', 'NEGLIGIBLE_EFFECT', 'DesignProblem', 'scales', 'build_problem']

CRITERIA = ('kpi', 'A', 'D', 'O1', 'cond')
# Relative column norm below which a parameter counts as having no effect at all.
NEGLIGIBLE_EFFECT = 1e-8


@dataclass(frozen=True)
class DesignProblem:
    """Linearised design problem at the nominal parameters.

    Attributes
    ----------
    parameter_names : tuple of str
        Identifiable parameters designed for (k).
    index : (k,) ndarray
        Their positions in ``model.params``.
    p : (n_p,) ndarray
        Parameters the Jacobians are evaluated at (nominal).
    weight : (3,) ndarray
        1/σ per tracker axis (1/m).
    column_scale : (k,) ndarray
        D: columns of W J D have unit rms over the rich pose set (numerics only).
    physical_scale : (k,) ndarray
        S: rms of ‖∂h/∂p_j‖ over the rich pose set (m per unit of p_j; 1 for a
        translation, the lever arm for an angle).
    kpi_jacobian : (t, 3, k) ndarray
        d s_t / d p of the KPI points (tracker frame).
    kpi_weights : (t,) ndarray
        ω_t, summing to 1.
    prior_information : (k, k) ndarray or None
        D Λ D: the precision of a Gaussian prior on the parameters (e.g. the last
        calibration widened by drift), column-scaled like the rows. Every design has it:
        M = D Λ D + Σ rows (the KPI criterion with the prior information added).
    """

    parameter_names: tuple[str, ...]
    index: np.ndarray
    p: np.ndarray
    weight: np.ndarray
    column_scale: np.ndarray
    physical_scale: np.ndarray
    kpi_jacobian: np.ndarray
    kpi_weights: np.ndarray
    prior_information: np.ndarray | None = None

    @property
    def k(self) -> int:
        """Number k of identified (designed-for) parameters."""
        return len(self.index)

    def rows(self, model: MeasurementModel, q: np.ndarray) -> np.ndarray:
        """Scaled weighted Jacobian rows W J D (N, 3R, k) of configurations ``q`` (N, n).

        Every row a measured pose gives (every reflector's point, every tracked body's rotation:
        R = ``model.rows_per_pose``, 1 for a single reflector).
        """
        _, jac = model.pose_jacobian(self.p, np.atleast_2d(q))
        weight = np.tile(self.weight, model.rows_per_pose)
        return jac[:, :, self.index] * weight[None, :, None] * self.column_scale

    def factor(self, criterion: str) -> np.ndarray:
        """L with ``loss = tr(L M̃⁻¹ Lᵀ)`` for M̃ = information of :meth:`rows`."""
        if criterion == 'kpi':
            w = np.sqrt(self.kpi_weights / 3.0)[:, None, None]
            return (w * self.kpi_jacobian * self.column_scale).reshape(-1, self.k)
        if criterion == 'A':
            return np.diag(self.column_scale * self.physical_scale) / np.sqrt(self.k)
        raise ValueError(f'criterion {criterion!r} has no trace form')

    def loss(self, criterion: str) -> Loss:
        """Loss object of :mod:`design_exchange` for ``criterion``."""
        if criterion in ('kpi', 'A'):
            return TraceLoss(self.factor(criterion))
        if criterion in ('D', 'O1'):
            return LogDetLoss()
        if criterion == 'cond':
            return ConditionLoss(1.0 / (self.column_scale * self.physical_scale))
        raise ValueError(f'criterion must be one of {CRITERIA}, got {criterion!r}')

    def information(self, rows: np.ndarray) -> np.ndarray:
        """M̃ of ``rows`` (N, 3R, k), the prior's information included."""
        info = information(rows)
        return info if self.prior_information is None else info + self.prior_information

    def parameter_covariance(self, rows: np.ndarray) -> np.ndarray:
        """C_p (k, k) of the identifiable parameters, in their own units."""
        d = self.column_scale
        return d[:, None] * np.linalg.inv(self.information(rows)) * d[None, :]

    def tcp_covariance(self, rows: np.ndarray) -> np.ndarray:
        """C_s,t (t, 3, 3) of the KPI points, m²."""
        c_p = self.parameter_covariance(rows)
        return self.kpi_jacobian @ c_p @ self.kpi_jacobian.transpose(0, 2, 1)

    def criteria(self, rows: np.ndarray) -> dict[str, float]:
        """Every criterion of the design with these rows (see module docstring)."""
        info = self.information(rows)
        sign, logdet = np.linalg.slogdet(info)
        if sign <= 0:
            return {c: float('inf') if c != 'O1' else 0.0 for c in CRITERIA}
        ds = self.column_scale * self.physical_scale
        log_scale = 2.0 * float(np.sum(np.log(ds)))
        tcp = self.tcp_covariance(rows)
        return {
            'kpi': float(self.kpi_weights @ np.trace(tcp, axis1=1, axis2=2) / 3.0),
            'A': TraceLoss(self.factor('A')).value(info),
            'D': float(np.exp((log_scale - logdet) / self.k)),
            'O1': float(np.exp(0.5 * (logdet - log_scale) / self.k)
                         / np.sqrt(rows.shape[0] * rows.shape[1])),
            'cond': self.loss('cond').value(info),
        }


def scales(jac: np.ndarray, weight_rows: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(column_scale, physical_scale)`` of a :class:`DesignProblem`.

    From the point Jacobians ``jac`` (R, 3·m, k) of its parameters over a pose set and the row
    weights ``weight_rows`` (3·m,) (1/σ per axis, per reflector): D = 1/rms of the weighted
    columns, S = rms of ‖∂h/∂p_j‖.
    """
    rms = np.sqrt(np.mean(np.sum((jac * weight_rows[None, :, None]) ** 2, axis=1), axis=0))
    return 1.0 / rms, np.sqrt(np.mean(np.sum(jac ** 2, axis=1), axis=0))


def build_problem(cell: DesignCell, q_rich: np.ndarray,
                  weights: Mapping[str, float] | None = None, prior: Prior | None = None,
                  p: np.ndarray | None = None,
                  free: Sequence[str] | None = None) -> DesignProblem:
    """Build the identifiable parameters, scalings and KPI Jacobians for a cell.

    Parameters
    ----------
    cell : DesignCell
    q_rich : (R, n) ndarray
        Many measurable configurations (a few hundred) for the rank analysis.
    weights : mapping of working pose name to weight, optional
    prior : Prior, optional
        Gaussian prior information every design has (e.g. the last calibration, widened
        by drift): its rows take part in the identifiability selection, as in
        :func:`kpi_calib_ros.core.estimation.least_squares.identify`, and its precision is added to
        the information of every design (``prior_information``).
    p : (n_p,) ndarray, optional
        Where to linearise (default: nominal; with a prior: its mean, e.g. the last
        calibration's values).
    free : sequence of str, optional
        The parameters the identification may free (default: all).
    """
    model = cell.model
    p = model.params.nominal.copy() if p is None else np.asarray(p, float)
    w = 1.0 / cell.sigma
    _, jac = model.pose_jacobian(p, q_rich)  # every row a measured pose gives
    wr = np.tile(w, model.rows_per_pose)
    names = list(model.params.names) if free is None else list(free)
    cols = model.params.indices(names)
    # Without `free`, all columns as they are: a copy indexed by every column changes the
    # QR pivot among equivalent parameters (round-off), and so every plain design.
    stacked = weighted_rows(jac, wr)
    if free is not None:
        stacked = stacked[:, cols]
    if prior is not None:
        # A parameter that moves no point moves no KPI point either: leave it out even
        # when the prior names it (its column scale would be infinite).
        norms = np.linalg.norm(stacked, axis=0)
        seen = norms > NEGLIGIBLE_EFFECT * norms.max()
        names = [n for n, ok in zip(names, seen) if ok]
        cols, stacked = cols[seen], stacked[:, seen]
    rows_prior = None
    if prior is not None:
        rows_prior = prior.rows(model.params)[0]
        # Scaled like the data rows of the rich set: a prior worth many poses is not
        # drowned by the few hundred rows used for the rank decision.
        stacked = np.vstack([stacked, rows_prior[:, cols] * np.sqrt(len(q_rich))])
    ident = select_identifiable(stacked, names,
                                method=cell.identification_method,
                                priority=list(cell.identification_priority) or None,
                                zero_column=NEGLIGIBLE_EFFECT, explain=False)
    idx = model.params.indices(ident.kept)
    column_scale, effect = scales(jac[:, :, idx], wr)
    poses = cell.working_pose_names
    weights = dict(weights or {})
    unknown = set(weights) - set(poses)
    if unknown:
        raise ConfigError('design.weights', f'unknown working poses {sorted(unknown)}; '
                          f'poses are {list(poses)}')
    omega = np.array([weights.get(n, 1.0) for n in poses], float)
    if omega.sum() <= 0:
        raise ConfigError('design.weights', 'at least one working pose needs a weight > 0')
    _, kpi_jac = model.jacobian(p, cell.q_work, cell.tau_work)
    prior_info = None
    if rows_prior is not None:
        scaled = rows_prior[:, idx] * column_scale  # D, the column scale of the rows
        prior_info = scaled.T @ scaled
    return DesignProblem(tuple(ident.kept), idx, p, w, column_scale, effect,
                         kpi_jac[:, :, idx], omega / omega.sum(), prior_info)
