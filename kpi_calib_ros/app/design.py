"""Measurement design for a cell: the ``kpi-calib design`` command and the node's ``~/design``.

Builds the typed design problem from the cell (:meth:`CellModel.design_cell`),
uses the cell file's ``design:`` settings, and writes design.yaml and its plots.
"""
from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import TYPE_CHECKING, Any, Callable, Sequence

import numpy as np

from kpi_calib_ros.app.cell_model import CellModel, build_cell_model
from kpi_calib_ros.app.robot_geometry import mesh_check
from kpi_calib_ros.core.design.optimum import (
    DesignResult,
    design_context,
    design_measurements,
    tcp_std_on_drawn_robots,
)
from kpi_calib_ros.core.diagnosis.model_selection import level_free
from kpi_calib_ros.core.estimation.drift_state import DriftSwing
from kpi_calib_ros.core.estimation.estimability import KpiEstimability, result_estimability
from kpi_calib_ros.core.estimation.prior import (
    DRIFT_ANGLE_PER_SQRT_HOUR,
    DRIFT_LENGTH_PER_SQRT_HOUR,
    PLACEMENT_PREFIXES,
    Prior,
)
from kpi_calib_ros.io.cell import load_cell
from kpi_calib_ros.io.design_io import plot_design, plot_ellipsoids, summary_text, write_design

if TYPE_CHECKING:  # a type only: run_design imports app.reidentify when given a prior
    from kpi_calib_ros.app.reidentify import CyclePrior


def design_cell_model(cm: CellModel, n: int, criterion: str, seed: int,
                      progress: Callable[[str], None] | None = None) -> DesignResult:
    """N configurations optimal for ``criterion`` in the cell of ``cm`` (its ``design:``
    settings), drawn with ``numpy.random.default_rng(seed)``, verified on the meshes."""
    result = design_measurements(cm.design_cell(), n, criterion, np.random.default_rng(seed),
                                 cm.design_settings, progress=progress)
    return mesh_verified(cm, result)[0]


def mesh_verified(cm: CellModel, result: DesignResult) -> tuple[DesignResult, dict[str, Any]]:
    """``result`` checked against the URDF collision MESHES (Pinocchio + coal), independently
    of the capsules the design used, and the geometry section of design.yaml.

    A configuration in mesh collision is a violation like any other: the design is then
    not ok. Returns the result (verification and status extended) and a YAML-ready
    ``{capsules, skipped_pairs, mesh_check}`` document.
    """
    geometry = cm.robot_geometry()
    doc = geometry.summary()
    if not geometry.has_meshes:
        doc['mesh_check'] = {'run': False, 'why': 'the URDF has no collision meshes '
                             '(or every link has hand-given capsules and the meshes were '
                             'not found)'}
        return result, doc
    check, at_default = mesh_check(geometry, cm.robot, result.configurations,
                                   cm.cell.ignore_pairs)
    lines = tuple(f'configuration {k}: mesh collision {a}~{b}'
                  for k, pairs in enumerate(check.collisions) for a, b in pairs)
    doc['mesh_check'] = {
        'run': True, 'configurations': len(check.collisions),
        'in_collision': len(check.colliding), 'pairs_checked': len(check.checked),
        'skipped_touching_at_default': [list(p) for p in at_default],
        'excluded': [{'links': list(k), 'why': v} for k, v in check.excluded.items()]}
    if not lines:
        return result, doc
    verification = dataclasses.replace(result.verification, ok=False,
                                       violations=result.verification.violations + lines)
    status = (f'{result.status}; {len(check.colliding)}/{len(check.collisions)} '
              'configurations in mesh collision (see verification)')
    return dataclasses.replace(result, verification=verification, status=status), doc


def design_estimability(cm: CellModel, configurations: np.ndarray,
                        prior: Prior | None = None, p: np.ndarray | None = None,
                        allowed: Sequence[str] | None = None) -> KpiEstimability:
    """Whether measuring ``configurations`` (N, n) determines the TCP at every working
    pose, for the cell's model level (``auto``: the full geometric model, the most
    demanding), at the nominal parameters (or ``p``); with ``prior`` (whose information
    counts) and ``allowed`` (the parameters a re-identification frees)."""
    free = design_free(cm, allowed)
    at = cm.model.params.nominal if p is None else p
    # Every row a designed pose gives: each reflector's point, each tracked body's rotation.
    rows = cm.model.pose_measurements(at, np.atleast_2d(configurations))
    return result_estimability(cm.model, rows.q, cm.cell.sigma, at, cm.q_work,
                               cm.working_pose_names, free, prior=prior,
                               reflector=rows.reflector, rotation=rows.rotation,
                               tau_work=cm.tau_work)


