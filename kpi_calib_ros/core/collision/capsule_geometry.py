"""Enclosing capsules of a point cloud (mesh vertices), by construction never smaller.

For an axis line (point ``c``, unit direction ``u``) and a radius ``R`` at least
the largest distance of a point from the line, the shortest segment on that line
whose capsule holds every point is exact: point ``i`` at axial ``t_i`` and radial
``r_i`` is inside iff the segment reaches ``t_i - sqrt(R² - r_i²)`` (upper end)
and ``t_i + sqrt(R² - r_i²)`` (lower end). Enclosure therefore holds for ANY
line and radius; the search over line and radius only makes the capsule tight.

A capsule around a convex set encloses the set iff it encloses its vertices, so
the fit runs on the convex-hull vertices. When one capsule is loose (volume
``loose_ratio`` times the hull's or more), the hull is cut into slabs along its
principal axis; each slab's points are the hull vertices in it plus the hull
edges' crossings of the cut planes, so the slab capsules together still enclose
the whole hull.
"""
from __future__ import annotations

import numpy as np
from scipy.optimize import minimize
from scipy.spatial import ConvexHull, QhullError

__all__ = [
    'capsule_volume', 'outside_distance', 'convex_hull_volume', 'enclosing_capsule',
    'fit_capsules',
]

# Added to every fitted radius (m): covers the round-off of the end-point formula.
_SAFETY = 1e-9


def capsule_volume(a: np.ndarray, b: np.ndarray, radius: float) -> float:
    """Volume (m³) of the capsule with segment ``a``-``b`` and ``radius``."""
    length = float(np.linalg.norm(np.asarray(b, float) - np.asarray(a, float)))
    return float(np.pi * radius ** 2 * length + 4.0 / 3.0 * np.pi * radius ** 3)


def outside_distance(points: np.ndarray, a: np.ndarray, b: np.ndarray,
                     radius: float) -> np.ndarray:
    """Signed distance (m) of each point outside the capsule (<= 0 inside), shape (N,)."""
    points = np.asarray(points, float)
    a, b = np.asarray(a, float), np.asarray(b, float)
    axis = b - a
    length2 = float(axis @ axis)
    s = np.zeros(len(points)) if length2 == 0 else np.clip((points - a) @ axis / length2, 0, 1)
    return np.linalg.norm(points - a - s[:, None] * axis, axis=1) - radius


def convex_hull_volume(points: np.ndarray) -> float:
    """Volume (m³) of the convex hull of ``points`` (N, 3); 0 for flat or too few points."""
    return _hull(np.asarray(points, dtype=float).reshape(-1, 3))[2]


