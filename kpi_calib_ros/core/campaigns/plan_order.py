"""The order of a campaign's poses: the plan ahead of it and the nested order of a design.

Every prefix of the measured poses should be close to the batch design of its size
(:mod:`kpi_calib_ros.core.campaigns.sequential`).
"""
from __future__ import annotations

from typing import Sequence

import numpy as np

from kpi_calib_ros.core.design.exchange import Loss, information

__all__ = ['PLAN_SWEEPS', 'plan_ahead', 'nested_order', 'inverse']

# Remove-and-replace sweeps over the plan at each measurement (the plan carries over, so
# they accumulate): a count, not a time, so a campaign chooses the same poses on any
# machine under any load. Measured on the default cell (30 planned poses, 2000 candidates,
# 27 parameters; targets 5 and 4 µm, seed 0): every plan converged within 4 sweeps, at
# most 0.27 s on an idle core.
PLAN_SWEEPS = 6


def plan_ahead(rows: np.ndarray, info: np.ndarray, m: int, loss: Loss,
               exclude: np.ndarray, max_sweeps: int = PLAN_SWEEPS,
               start_plan: Sequence[int] = ()) -> np.ndarray:
    """``m`` candidates that, added to the measured information ``info``, lower ``loss`` most.

    ``info`` is (k, k). Greedy additions, then remove-and-replace sweeps over the planned ones
    only (the measured ones are fixed), as steps 3-4 of
    :func:`kpi_calib_ros.core.design.exchange.exchange`, until no exchange improves or after
    ``max_sweeps`` sweeps. ``start_plan`` (the previous plan) is kept where still allowed, so
    the sweeps continue from one measurement to the next instead of starting over. Returns the
    indices (m,), the one whose single addition lowers the loss most first.

    Planning ahead rather than adding greedily one at a time is what keeps every prefix
    close to the batch design of its size: a greedy first choice for a criterion of rank
    3 (one working pose) is often not a member of a good larger design.
    """
    banned = np.zeros(len(rows), bool)
    banned[exclude] = True
    chosen = [int(i) for i in start_plan if not banned[i]][:m]
    current = info.copy()
    for i in chosen:
        current = current + rows[i].T @ rows[i]
    for _ in range(min(m, int(np.sum(~banned))) - len(chosen)):
        gain = loss.delta(inverse(current), rows, +1.0)
        gain[banned] = np.inf
        gain[chosen] = np.inf
        best = int(np.argmin(gain))
        chosen.append(best)
        current = current + rows[best].T @ rows[best]
    value = loss.value(current)
    improved, sweeps = True, 0
    while improved and sweeps < max_sweeps:
        improved, sweeps = False, sweeps + 1
        for pos in range(len(chosen)):
            a = rows[chosen[pos]]
            rest = current - a.T @ a
            gain = loss.delta(inverse(rest), rows, +1.0)
            gain[banned] = np.inf
            gain[chosen] = np.inf
            best = int(np.argmin(gain))
            trial = rest + rows[best].T @ rows[best]
            trial_value = loss.value(trial)
            if trial_value < value - 1e-9 * abs(value):
                chosen[pos], current, value, improved = best, trial, trial_value, True
    first = loss.delta(inverse(info), rows[chosen], +1.0)
    return np.array(chosen)[np.argsort(first, kind='stable')]


def nested_order(rows: np.ndarray, design: np.ndarray, loss: Loss, n_min: int,
                 base: np.ndarray | None = None) -> np.ndarray:
    """Order the poses of ``design`` so that every prefix is a good design of its size.

    ``design`` indexes ``rows`` (c, 3, k); every prefix of at least ``n_min`` poses counts.
    Backward elimination, repeatedly removing the pose whose removal raises ``loss`` least
    (never one that makes the information singular) down to ``n_min``; the removed ones follow
    the rest in reverse order of removal. ``base`` (k, k): information every design has (a
    prior's), added to each prefix's.
    """
    kept = [int(i) for i in design]
    removed: list[int] = []
    while len(kept) > max(n_min, 1):
        info = information(rows[kept])
        raise_ = loss.delta(inverse(info if base is None else info + base), rows[kept], -1.0)
        if not np.any(np.isfinite(raise_)):
            break
        removed.append(kept.pop(int(np.argmin(raise_))))
    return np.array(kept + removed[::-1], int)



def inverse(info: np.ndarray) -> np.ndarray:
    """Inverse of the information ``info`` (k, k); its pseudo-inverse if singular."""
    try:
        return np.linalg.inv(info)
    except np.linalg.LinAlgError:
        return np.linalg.pinv(info)
