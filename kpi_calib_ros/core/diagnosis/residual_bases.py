"""The bases of the residual analysis: spline, Fourier, one harmonic, one constant per value.

Each input's misfit is fitted in these functions of its values
(:mod:`kpi_calib_ros.core.diagnosis.residual_analysis`).
"""
from __future__ import annotations

from typing import Sequence

import numpy as np
import scipy.interpolate

from kpi_calib_ros.core.diagnosis.residual_inputs import ResidualInput

__all__ = ['Basis', 'spline_basis', 'one_hot', 'fourier_basis', 'basis_columns', 'basis_text',
           'candidate_bases']

# A basis: ('spline', functions), ('harmonics', H), ('harmonic', k) or ('categories', 0).
Basis = tuple[str, int]


def spline_basis(x: np.ndarray, size: int, support: np.ndarray | None = None) -> np.ndarray:
    """Cubic B-spline basis (M, size) at ``x`` (M,), constant beyond the ends.

    Interior knots at the quantiles of ``support`` (default ``x``) so that every piece holds
    data.

    ``size`` is capped by the distinct values of ``support`` (fewer columns then).
    """
    support = np.asarray(x if support is None else support, float)
    lo, hi = float(np.min(support)), float(np.max(support))
    distinct = len(np.unique(support))
    size = max(1, min(size, distinct))
    if size < 4 or hi <= lo:  # too few values for a cubic: a polynomial of low degree
        t = (np.clip(x, lo, hi) - lo) / (hi - lo) if hi > lo else np.zeros(len(x))
        return np.vander(t, size, increasing=True)
    inner = np.quantile(support, np.linspace(0, 1, size - 2)[1:-1])
    inner = np.unique(inner)
    knots = np.concatenate([[lo] * 4, inner, [hi] * 4])
    xc = np.clip(np.asarray(x, float), lo, hi)
    return scipy.interpolate.BSpline.design_matrix(xc, knots, 3).toarray()


def one_hot(codes: np.ndarray, support: np.ndarray) -> np.ndarray:
    """Return columns (M, L), 1 where ``codes`` (M,) equals each of the L values of ``support``."""
    levels = np.unique(support)
    return (np.asarray(codes)[:, None] == levels[None, :]).astype(float)


def fourier_basis(x: np.ndarray, harmonics: int) -> np.ndarray:
    """(M, 2H + 1) columns 1, cos(k x), sin(k x), k = 1..H, of angles ``x`` (rad)."""
    k = np.arange(1, harmonics + 1)
    kx = np.asarray(x, float)[:, None] * k[None, :]
    return np.hstack([np.ones((len(kx), 1)), np.cos(kx), np.sin(kx)])


def basis_columns(x: np.ndarray, size: Basis, support: np.ndarray) -> np.ndarray:
    """Return the columns (M, ·) of the basis ``size`` at ``x`` (M,), knots from ``support``."""
    kind, m = size
    if kind == 'categories':
        return one_hot(x, support)
    if kind == 'harmonics':
        return fourier_basis(x, m)
    if kind == 'harmonic':
        return np.stack([np.cos(m * np.asarray(x, float)), np.sin(m * np.asarray(x, float))],
                        axis=1)
    return spline_basis(x, m, support)


def basis_text(size: Basis) -> str:
    """Return plain words for the basis ``size`` (the report's text)."""
    kind, m = size
    return {'categories': 'one constant per value',
            'harmonics': f'harmonics 1-{m} of the turn',
            'harmonic': f'{m} cycles per turn',
            'spline': f'cubic spline, {m} functions'}[kind]


def candidate_bases(inp: ResidualInput, support: np.ndarray, cap: int, sizes: Sequence[int],
                     harmonics: Sequence[int]) -> list[Basis]:
    """Return the bases tried for ``inp``.

    Splines of ``sizes`` up to ``cap`` functions, Fourier bases of a periodic input, one
    constant per value of a categorical one.
    """
    if inp.categorical:
        return [('categories', 0)]
    out: list[Basis] = [('spline', m) for m in
                        sorted({min(s, cap, len(np.unique(support))) for s in sizes})]
    if inp.periodic:
        out += [('harmonics', h) for h in harmonics if 2 * h + 1 <= cap]
        out += [('harmonic', k) for k in range(2, max(harmonics, default=1) + 1)]
    return out
