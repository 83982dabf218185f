"""Continuous design NLP (eq. 24) in CasADi, solved by IPOPT with exact derivatives.

Variables are all N configurations. The information matrix is a sum over a
mapped per-configuration function, so its derivatives are exact; the
constraints (incidence cosine and capsule margins, :func:`feasibility_function`)
are mapped the same way, which keeps their Jacobian block-diagonal. Joint limits
are variable bounds. The Lagrangian Hessian is approximated by L-BFGS: the exact
one of tr(L M⁻¹ Lᵀ) is dense in all 6N variables and costs more than it saves.
The objective is scaled by its value at the start so IPOPT sees O(1) numbers.
"""
from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Any, Callable, Sequence

import casadi as ca
import numpy as np

from kpi_calib_ros.core.collision.capsules import CollisionScene
from kpi_calib_ros.core.design.cell import DesignCell
from kpi_calib_ros.core.design.constraints import feasibility_function
from kpi_calib_ros.core.design.criteria import DesignProblem

__all__ = ['NlpResult', 'solve_design_nlp']


@dataclass(frozen=True)
class NlpResult:
    """IPOPT outcome: configurations (N, n), losses at start and end, status."""

    configurations: np.ndarray
    loss_start: float
    loss: float
    success: bool
    status: str
    iterations: int
    seconds: float


class _Monitor(ca.Callback):
    """IPOPT iteration callback: reports progress and stops a stalled solve.

    L-BFGS crawls near the optimum; once the feasible objective has not improved
    by ``stall_tol`` (relative) for ``stall_iterations`` iterations the solve is
    stopped (IPOPT status User_Requested_Stop) and the current iterate kept.
    """

    def __init__(self, nx: int, lbg: np.ndarray, report: Callable[[str], None] | None,
                 every: int, scale: float, stall_iterations: int = 40,
                 stall_tol: float = 1e-4) -> None:
        ca.Callback.__init__(self)
        self.nx, self.ng, self.lbg = nx, len(lbg), lbg
        self.report, self.every, self.scale = report, every, scale
        self.stall_iterations, self.stall_tol = stall_iterations, stall_tol
        self.iteration, self.best, self.significant, self.stalled = 0, np.inf, np.inf, 0
        self.best_x: np.ndarray | None = None
        self.construct('design_monitor', {})

    def get_n_in(self) -> int:
        return ca.nlpsol_n_out()

    def get_n_out(self) -> int:
        return 1

    def get_name_in(self, i: int) -> str:
        return ca.nlpsol_out(i)

    def get_name_out(self, i: int) -> str:
        return 'ret'

    def get_sparsity_in(self, i: int) -> ca.Sparsity:
        name = ca.nlpsol_out(i)
        if name == 'f':
            return ca.Sparsity.scalar()
        if name in ('x', 'lam_x'):
            return ca.Sparsity.dense(self.nx)
        if name in ('g', 'lam_g'):
            return ca.Sparsity.dense(self.ng)
        return ca.Sparsity(0, 0)

    def eval(self, arg: Sequence[ca.DM]) -> list[int]:
        self.iteration += 1
        f = float(arg[ca.nlpsol_out().index('f')])
        g = np.array(arg[ca.nlpsol_out().index('g')]).ravel()
        worst = max(float(np.max(self.lbg - g)) if g.size else 0.0, 0.0)
        if worst <= 1e-6:
            if f < self.best:
                self.best = f
                self.best_x = np.array(arg[ca.nlpsol_out().index('x')]).ravel()
            # Only feasible iterates count; the clock restarts on a real gain.
            if f < self.significant - self.stall_tol * max(abs(self.significant), 1.0):
                self.significant, self.stalled = f, 0
            else:
                self.stalled += 1
        if self.report is not None and self.iteration % self.every == 0:
            self.report(f'ipopt: iteration {self.iteration}, objective {f * self.scale:.4g}, '
                        f'worst constraint violation {worst:.2e}')
        return [1 if self.stalled > self.stall_iterations else 0]


