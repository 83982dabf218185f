"""Simulation: measurement campaigns written as MCAP bags (the built-in test bench).

A campaign draws a "true" robot (nominal + realistic errors), measures poses
that are reachable, visible to the tracker and collision-free, and records the
joint-state and tracker-point streams exactly as ``ros2 bag record -s mcap``
would: every reflector of the cell at every pose (frame id ``<tracker>#<name>`` for a
``reflectors:`` cell), a reflector with an ``orientation`` as a tracked 6-DoF pose
(PoseStamped, orientation noise ``noise.sigma_rotation``). The truth is written next
to the bag (``<bag>.truth.yaml``) so that an identification can be checked against it.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from kpi_calib_ros.app.cell_model import CellModel, build_cell_model
from kpi_calib_ros.core.acquisition.reflector_frames import reflector_frame
from kpi_calib_ros.core.acquisition.streams import PointSample, synthesize_streams
from kpi_calib_ros.core.collision.check import verify_configuration
from kpi_calib_ros.core.errors import ConfigError
from kpi_calib_ros.core.measurement.pose import noisy_rotations, quaternion_from_rotation
from kpi_calib_ros.core.model.kinematics import link_poses, link_poses_function, reflector_point
from kpi_calib_ros.core.simulation import (
    random_configurations,
    simulate_measurements,
    true_parameters,
)
from kpi_calib_ros.io.bag import write_bag
from kpi_calib_ros.io.cell import Cell, load_cell
from kpi_calib_ros.io.cell_settings import hidden_effects
from kpi_calib_ros.io.design_io import read_design_poses
from kpi_calib_ros.io.names import truth_path
from kpi_calib_ros.io.results import write_truth


def collision_filter(cm: CellModel):
    """Callable (M, n) -> (M,) bool: True where the coal check finds no collision
    (robot, obstacles and the laser beam) at nominal geometry."""
    scene = cm.collision_scene()
    fk = link_poses_function(cm.robot, cm.geometric)
    p = cm.geometric.nominal
    tracker = cm.tracker_in_base[:3, 3]
    offset = cm.cell.reflector_offset

    def accept(q: np.ndarray) -> np.ndarray:
        ok = np.zeros(len(q), dtype=bool)
        for i, row in enumerate(q):
            poses, tip = link_poses(fk, cm.robot, p, row)
            reflector = reflector_point(tip, offset)
            ok[i] = verify_configuration(scene, poses, tracker, reflector).ok
        return ok
    return accept


def truth_cell_model(cell: Cell) -> tuple[CellModel, dict[str, float]]:
    """The cell's model plus the effects of ``simulation.hidden_effects``, and their
    true values (parameter name -> value) for the simulated robot."""
    cm = build_cell_model(cell)
    effects, overrides = hidden_effects(cell.simulation.hidden_effects or None, cm.robot,
                                        base_dir=cell.source_dir or None,
                                        allow_code=cell.allow_code_effects,
                                        temperatures=cm.model.joint_temperatures)
    if effects:
        cm = build_cell_model(cell, effects=effects)
    return cm, overrides


def simulate_campaign(cell_path: str | Path, n: int, out: str | Path, seed: int,
                      poses: tuple[list[str], np.ndarray] | None = None,
                      cm: CellModel | None = None,
                      p_true: np.ndarray | None = None,
                      allow_code_effects: bool = False) -> str:
    """Simulate ``n`` measurements in the cell and write ``out`` (.mcap) and its truth.

    Parameters
    ----------
    poses : (joint_names, (N, n) configurations), optional
        Measure these (URDF joint values, e.g. an optimal design) instead of random poses.
    cm, p_true : optional
        A prepared cell model (e.g. with hidden effects) and true parameters.
        By default the cell file's model with its ``simulation.hidden_effects``
        (see :func:`truth_cell_model`) and random geometric errors.

    Returns
    -------
    str
        A one-paragraph summary for the terminal.
    """
    if n < 1:
        raise ConfigError('n', 'must be at least 1')
    overrides: dict[str, float] = {}
    if cm is None:
        cm, overrides = truth_cell_model(load_cell(cell_path,
                                                   allow_code_effects=allow_code_effects))
    rng = np.random.default_rng(seed)
    if p_true is None:
        p_true = true_parameters(cm.model.params, rng, overrides=overrides)
    if poses is not None:
        names, q = poses
        if list(names) != cm.joint_names:
            raise ConfigError('poses.joint_names', f'{list(names)} differ from the robot chain '
                              f'{cm.joint_names}')
        q = np.atleast_2d(q)
    else:
        q = random_configurations(cm.model, cm.model.params.nominal, n, rng,
                                  cm.cell.max_incidence, accept=collision_filter(cm))
    # The points of the true poses q; the joint readings (data.q) carry the cell's
    # noise.joint_sigma when it states one.
    data = simulate_measurements(cm.model, p_true, q, cm.cell.sigma, rng, cm.model.joint_noise_map)
    # The joint states as the controller reports them (robot.joint_coupling).
    joints, points = synthesize_streams(cm.joint_coupling.to_controller(data.q), cm.joint_names,
                                        data.eta, cm.cell.tracker_frame, rng=rng)
    points = every_reflector(cm, p_true, q, points, rng)
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    write_bag(out, joints, points, pose_topic=cm.cell.pose_topic)
    truth = {'seed': seed, 'parameters': {name: float(v) for name, v in
                                          zip(cm.model.params.names, p_true)},
             'tcp_true': [[float(x) for x in row]
                          for row in cm.model.predict(p_true, cm.q_work, cm.tau_work)],
             'working_poses': list(cm.working_pose_names)}
    write_truth(out, truth)
    return (f'simulated {len(q)} poses ({len(joints)} joint states, {len(points)} tracker '
            f'points) -> {out}\ntruth -> {truth_path(out)}')


def every_reflector(cm: CellModel, p_true: np.ndarray, q: np.ndarray,
                    first: list[PointSample], rng: np.random.Generator) -> list[PointSample]:
    """The tracker's samples of every reflector at every pose, stamped like ``first``
    (reflector 0's points, already drawn): each further reflector's point with its own
    noise, frame ids ``<tracker>#<name>`` in a ``reflectors:`` cell, and a tracked body's
    orientation (noise ``noise.sigma_rotation`` in the body frame) with its point."""
    names = cm.cell.reflector_names
    if not names:
        return first
    tracker = cm.cell.tracker_frame
    sigma = np.broadcast_to(np.asarray(cm.cell.sigma, float), (3,))
    eta = {0: np.array([p.xyz for p in first])}
    for k in range(1, len(names)):
        eta[k] = (cm.model.predict(p_true, q, reflector=np.full(len(q), k))
                  + rng.normal(size=(len(q), 3)) * sigma)
    rotations = {k: noisy_rotations(cm.model.body_rotations(p_true, q, k),
                                    float(cm.cell.sigma_rotation or 0.0), rng)
                 for k in sorted(cm.model.orientations)}
    out = []
    for i, sample in enumerate(first):
        for k, name in enumerate(names):
            out.append(PointSample(sample.stamp_ns, reflector_frame(tracker, name),
                                   eta[k][i], quaternion_from_rotation(rotations[k][i])
                                   if k in rotations else None))
    return out


def run_simulate(cell_path: str | Path, n: int, out: str | Path, seed: int,
                 poses_path: str | Path | None = None, allow_code_effects: bool = False) -> int:
    """``kpi-calib simulate``: the bag and its truth; ``poses_path`` a design.yaml to measure."""
    poses = read_design_poses(poses_path) if poses_path else None
    if poses is not None:  # design files hold controller values (robot.joint_coupling)
        coupling = build_cell_model(load_cell(cell_path, allow_code_effects=allow_code_effects)
                                    ).joint_coupling
        poses = (poses[0], coupling.to_urdf(np.atleast_2d(poses[1])))
    print(simulate_campaign(cell_path, n, out, seed, poses=poses,
                            allow_code_effects=allow_code_effects))
    return 0
