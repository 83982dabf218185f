"""Folds over poses for cross-validation: which poses each refit holds out.

Rows measured at the same joint values are one pose (:func:`pose_index`) and stay in one
fold. Leave one pose out by default, or k-fold: random folds, then folds stratified by the
joints moved (:func:`stratified_fold_ids`) when a random one leaves a parameter without
excitation (:func:`identifiable_folds`); every fold keeps every identified parameter
determined (:func:`folds_keep_rank`: I − H_FF nonsingular). Region-blocked folds
(:func:`region_folds`) hold out whole clusters of poses in joint space: the error where
no pose was measured; range-end folds (:func:`range_end_folds`) hold out the ends of each
joint's range: the error by extrapolation. The held-out error over these folds is
:mod:`kpi_calib_ros.core.estimation.cross_validation`'s.
"""
from __future__ import annotations

from typing import Iterator, Sequence

import numpy as np

from kpi_calib_ros.core.estimation.residuals import orthonormal_basis

__all__ = [
    'fold_ids', 'campaign_home', 'moved_joints', 'stratified_fold_ids', 'RANK_TOLERANCE',
    'LEAVE_ONE_OUT', 'HeldOutBlock', 'held_out_blocks', 'fold_rows', 'fold_blocks',
    'folds_keep_rank', 'identifiable_folds', 'pose_index',
    'REGION_BLOCKS', 'region_fold_ids', 'region_folds', 'RANGE_END', 'range_end_folds',
]


def fold_ids(n_poses: int, folds: int, seed: int) -> np.ndarray:
    """Random fold of each pose, (n_poses,) ints in [0, folds), sizes within one."""
    if folds == LEAVE_ONE_OUT:
        return np.arange(n_poses)
    if not 2 <= folds <= n_poses:
        raise ValueError(f'folds must be in [2, {n_poses}] (number of poses), got {folds}')
    ids = np.empty(n_poses, dtype=int)
    ids[np.random.default_rng(seed).permutation(n_poses)] = np.arange(n_poses) % folds
    return ids


def campaign_home(q: np.ndarray, atol: float = 1e-6) -> np.ndarray:
    """(n,) the campaign's home configuration.

    The most frequent value of each joint (to ``atol``).
    """
    q = np.atleast_2d(np.asarray(q, float))
    home = np.empty(q.shape[1])
    for j in range(q.shape[1]):
        values, counts = np.unique(np.round(q[:, j] / atol), return_counts=True)
        home[j] = values[np.argmax(counts)] * atol
    return home


def moved_joints(q: np.ndarray, atol: float = 1e-6) -> np.ndarray:
    """(N, n) bool: which joints of each pose differ from the campaign's home value.

    The home value is that of :func:`campaign_home`. One-joint-at-a-time campaigns (the circle
    point method) give rows with a single True.
    """
    q = np.atleast_2d(np.asarray(q, float))
    return np.abs(q - campaign_home(q, atol)) > atol


def stratified_fold_ids(q: np.ndarray, folds: int, seed: int) -> np.ndarray:
    """Folds stratified by the joints moved.

    Each group of poses that move the same joints is dealt round the folds, so every fold holds
    out a share of every group and every training set keeps poses of every group.
    """
    q = np.atleast_2d(q)
    n = len(q)
    if folds == LEAVE_ONE_OUT:
        return np.arange(n)
    if not 2 <= folds <= n:
        raise ValueError(f'folds must be in [2, {n}] (number of poses), got {folds}')
    rng = np.random.default_rng(seed)
    _, group = np.unique(moved_joints(q), axis=0, return_inverse=True)
    ids = np.empty(n, dtype=int)
    next_fold = 0
    for g in rng.permutation(group.max() + 1):
        members = rng.permutation(np.flatnonzero(group.ravel() == g))
        ids[members] = (next_fold + np.arange(len(members))) % folds
        next_fold = (next_fold + len(members)) % folds
    return ids


