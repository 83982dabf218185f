"""Capsules from stock collision meshes and the sampled collision matrix: UR10 and Panda.

For each robot of example-robot-data (meshes behind package:// URIs, resolved with
no configuration): URI resolution, capsule fitting over the chain links (timed
with perf_counter, three repeats, median), the largest distance of a mesh vertex
outside its link's capsules (must be <= 0), the capsule / convex-hull volume
ratio per link, the collision-matrix time for 2000 seeded samples and the pairs in
each class, and the mesh self-collision check of 500 random poses. Writes
bench/results/mesh_capsules.md.

Usage: .venv/bin/python bench/mesh_capsules.py
"""
from __future__ import annotations

import os
import sys
import time
from pathlib import Path

import numpy as np

from kpi_calib_ros.core.collision.capsule_fit import capsules_from_urdf, collision_vertices
from kpi_calib_ros.core.collision.capsule_geometry import (
    capsule_volume,
    convex_hull_volume,
    outside_distance,
)
from kpi_calib_ros.core.collision.check import mesh_collisions
from kpi_calib_ros.core.collision.matrix import classify_link_pairs
from kpi_calib_ros.core.model.robot import RobotModel
from kpi_calib_ros.io.resources import resolve_mesh_uris, resolve_uri

ROBOTS = (('UR10', 'ur_description/urdf/ur10_robot.urdf', 'base_link', 'tool0'),
          ('Panda', 'panda_description/urdf/panda.urdf', 'panda_link0', 'panda_hand'))
SAMPLES = 2000
REPEATS = 3


def _timed(fn, repeats: int = REPEATS):
    times, out = [], None
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - t0)
    return out, float(np.median(times))


def main() -> int:
    lines = ['# Capsules from meshes and the collision matrix (example-robot-data 6.0.0)', '',
             'Command: `.venv/bin/python bench/mesh_capsules.py`; '
             f'{os.cpu_count()} cores shared with other work; times are medians of '
             f'{REPEATS} runs.', '',
             '| robot | links | capsules | resolve s | fit s | max vertex outside m | '
             'volume / hull | matrix s (2000 samples) | adjacent | default | always | never '
             '| sometimes | mesh check s (500 poses) | poses in mesh collision |',
             '|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|']
    for name, path, base, tip in ROBOTS:
        uri = f'package://example-robot-data/robots/{path}'
        xml, t_resolve = _timed(lambda uri=uri: resolve_mesh_uris(resolve_uri(uri).read_text()))
        robot = RobotModel(xml, base, tip)
        caps, t_fit = _timed(lambda xml=xml, robot=robot: capsules_from_urdf(xml, robot.link_names))
        vertices = collision_vertices(xml, robot.link_names)
        worst, ratios = -np.inf, []
        for link in robot.link_names:
            mine = [c for c in caps if c.frame == link]
            outside = np.min([outside_distance(vertices[link], c.a, c.b, c.radius)
                              for c in mine], axis=0)
            worst = max(worst, float(outside.max()))
            ratios.append(sum(capsule_volume(c.a, c.b, c.radius) for c in mine)
                          / convex_hull_volume(vertices[link]))
        matrix, t_matrix = _timed(lambda robot=robot, caps=caps: classify_link_pairs(
            robot, caps, SAMPLES, seed=0))
        counts = {k: len(matrix.of_kind(k))
                  for k in ('adjacent', 'default', 'always', 'never', 'sometimes')}
        rng = np.random.default_rng(1)
        lower = np.where(np.isfinite(robot.lower), robot.lower, -np.pi)
        upper = np.where(np.isfinite(robot.upper), robot.upper, np.pi)
        q = rng.uniform(lower, upper, size=(500, robot.n_joints))
        check, t_check = _timed(
            lambda xml=xml, base=base, robot=robot, q=q, matrix=matrix: mesh_collisions(
                xml, [], base, robot.joint_names, q, matrix.skip_pairs()), 1)
        print(f'{name}: {len(robot.link_names)} links -> {len(caps)} capsules; resolve '
              f'{t_resolve:.3f} s, fit {t_fit:.2f} s, max vertex outside {worst:.2e} m, '
              f'volume/hull {min(ratios):.2f}..{max(ratios):.2f}; matrix {t_matrix:.2f} s '
              f'{counts}; mesh check {t_check:.2f} s, {len(check.colliding)}/500 in collision',
              flush=True)
        for p in matrix.pairs:
            if p.kind != 'sometimes':
                print(f'   {p.kind:9s} {p.links[0]} ~ {p.links[1]} '
                      f'{"" if p.fraction is None else f"{p.fraction:.3f}"}')
        lines.append(f'| {name} | {len(robot.link_names)} | {len(caps)} | {t_resolve:.3f} | '
                     f'{t_fit:.2f} | {worst:.1e} | {min(ratios):.2f}..{max(ratios):.2f} | '
                     f'{t_matrix:.2f} | ' + ' | '.join(str(counts[k]) for k in counts)
                     + f' | {t_check:.2f} | {len(check.colliding)}/500 |')
    lines += ['', 'Max vertex outside: largest signed distance of a collision-mesh vertex from '
              "its link's capsules (<= 0: enclosed; the 1e-9 m safety shows as -1e-9). "
              'Poses in mesh collision: uniform random poses within the joint limits, '
              'the skipped pairs (adjacent, default, always) excluded; random poses of a '
              'whole arm do self-collide.']
    out = Path(__file__).resolve().parent / 'results' / 'mesh_capsules.md'
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text('\n'.join(lines) + '\n')
    print('\n'.join(lines))
    return 0


if __name__ == '__main__':
    sys.exit(main())
