"""Link pairs to skip in self-collision checks, computed by sampling (as MoveIt's setup assistant).

Every pair of chain links that carry capsules gets one class, first match wins:

``adjacent``
    parent and child (or linked only through links without geometry): they
    touch at their joint by construction and the joint limits keep them apart;
``default``
    in collision at the default configuration, the middle of the joint ranges
    (a robot at rest there is not self-colliding, so the geometry overlaps by
    construction; the all-zero pose is no default: it is outside the limits or
    folded for many arms);
``always``
    in collision in at least ``always_fraction`` of the random samples;
``never``
    in collision in none of the samples;
``sometimes``
    everything else: a real constraint, always checked.

The first three are skipped by a design; ``never`` may be (MoveIt does) but is
kept by default, because a design optimiser explores exactly the corners that
random sampling misses. Samples are uniform within the joint limits from a
seeded generator, and the margins come from the same CasADi capsule code as
the design constraints (:class:`~kpi_calib_ros.core.collision.capsules.CollisionScene`),
evaluated for all samples at once.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np
import pinocchio as pin

from kpi_calib_ros.core.collision.capsules import BEAM, Capsule, CollisionScene
from kpi_calib_ros.core.model.robot import RobotModel, frame_id

__all__ = [
    'SKIPPED_KINDS', 'PairClass', 'CollisionMatrix', 'link_transforms', 'classify_link_pairs',
]

SKIPPED_KINDS = ('adjacent', 'default', 'always')


@dataclass(frozen=True)
class PairClass:
    """Class of one link pair.

    Attributes
    ----------
    links : (str, str)
        The two links, in chain order.
    kind : str
        ``'adjacent'``, ``'default'``, ``'always'``, ``'never'`` or ``'sometimes'``.
    fraction : float or None
        Fraction of the samples in collision (0..1); None for adjacent pairs (not sampled).
    """

    links: tuple[str, str]
    kind: str
    fraction: float | None


@dataclass(frozen=True)
class CollisionMatrix:
    """Classified link pairs of one robot's capsules.

    Attributes
    ----------
    pairs : tuple of PairClass
        Every pair of chain links that carry capsules.
    samples : int
        Random configurations drawn.
    seed : int
        Seed of the generator that drew them.
    """

    pairs: tuple[PairClass, ...]
    samples: int
    seed: int

    def of_kind(self, kind: str) -> list[PairClass]:
        """Pairs of one class."""
        return [p for p in self.pairs if p.kind == kind]

    def skip_pairs(self, include_never: bool = False) -> set[frozenset[str]]:
        """Link pairs to leave out, as ``CollisionScene(ignore_pairs=...)`` takes them."""
        kinds = SKIPPED_KINDS + (('never',) if include_never else ())
        return {frozenset(p.links) for p in self.pairs if p.kind in kinds}

    def summary(self) -> list[dict]:
        """Skipped pairs, YAML-ready: ``{links: [a, b], class: kind, fraction: f}``."""
        return [{'links': list(p.links), 'class': p.kind,
                 'fraction': None if p.fraction is None else round(p.fraction, 4)}
                for p in self.pairs if p.kind in SKIPPED_KINDS]


def link_transforms(robot: RobotModel, q: np.ndarray, links: Sequence[str]) -> np.ndarray:
    """Poses (N, L, 4, 4) of ``links`` in the robot base frame for chain values ``q`` (N, n)."""
    model = robot.pin_model
    data = model.createData()
    ids = [model.getFrameId(link, pin.BODY) for link in links]
    base_id = frame_id(model, robot.base_frame)
    q = np.atleast_2d(np.asarray(q, dtype=float))
    out = np.empty((len(q), len(links), 4, 4))
    for k, row in enumerate(q):
        pin.framesForwardKinematics(model, data, robot.pin_configuration(row))
        base_inv = data.oMf[base_id].inverse()
        for j, fid in enumerate(ids):
            out[k, j] = (base_inv * data.oMf[fid]).homogeneous
    return out


def classify_link_pairs(robot: RobotModel, capsules: Sequence[Capsule], samples: int = 2000,
                        seed: int = 0, always_fraction: float = 0.95,
                        q_default: np.ndarray | None = None) -> CollisionMatrix:
    """Class of every pair of chain links carrying capsules, from ``samples`` random poses.

    Parameters
    ----------
    robot : RobotModel
    capsules : sequence of Capsule
        Robot capsules, each on a link of ``robot.link_names`` (link frame, m).
    samples : int
        Configurations drawn uniformly within the joint limits (continuous joints on [-π, π]).
    seed : int
        Seed of ``np.random.default_rng``: the same inputs give the same matrix.
    always_fraction : float
        A pair colliding in at least this fraction of the samples is ``'always'``.
    q_default : (n,) array, optional
        Default configuration; the middle of the joint ranges when omitted.

    Returns
    -------
    CollisionMatrix
    """
    if samples < 1:
        raise ValueError(f'samples must be >= 1, got {samples}')
    if not 0.0 < always_fraction <= 1.0:
        raise ValueError(f'always_fraction must be in (0, 1], got {always_fraction}')
    chain = robot.link_names
    for cap in capsules:
        if cap.frame not in chain:
            raise ValueError(f'capsule {cap.name!r} is on {cap.frame!r}, not on the chain {chain}')
    carrying = [link for link in chain if any(c.frame == link for c in capsules)]
    # The beam is not part of the robot: drop its pairs so only capsule pairs remain.
    scene = CollisionScene(list(capsules), [], chain,
                           ignore_pairs={frozenset({BEAM, c.name}) for c in capsules})
    frame_of = {c.name: c.frame for c in capsules}

    rng = np.random.default_rng(seed)
    if q_default is None:
        q_default = robot.middle_configuration()
    q = np.vstack([np.asarray(q_default, dtype=float).reshape(1, -1),
                   robot.sample_configurations(rng, samples)])
    margins = _margins(scene, link_transforms(robot, q, scene.frames))  # (count, 1 + samples)

    hit: dict[frozenset[str], np.ndarray] = {}
    for label, row in zip(scene.labels, margins):
        first, second = label.split('~')
        key = frozenset({frame_of[first], frame_of[second]})
        hit[key] = hit.get(key, np.zeros(len(q), dtype=bool)) | (row < 0.0)

    pairs = []
    for i, a in enumerate(carrying):
        for j, b in enumerate(carrying[i + 1:], start=i + 1):
            key = frozenset({a, b})
            # Consecutive among the links with geometry: parent/child, or linked only
            # through geometry-less links (MoveIt's rule).
            if j == i + 1 or key not in hit:
                pairs.append(PairClass((a, b), 'adjacent', None))
                continue
            fraction = float(hit[key][1:].mean())
            if hit[key][0]:
                kind = 'default'
            elif fraction >= always_fraction:
                kind = 'always'
            elif fraction == 0.0:
                kind = 'never'
            else:
                kind = 'sometimes'
            pairs.append(PairClass((a, b), kind, fraction))
    return CollisionMatrix(tuple(pairs), samples, seed)


def _margins(scene: CollisionScene, transforms: np.ndarray) -> np.ndarray:
    """Margins (count, N) of ``scene`` for stacked link poses (N, L, 4, 4), in one call."""
    n, n_links = transforms.shape[:2]
    if scene.count == 0:
        return np.zeros((0, n))
    stacked = transforms.reshape(n, 4 * n_links, 4).transpose(1, 0, 2).reshape(4 * n_links, 4 * n)
    zeros = np.zeros((3, n))
    out = scene.function().map(n)(stacked, zeros, zeros)
    return np.asarray(out, dtype=float).reshape(scene.count, n)
