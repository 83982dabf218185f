"""Optimal measurement design for KPIs (Jost et al. 2017, eq. 24), collision-free.

A design is N joint configurations ``q_meas``. For the identifiable parameters
(QR on a rich random pose set, once per cell) the linearised covariance at the
nominal parameters is ``C_p = M⁻¹`` with the information ``M = Σ_i J_iᵀ W² J_i``
(W = diag(1/σ)), and the KPI covariance at working pose t is
``C_s,t = J_w,t C_p J_w,tᵀ`` (eq. 19; the KPI point is the reflector centre at
the working pose in the tracker frame, gauge-free). Criteria, all "smaller is
better" except O1:

* ``kpi``  Σ_t ω_t tr(C_s,t) / 3 with weights ω summing to 1 (m²): eq. (24a)
  with P projecting onto the TCP points; the average TCP variance.
* ``A``    tr(S C_p S) / k (m²): the parameter-optimal "state of the art" q_p.
  S_j is the rms length by which a unit change of parameter j moves the
  measured point (1 for a translation, the lever arm for an angle), so every
  term is the point variance that parameter's uncertainty causes: m and rad
  add up, and a parameter the reflector barely feels cannot dominate.
* ``D``    det(S C_p S)^(1/k) (m²).
* ``O1``   Borm-Menq (σ₁⋯σ_k)^(1/k)/√m of the S-scaled Jacobian (larger is better).
* ``cond`` condition number of the S-scaled Jacobian.

Constraints (eq. 24b): joint limits, incidence angle ≤ ``max_incidence`` (eq. 4)
and every capsule margin of :class:`CollisionScene` (eq. 20-22, line of sight).
Candidates are uniform random draws kept when they satisfy all of them; the
exchange algorithm (:mod:`design_exchange`) picks N of them and an IPOPT NLP
(:mod:`design_nlp`) refines all N configurations continuously. The returned
design is re-checked by :func:`verify_design` with Pinocchio and coal, not with
the optimiser's own constraint code.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field, replace
from typing import Any, Callable, Mapping

import numpy as np

from kpi_calib_ros.core.collision import CollisionScene
from kpi_calib_ros.core.design_constraints import (CandidateSet, DesignVerification, flag_pairs,
                                                   generate_candidates, scene_without,
                                                   verify_design)
from kpi_calib_ros.core.design_exchange import (ConditionLoss, LogDetLoss, TraceLoss, exchange,
                                                information)
from kpi_calib_ros.core.design_nlp import solve_design_nlp
from kpi_calib_ros.core.errors import ConfigError
from kpi_calib_ros.core.identifiability import select_identifiable

CRITERIA = ('kpi', 'A', 'D', 'O1', 'cond')
DESIGN_CRITERIA = CRITERIA + ('random',)
# Relative column norm below which a parameter counts as having no effect at all.
NEGLIGIBLE_EFFECT = 1e-8


# ------------------------------------------------------------------------ settings
@dataclass(frozen=True)
class DesignSettings:
    """Options of :func:`design_measurements`; the cell file's ``design:`` section.

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


def design_settings(raw: Mapping[str, Any] | None) -> DesignSettings:
    """Validate the ``design:`` mapping of a cell file; errors name the key."""
    raw = dict(raw or {})
    defaults = DesignSettings()
    known = set(defaults.__dataclass_fields__)
    for key in raw:
        if key not in known:
            raise ConfigError(f'design.{key}', f'unknown key; allowed: {sorted(known)}')
    values: dict[str, Any] = {}
    for key, value in raw.items():
        default = getattr(defaults, key)
        path = f'design.{key}'
        if key == 'weights':
            if not isinstance(value, Mapping) or not all(
                    isinstance(v, (int, float)) and v >= 0 for v in value.values()):
                raise ConfigError(path, 'must map working pose names to weights >= 0')
            values[key] = {str(k): float(v) for k, v in value.items()}
        elif isinstance(default, bool):
            if not isinstance(value, bool):
                raise ConfigError(path, f'must be true or false, got {value!r}')
            values[key] = value
        elif isinstance(default, int):
            if not isinstance(value, int) or isinstance(value, bool) or value < 1:
                raise ConfigError(path, f'must be a positive integer, got {value!r}')
            values[key] = value
        else:
            if not isinstance(value, (int, float)) or isinstance(value, bool) or value < 0:
                raise ConfigError(path, f'must be a number >= 0, got {value!r}')
            values[key] = float(value)
    if values.get('flag_threshold', 0.5) > 1:
        raise ConfigError('design.flag_threshold', 'must be a fraction in [0, 1]')
    return replace(defaults, **values)


