"""Exchange algorithm over a candidate set (seed 004, Sec. 3.3.1) with rank-3 updates.

A design is a set of N candidate indices; its (column-scaled) information
matrix is ``M = Σ_i A_iᵀ A_i`` with ``A_i`` (3, k) the weighted Jacobian rows of
one tracker point. Adding or removing one configuration changes M by a rank-3
term, so every candidate's effect on the criterion follows from the
Sherman-Morrison-Woodbury identity with 3x3 solves only:

    (M ± AᵀA)⁻¹ = M⁻¹ ∓ M⁻¹Aᵀ S⁻¹ A M⁻¹,     S = I ± A M⁻¹ Aᵀ,
    det(M ± AᵀA) = det M · det S.

Losses (smaller is better) are ``tr(L M⁻¹ Lᵀ)`` (KPI and A criteria),
``-log det M`` (D, O1) and the condition number (rescaled, by eigenvalues).
The algorithm: (1) a random nonsingular start of ``n_init`` configurations,
(2) remove the least useful and add the best candidate while that improves,
(3) add the best candidates up to N, (4) final remove-and-replace sweeps over
every selected configuration until none improves.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Protocol, Sequence

import numpy as np

__all__ = [
    'Loss', 'TraceLoss', 'LogDetLoss', 'ConditionLoss', 'ExchangeResult', 'information',
    'exchange',
]


class Loss(Protocol):
    """A design criterion as the exchange algorithm uses it (smaller is better)."""

    def value(self, info: np.ndarray) -> float:
        """Loss of the information matrix ``info`` (k, k); inf when singular."""

    def delta(self, info_inv: np.ndarray, rows: np.ndarray, sign: float) -> np.ndarray:
        """Change of the loss (c,) when each of ``rows`` (c, 3, k) is added (+1) or removed (-1)."""


class TraceLoss:
    """``tr(L M⁻¹ Lᵀ)`` for a fixed factor ``L`` (r, k): the KPI and A criteria."""

    def __init__(self, factor: np.ndarray) -> None:
        self.factor = np.asarray(factor, float)

    def value(self, info: np.ndarray) -> float:
        """Loss ``tr(L M⁻¹ Lᵀ)`` of the information matrix ``info`` (k, k); inf when singular."""
        try:
            chol = np.linalg.cholesky(info)
        except np.linalg.LinAlgError:
            return float('inf')
        y = np.linalg.solve(chol, self.factor.T)
        return float(np.sum(y * y))

    def delta(self, info_inv: np.ndarray, rows: np.ndarray, sign: float) -> np.ndarray:
        """Change of the loss when each of ``rows`` (c, 3, k) is added (+1) or removed (-1)."""
        b = rows @ info_inv                                   # (c, 3, k)
        s = np.eye(rows.shape[1]) + sign * b @ rows.transpose(0, 2, 1)  # (c, 3, 3)
        bl = b @ self.factor.T                                # (c, 3, r)
        h = bl @ bl.transpose(0, 2, 1)
        out = np.full(len(rows), np.inf if sign < 0 else 0.0)
        ok = np.linalg.det(s) > 1e-12
        out[ok] = -sign * np.trace(np.linalg.solve(s[ok], h[ok]), axis1=1, axis2=2)
        return out


class LogDetLoss:
    """``-log det M``: the D criterion (and O1, equivalent for a fixed N)."""

    def value(self, info: np.ndarray) -> float:
        """Loss ``-log det M`` of ``info`` (k, k); inf when not positive definite."""
        sign, logdet = np.linalg.slogdet(info)
        return float(-logdet) if sign > 0 else float('inf')

    def delta(self, info_inv: np.ndarray, rows: np.ndarray, sign: float) -> np.ndarray:
        """Change of the loss (c,) when each of ``rows`` (c, 3, k) is added (+1) or removed (-1)."""
        s = np.eye(rows.shape[1]) + sign * (rows @ info_inv) @ rows.transpose(0, 2, 1)
        det_sign, logdet = np.linalg.slogdet(s)
        return np.where(det_sign > 0, -logdet, np.inf)


class ConditionLoss:
    """Condition number of the Jacobian in physical units, ``sqrt(λmax/λmin)`` of T M T."""

    def __init__(self, transform: np.ndarray) -> None:
        self.transform = np.asarray(transform, float)  # (k,) diagonal

    def _cond(self, info: np.ndarray) -> np.ndarray:
        t = self.transform
        eig = np.linalg.eigvalsh(info * t[..., :, None] * t[..., None, :])
        lo, hi = eig[..., 0], eig[..., -1]
        return np.where(lo > 0, np.sqrt(np.abs(hi / np.where(lo > 0, lo, 1.0))), np.inf)

    def value(self, info: np.ndarray) -> float:
        """Condition number of the rescaled ``info`` (k, k); inf when singular."""
        return float(self._cond(info))

    def delta(self, info_inv: np.ndarray, rows: np.ndarray, sign: float) -> np.ndarray:
        """Change of the loss (c,) when each of ``rows`` (c, 3, k) is added (+1) or removed (-1)."""
        info = np.linalg.inv(info_inv)
        updated = info[None] + sign * rows.transpose(0, 2, 1) @ rows
        return self._cond(updated) - self.value(info)


@dataclass(frozen=True)
class ExchangeResult:
    """Selected candidate indices (N,), final loss and the loss after each accepted step."""

    selected: np.ndarray
    loss: float
    history: tuple[float, ...]
    exchanges: int


def information(rows: np.ndarray) -> np.ndarray:
    """``Σ_i A_iᵀ A_i`` (k, k) of rows (N, 3, k)."""
    flat = rows.reshape(-1, rows.shape[-1])
    return flat.T @ flat


def exchange(rows: np.ndarray, n: int, loss: Loss, rng: np.random.Generator,
             n_init: int | None = None, max_sweeps: int = 20,
             progress: Callable[[str], None] | None = None,
             base: np.ndarray | None = None) -> ExchangeResult:
    """Choose ``n`` of the candidates ``rows`` (c, 3, k) that minimise ``loss``.

    Parameters
    ----------
    rows : (c, 3, k) ndarray
        Column-scaled weighted Jacobian rows of every candidate.
    n : int
        Design size N (each candidate used at most once).
    loss : TraceLoss, LogDetLoss or ConditionLoss
    n_init : int, optional
        Size of the random start (step 1); default ``ceil(k/3) + 2``.
    max_sweeps : int
        Cap on the passes of steps 2 and 4 (each pass is N exchanges at most).
    base : (k, k) ndarray, optional
        Information every design already has (a prior's precision, column-scaled like
        the rows): M = base + Σ_i A_iᵀ A_i. With it fewer than k/3 configurations do.

    Raises
    ------
    ValueError
        Fewer candidates than ``n``, or no nonsingular random start found.
    """
    c, _, k = rows.shape
    if n > c:
        raise ValueError(f'n = {n} exceeds the {c} candidates')
    prior_info = np.zeros((k, k)) if base is None else np.asarray(base, float)

    def information_of(chosen: Sequence[int] | np.ndarray) -> np.ndarray:
        return information(rows[chosen]) + prior_info

    if base is None and 3 * n <= k:
        # identify needs a degree of freedom left (the noise it estimates): as many
        # equations as parameters is a design it refuses to identify.
        raise ValueError(f'n = {n} configurations give {3 * n} equations for {k} parameters; '
                         f'at least {k // 3 + 1} are needed (identify needs more equations '
                         'than parameters)')
    n_init = min(n, max(int(np.ceil(k / 3)) + 2, 1) if n_init is None else n_init)
    say = progress or (lambda _msg: None)
    # (1) Initialise: a random subset with a nonsingular information matrix.
    for _ in range(100):
        selected = list(rng.choice(c, size=n_init, replace=False))
        current = loss.value(information_of(selected))
        if np.isfinite(current):
            break
    else:
        raise ValueError('no nonsingular random start in 100 tries; are the parameters '
                         'identifiable over the candidates?')
    history = [current]

    def best_add(info_inv: np.ndarray, chosen: list[int]) -> tuple[int, float]:
        gain = loss.delta(info_inv, rows, +1.0)
        gain[chosen] = np.inf
        best = int(np.argmin(gain))
        return best, float(gain[best])

    def state(chosen: list[int]) -> tuple[np.ndarray, np.ndarray]:
        info = information_of(chosen)
        return info, np.linalg.inv(info)

    # (2) Remove the configuration whose loss increases least, add the best one.
    exchanges = 0
    for _ in range(max_sweeps * n_init):
        info, info_inv = state(selected)
        drop = loss.delta(info_inv, rows[selected], -1.0)
        j = int(np.argmin(drop))
        rest = selected[:j] + selected[j + 1:]
        _, rest_inv = state(rest) if np.isfinite(drop[j]) else (None, None)
        if rest_inv is None:
            break
        add, gain = best_add(rest_inv, selected)
        trial = current + drop[j] + gain
        if not trial < current - 1e-12 * abs(current):
            break
        selected = rest + [add]
        current = loss.value(information_of(selected))
        history.append(current)
        exchanges += 1
    say(f'exchange: start {history[0]:.4g}, after remove-and-replace {current:.4g}')
    # (3) Add the best candidate until the design has n configurations.
    while len(selected) < n:
        _, info_inv = state(selected)
        add, _ = best_add(info_inv, selected)
        selected.append(add)
        current = loss.value(information_of(selected))
        history.append(current)
    say(f'exchange: {n} configurations, loss {current:.4g}')
    # (4) Final remove-and-replace: try every selected configuration in turn.
    for sweep in range(max_sweeps):
        improved = False
        for pos in range(n):
            rest = selected[:pos] + selected[pos + 1:]
            rest_info = information_of(rest)
            rest_loss = loss.value(rest_info)
            if not np.isfinite(rest_loss):
                continue
            try:  # n near k/3: without one pose the information can be singular in fact
                rest_inv = np.linalg.inv(rest_info)
            except np.linalg.LinAlgError:
                continue
            add, gain = best_add(rest_inv, selected)
            if rest_loss + gain < current - 1e-9 * abs(current):
                selected[pos] = add
                current = loss.value(information_of(selected))
                history.append(current)
                exchanges += 1
                improved = True
        say(f'exchange: final sweep {sweep + 1}, loss {current:.4g}')
        if not improved:
            break
    return ExchangeResult(np.array(selected), current, tuple(history), exchanges)