def design_point(cm: CellModel, cp: CyclePrior) -> np.ndarray:
    """Where a design with the previous calibration ``cp`` as prior linearises (n_p,): every
    robot parameter at the calibration's value; the base and reflector placement, when the
    new cycle identifies it anew (not ``cp.keep_placement``), where the cell file puts it.

    The cell file describes the station the design is for. A calibration of several
    recordings holds the first recording's placement in ``base.*``: from another station
    (metres and tens of degrees away) linearised there, the predicted TCP covariance was
    that of the first station's frame, not of the identification the design plans (37 %
    off on the default cell with the station 30° turned).
    """
    p = cm.model.params.with_values(cp.values)
    if cp.keep_placement:
        return p
    placed = [i for i, n in enumerate(cm.model.params.names) if n.startswith(PLACEMENT_PREFIXES)]
    p[placed] = cm.model.params.nominal[placed]
    return p


def prior_cell_model(cm: CellModel, cp: CyclePrior) -> tuple[CellModel, np.ndarray]:
    """``cm`` as a design with the previous calibration ``cp`` as prior sees it, and where
    it linearises (:func:`design_point`): the new points weighted as ``identify --prior``
    will weigh them, at the noise the prior showed (σ·√scale,
    :func:`~kpi_calib_ros.app.reidentify.with_noise_scale`), not the cell's σ."""
    from kpi_calib_ros.app.reidentify import with_noise_scale
    cm = with_noise_scale(cm, cp.noise_scale)
    return cm, design_point(cm, cp)


def prior_design(cm: CellModel, cp: CyclePrior, n: int, criterion: str, seed: int
                 ) -> tuple[CellModel, DesignResult, np.ndarray]:
    """``n`` configurations optimal for ``criterion`` with ``cp``'s information added (as
    ``kpi-calib design --prior``), verified on the meshes: the cell model they were
    designed in (:func:`prior_cell_model`), the design and the linearisation point."""
    cm, p = prior_cell_model(cm, cp)
    rng = np.random.default_rng(seed)
    context = design_context(cm.design_cell(), rng, cm.design_settings, prior=cp.prior, p=p,
                             free=design_free(cm, cp.allowed))
    result = design_measurements(cm.design_cell(), n, criterion, rng, cm.design_settings,
                                 context=context)
    return cm, mesh_verified(cm, result)[0], p


def design_free(cm: CellModel, allowed: Sequence[str] | None = None) -> list[str]:
    """Free parameters of the cell's model level (``auto``: geometric), within
    ``allowed`` when given."""
    level = cm.cell.identification.model
    free = level_free(cm.model.params, 'geometric' if level == 'auto' else level,
                      len(cm.geometric))
    return free if allowed is None else [n for n in free if n in set(allowed)]


def drawn_robots_section(cm: CellModel, design: DesignResult,
                         seed: int) -> tuple[dict[str, Any], str]:
    """design.yaml's ``drawn_robots`` section and a summary line: the TCP std the
    identification of ``design`` (URDF joint values) will report on robots drawn around
    the nominal geometry (:func:`~kpi_calib_ros.core.design.optimum.tcp_std_on_drawn_robots`),
    where it may free parameters the nominal design problem cannot."""
    drawn = tcp_std_on_drawn_robots(cm.design_cell(), design.configurations,
                                    cm.design_settings.weights, np.random.default_rng([seed, 1]))
    doc = drawn.to_dict(len(design.parameter_names), design.working_pose_names,
                        design.tcp_std)
    counts = sorted(set(drawn.parameters))
    text = (f"  on {doc['robots']} robots drawn around the nominal geometry the "
            f"identification frees {'/'.join(map(str, counts))} parameters "
            f"({doc['nominal_parameters']} at the nominal geometry): TCP std "
            + '; '.join(f"{name} {np.round(np.array(v['median']) * 1e6, 2).tolist()} µm "
                        f"(x{v['ratio_to_nominal_median']:.3f} on the largest axis)"
                        for name, v in doc['tcp_std_m'].items()))
    return doc, text


def controller_design(cm: CellModel, design: DesignResult) -> DesignResult:
    """``design`` with its configurations in the controller's joint values
    (``robot.joint_coupling``): what design.yaml and ``~/measurement_poses`` give the
    robot program. The identity for an uncoupled controller."""
    if cm.joint_coupling.is_identity:
        return design
    return dataclasses.replace(design, configurations=cm.joint_coupling.to_controller(
        design.configurations), joint_names=tuple(cm.joint_names))