# ------------------------------------------------------------------------ problem
@dataclass(frozen=True)
class DesignProblem:
    """Linearised design problem at the nominal parameters.

    Attributes
    ----------
    parameter_names : tuple of str
        Identifiable parameters designed for (k).
    index : (k,) ndarray
        Their positions in ``model.params``.
    p : (n_p,) ndarray
        Parameters the Jacobians are evaluated at (nominal).
    weight : (3,) ndarray
        1/σ per tracker axis (1/m).
    column_scale : (k,) ndarray
        D: columns of W J D have unit rms over the rich pose set (numerics only).
    physical_scale : (k,) ndarray
        S: rms of ‖∂h/∂p_j‖ over the rich pose set (m per unit of p_j; 1 for a
        translation, the lever arm for an angle).
    kpi_jacobian : (t, 3, k) ndarray
        d s_t / d p of the KPI points (tracker frame).
    kpi_weights : (t,) ndarray
        ω_t, summing to 1.
    """

    parameter_names: tuple[str, ...]
    index: np.ndarray
    p: np.ndarray
    weight: np.ndarray
    column_scale: np.ndarray
    physical_scale: np.ndarray
    kpi_jacobian: np.ndarray
    kpi_weights: np.ndarray

    @property
    def k(self) -> int:
        return len(self.index)

    def rows(self, model, q: np.ndarray) -> np.ndarray:
        """Scaled weighted Jacobian rows W J D (N, 3, k) of configurations ``q`` (N, n)."""
        _, jac = model.jacobian(self.p, np.atleast_2d(q))
        return jac[:, :, self.index] * self.weight[None, :, None] * self.column_scale

    def factor(self, criterion: str) -> np.ndarray:
        """L with ``loss = tr(L M̃⁻¹ Lᵀ)`` for M̃ = information of :meth:`rows`."""
        if criterion == 'kpi':
            w = np.sqrt(self.kpi_weights / 3.0)[:, None, None]
            return (w * self.kpi_jacobian * self.column_scale).reshape(-1, self.k)
        if criterion == 'A':
            return np.diag(self.column_scale * self.physical_scale) / np.sqrt(self.k)
        raise ValueError(f'criterion {criterion!r} has no trace form')

    def loss(self, criterion: str):
        """Loss object of :mod:`design_exchange` for ``criterion``."""
        if criterion in ('kpi', 'A'):
            return TraceLoss(self.factor(criterion))
        if criterion in ('D', 'O1'):
            return LogDetLoss()
        if criterion == 'cond':
            return ConditionLoss(1.0 / (self.column_scale * self.physical_scale))
        raise ValueError(f'criterion must be one of {CRITERIA}, got {criterion!r}')

    def parameter_covariance(self, rows: np.ndarray) -> np.ndarray:
        """C_p (k, k) of the identifiable parameters, in their own units."""
        d = self.column_scale
        return d[:, None] * np.linalg.inv(information(rows)) * d[None, :]

    def tcp_covariance(self, rows: np.ndarray) -> np.ndarray:
        """C_s,t (t, 3, 3) of the KPI points, m²."""
        c_p = self.parameter_covariance(rows)
        return self.kpi_jacobian @ c_p @ self.kpi_jacobian.transpose(0, 2, 1)

    def criteria(self, rows: np.ndarray) -> dict[str, float]:
        """Every criterion of the design with these rows (see module docstring)."""
        info = information(rows)
        sign, logdet = np.linalg.slogdet(info)
        if sign <= 0:
            return {c: float('inf') if c != 'O1' else 0.0 for c in CRITERIA}
        ds = self.column_scale * self.physical_scale
        log_scale = 2.0 * float(np.sum(np.log(ds)))
        tcp = self.tcp_covariance(rows)
        return {
            'kpi': float(self.kpi_weights @ np.trace(tcp, axis1=1, axis2=2) / 3.0),
            'A': TraceLoss(self.factor('A')).value(info),
            'D': float(np.exp((log_scale - logdet) / self.k)),
            'O1': float(np.exp(0.5 * (logdet - log_scale) / self.k)
                         / np.sqrt(rows.shape[0] * rows.shape[1])),
            'cond': self.loss('cond').value(info),
        }