# A fold whose training poses leave a direction of the identified parameters with less
# than this fraction of its full-data information cannot refit it (I − H_FF singular).
RANK_TOLERANCE = 1e-9
LEAVE_ONE_OUT = 0  # ``folds`` value: every pose its own fold (exact, the default)


class HeldOutBlock:
    """I − H_FF of one fold F, H = U Uᵀ the hat matrix, without forming it when F is large.

    ``uf`` (f, r): the fold's rows of the orthonormal basis U. I − U_F U_Fᵀ (f, f) has the
    eigenvalues 1 − λ of the Gram matrix G = U_Fᵀ U_F (r, r) and 1 for the rest, and
    (I − U_F U_Fᵀ)⁻¹ = I + U_F (I − G)⁻¹ U_Fᵀ (Woodbury). A fold of more rows than the
    basis has columns (a region of a real campaign: tens of thousands of rows) costs
    O(f r²) time and O(f r) memory through G; the dense f × f matrix would take f² memory
    and f³ time (17 GiB for one region of 12 000 poses). Small folds use the dense matrix.
    """

    def __init__(self, uf: np.ndarray,
                 eigen: tuple[np.ndarray, np.ndarray] | None = None) -> None:
        self._uf = uf
        f, r = uf.shape
        self._dense = f <= r
        if self._dense:
            # ``eigen``: the eigenpairs of I − U_F U_Fᵀ already at hand (held_out_blocks).
            lam, self._v = np.linalg.eigh(np.eye(f) - uf @ uf.T) if eigen is None else eigen
            self.eigenvalues = lam
        else:
            gram, self._v = np.linalg.eigh(uf.T @ uf)
            self.eigenvalues = 1.0 - gram[::-1]  # those of I − U_F U_Fᵀ below 1, ascending
            self._v = self._v[:, ::-1]
        self.smallest = float(self.eigenvalues[0]) if len(self.eigenvalues) else 1.0

    def solve(self, e: np.ndarray) -> np.ndarray:
        """(I − H_FF)⁻¹ e for ``e`` (f,): the held-out residuals of the fold's refit."""
        proj = self._v.T @ (e if self._dense else self._uf.T @ e)
        if self._dense:
            return self._v @ (proj / self.eigenvalues)
        return e + self._uf @ (self._v @ (proj / self.eigenvalues))

    def trace_inverse(self) -> float:
        """Return tr (I − H_FF)⁻¹: the expected sum of squares of unit noise held out."""
        f = self._uf.shape[0]
        return float(np.sum(1.0 / self.eigenvalues) + f - len(self.eigenvalues))


def fold_rows(pose_folds: np.ndarray) -> Iterator[tuple[np.ndarray, np.ndarray]]:
    """Yield (fold id, row indices) of each fold, three rows per pose of ``pose_folds`` (N,).

    In ascending fold order, each fold's rows ascending; rows past 3N (a prior's) are in no
    fold. One sort: a leave-one-out over thousands of poses does not scan
    every row once per fold.
    """
    rows = np.repeat(np.asarray(pose_folds), 3)
    order = np.argsort(rows, kind='stable')
    ids, starts = np.unique(rows[order], return_index=True)
    for k, idx in zip(ids, np.split(order, starts[1:])):
        yield k, idx


def held_out_blocks(u: np.ndarray, folds: Sequence[np.ndarray]) -> list[HeldOutBlock]:
    """I − H_FF of each fold of ``folds`` (row indices), H = U Uᵀ, ``u`` (3N, r) orthonormal.

    The folds no larger than the basis (a pose, a few poses) are decomposed together, one
    stacked eigendecomposition per fold size: a leave-one-out over a few hundred poses,
    done for every candidate effect of a diagnosis, spent most of its time calling the
    decomposition once per fold.
    """
    folds = list(folds)
    sizes = np.array([len(rows) for rows in folds], dtype=int)
    eigen: dict[int, tuple[np.ndarray, np.ndarray]] = {}
    for f in np.unique(sizes[sizes <= u.shape[1]]):
        which = np.flatnonzero(sizes == f)
        uf = u[np.stack([folds[i] for i in which])]  # (g, f, r)
        lam, v = np.linalg.eigh(np.eye(f) - uf @ uf.transpose(0, 2, 1))
        eigen.update((int(i), (lam[j], v[j])) for j, i in enumerate(which))
    return [HeldOutBlock(u[rows], eigen.get(i)) for i, rows in enumerate(folds)]


