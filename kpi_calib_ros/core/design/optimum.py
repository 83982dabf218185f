"""Optimal measurement design for KPIs (Jost et al. 2017, eq. 24), collision-free.

A design is N joint configurations ``q_meas`` chosen to minimise a criterion of
the linearised covariance (:mod:`design_criteria`: the KPI criterion, the
parameter A-criterion q_p of the "state of the art", D, O1, condition number)
subject to eq. (24b): joint limits, incidence angle ≤ ``max_incidence`` (eq. 4)
and every capsule margin of :class:`CollisionScene` (eq. 20-22, line of sight).

Candidates are uniform random draws kept when they satisfy every constraint
(:mod:`design_constraints`); the exchange algorithm (:mod:`design_exchange`)
picks N of them and an IPOPT NLP (:mod:`design_nlp`) refines all N
configurations continuously. The returned design is re-checked by
:func:`verify_design` with Pinocchio and coal, not with the optimiser's own
constraint code; an NLP result that fails that check is never returned.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Callable, Mapping, Sequence

import numpy as np

from kpi_calib_ros.core.collision.capsules import CollisionScene
from kpi_calib_ros.core.design.cell import DesignCell
from kpi_calib_ros.core.design.constraints import (
    CandidateSet,
    DesignVerification,
    flag_pairs,
    generate_candidates,
    scene_without,
    verify_design,
)
from kpi_calib_ros.core.design.criteria import CRITERIA, DesignProblem, build_problem
from kpi_calib_ros.core.design.exchange import exchange
from kpi_calib_ros.core.design.nlp import solve_design_nlp
from kpi_calib_ros.core.errors import ConfigError
from kpi_calib_ros.core.estimation.prior import Prior
from kpi_calib_ros.core.simulation import true_parameters

DESIGN_CRITERIA = CRITERIA + ('random',)
# Robots drawn from the simulation's error magnitudes on which a design's TCP std is
# also predicted (:func:`tcp_std_on_drawn_robots`).
DRAWN_ROBOTS = 4
__all__ = ['CRITERIA', 'DESIGN_CRITERIA', 'DesignCell', 'DesignContext', 'DesignProblem',
           'DesignResult', 'DesignSettings', 'build_problem', 'design_context',
           'design_measurements']


# ------------------------------------------------------------------------ settings
@dataclass(frozen=True)
class DesignSettings:
    """Options of :func:`design_measurements`; the cell file's ``design:`` section.

    Validated by :func:`kpi_calib_ros.io.cell_settings.design_settings`.

    Attributes
    ----------
    candidates : int
        Size of the random feasible candidate set of the exchange algorithm.
    weights : dict of str to float
        Weight of each working pose in the KPI criterion (default: equal).
    collision : bool
        Impose the capsule constraints (False: limits and incidence only).
    clearance : float
        Margin (m) the optimiser keeps from every capsule pair; verification uses 0.
    incidence_clearance : float
        Margin (rad) the optimiser keeps below ``max_incidence``; verification uses 0.
    nlp : bool
        Refine the exchange result with IPOPT.
    exchange_starts : int
        Random restarts of the exchange algorithm; the best is kept.
    max_iterations : int
        IPOPT iteration limit.
    ignore_flagged : bool
        Drop pairs violated in nearly every measurable pose (reported) instead of failing.
    flag_threshold : float
        Fraction of measurable random poses above which a pair is flagged.
    """

    candidates: int = 4000
    weights: Mapping[str, float] = field(default_factory=dict)
    collision: bool = True
    clearance: float = 0.002
    incidence_clearance: float = 0.002
    nlp: bool = True
    exchange_starts: int = 1
    max_iterations: int = 300
    ignore_flagged: bool = False
    flag_threshold: float = 0.98


# ------------------------------------------------------------------------- result
@dataclass(frozen=True)
class DesignResult:
    """A measurement design and everything known about it.

    Attributes
    ----------
    configurations : (N, n) ndarray
        Joint values in chain order (rad).
    joint_names : tuple of str
    criterion : str
        One of :data:`DESIGN_CRITERIA`.
    objective : float
        Value of ``criterion`` for this design (for ``'random'``: the KPI value).
    criteria : dict of str to float
        Every criterion of :data:`CRITERIA`, for comparison.
    tcp_covariance : (t, 3, 3) ndarray
        Predicted C_s per working pose (m²), at σ of the cell.
    tcp_std : (t, 3) ndarray
        Its square-root diagonal (m).
    working_pose_names, parameter_names : tuple of str
    min_margin : (N,) ndarray
        Smallest verified capsule distance per configuration (m; inf without scene).
    incidence_deg : (N,) ndarray
    constraint_count : int
        Constraints per configuration (capsule pairs + incidence); bounds extra.
    verification : DesignVerification
        Independent check (Pinocchio + coal) of the returned configurations.
    flagged_pairs : dict of str to float
        Pairs violated in nearly all measurable poses, with that fraction.
    status : str
        What happened, including any fallback or violation.
    timings : dict of str to float
        Seconds per stage: candidates, exchange, nlp, verify, total.
    candidates : int
    exchange_objective : float
        Criterion value after the exchange algorithm (before the NLP).
    """

    configurations: np.ndarray
    joint_names: tuple[str, ...]
    criterion: str
    objective: float
    criteria: dict[str, float]
    tcp_covariance: np.ndarray
    tcp_std: np.ndarray
    working_pose_names: tuple[str, ...]
    parameter_names: tuple[str, ...]
    min_margin: np.ndarray
    incidence_deg: np.ndarray
    constraint_count: int
    verification: DesignVerification
    flagged_pairs: dict[str, float]
    status: str
    timings: dict[str, float]
    candidates: int
    exchange_objective: float


@dataclass(frozen=True)
class DesignContext:
    """Reusable pieces for several designs of one cell: scene, candidates, problem."""

    scene: CollisionScene | None
    check_scene: CollisionScene | None
    candidates: CandidateSet
    problem: DesignProblem
    rows: np.ndarray
    flagged: dict[str, float]
    seconds: float


def design_context(cell: DesignCell, rng: np.random.Generator,
                   settings: DesignSettings | None = None, prior: Prior | None = None,
                   p: np.ndarray | None = None,
                   free: Sequence[str] | None = None) -> DesignContext:
    """Collision scene, feasible candidates and the linearised problem of a cell.

    ``prior``, ``p`` and ``free`` (a previous calibration as prior, its values, the
    parameters a re-identification frees) go to :func:`build_problem`: every design of
    this context then counts the prior's information.

    Raises
    ------
    ConfigError
        Capsule pairs are violated in nearly every measurable pose and
        ``ignore_flagged`` is off (the message names them and the fix).
    """
    start = time.perf_counter()
    settings = settings or DesignSettings()
    full = cell.scene
    flagged = flag_pairs(cell, full, rng, threshold=settings.flag_threshold)
    # A line of sight crossed at nearly every pose is no overlap by construction: the tracker
    # stands beyond or inside the obstacle. Dropped (design.ignore_flagged), the design's
    # beam crossed a capsule round the tracker at 12 of 12 poses with a warning alone.
    sight = {k: v for k, v in flagged.items() if k.split('~')[0] == 'beam'}
    if sight:
        raise ConfigError('obstacles', 'the laser beam crosses obstacle(s) '
                          + ', '.join(f"{k.split('~')[1]} ({100 * v:.0f} %)"
                                      for k, v in sight.items())
                          + ' in nearly every measurable pose: the tracker stands beyond or '
                          'inside them; check tracker.base_in_tracker and the obstacles (a '
                          'stand of the tracker is no obstacle of its beam: leave it out, or '
                          'add beam~<name> to collision.ignore_pairs when the beam truly '
                          'passes above it); design.ignore_flagged drops no line of sight')
    if flagged and not settings.ignore_flagged:
        text = ', '.join(f'{k} ({100 * v:.0f} %)' for k, v in flagged.items())
        raise ConfigError('collision.ignore_pairs', f'pairs in collision in nearly every '
                          f'measurable pose: {text}; if the capsules only overlap by '
                          'construction, add the pairs to collision.ignore_pairs (or set '
                          'design.ignore_flagged: true)')
    check = scene_without(full, tuple(flagged)) if flagged else full
    scene = check if settings.collision else None
    cand = generate_candidates(cell, scene, settings.candidates, rng,
                               clearance=settings.clearance if scene is not None else 0.0,
                               incidence_clearance=settings.incidence_clearance,
                               flag_threshold=settings.flag_threshold)
    problem = build_problem(cell, cand.configurations[:min(len(cand.configurations), 600)],
                            settings.weights, prior=prior, p=p, free=free)
    rows = problem.rows(cell.model, cand.configurations)
    return DesignContext(scene, check, cand, problem, rows, flagged,
                         time.perf_counter() - start)


def design_measurements(cell: DesignCell, n: int, criterion: str, rng: np.random.Generator,
                        settings: DesignSettings | None = None,
                        context: DesignContext | None = None,
                        progress: Callable[[str], None] | None = None) -> DesignResult:
    """N measurement configurations optimal for ``criterion`` under every constraint.

    Parameters
    ----------
    cell : DesignCell
        The cell's design problem, e.g. ``CellModel.design_cell()``.
    n : int
        Number of configurations N.
    criterion : {'kpi', 'A', 'D', 'O1', 'cond', 'random'}
        ``'random'`` is the heuristic baseline: N uniform draws that satisfy
        every constraint.
    rng : numpy.random.Generator
    settings : DesignSettings, optional
        Default: :class:`DesignSettings` defaults (a cell file's ``design:``
        section is ``Cell.design``).
    context : DesignContext, optional
        Reuse candidates and problem across criteria (same cell and settings).
    progress : callable(str), optional
        Receives progress lines (exchange steps, IPOPT iterations).

    Returns
    -------
    DesignResult
        The design is verified independently; violations are listed in
        ``verification`` and ``status``, never dropped.
    """
    if criterion not in DESIGN_CRITERIA:
        raise ValueError(f'criterion must be one of {DESIGN_CRITERIA}, got {criterion!r}')
    settings = settings or DesignSettings()
    say = progress or (lambda _msg: None)
    total = time.perf_counter()
    ctx = context or design_context(cell, rng, settings)
    cand_q, rows, problem = ctx.candidates.configurations, ctx.rows, ctx.problem
    if n > len(cand_q):
        raise ValueError(f'n = {n} exceeds the {len(cand_q)} candidates; raise design.candidates')
    timings = {'candidates': ctx.seconds if context is None else 0.0}
    say(f'{len(cand_q)} feasible candidates, {problem.k} identifiable parameters, '
        f'{1 + (ctx.scene.count if ctx.scene else 0)} constraints per configuration')
    t = time.perf_counter()
    status = []
    if criterion == 'random':
        q = cand_q[rng.choice(len(cand_q), size=n, replace=False)]
        exchange_value = problem.criteria(problem.rows(cell.model, q))['kpi']
    else:
        loss = problem.loss(criterion)
        best = None
        for _ in range(settings.exchange_starts):
            res = exchange(rows, n, loss, rng, progress=say, base=problem.prior_information)
            if best is None or res.loss < best.loss:
                best = res
        if best is None:
            raise ValueError('settings.exchange_starts must be >= 1, got '
                             f'{settings.exchange_starts}')
        q = cand_q[best.selected]
        exchange_value = problem.criteria(rows[best.selected])[criterion]
        status.append(f'exchange: {best.exchanges} exchanges')
    timings['exchange'] = time.perf_counter() - t
    t = time.perf_counter()
    if settings.nlp and criterion in ('kpi', 'A', 'D', 'O1') and cell.model.uses_torque:
        # A compliance, a play: the point reads the gravity torque, computed by Pinocchio
        # (no CasADi form here), which the symbolic NLP cannot differentiate; it crashed.
        status.append('ipopt refinement skipped: an effect of the model reads the gravity '
                      'torque, which the symbolic refinement cannot differentiate; the '
                      'design is the exchange over the feasible candidates')
    elif settings.nlp and criterion in ('kpi', 'A', 'D', 'O1'):
        nlp = solve_design_nlp(problem, cell, ctx.scene, q, criterion,
                               clearance=settings.clearance,
                               incidence_clearance=settings.incidence_clearance,
                               max_iterations=settings.max_iterations, progress=progress)
        status.append(f'ipopt: {nlp.status} after {nlp.iterations} iterations, loss '
                      f'{nlp.loss_start:.4g} -> {nlp.loss:.4g}')
        if nlp.loss < nlp.loss_start:
            trial = verify_design(cell, ctx.scene, nlp.configurations)
            refused = (0 if cell.accept is None
                       else int(np.sum(~np.asarray(cell.accept(nlp.configurations), bool))))
            if trial.ok and not refused:
                q = nlp.configurations
            elif trial.ok:
                status.append(f'the NLP result put {refused} configuration(s) in contact on '
                              'the collision meshes; returned the exchange design')
            else:
                status.append(f'the NLP result failed the independent check '
                              f'({len(trial.violations)} violations, first: '
                              f'{trial.violations[0]}); returned the exchange design')
        else:
            status.append('the NLP did not improve on the exchange design; returned that')
    timings['nlp'] = time.perf_counter() - t
    t = time.perf_counter()
    verification = verify_design(cell, ctx.check_scene, q)
    timings['verify'] = time.perf_counter() - t
    if not verification.ok:
        where = 'without collision constraints: ' if ctx.scene is None else ''
        status.append(f'{where}{len(verification.violations)} constraint violations '
                      f'(see verification)')
    final_rows = problem.rows(cell.model, q)
    values = problem.criteria(final_rows)
    tcp = problem.tcp_covariance(final_rows)
    timings['total'] = time.perf_counter() - total + timings['candidates']
    return DesignResult(
        configurations=q, joint_names=tuple(cell.robot.joint_names),
        criterion=criterion, objective=values['kpi' if criterion == 'random' else criterion],
        criteria=values, tcp_covariance=tcp,
        tcp_std=np.sqrt(np.diagonal(tcp, axis1=1, axis2=2)),
        working_pose_names=tuple(cell.working_pose_names),
        parameter_names=problem.parameter_names, min_margin=verification.min_margin,
        incidence_deg=verification.incidence_deg,
        constraint_count=verification.constraint_count, verification=verification,
        flagged_pairs=dict(ctx.flagged), status='; '.join(status) or 'ok', timings=timings,
        candidates=len(cand_q), exchange_objective=float(exchange_value))


@dataclass(frozen=True)
class DrawnRobots:
    """A design's predicted TCP std on robots drawn around the nominal geometry.

    Where the nominal geometry is degenerate (parallel axes, a reflector on the flange
    axis) some parameter directions vanish there that a real robot has: the identification
    of the designed poses, which selects its parameters at the estimate, frees them, and
    its TCP std is larger than the nominal design problem's (on the default cell 27
    parameters against 25, +1 to +10 % depending on the working poses).

    Attributes
    ----------
    parameters : tuple of int
        Parameters identifiable from the designed poses at each drawn robot.
    tcp_std : (draws, t, 3) ndarray
        Predicted TCP std per robot, working pose and axis (m), at σ of the cell.
    """

    parameters: tuple[int, ...]
    tcp_std: np.ndarray

    def to_dict(self, nominal_parameters: int, pose_names: Sequence[str],
                nominal_std: np.ndarray) -> dict:
        """YAML-ready summary: counts, and per working pose the std figures.

        The median and largest std (m) and the median ratio of the largest axis to the nominal
        problem's.
        """
        worst = np.max(self.tcp_std, axis=2) / np.max(nominal_std, axis=1)[None, :]
        return {
            'robots': len(self.parameters), 'parameters': list(self.parameters),
            'nominal_parameters': int(nominal_parameters),
            'tcp_std_m': {name: {'median': [float(x) for x in np.median(self.tcp_std[:, i],
                                                                          axis=0)],
                                 'max': [float(x) for x in np.max(self.tcp_std[:, i], axis=0)],
                                 'ratio_to_nominal_median': float(np.median(worst[:, i]))}
                          for i, name in enumerate(pose_names)},
            'why': 'identification selects its parameters at the estimate: on a real robot '
                   'it frees directions the nominal geometry lacks (parallel axes, a '
                   'reflector on the flange axis); robots drawn from the simulation\'s '
                   'error magnitudes'}


def tcp_std_on_drawn_robots(cell: DesignCell, configurations: np.ndarray,
                            weights: Mapping[str, float] | None,
                            rng: np.random.Generator,
                            draws: int = DRAWN_ROBOTS) -> DrawnRobots:
    """Predict the TCP std the identification of ``configurations`` (N, n) will report.

    On ``draws`` robots drawn from :class:`~kpi_calib_ros.core.simulation.ErrorMagnitudes`: the
    design problem at each robot, its identifiable parameters selected from the designed poses
    themselves, as :func:`kpi_calib_ros.core.estimation.least_squares.identify` selects them
    from the measured ones.
    """
    q = np.atleast_2d(configurations)
    counts, stds = [], []
    for _ in range(draws):
        p = true_parameters(cell.model.params, rng)
        problem = build_problem(cell, q, weights, p=p)
        tcp = problem.tcp_covariance(problem.rows(cell.model, q))
        counts.append(problem.k)
        stds.append(np.sqrt(np.diagonal(tcp, axis1=1, axis2=2)))
    return DrawnRobots(tuple(counts), np.array(stds))