def build_problem(cell_model, q_rich: np.ndarray,
                  weights: Mapping[str, float] | None = None) -> DesignProblem:
    """Identifiable parameters, scalings and KPI Jacobians for a cell.

    Parameters
    ----------
    cell_model : CellModel
    q_rich : (R, n) ndarray
        Many measurable configurations (a few hundred) for the rank analysis.
    weights : mapping of working pose name to weight, optional
    """
    model, cell = cell_model.model, cell_model.cell
    p = model.params.nominal.copy()
    w = 1.0 / cell.sigma
    _, jac = model.jacobian(p, q_rich)
    stacked = (jac * w[None, :, None]).reshape(-1, len(p))
    # A column at round-off level (a rotation about an axis the reflector sits on)
    # has no effect; normalised it would pass the QR as noise with a huge variance.
    norms = np.linalg.norm(stacked, axis=0)
    stacked[:, norms < NEGLIGIBLE_EFFECT * norms.max()] = 0.0
    ident = select_identifiable(stacked, list(model.params.names),
                                method=cell.identification_method,
                                priority=list(cell.identification_priority) or None)
    idx = model.params.indices(ident.kept)
    rms = np.sqrt(np.mean(np.sum((jac[:, :, idx] * w[None, :, None]) ** 2, axis=1), axis=0))
    effect = np.sqrt(np.mean(np.sum(jac[:, :, idx] ** 2, axis=1), axis=0))
    names = cell_model.working_pose_names
    weights = dict(weights or {})
    unknown = set(weights) - set(names)
    if unknown:
        raise ConfigError('design.weights', f'unknown working poses {sorted(unknown)}; '
                          f'poses are {list(names)}')
    omega = np.array([weights.get(n, 1.0) for n in names], float)
    if omega.sum() <= 0:
        raise ConfigError('design.weights', 'at least one working pose needs a weight > 0')
    _, kpi_jac = model.jacobian(p, cell_model.q_work)
    return DesignProblem(tuple(ident.kept), idx, p, w, 1.0 / rms, effect,
                         kpi_jac[:, :, idx], omega / omega.sum())


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


def design_context(cell_model, rng: np.random.Generator,
                   settings: DesignSettings | None = None) -> DesignContext:
    """Collision scene, feasible candidates and the linearised problem of a cell.

    Raises
    ------
    ConfigError
        Capsule pairs are violated in nearly every measurable pose and
        ``ignore_flagged`` is off (the message names them and the fix).
    """
    start = time.perf_counter()
    settings = settings or design_settings(cell_model.cell.raw.get('design'))
    full = cell_model.collision_scene()
    flagged = flag_pairs(cell_model, full, rng, threshold=settings.flag_threshold)
    if flagged and not settings.ignore_flagged:
        text = ', '.join(f'{k} ({100 * v:.0f} %)' for k, v in flagged.items())
        raise ConfigError('collision.ignore_pairs', f'pairs in collision in nearly every '
                          f'measurable pose: {text}; if the capsules only overlap by '
                          'construction, add the pairs to collision.ignore_pairs (or set '
                          'design.ignore_flagged: true)')
    check = scene_without(full, tuple(flagged)) if flagged else full
    scene = check if settings.collision else None
    cand = generate_candidates(cell_model, scene, settings.candidates, rng,
                               clearance=settings.clearance if scene is not None else 0.0,
                               incidence_clearance=settings.incidence_clearance,
                               flag_threshold=settings.flag_threshold)
    problem = build_problem(cell_model, cand.configurations[:min(len(cand.configurations), 600)],
                            settings.weights)
    rows = problem.rows(cell_model.model, cand.configurations)
    return DesignContext(scene, check, cand, problem, rows, flagged,
                         time.perf_counter() - start)