def fold_blocks(a: np.ndarray, pose_folds: np.ndarray, u: np.ndarray | None = None
                ) -> Iterator[tuple[np.ndarray, HeldOutBlock]]:
    """Yield (rows, I − H_FF) of each fold F, H = U Uᵀ the hat matrix of span(a).

    ``rows``: the row indices of the fold's held-out rows (ascending), three per pose of
    ``pose_folds`` (N,); I − H_FF as a :class:`HeldOutBlock`. Rows of ``a`` after the 3N of
    the measurements (a prior's) are in every training set. ``u``: an orthonormal basis of
    span(a) already at hand.
    """
    u = orthonormal_basis(a) if u is None else u
    folds = [rows for _, rows in fold_rows(pose_folds)]
    yield from zip(folds, held_out_blocks(u, folds))


def folds_keep_rank(a: np.ndarray, pose_folds: np.ndarray) -> bool:
    """Return True when every fold's training rows determine every column of ``a`` (3N, k).

    The training rows are the other folds' poses: I − H_FF is nonsingular for every fold F.
    """
    return all(m.smallest > RANK_TOLERANCE for _, m in fold_blocks(a, pose_folds))


def identifiable_folds(a: np.ndarray, q: np.ndarray, folds: int,
                       seed: int) -> np.ndarray | None:
    """Folds over poses that keep every identified parameter determined in each fold.

    ``folds`` 0 (or >= N): leave one pose out. Otherwise random folds first; when one of
    them leaves a parameter without excitation (a fold that holds out the poses moving
    one joint), folds stratified by the joints moved. ``None`` when no such folds exist:
    the design cannot estimate an out-of-sample error by refitting without some of its
    poses ("not estimable from this design").

    Parameters
    ----------
    a : (3N, k) ndarray
        Weighted Jacobian of the identified parameters, three rows per measurement.
    q : (N, n) ndarray
        Joint values of the measurements (rad): rows with equal values are one pose.
    """
    # Rows measured at the same joint values (several reflectors, or repeated shots) are
    # one pose and stay in one fold: held-out poses, not held-out points.
    poses, pose = pose_index(q)
    n = len(poses)
    if folds == LEAVE_ONE_OUT or folds >= n:
        ids = pose
        return ids if folds_keep_rank(a, ids) else None
    for ids in (fold_ids(n, folds, seed)[pose], stratified_fold_ids(poses, folds, seed)[pose]):
        if folds_keep_rank(a, ids):
            return ids
    return None


