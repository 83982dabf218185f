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

DEFAULT_TOLERANCE = 1e-7
ZERO_COLUMN = 1e-10


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
                        zero_column: float = ZERO_COLUMN) -> Identifiability:
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
        ``'priority'``: keep columns in the order of ``priority`` unless they
        are (numerically) combinations of columns already kept.
    priority : list of str, optional
        Order for ``method='priority'``; names not listed follow in vector order.
    zero_column : float
        Columns whose norm is below this fraction of the largest count as having
        no effect at all (reported as such, never normalised into noise).
    """
    names = list(names)
    if jacobian.shape[1] != len(names):
        raise ValueError('jacobian columns and names differ in number')
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
        kept_pos, kept_diag = _greedy(a, _priority_order([names[i] for i in cols],
                                                         priority or []), tolerance)
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


def _greedy(a: np.ndarray, order: list[int], tolerance: float) -> tuple[np.ndarray, np.ndarray]:
    """Keep columns in ``order`` whose residual after projecting out the kept ones is large.

    Gram-Schmidt (applied twice for orthogonality) rather than unpivoted
    Householder QR, which mis-handles a dependent column in the middle.
    """
    basis = np.zeros((a.shape[0], 0))
    kept, sizes = [], []
    for i in order:
        v = a[:, i].copy()
        for _ in range(2):
            v -= basis @ (basis.T @ v)
        size = np.linalg.norm(v)
        if size > tolerance:
            basis = np.hstack([basis, (v / size)[:, None]])
            kept.append(i)
            sizes.append(size)
    return np.array(kept, dtype=int), np.array(sizes)