def solve_design_nlp(problem: DesignProblem, cell: DesignCell, scene: CollisionScene | None,
                     q0: np.ndarray, criterion: str,
                     clearance: float = 0.002, incidence_clearance: float = 0.002,
                     max_iterations: int = 300,
                     progress: Callable[[str], None] | None = None,
                     every: int = 25) -> NlpResult:
    """Refine a design by IPOPT over all configurations.

    Parameters
    ----------
    problem : DesignProblem
    cell : DesignCell
    scene : CollisionScene or None
        Capsule pairs to keep apart by ``clearance`` (m); None: limits and incidence only.
    q0 : (N, n) ndarray
        Start (the exchange result); should be feasible.
    criterion : {'kpi', 'A', 'D', 'O1'}
    """
    start = time.perf_counter()
    model = cell.model
    n_conf, n = q0.shape
    q = ca.SX.sym('q', n)
    p_sym = ca.SX.sym('p', len(problem.p))
    # Every row a measured pose gives (reflector points, tracked bodies' rotations).
    point = model.pose_point_expression(p_sym, q, p_measured=ca.DM(problem.p))
    jac = ca.jacobian(point, p_sym)[:, list(problem.index)]
    rows_fun = ca.Function('rows', [p_sym, q], [jac])
    weight = np.tile(problem.weight, model.rows_per_pose)
    rows = ca.diag(ca.DM(weight)) @ rows_fun(ca.DM(problem.p), q) @ ca.diag(
        ca.DM(problem.column_scale))
    info_fun = ca.Function('info', [q], [ca.mtimes(rows.T, rows)])
    # The variables are the actuated joints: mimic joints follow them (q = M x_a + d).
    robot = model.robot
    n_act = len(robot.actuated_names)
    x_act = ca.MX.sym('x', n_act, n_conf)
    x = x_act if not robot.has_mimic else (
        ca.DM(robot.mimic_matrix) @ x_act + ca.repmat(ca.DM(robot.mimic_offset), 1, n_conf))
    a0 = robot.actuated_values(q0)
    info = info_fun.map('info_sum', 'serial', n_conf, [], [0])(x)
    if problem.prior_information is not None:
        info = info + ca.DM(problem.prior_information)
    if criterion in ('kpi', 'A'):
        factor = ca.DM(problem.factor(criterion))
        loss = ca.sum1(ca.sum2(factor.T * ca.solve(info, factor.T)))
    elif criterion in ('D', 'O1'):
        loss = -ca.log(ca.det(info))
    else:
        raise ValueError(f"the NLP handles 'kpi', 'A', 'D' and 'O1', not {criterion!r}")
    loss_fun = ca.Function('loss', [x_act], [loss])
    loss_start = float(loss_fun(a0.T))
    if criterion in ('kpi', 'A'):
        scale, objective = loss_start, loss / loss_start
    else:
        scale, objective = 1.0, loss - loss_start
    cos_max = float(np.cos(cell.max_incidence - incidence_clearance))
    feas = feasibility_function(cell, scene)
    per = feas.size1_out(0)
    g = feas.map('feasibility_all', 'serial', n_conf, [], [])(x)
    g = ca.reshape(g, per * n_conf, 1)
    lbg = np.tile(np.r_[cos_max, np.full(per - 1, clearance)], n_conf)
    lower, upper = robot.sampling_bounds()
    opts: dict[str, Any]  # values of several types, and the iteration callback below
    opts = {'ipopt.print_level': 0, 'print_time': False, 'ipopt.sb': 'yes',
            'ipopt.max_iter': int(max_iterations),
            'ipopt.hessian_approximation': 'limited-memory',
            # L-BFGS crawls near the optimum: stop once the objective has settled.
            'ipopt.tol': 1e-6, 'ipopt.acceptable_tol': 1e3, 'ipopt.acceptable_iter': 10,
            'ipopt.acceptable_obj_change_tol': 1e-5,
            # The clearances are the safety margin: a micrometre of violation is harmless.
            'ipopt.constr_viol_tol': 1e-6, 'ipopt.acceptable_constr_viol_tol': 1e-6,
            'ipopt.mu_strategy': 'adaptive'}
    # Kept referenced until the solve ends: IPOPT calls back into it.
    monitor = _Monitor(n_act * n_conf, lbg, progress, every, scale)
    opts['iteration_callback'] = monitor
    solver = ca.nlpsol('design', 'ipopt', {'x': ca.vec(x_act), 'f': objective, 'g': g}, opts)
    sol = solver(x0=a0.ravel(),  # vec of the (m, N) matrix = rows of a0 in turn
                 lbx=np.tile(lower, n_conf), ubx=np.tile(upper, n_conf),
                 lbg=lbg, ubg=np.inf)
    stats = solver.stats()
    final: np.ndarray | None = np.array(sol['x']).ravel()
    if np.max(lbg - np.array(sol['g']).ravel()) > 1e-6:
        final = monitor.best_x  # IPOPT stopped infeasible: keep the best feasible iterate
    elif monitor.best_x is not None and monitor.best < float(sol['f']):
        final = monitor.best_x
    if final is None:
        return NlpResult(q0, loss_start, loss_start, False, 'no feasible iterate: '
                         + str(stats['return_status']), int(stats['iter_count']),
                         time.perf_counter() - start)
    a_opt = np.clip(final.reshape(n_conf, n_act), lower, upper)
    q_opt = robot.chain_values(a_opt)
    return NlpResult(q_opt, loss_start, float(loss_fun(a_opt.T)), bool(stats['success']),
                     str(stats['return_status']), int(stats['iter_count']),
                     time.perf_counter() - start)