def pose_index(q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Return the distinct poses of ``q`` (N, n) in order of first appearance.

    Also each row's pose index (N,).
    """
    q = np.atleast_2d(q)
    _, first, inverse = np.unique(q, axis=0, return_index=True, return_inverse=True)
    order = np.argsort(first)  # unique sorts; renumber by first appearance
    rank = np.empty_like(order)
    rank[order] = np.arange(len(order))
    return q[np.sort(first)], rank[np.asarray(inverse).reshape(-1)]


# Region blocks of joint space a region-blocked cross-validation holds out in turn.
REGION_BLOCKS = 5
_KMEANS_ROUNDS = 50


def region_fold_ids(q: np.ndarray, blocks: int = REGION_BLOCKS, seed: int = 0) -> np.ndarray:
    """Region of each pose, (n_poses,) ints in [0, blocks): k-means in normalised joint space.

    ``q`` (n_poses, n) are distinct poses (rad, m). Each joint is scaled to [0, 1] over its
    measured range (a joint that does not move is left out), the seeded k-means++ start is
    refined by Lloyd's iterations. A fold is then a region of joint space held out whole:
    its prediction is the model's error where no pose was measured.
    """
    q = np.atleast_2d(np.asarray(q, float))
    n = len(q)
    if not 2 <= blocks <= n:
        raise ValueError(f'blocks must be in [2, {n}] (number of poses), got {blocks}')
    span = np.ptp(q, axis=0)
    x = (q[:, span > 0] - q[:, span > 0].min(axis=0)) / span[span > 0]
    rng = np.random.default_rng(seed)
    centres = [x[rng.integers(n)]]
    for _ in range(1, blocks):
        d2 = np.min([np.sum((x - c) ** 2, axis=1) for c in centres], axis=0)
        total = float(d2.sum())
        centres.append(x[rng.choice(n, p=d2 / total)] if total > 0 else x[rng.integers(n)])
    c = np.array(centres)
    label = np.zeros(n, int)
    for _ in range(_KMEANS_ROUNDS):
        label = np.argmin(((x[:, None, :] - c[None]) ** 2).sum(axis=2), axis=1)
        new = np.array([x[label == b].mean(axis=0) if np.any(label == b) else c[b]
                        for b in range(blocks)])
        if np.allclose(new, c):
            break
        c = new
    _, label = np.unique(label, return_inverse=True)  # empty clusters dropped
    return np.asarray(label).reshape(-1)


def region_folds(a: np.ndarray, q: np.ndarray, blocks: int = REGION_BLOCKS, seed: int = 0
                 ) -> tuple[np.ndarray, int] | None:
    """Region-blocked folds over the rows of ``q`` (N, n) that keep the rank of ``a``.

    ``a`` (3N (+ prior rows), k): the weighted Jacobian of the identified parameters.
    :func:`region_fold_ids` with ``blocks`` regions first; when a region's training poses
    leave an identified parameter undetermined (one region holds every pose that moves a
    joint), more and smaller regions (twice as many each time). Returns the pose folds and
    the number of regions, or None when not even one pose per region keeps the rank.
    """
    poses, pose = pose_index(q)
    n = len(poses)
    b = blocks
    while 2 <= b < n:
        ids = region_fold_ids(poses, b, seed)[pose]
        if folds_keep_rank(a, ids):
            return ids, int(ids.max()) + 1
        b *= 2
    return (pose, n) if n >= 2 and folds_keep_rank(a, pose) else None


# Fraction of each joint's measured range a range-end fold holds out (its lowest and its
# highest fifth): the poses beyond the rest's range of that joint, which an effect of the
# joint (a periodic error, a scale, a bending) must predict by extrapolation.
RANGE_END = 0.2


def range_end_folds(q: np.ndarray, fraction: float = RANGE_END) -> list[np.ndarray]:
    """Pose masks (N,) bool of the range-end folds of ``q`` (N, n) (rad, m).

    For every joint that moves, the poses in the lowest ``fraction`` of its measured range
    and those in the highest; each is held out in turn. Unlike the k-means regions, which
    lie inside the measured ranges, these ask every joint's effect to extrapolate.
    """
    if not 0 < fraction < 0.5:
        raise ValueError(f'fraction must be in (0, 0.5), got {fraction}')
    q = np.atleast_2d(np.asarray(q, float))
    masks = []
    for j in range(q.shape[1]):
        lo, hi = float(q[:, j].min()), float(q[:, j].max())
        if hi - lo <= 0:
            continue
        for mask in (q[:, j] <= lo + fraction * (hi - lo), q[:, j] >= hi - fraction * (hi - lo)):
            if 0 < mask.sum() < len(q):
                masks.append(mask)
    return masks
