"""The function a flagged input implies: its values, its fitted curve, where it is large.

The residual analysis (:mod:`kpi_calib_ros.core.diagnosis.residual_analysis`) reports for
each flagged input the curve of the misfit over the input's range, determined where it is
clear of the noise, and the ranges where it is at least half its largest size.
"""
from __future__ import annotations

import numpy as np

from kpi_calib_ros.core.diagnosis.residual_bases import Basis, basis_columns
from kpi_calib_ros.core.diagnosis.residual_inputs import ResidualInput
from kpi_calib_ros.core.measurement.weighting import weighted_rows

__all__ = ['CURVE_POINTS', 'DETERMINED_SE', 'GAP_SHARE', 'implied_values', 'fitted_curve',
           'curve_region']

CURVE_POINTS = 200


def implied_values(inp: ResidualInput, residuals: np.ndarray, w: np.ndarray
             ) -> tuple[np.ndarray, np.ndarray]:
    """Return per row and field the function value the residual implies and its weight."""
    g = inp.fields
    g2 = np.sum(g ** 2, axis=1)                                        # (N, d)
    with np.errstate(invalid='ignore', divide='ignore'):
        implied = np.where(g2 > 0, np.einsum('nak,na->nk', g, residuals) / g2, np.nan)
    weight = np.stack([np.sum(weighted_rows(g[:, :, k:k + 1], w).reshape(-1, 3) ** 2, axis=1)
                       for k in range(g.shape[2])], axis=1)
    return implied, weight


# The size of a fitted function is read only where it is determined: at least this many
# standard errors (from the stated σ) from zero. Elsewhere (rows where the input barely moves
# the point: a short lever, a small field) the implied value is noise over a tiny field, and
# a spline piece fitted to such rows alone reached 7.4e7 µrad.
DETERMINED_SE = 3.0


def fitted_curve(inp: ResidualInput, implied: np.ndarray, weight: np.ndarray, size: Basis,
           support: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Return the weighted spline fit of each field's implied values on a grid of the input.

    Returns the grid, the fit (grid, d) and the fit where it is determined (NaN where it is
    within :data:`DETERMINED_SE` standard errors of zero). ``weight`` is the inverse variance
    of each implied value under the stated σ, so (BᵀWB)⁻¹ is the coefficients' covariance.
    """
    if inp.categorical:
        grid = np.unique(support)
    else:
        grid = np.linspace(np.min(support), np.max(support), CURVE_POINTS)
    out = np.full((len(grid), implied.shape[1]), np.nan)
    determined = np.full_like(out, np.nan)
    for k in range(implied.shape[1]):
        ok = weight[:, k] > 0
        if ok.sum() < 2:
            continue
        b = basis_columns(inp.values[ok], size, support)
        sw = np.sqrt(weight[ok, k])
        coef, *_ = np.linalg.lstsq(b * sw[:, None], implied[ok, k] * sw, rcond=None)
        at = basis_columns(grid, size, support)
        out[:, k] = at @ coef
        # The coefficients' covariance from the SVD of the weighted design (as lstsq solves
        # it): a direction it cannot resolve leaves the grid points it touches undetermined.
        _, sv, vt = np.linalg.svd(b * sw[:, None], full_matrices=False)
        keep = sv > np.finfo(float).eps * max(b.shape) * sv[0]
        se = np.sqrt(np.sum((at @ vt[keep].T / sv[keep]) ** 2, axis=1))
        unresolved = np.linalg.norm(at @ vt[~keep].T, axis=1) > 1e-9 * np.linalg.norm(at, axis=1)
        se[unresolved] = np.inf
        determined[:, k] = np.where(np.abs(out[:, k]) >= DETERMINED_SE * se, out[:, k], np.nan)
    if not inp.categorical:
        far = ~_near_values(grid, np.asarray(inp.values, float))
        out[far] = np.nan
        determined[far] = np.nan
    return grid, out, determined


# A stretch between two neighbouring measured values longer than this share of their span
# is a gap no row measured: recordings a day apart on the time axis, where the spline's
# value is an extrapolation (it reached 7.75e4 µm between two recordings whose largest
# residual was 416 µm). Random poses leave gaps of a few per cent: read through.
GAP_SHARE = 0.1


def _near_values(grid: np.ndarray, values: np.ndarray) -> np.ndarray:
    """Which points of ``grid`` lie outside every gap of the measured ``values``."""
    values = np.unique(values[np.isfinite(values)])
    if len(values) < 3:
        return np.ones(len(grid), bool)
    gaps = np.flatnonzero(np.diff(values) > GAP_SHARE * (values[-1] - values[0]))
    near = np.ones(len(grid), bool)
    for i in gaps:
        near &= ~((grid > values[i]) & (grid < values[i + 1]))
    return near


_SHOWN = {'rad': (1e6, 'µrad'), 'm': (1e6, 'µm'), '': (1e6, 'ppm')}


def curve_region(inp: ResidualInput, grid: np.ndarray, curve: np.ndarray,
                 largest_m: float = np.inf) -> str:
    """Return where the fitted function is at least half its largest size.

    The widest (up to three) ranges of the input, in degrees for a joint angle. ``curve``
    is NaN where the fit is not determined (:func:`fitted_curve`): its size there says nothing.
    A size that would move the points more than twice the largest residual (``largest_m``)
    is no size the data show (the function is nearly one the geometry has, its value
    arbitrary along it: a real TIAGo's "joint error up to 6.05e+05 µrad", 278 mm at the
    points, where no point missed by more than 7.1 mm): the region is stated without it.
    """
    if not np.isfinite(curve).any():
        return ''
    # The function that moves the points most (m): each function's size times how far a
    # unit of it moves a point (rms over the rows it moves). Compared in their own units, a
    # 4.95 ppm scale outranked the drifts of a recording whose misfit was 48 µm.
    norms = np.linalg.norm(np.asarray(inp.fields, float), axis=1)
    moved = norms.any(axis=1)
    lever = np.sqrt(np.mean(norms[moved] ** 2, axis=0)) if moved.any() \
        else np.ones(curve.shape[1])
    size = np.where(np.isfinite(curve), np.abs(curve), -1.0)
    k = int(np.argmax(size.max(axis=0) * lever))
    c = size[:, k]
    peak = float(c.max())
    high = np.append(c >= 0.5 * peak, False)
    runs, start = [], None
    for i, h in enumerate(high):
        if h and start is None:
            start = i
        elif not h and start is not None:
            runs.append((grid[start], grid[i - 1]))
            start = None
    runs = sorted(sorted(runs, key=lambda ab: ab[0] - ab[1])[:3])
    scale, unit = (np.degrees(1.0), 'deg') if inp.periodic else (1.0, inp.unit)
    where = ', '.join(f'{a * scale:.4g} to {b * scale:.4g}' if a != b else f'{a * scale:.4g}'
                      for a, b in runs)
    factor, shown = _SHOWN.get(inp.field_units[k], (1.0, inp.field_units[k]))
    if peak * lever[k] > 2.0 * largest_m:
        return (f'{inp.field_names[k]} largest (its size not what the points show: more than '
                f'twice the largest residual) where {inp.name} is {where} {unit}').strip()
    points = (f' (~{peak * lever[k] * 1e6:.3g} µm at the points)'
              if inp.field_units[k] != 'm' else '')
    return (f'{inp.field_names[k]} up to {peak * factor:.3g} {shown}{points} where '
            f'{inp.name} is {where} {unit}').strip()
