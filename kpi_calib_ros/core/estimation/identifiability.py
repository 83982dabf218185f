"""Identifiable base parameters by QR decomposition of the stacked Jacobian.

Position-only tracker data cannot separate every error parameter: a rotation
of the base about the first joint axis equals a first-joint offset, a shift of
the reflector along the last axis equals a last-placement shift, and so on.
Fitting all of them gives a singular problem. As in the Stäubli toolkit (seed
004, §3.1/§4.1), QR with column pivoting on the column-equilibrated Jacobian
keeps a maximal independent subset; each dropped parameter is reported with the
kept parameters that absorb it, so a person sees *why* it was dropped.

The tolerance decides at one point of the parameter space. A direction that vanishes at
the nominal geometry (a rotation about the flange axis the nominal reflector sits on) is
there at any point off it, the estimate included, however little the estimate moved off
it. Whether the *truth* has it is a question of statistics: `significant_rank` tests the
directions a selection at the estimate adds by a Wald test of their singular values
against what the estimate's own noise produces (sequential rank test, as Robin & Smith,
Econometric Theory 16 (2000), for a matrix known only through an estimate).
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Callable, Sequence

import numpy as np
import scipy.linalg
import scipy.stats

__all__ = [
    'DEFAULT_TOLERANCE', 'ZERO_COLUMN', 'PRIORITY_PIVOT_FRACTION', 'RANK_ALPHA',
    'DroppedParameter', 'Identifiability', 'RankTest', 'select_identifiable', 'significant_rank',
]

DEFAULT_TOLERANCE = 1e-7
ZERO_COLUMN = 1e-10
# Threshold pivoting for method='priority': the next column in priority order is kept only
# if its residual is at least this fraction of the largest remaining one. Without it the
# order alone decides, and a column that is a combination of the kept ones up to 1e-6
# is "independent": the kept set then had a condition number ~2e6 (pivoted: ~190) and
# Gauss-Newton stopped at its iteration limit, 34 µm rms against 32 µm.
PRIORITY_PIVOT_FRACTION = 0.1
# Level of the Wald test of `significant_rank`: the probability that a direction the truth
# lacks is identified because the estimate's noise put it there. As the change test's
# level (core.campaigns.change_detection): such a direction costs a fit that crawls along
# it (see `significant_rank`), a direction the truth has but the test misses is one whose
# singular value is within a few std of zero, whose effect on the predictions is as small.
RANK_ALPHA = 1e-3


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


@dataclass(frozen=True)
class RankTest:
    """Outcome of `significant_rank`.

    Attributes
    ----------
    rank : int
        Number of the candidate's directions the data establish.
    statistic, dof, p_value : float, int, float
        Wald statistic, its χ² degrees of freedom and upper-tail probability of the last
        hypothesis tested (the one accepted; when every one was rejected, the last
        rejected); statistic nan and dof 0 when nothing was tested.
    """

    rank: int
    statistic: float
    dof: int
    p_value: float

    def reason(self, alpha: float = RANK_ALPHA) -> str:
        """Say in words why the directions above `rank` are left out."""
        return (f'identifiable at the estimate only through its noise (Wald χ² '
                f'{self.statistic:.3g} on {self.dof} dof, p = {self.p_value:.2g} ≥ {alpha:g})')


def significant_rank(jacobian_at: Callable[[np.ndarray], np.ndarray], x: np.ndarray,
                     candidate: Sequence[int], estimated: Sequence[int],
                     alpha: float = RANK_ALPHA, step: float = 1.0) -> RankTest:
    """Test how many directions of ``candidate`` the truth has, after a fit to ``x``.

    The fit over ``estimated`` reached ``x``, where the selection keeps ``candidate``. The
    column-equilibrated Jacobian A (m, k) of the candidate set at the estimate has the
    singular value decomposition A = U diag(s) Vᵀ. That its directions ``r + 1 … k``
    vanish at the truth is the hypothesis M(x_true) = 0 for M = U₂ᵀ A V₂ (U₂, V₂ the last
    k − r singular vectors). The estimate is off the truth by δ ~ N(0, C), C = (F_EᵀF_E)⁻¹
    the covariance of the fit over ``estimated``, so under the hypothesis
    vec M(x) = G δ, G = ∂ vec M / ∂x_E, and the Wald statistic
    W = vec Mᵀ (G C Gᵀ)⁺ vec M is χ² with rank(G C Gᵀ) degrees of freedom. The rank is the
    first r from ``len(estimated)`` up whose hypothesis is not rejected at level ``alpha``
    (Robin & Smith's sequential test), or k.

    G comes from second derivatives of the model: ∂M_ab/∂x = ∇²(u_aᵀ h) d_b with
    d_b = D⁻¹ v_b (D the column norms at ``x``, held fixed: the hypothesis is then about
    A = F D⁻¹ with one scaling, and the test does not depend on it), a central difference
    of the Jacobian along d_b with step 1 (a move of the predictions by about one σ: each
    column of A has norm 1). Measured on the default cell (noise only and drawn robots):
    W the same to 6 digits for steps 0.01 to 100.

    The directions tested are the smallest singular values of the *equilibrated*
    Jacobian, those a trust region in these units crawls along. A single parameter whose
    column vanishes at the truth but stands independent at the estimate has a unit column
    there and is not small in these units; it is not tested (it does not slow the fit).

    Parameters
    ----------
    jacobian_at : callable
        x (n,) -> (m, n) weighted Jacobian of the residual rows (prior rows included) over
        the free coordinates, dimensionless per unit of each coordinate.
    x : (n,) ndarray
        The estimate, free coordinates.
    candidate : sequence of int
        Columns of the selection at ``x``; their number k is the rank tolerance alone gives.
    estimated : sequence of int
        Columns the fit that reached ``x`` was over; its rank is taken as established.
    alpha : float
        Level of each test.
    step : float
        Central-difference step along d_b, equilibrated units.

    Returns
    -------
    RankTest
    """
    candidate, estimated = list(candidate), list(estimated)
    k, r0 = len(candidate), len(estimated)
    if k <= r0:
        return RankTest(k, float('nan'), 0, float('nan'))
    f = jacobian_at(x)
    norms = np.linalg.norm(f[:, candidate], axis=0)
    u, _, vt = np.linalg.svd(f[:, candidate] / norms, full_matrices=False)
    # C^½ of the fit over ``estimated``: C = (FᵀF)⁻¹ = V diag(1/s²) Vᵀ.
    _, s_e, vt_e = np.linalg.svd(f[:, estimated], full_matrices=False)
    c_half = vt_e.T / s_e
    weak = range(r0, k)
    # ∂(F d_b)/∂x restricted to the rows' projections on u_a: hess[b][:, a] = ∂M_ab/∂x_E.
    hess = {}
    for b in weak:
        d = np.zeros_like(x)
        d[candidate] = step * vt[b] / norms
        diff = (jacobian_at(x + d) - jacobian_at(x - d))[:, estimated] / (2.0 * step)
        if not np.all(np.isfinite(diff)):
            # A saturating effect's Jacobian is not finite there: no test, as before.
            return RankTest(k, float('nan'), 0, float('nan'))
        hess[b] = diff.T @ u[:, r0:]
    test = RankTest(k, float('nan'), 0, float('nan'))
    for r in range(r0, k):
        block = range(r, k)
        m = np.array([u[:, a] @ (f[:, candidate] / norms) @ vt[b] for a in block for b in block])
        g = np.array([hess[b][:, a - r0] for a in block for b in block])
        gc = g @ c_half
        cov = gc @ gc.T
        eig = np.linalg.eigvalsh(cov)
        dof = int(np.sum(eig > eig.max() * 1e-10)) if eig.max() > 0 else 0
        stat = float(m @ np.linalg.pinv(cov, rcond=1e-10, hermitian=True) @ m) if dof else np.inf
        p_value = float(scipy.stats.chi2.sf(stat, dof)) if dof else 0.0
        test = RankTest(r, stat, dof, p_value)
        if p_value >= alpha:
            return test
    return dataclasses.replace(test, rank=k)


def select_identifiable(jacobian: np.ndarray, names: list[str] | tuple[str, ...],
                        tolerance: float = DEFAULT_TOLERANCE,
                        method: str = 'pivoted',
                        priority: list[str] | None = None,
                        zero_column: float = ZERO_COLUMN,
                        pivot_fraction: float = PRIORITY_PIVOT_FRACTION,
                        max_rank: int | None = None,
                        cut_reason: str = 'beyond the rank limit',
                        first: Sequence[str] = (), explain: bool = True) -> Identifiability:
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
    max_rank : int, optional
        Keep at most this many columns (the rank `significant_rank` found); a column
        left out by this limit though independent of the kept ones above ``tolerance``
        is reported with ``cut_reason``.
    cut_reason : str
        Why a column is left out by ``max_rank``.
    first : sequence of str
        Columns kept before any other, in this order, each one independent of those before
        it (the placements of several recordings: each set-up's own, never a gauge the
        robot's parameters carry); ``method`` then chooses among the others with these
        projected out. Empty (default): ``method`` alone.
    explain : bool
        Give every dropped parameter its reason (a least-squares fit of its column on the
        kept ones, the most of the time here); False: ``dropped`` is empty, the rest the
        same, for a caller that needs the kept set only.

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
    if method not in ('pivoted', 'priority'):
        raise ValueError(f"method must be 'pivoted' or 'priority', not {method!r}")
    head = [cols.index(names.index(n)) for n in first if names.index(n) in cols]
    head_pos, head_diag = _threshold_pivoting(a[:, head], list(range(len(head))), tolerance,
                                              0.0) if head else (np.zeros(0, int), np.zeros(0))
    head_pos = np.array([head[i] for i in head_pos], dtype=int)
    rest = [i for i in range(a.shape[1]) if i not in set(head_pos.tolist())]
    b = a[:, rest]
    if len(head_pos):
        basis_q, _ = np.linalg.qr(a[:, head_pos])
        b = b - basis_q @ (basis_q.T @ b)
    if not rest:
        kept_pos, kept_diag = np.zeros(0, int), np.zeros(0)
    elif method == 'pivoted':
        _, r, perm = scipy.linalg.qr(b, mode='economic', pivoting=True)
        diag = np.abs(np.diag(r))
        # unit columns: the first pivot of the whole matrix is 1
        reference = 1.0 if len(head_pos) else diag[0]
        kept_pos = np.array(rest)[perm[:len(diag)][diag > tolerance * reference]]
        kept_diag = diag[diag > tolerance * reference]
    else:
        found, kept_diag = _threshold_pivoting(
            b, _priority_order([names[cols[i]] for i in rest], priority or []), tolerance,
            pivot_fraction)
        kept_pos = np.array(rest)[found] if len(found) else np.zeros(0, int)
    kept_pos = np.concatenate([head_pos, kept_pos]).astype(int)
    kept_diag = np.concatenate([head_diag, kept_diag])
    if max_rank is not None:
        kept_pos, kept_diag = kept_pos[:max_rank], kept_diag[:max_rank]
    kept_cols = [cols[i] for i in sorted(kept_pos)]
    kept_local = sorted(kept_pos)
    dropped = [DroppedParameter(n, 'no effect on the measurements at the nominal geometry', {})
               for n in unseen] if explain else []
    basis = a[:, kept_local]
    for local in range(a.shape[1]):
        if local in kept_local or not explain:
            continue
        coef, *_ = np.linalg.lstsq(basis, a[:, local], rcond=None)
        top = np.argsort(-np.abs(coef))[:4]
        absorbed = {names[cols[kept_local[t]]]: float(coef[t]) for t in top
                    if abs(coef[t]) > 1e-3}
        text = ', '.join(f'{k} ({v:+.2f})' for k, v in absorbed.items())
        cut = np.linalg.norm(a[:, local] - basis @ coef) > tolerance
        reason = (f'{cut_reason}; nearly dependent on {text}' if cut
                  else f'linearly dependent on {text}')
        dropped.append(DroppedParameter(names[cols[local]], reason, absorbed))
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