def design_measurements(cell_model, n: int, criterion: str, rng: np.random.Generator,
                        settings: DesignSettings | None = None,
                        context: DesignContext | None = None,
                        progress: Callable[[str], None] | None = None) -> DesignResult:
    """N measurement configurations optimal for ``criterion`` under every constraint.

    Parameters
    ----------
    cell_model : CellModel
        From :func:`kpi_calib_ros.io.cell.build_cell_model`.
    n : int
        Number of configurations N.
    criterion : {'kpi', 'A', 'D', 'O1', 'cond', 'random'}
        ``'random'`` is the heuristic baseline: N uniform draws that satisfy
        every constraint.
    rng : numpy.random.Generator
    settings : DesignSettings, optional
        Default: the cell's ``design:`` section.
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
    settings = settings or design_settings(cell_model.cell.raw.get('design'))
    say = progress or (lambda _msg: None)
    total = time.perf_counter()
    ctx = context or design_context(cell_model, rng, settings)
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
        exchange_value = problem.criteria(problem.rows(cell_model.model, q))['kpi']
    else:
        loss = problem.loss(criterion)
        best = None
        for _ in range(settings.exchange_starts):
            res = exchange(rows, n, loss, rng, progress=say)
            if best is None or res.loss < best.loss:
                best = res
        q = cand_q[best.selected]
        exchange_value = problem.criteria(rows[best.selected])[criterion]
        status.append(f'exchange: {best.exchanges} exchanges')
    timings['exchange'] = time.perf_counter() - t
    t = time.perf_counter()
    if settings.nlp and criterion in ('kpi', 'A', 'D', 'O1'):
        nlp = solve_design_nlp(problem, cell_model, ctx.scene, q, criterion,
                               clearance=settings.clearance,
                               incidence_clearance=settings.incidence_clearance,
                               max_iterations=settings.max_iterations, progress=progress)
        status.append(f'ipopt: {nlp.status} after {nlp.iterations} iterations, loss '
                      f'{nlp.loss_start:.4g} -> {nlp.loss:.4g}')
        if nlp.loss < nlp.loss_start:
            trial = verify_design(cell_model, ctx.scene, nlp.configurations)
            if trial.ok:
                q = nlp.configurations
            else:
                status.append(f'the NLP result failed the independent check '
                              f'({len(trial.violations)} violations, first: '
                              f'{trial.violations[0]}); returned the exchange design')
        else:
            status.append('the NLP did not improve on the exchange design; returned that')
    timings['nlp'] = time.perf_counter() - t
    t = time.perf_counter()
    verification = verify_design(cell_model, ctx.check_scene, q)
    timings['verify'] = time.perf_counter() - t
    if not verification.ok:
        where = 'without collision constraints: ' if ctx.scene is None else ''
        status.append(f'{where}{len(verification.violations)} constraint violations '
                      f'(see verification)')
    final_rows = problem.rows(cell_model.model, q)
    values = problem.criteria(final_rows)
    tcp = problem.tcp_covariance(final_rows)
    timings['total'] = time.perf_counter() - total + timings['candidates']
    return DesignResult(
        configurations=q, joint_names=tuple(cell_model.robot.joint_names),
        criterion=criterion, objective=values['kpi' if criterion == 'random' else criterion],
        criteria=values, tcp_covariance=tcp,
        tcp_std=np.sqrt(np.diagonal(tcp, axis1=1, axis2=2)),
        working_pose_names=tuple(cell_model.working_pose_names),
        parameter_names=problem.parameter_names, min_margin=verification.min_margin,
        incidence_deg=verification.incidence_deg,
        constraint_count=verification.constraint_count, verification=verification,
        flagged_pairs=dict(ctx.flagged), status='; '.join(status) or 'ok', timings=timings,
        candidates=len(cand_q), exchange_objective=float(exchange_value))