def run_design(cell_path: str | Path, n: int, criterion: str, out: str | Path,
               seed: int = 0, allow_code_effects: bool = False,
               prior_path: str | Path | None = None, hours: float = 1.0,
               drift: tuple[float, ...] = (DRIFT_LENGTH_PER_SQRT_HOUR,
                                           DRIFT_ANGLE_PER_SQRT_HOUR),
               keep_placement: bool = False, drift_model: str = 'thermal',
               swing: DriftSwing | None = None) -> int:
    """``kpi-calib design``: design.yaml, ``<stem>_poses.png`` and ``<stem>_ellipsoids.png``
    (heuristic vs this design) and a summary on stdout.

    ``prior_path`` (``--prior``): a previous calibration whose information every design
    has (the KPI criterion with the prior precision added), widened by ``drift`` for
    ``hours`` (:func:`kpi_calib_ros.app.reidentify.cycle_prior`, the same prior the
    re-identification of the measured poses will use; with ``swing``, extrapolated along
    its drift state) and linearised at its values.

    Returns 0, or 1 when the independent verification failed or the design (with the
    prior) leaves the KPI not estimable.
    """
    cm = build_cell_model(load_cell(cell_path, allow_code_effects=allow_code_effects))
    cell, settings = cm.design_cell(), cm.design_settings
    rng = np.random.default_rng(seed)
    prior, p, allowed, prior_doc = None, None, None, None
    if prior_path is not None:
        from kpi_calib_ros.app.reidentify import cycle_prior, read_prior_calibration
        old = read_prior_calibration(prior_path)
        cp = cycle_prior(cm, old, None, drift[0], drift[1], keep_placement=keep_placement,
                         drift_model=drift_model, hours=hours,
                         rotation_rate=drift[2] if len(drift) > 2 else None,
                         placement_rate=drift[3] if len(drift) > 3 else None,
                         swing=swing)
        cm, p = prior_cell_model(cm, cp)
        cell, settings = cm.design_cell(), cm.design_settings
        prior, allowed = cp.prior, cp.allowed
        prior_doc = {'source': str(prior_path), 'description': cp.description,
                     'hours': float(hours), 'keep_placement': keep_placement}
        print(cp.description)
    context = design_context(cell, rng, settings, prior=prior, p=p,
                             free=None if allowed is None else design_free(cm, allowed))
    print(f'{context.candidates.configurations.shape[0]} feasible candidates from '
          f'{context.candidates.draws} draws ({context.seconds:.1f} s)')
    result = design_measurements(cell, n, criterion, rng, settings, context=context,
                                 progress=print)
    result, geometry_doc = mesh_verified(cm, result)
    baseline = result if criterion == 'random' else design_measurements(
        cell, n, 'random', rng, settings, context=context)
    out = Path(out)
    extra: dict[str, Any] = {'geometry': geometry_doc}
    drawn_text = ''
    if prior_doc is not None:
        extra['prior'] = prior_doc
    else:  # with a prior the problem is linearised at its values, not at the nominal
        extra['drawn_robots'], drawn_text = drawn_robots_section(cm, result, seed)
    write_design(out, controller_design(cm, result), extra=extra)
    stem = out.with_suffix('')
    poses_png = plot_design(cell, context.check_scene, result, f'{stem}_poses.png')
    shown = [baseline] if result is baseline else [baseline, result]
    names = ['heuristic'] if result is baseline else ['heuristic', f'{criterion}-optimal']
    ell_png = plot_ellipsoids(shown, names, f'{stem}_ellipsoids.png')
    print(summary_text(result, None if result is baseline else baseline))
    if drawn_text:
        print(drawn_text)
    print('\n'.join(cm.robot_geometry().summary_lines()))
    mesh = geometry_doc['mesh_check']
    print(f"  mesh check: {mesh['in_collision']}/{mesh['configurations']} configurations in "
          f"mesh collision ({mesh['pairs_checked']} link pairs checked)" if mesh['run'] else
          f"  mesh check: not run, {mesh['why']}")
    estimability = design_estimability(cm, result.configurations, prior, p, allowed)
    print(('' if estimability.all_estimable else 'WARNING: ') + estimability.summary())
    print(f'written: {out}, {poses_png}, {ell_png}')
    return 0 if result.verification.ok and estimability.all_estimable else 1
