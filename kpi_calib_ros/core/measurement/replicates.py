"""The same pose measured again: the one definition of replicates in joint space.

Two joint vectors are *the same pose* when every joint differs by at most
:data:`SAME_POSE_TOLERANCE` (rad, or m for a prismatic joint). Rows joined by a chain of
such pairs are one pose (:func:`pose_groups`). Every consumer uses this: the replicates of
the outlier rule (:mod:`kpi_calib_ros.core.estimation.outliers`), the pure error of the sequential
campaign's lack-of-fit test and the candidate a measured pose was
(:mod:`kpi_calib_ros.core.campaigns.sequential`), and the validation poses repeated from training
(:mod:`kpi_calib_ros.core.diagnosis.validation`).

Why 1e-3: a robot commanded to one pose reads back within encoder counts and servo
settling, not exactly. On the TIAGo motion-capture sessions of 2021-11 (the postures of
three validation sessions against the training session) the repeated postures read within
3.6e-4 rad of the training ones on every joint, while the nearest distinct posture is
0.087 rad away; 1e-4 would miss 23 of the 37 repeats of a session, 1e-3 and 1e-2 find the
same 37. 1e-3 keeps a factor 2.8 above that scatter and 87 below the nearest other pose;
designed poses (random or optimised candidates) differ by far more on some joint.
"""
from __future__ import annotations

import numpy as np
import scipy.sparse
import scipy.sparse.csgraph
import scipy.spatial

SAME_POSE_TOLERANCE = 1e-3


def same_pose(q: np.ndarray, others: np.ndarray,
              tolerance: float = SAME_POSE_TOLERANCE) -> np.ndarray:
    """Whether each row of ``q`` (N, n) is the same pose as some row of ``others`` (M, n).

    Returns
    -------
    (N,) bool ndarray
        Every joint within ``tolerance`` (rad, m) of one row of ``others``; all False
        when ``others`` is empty.
    """
    q = np.atleast_2d(np.asarray(q, float))
    others = np.asarray(others, float)
    if not others.size:
        return np.zeros(len(q), bool)
    others = others.reshape(-1, q.shape[1])
    return np.array([bool(np.any(np.all(np.abs(others - row) <= tolerance, axis=1)))
                     for row in q], bool).reshape(len(q))


def pose_groups(q: np.ndarray, tolerance: float = SAME_POSE_TOLERANCE) -> np.ndarray:
    """Pose index (N,) of every row of ``q`` (N, n).

    Rows that are the same pose as another (:func:`same_pose`), directly or through a chain of
    others, share one, numbered 0, 1, ... in order of first appearance.
    """
    q = np.atleast_2d(np.asarray(q, float))
    if not len(q):
        return np.zeros(0, int)
    tree = scipy.spatial.cKDTree(q)
    pairs = tree.query_pairs(tolerance, p=np.inf, output_type='ndarray')
    graph = scipy.sparse.coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])),
                                    shape=(len(q), len(q)))
    _, labels = scipy.sparse.csgraph.connected_components(graph, directed=False)
    _, first, inverse = np.unique(labels, return_index=True, return_inverse=True)
    rank = np.empty(len(first), int)
    rank[np.argsort(first)] = np.arange(len(first))
    return rank[inverse.reshape(-1)]


__all__ = ['SAME_POSE_TOLERANCE', 'pose_groups', 'as_first_of_pose', 'same_pose', 'same_turn']


def as_first_of_pose(q: np.ndarray) -> np.ndarray:
    """Return ``q`` (N, n) with every row replaced by the first row of its pose.

    Poses as :func:`pose_groups` makes them: folds over exact poses then hold a posture out
    with its repeats (another session's readings within a reading's tolerance).
    """
    q = np.atleast_2d(np.asarray(q, float))
    groups = pose_groups(q)
    return q[np.unique(groups, return_index=True)[1][groups]]


def same_turn(q: np.ndarray, lower: np.ndarray, upper: np.ndarray,
              turns: np.ndarray) -> np.ndarray:
    """Return ``q`` (N, n) with each continuous joint's reading moved by whole turns.

    ``turns`` (n,) bool marks the continuous joints; each goes to the reading nearest the
    middle of its training range (``lower``, ``upper``; 0 when unbounded). A continuous
    joint read 2π further is the same pose: 60 points of a Kinova's joints 1 and 4 read
    one turn on were all "outside the training ranges", predicted alike.
    """
    q = np.array(np.atleast_2d(q), dtype=float)
    turns = np.asarray(turns, dtype=bool)
    if turns.any() and q.shape[1] == len(turns):
        lo, hi = np.asarray(lower, float)[turns], np.asarray(upper, float)[turns]
        mid = np.where(np.isfinite(lo) & np.isfinite(hi), 0.5 * (lo + hi), 0.0)
        q[:, turns] += 2.0 * np.pi * np.round((mid - q[:, turns]) / (2.0 * np.pi))
    return q
