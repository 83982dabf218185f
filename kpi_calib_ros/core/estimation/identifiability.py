"""Identifiable base parameters by QR decomposition of the stacked Jacobian.

Position-only tracker data cannot separate every error parameter: a rotation
of the base about the first joint axis equals a first-joint offset, a shift of
the reflector along the last axis equals a last-placement shift, and so on.
Fitting all of them gives a singular problem. As in the Stäubli toolkit (seed
004, §3.1/§4.1), QR with column pivoting on the column-equilibrated Jacobian
keeps a maximal independent subset; each dropped parameter is reported with the
kept parameters that absorb it, so a person sees *why* it was dropped.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.linalg

__all__ = [
    'DEFAULT_TOLERANCE', 'ZERO_COLUMN', 'PRIORITY_PIVOT_FRACTION', 'DroppedParameter',
    'Identifiability', 'select_identifiable',
]

DEFAULT_TOLERANCE = 1e-7
ZERO_COLUMN = 1e-10
# Threshold pivoting for method='priority': the next column in priority order is kept only
# if its residual is at least this fraction of the largest remaining one. Without it the
# order alone decides, and a column that is a combination of the kept ones up to 1e-6
# is "independent": the kept set then had a condition number ~2e6 (pivoted: ~190) and
# Gauss-Newton stopped at its iteration limit, 34 µm rms against 32 µm.
PRIORITY_PIVOT_FRACTION = 0.1


@dataclass(frozen=True)
class DroppedParameter:
    """A parameter left at its nominal value.

    ``absorbed_by`` maps kept parameter names to the coefficients (in
    column-normalised units) of the combination that reproduces its effect.
    """

    name: str
    reason: str
    absorbed_by: dict[str, float]


@dataclass(frozen=True)
class Identifiability:
    """Result of the rank analysis: ``kept`` names in vector order, ``dropped`` with reasons."""

    kept: tuple[str, ...]
    dropped: tuple[DroppedParameter, ...]
    rank: int
    singular_ratio: float


def select_identifiable(jacobian: np.ndarray, names: list[str] | tuple[str, ...],
                        tolerance: float = DEFAULT_TOLERANCE,
                        method: str = 'pivoted',
                        priority: list[str] | None = None,
                        zero_column: float = ZERO_COLUMN,
                        pivot_fraction: float = PRIORITY_PIVOT_FRACTION) -> Identifiability:
    """Choose a maximal identifiable subset of parameters.

    Parameters
    ----------
    jacobian : (m, n_p) ndarray
        Stacked (weighted) measurement Jacobian over the configurations.
    names : sequence of str
        Parameter names, one per column.
    tolerance : float
        Relative threshold on |R_kk| / |R_00| of the column-normalised QR.
    method : {'pivoted', 'priority'}
        ``'pivoted'``: QR with column pivoting (largest remaining column first).
        ``'priority'``: QR with threshold pivoting: the next column is the first in
        the order of ``priority`` whose residual (after projecting out the kept
        columns) is at least ``pivot_fraction`` of the largest remaining one. Same
        rank as ``'pivoted'``, a preferred choice of columns, and a conditioning within
        a known factor of the pivoted one.
    priority : list of str, optional
        Order for ``method='priority'``; names not listed follow in vector order.
    zero_column : float
        Columns whose norm is below this fraction of the largest count as having
        no effect at all (reported as such, never normalised into noise).
    pivot_fraction : float
        In [0, 1]; 0 keeps columns in priority order whenever they are independent
        at all (used to restate an already chosen, well-conditioned set).

    Raises
    ------
    ValueError
        ``priority`` names a parameter not in ``names``.
    """
    names = list(names)
    if jacobian.shape[1] != len(names):
        raise ValueError('jacobian columns and names differ in number')
    unknown = [p for p in priority or [] if p not in names]
    if unknown:
        raise ValueError(f'priority names unknown parameters {unknown}; valid: {names}')
    norms = np.linalg.norm(jacobian, axis=0)
    # A column at round-off level (e.g. a rotation about an axis the reflector sits on)
    # must not be normalised into noise that QR would take for information.
    floor = zero_column * norms.max()
    unseen = [n for n, v in zip(names, norms) if v <= floor]
    cols = [i for i, v in enumerate(norms) if v > floor]
    a = jacobian[:, cols] / norms[cols]
    if method == 'pivoted':
        _, r, perm = scipy.linalg.qr(a, mode='economic', pivoting=True)
        diag = np.abs(np.diag(r))
        kept_pos = perm[:len(diag)][diag > tolerance * diag[0]]
        kept_diag = diag[diag > tolerance * diag[0]]
    elif method == 'priority':
        kept_pos, kept_diag = _threshold_pivoting(
            a, _priority_order([names[i] for i in cols], priority or []), tolerance,
            pivot_fraction)
    else:
        raise ValueError(f"method must be 'pivoted' or 'priority', not {method!r}")
    kept_cols = [cols[i] for i in sorted(kept_pos)]
    kept_local = sorted(kept_pos)
    dropped = [DroppedParameter(n, 'no effect on the measurements at the nominal geometry', {})
               for n in unseen]
    basis = a[:, kept_local]
    for local in range(a.shape[1]):
        if local in kept_local:
            continue
        coef, *_ = np.linalg.lstsq(basis, a[:, local], rcond=None)
        top = np.argsort(-np.abs(coef))[:4]
        absorbed = {names[cols[kept_local[t]]]: float(coef[t]) for t in top
                    if abs(coef[t]) > 1e-3}
        text = ', '.join(f'{k} ({v:+.2f})' for k, v in absorbed.items())
        dropped.append(DroppedParameter(names[cols[local]],
                                        f'linearly dependent on {text}', absorbed))
    ratio = float(kept_diag.min() / kept_diag.max()) if len(kept_diag) else 0.0
    return Identifiability(tuple(names[c] for c in kept_cols),
                           tuple(sorted(dropped, key=lambda d: names.index(d.name))),
                           len(kept_cols), ratio)


def _priority_order(names: list[str], priority: list[str]) -> list[int]:
    ranked = [names.index(p) for p in priority if p in names]
    return ranked + [i for i in range(len(names)) if i not in ranked]


def _threshold_pivoting(a: np.ndarray, order: list[int], tolerance: float,
                        fraction: float) -> tuple[np.ndarray, np.ndarray]:
    """Column selection of unit columns ``a`` by QR with threshold pivoting.

    At each step the residuals of the remaining columns (after projecting out the kept
    ones) are compared with the largest: the first column in ``order`` within
    ``fraction`` of it is kept. Stops when the largest residual is below ``tolerance``
    (the pivoted rule, whose first pivot is 1 for unit columns). Gram-Schmidt, applied
    twice for orthogonality.

    Returns
    -------
    kept : ndarray of int
        Positions in ``a`` in the order chosen.
    sizes : ndarray
        Their residual norms (the pivots).
    """
    residual = a.copy()
    remaining = list(order)
    kept, sizes = [], []
    while remaining:
        norms = np.linalg.norm(residual[:, remaining], axis=0)
        largest = norms.max()
        if largest <= tolerance:
            break
        pick = next(k for k, size in enumerate(norms) if size >= fraction * largest
                    and size > tolerance)
        i = remaining.pop(pick)
        v = residual[:, i] / norms[pick]
        for _ in range(2):
            residual -= np.outer(v, v @ residual)
        kept.append(i)
        sizes.append(norms[pick])
    return np.array(kept, dtype=int), np.array(sizes)