def _hull(points: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
    """(hull vertices, hull edges (E, 2, 3), volume); the points themselves if flat."""
    try:
        hull = ConvexHull(points)
    except (QhullError, ValueError):  # coplanar / too few points: no volume to split
        return points, np.zeros((0, 2, 3)), 0.0
    edges = np.concatenate([hull.simplices[:, [0, 1]], hull.simplices[:, [1, 2]],
                            hull.simplices[:, [0, 2]]])
    edges = np.unique(np.sort(edges, axis=1), axis=0)
    return points[hull.vertices], points[edges], float(hull.volume)


def _frame(u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two unit vectors completing ``u`` to an orthonormal basis."""
    helper = np.eye(3)[int(np.argmin(np.abs(u)))]
    e1 = np.cross(u, helper)
    e1 /= np.linalg.norm(e1)
    return e1, np.cross(u, e1)


def _on_line(points: np.ndarray, c: np.ndarray, u: np.ndarray
             ) -> tuple[np.ndarray, np.ndarray, np.ndarray, int]:
    """Axial ``t`` (N,), radii tried (K,), segment ends (K, 2) and best index for line c+su."""
    d = points - c
    t = d @ u
    r2 = np.maximum(np.sum(d * d, axis=1) - t * t, 0.0)
    r_min = float(np.sqrt(r2.max()))
    span = float(t.max() - t.min())
    # Radii from the smallest possible up to a ball over the whole span: the volume
    # is not convex in R, so a dense 1-D grid is safer than a local search.
    radii = r_min + (0.5 * span + 1e-12) * np.linspace(0.0, 1.0, 33) ** 2
    reach = np.sqrt(np.maximum(radii[:, None] ** 2 - r2[None, :], 0.0))
    hi = np.max(t[None, :] - reach, axis=1)
    lo = np.min(t[None, :] + reach, axis=1)
    length = np.maximum(hi - lo, 0.0)
    volume = np.pi * radii ** 2 * length + 4.0 / 3.0 * np.pi * radii ** 3
    k = int(np.argmin(volume))
    return t, radii, np.column_stack([lo, hi]), k


def _capsule_on_line(points: np.ndarray, c: np.ndarray, u: np.ndarray
                     ) -> tuple[np.ndarray, np.ndarray, float]:
    _, radii, ends, k = _on_line(points, c, u)
    lo, hi = ends[k]
    if lo > hi:  # a ball: any point of [hi, lo] on the line is a valid centre
        lo = hi = 0.5 * (lo + hi)
    return c + lo * u, c + hi * u, float(radii[k])


def enclosing_capsule(points: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
    """Return a small capsule holding every point of ``points`` (N, 3), in their frame (m).

    Starts from each principal axis through the bounding-box centre and refines
    the line (tilt and offset, 4 numbers) by Nelder-Mead on the volume; the
    segment and radius for a line are exact (module docstring), so the result
    encloses every point whatever the search does.

    Returns
    -------
    a, b : (3,) ndarray
        Segment end points.
    radius : float
        Radius (m), including a 1e-9 m safety for round-off.
    """
    points = np.asarray(points, dtype=float).reshape(-1, 3)
    if len(points) == 0:
        raise ValueError('enclosing_capsule needs at least one point')
    centre = points.mean(axis=0)
    _, _, vt = np.linalg.svd(points - centre, full_matrices=False)
    axes = list(vt) + [np.eye(3)[k] for k in range(3 - len(vt))]
    # Each principal axis through the bounding-box centre; the best one is refined.
    starts = []
    for u0 in axes:
        e1, e2 = _frame(u0)
        c0 = e1 * 0.5 * (np.max(points @ e1) + np.min(points @ e1)) \
            + e2 * 0.5 * (np.max(points @ e2) + np.min(points @ e2))
        starts.append((capsule_volume(*_capsule_on_line(points, c0, u0)), u0, e1, e2, c0))
    _, u0, e1, e2, c0 = min(starts, key=lambda s: s[0])

    def line(x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        u = u0 + x[0] * e1 + x[1] * e2
        return c0 + x[2] * e1 + x[3] * e2, u / np.linalg.norm(u)

    def cost(x: np.ndarray) -> float:
        return capsule_volume(*_capsule_on_line(points, *line(x)))

    scale = float(np.ptp(points, axis=0).max()) or 1.0
    simplex = np.vstack([np.zeros(4), 0.05 * np.eye(4) * [1, 1, scale, scale]])
    res = minimize(cost, np.zeros(4), method='Nelder-Mead',
                   options={'initial_simplex': simplex, 'xatol': 1e-4, 'fatol': 1e-9,
                            'maxfev': 160})
    best = line(res.x if res.fun <= cost(np.zeros(4)) else np.zeros(4))
    a, b, radius = _capsule_on_line(points, *best)
    return a, b, radius + _SAFETY


def _slab(vertices: np.ndarray, edges: np.ndarray, u: np.ndarray, lo: float,
          hi: float) -> np.ndarray:
    """Vertices of (hull ∩ {lo <= u.x <= hi}): inner vertices and edge crossings."""
    t = vertices @ u
    parts = [vertices[(t >= lo) & (t <= hi)]]
    te = edges @ u  # (E, 2)
    for cut in (lo, hi):
        cross = (np.minimum(te[:, 0], te[:, 1]) < cut) & (np.maximum(te[:, 0], te[:, 1]) > cut)
        p, q = edges[cross, 0], edges[cross, 1]
        w = ((cut - te[cross, 0]) / (te[cross, 1] - te[cross, 0]))[:, None]
        parts.append(p + w * (q - p))
    return np.vstack(parts)


def fit_capsules(points: np.ndarray, max_pieces: int = 3, loose_ratio: float = 2.5
                 ) -> list[tuple[np.ndarray, np.ndarray, float]]:
    """One enclosing capsule, or up to ``max_pieces`` where one is loose.

    Parameters
    ----------
    points : (N, 3) array_like
        Mesh vertices in one frame (m).
    max_pieces : int
        Most capsules returned (>= 1).
    loose_ratio : float
        Split while the capsules' total volume is above ``loose_ratio`` times the
        convex hull's and a split into one more piece shrinks it by 20 % or more.

    Returns
    -------
    list of (a (3,), b (3,), radius)
        Capsules whose union holds the convex hull of ``points`` (m).
    """
    if max_pieces < 1:
        raise ValueError(f'max_pieces must be >= 1, got {max_pieces}')
    points = np.asarray(points, dtype=float).reshape(-1, 3)
    vertices, edges, hull_volume = _hull(points)
    best = [enclosing_capsule(vertices)]
    if hull_volume <= 0.0:
        return best
    centre = vertices.mean(axis=0)
    u = np.linalg.svd(vertices - centre, full_matrices=False)[2][0]
    t = vertices @ u

    def total(caps: list) -> float:
        return sum(capsule_volume(*c) for c in caps)

    for pieces in range(2, max_pieces + 1):
        if total(best) <= loose_ratio * hull_volume:
            break
        cuts = np.linspace(t.min(), t.max(), pieces + 1)
        split = [enclosing_capsule(_slab(vertices, edges, u, lo, hi))
                 for lo, hi in zip(cuts[:-1], cuts[1:])]
        if total(split) <= 0.8 * total(best):
            best = split
    return best
