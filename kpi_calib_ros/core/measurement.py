"""Measurement model of a laser tracker, eq. (3), and its incidence angle, eq. (4).

``h(p, q) = T_tracker_base(p) · TCP(p, q) · r(p)``: the reflector centre in the
tracker frame. Physical effects (joint compliance, cyclic gear errors, …) plug
in as corrections of the joint values or of the measured point; their
parameters are appended to the geometric ones so every derivative stays exact.

Several reflectors (or motion-capture markers) on one tool are one model: each
measurement row is a (pose, reflector) pair, ``Measurements.reflector`` holds the
reflector index of every row, and every numeric method takes that index array
(``None``: reflector 0 throughout).

The KPI point of a working pose is ``h(p, q_work)`` of reflector 0 (the first
reflector of the cell): the reflector/TCP centre at
the working configuration expressed in the tracker frame. Unlike a TCP "in the
base frame", this point is observable and does not depend on which redundant
parameters the identifiability analysis keeps (a gauge-free quantity).
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Protocol, Sequence

import casadi as ca
import numpy as np

from kpi_calib_ros.core.kinematics import SymbolicChain, reflector_point
from kpi_calib_ros.core.parameters import ParameterSet
from kpi_calib_ros.core.robot import RobotModel


class Effect(Protocol):
    """A physical effect that the geometric model lacks.

    Implementations give parameter names/units/nominal values and CasADi
    expressions; see :mod:`kpi_calib_ros.core.effects` for the library.
    """

    # Read-only: implementations may be frozen dataclasses.
    @property
    def name(self) -> str: ...

    @property
    def parameter_names(self) -> tuple[str, ...]: ...

    @property
    def units(self) -> tuple[str, ...]: ...

    @property
    def uses_torque(self) -> bool: ...

    def joint_correction(self, q, tau, theta):
        """Additive joint-value correction (n,) or None."""

    def point_correction(self, point, theta):
        """Measured point (3,) in the tracker frame after the effect, or None."""


@dataclass(frozen=True)
class Measurements:
    """Paired measurement data.

    q : (N, n) joint values in chain order; eta : (N, 3) measured points in the
    tracker frame (m); tau : (N, n) gravity torques or None; stamps_ns : (N,);
    reflector : (N,) int index of the reflector each row measured, or None (all 0).
    One pose measured by R reflectors is R rows with the same ``q``.
    """

    q: np.ndarray
    eta: np.ndarray
    tau: np.ndarray | None = None
    stamps_ns: np.ndarray | None = field(default=None)
    reflector: np.ndarray | None = field(default=None)

    def __len__(self) -> int:
        return len(self.q)

    def subset(self, keep: np.ndarray) -> Measurements:
        """The rows selected by the boolean or index array ``keep``, every field kept."""
        def pick(values: np.ndarray | None) -> np.ndarray | None:
            return None if values is None else np.asarray(values)[keep]
        return Measurements(q=np.atleast_2d(self.q)[keep], eta=np.atleast_2d(self.eta)[keep],
                            tau=pick(self.tau), stamps_ns=pick(self.stamps_ns),
                            reflector=pick(self.reflector))


class MeasurementModel:
    """Eq. (3) for one robot in one cell, with exact Jacobians.

    Parameters
    ----------
    robot : RobotModel
    geometric : ParameterSet
        From :func:`geometric_parameters`.
    effects : sequence of Effect
        Extra physical effects; their parameters are appended to ``params``.
    reflector_axis : (3,) array
        Reflector central axis in the tip frame, for the incidence angle.
    """

    def __init__(self, robot: RobotModel, geometric: ParameterSet,
                 effects: Sequence[Effect] = (),
                 reflector_axis: np.ndarray | Sequence[float] = (0.0, 0.0, 1.0)) -> None:
        self.robot = robot
        self.geometric = geometric
        self.effects = tuple(effects)
        params = geometric
        for effect in self.effects:
            params = params.extended(list(effect.parameter_names),
                                     np.zeros(len(effect.parameter_names)), list(effect.units))
        self.params = params
        self.reflector_axis = np.asarray(reflector_axis, float)
        self.chain = SymbolicChain(robot, params)
        self.uses_torque = any(e.uses_torque for e in self.effects)
        n = robot.n_joints
        p = ca.SX.sym('p', len(params))
        q = ca.SX.sym('q', n)
        tau = ca.SX.sym('tau', n)
        self._h, self._hj, self._hq = [], [], []
        for k in range(self.chain.n_reflectors):
            point = self.point_expression(p, q, tau, k)
            self._h.append(ca.Function('h', [p, q, tau], [point]))
            self._hj.append(ca.Function('hj', [p, q, tau], [point, ca.jacobian(point, p)]))
            self._hq.append(ca.Function('hq', [p, q, tau], [ca.jacobian(point, q)]))
        self._cos = ca.Function('cos_incidence', [p, q], [self.incidence_cos_expression(p, q)])

    @property
    def n_reflectors(self) -> int:
        """Reflectors (or markers) on the tool; index 0 is the KPI reflector."""
        return self.chain.n_reflectors

    # ------------------------------------------------------------ symbolic API
    def point_expression(self, p, q, tau=None, reflector: int = 0):
        """Centre of reflector ``reflector`` in the tracker frame, CasADi expression (3,)."""
        q_eff = q
        offset = len(self.geometric)
        thetas = []
        for effect in self.effects:
            theta = p[offset:offset + len(effect.parameter_names)]
            offset += len(effect.parameter_names)
            thetas.append(theta)
            correction = effect.joint_correction(q, tau, theta)
            if correction is not None:
                q_eff = q_eff + correction
        tip = self.chain.tip_transform(p, q_eff)
        world = self.chain.base_in_tracker(p) @ tip
        point = reflector_point(world, self.chain.reflector(p, reflector))
        for effect, theta in zip(self.effects, thetas):
            corrected = effect.point_correction(point, theta)
            if corrected is not None:
                point = corrected
        return point

    def incidence_cos_expression(self, p, q):
        """cos β between the reflector axis and the beam towards the tracker, eq. (4)."""
        world = self.chain.base_in_tracker(p) @ self.chain.tip_transform(p, q)
        point = reflector_point(world, self.chain.reflector(p))
        axis = world[0:3, 0:3] @ ca.DM(self.reflector_axis)
        beam = -point / ca.norm_2(point)  # the tracker sits at the tracker-frame origin
        return ca.dot(axis, beam) / ca.norm_2(axis)

    # ------------------------------------------------------------- numerics
    def _torques(self, q: np.ndarray, tau: np.ndarray | None) -> np.ndarray:
        if tau is not None:
            return np.atleast_2d(tau)
        if self.uses_torque:
            return np.atleast_2d(self.robot.gravity_torques(q))
        return np.zeros_like(np.atleast_2d(q))

    def _groups(self, n: int, reflector: np.ndarray | None) -> list[tuple[int, np.ndarray]]:
        """(reflector index, rows) pairs covering rows 0..n-1."""
        if reflector is None:
            return [(0, np.arange(n))]
        ref = np.asarray(reflector, dtype=int).reshape(-1)
        if len(ref) != n:
            raise ValueError(f'reflector must hold one index per row ({n}), got {len(ref)}')
        if n and (ref.min() < 0 or ref.max() >= self.n_reflectors):
            raise ValueError(f'reflector indices must be in [0, {self.n_reflectors}), got '
                             f'{sorted(set(ref.tolist()))}')
        return [(int(k), np.flatnonzero(ref == k)) for k in np.unique(ref)]

    def predict(self, p: np.ndarray, q: np.ndarray, tau: np.ndarray | None = None,
                reflector: np.ndarray | None = None) -> np.ndarray:
        """Predicted points (N, 3) in the tracker frame for joint values ``q`` (N, n)
        and reflector indices ``reflector`` (N,) (None: reflector 0)."""
        q = np.atleast_2d(q)
        tau = self._torques(q, tau)
        out = np.zeros((len(q), 3))
        for k, rows in self._groups(len(q), reflector):
            if len(rows):
                out[rows] = np.array(self._h[k].map(len(rows))(p, q[rows].T, tau[rows].T)).T
        return out

    def jacobian(self, p: np.ndarray, q: np.ndarray, tau: np.ndarray | None = None,
                 reflector: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Predicted points (N, 3) and their Jacobian (N, 3, n_p) w.r.t. p."""
        q = np.atleast_2d(q)
        tau = self._torques(q, tau)
        n_p = len(self.params)
        pts, jac = np.zeros((len(q), 3)), np.zeros((len(q), 3, n_p))
        for k, rows in self._groups(len(q), reflector):
            if len(rows):
                h, j = self._hj[k].map(len(rows))(p, q[rows].T, tau[rows].T)
                pts[rows] = np.array(h).T
                jac[rows] = np.array(j).reshape(3, len(rows), n_p).transpose(1, 0, 2)
        return pts, jac

    def joint_jacobian(self, p: np.ndarray, q: np.ndarray, tau: np.ndarray | None = None,
                       reflector: np.ndarray | None = None) -> np.ndarray:
        """Jacobian (N, 3, n) of the predicted points w.r.t. the joint values."""
        q = np.atleast_2d(q)
        tau = self._torques(q, tau)
        out = np.zeros((len(q), 3, q.shape[1]))
        for k, rows in self._groups(len(q), reflector):
            if len(rows):
                jac = self._hq[k].map(len(rows))(p, q[rows].T, tau[rows].T)
                out[rows] = np.array(jac).reshape(3, len(rows), q.shape[1]).transpose(1, 0, 2)
        return out

    def pose_jacobian(self, p: np.ndarray, q: np.ndarray,
                      tau: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Every reflector at every configuration, as the design sees a pose: points
        (N, 3R) and Jacobian (N, 3R, n_p), reflector k in rows 3k..3k+2."""
        q = np.atleast_2d(q)
        parts = [self.jacobian(p, q, tau, np.full(len(q), k)) for k in range(self.n_reflectors)]
        return (np.concatenate([pt for pt, _ in parts], axis=1),
                np.concatenate([j for _, j in parts], axis=1))

    def pose_point_expression(self, p, q, tau=None):
        """Every reflector's centre stacked, CasADi expression (3R,)."""
        return ca.vertcat(*[self.point_expression(p, q, tau, k)
                            for k in range(self.n_reflectors)])

    def incidence_cos(self, p: np.ndarray, q: np.ndarray) -> np.ndarray:
        """cos of the incidence angle (N,) at joint values ``q`` (N, n)."""
        q = np.atleast_2d(q)
        return np.array(self._cos.map(len(q))(p, q.T)).ravel()


def weighted_rows(jac: np.ndarray, w: np.ndarray, idx: np.ndarray | None = None) -> np.ndarray:
    """Stacked weighted Jacobian ``W J`` (3N, k) of point Jacobians ``jac`` (N, 3, n_p).

    Parameters
    ----------
    jac : (N, 3, n_p) ndarray
        d h_i / d p per measurement (m per unit of each parameter).
    w : (3,), (3R,) or (N, 3) ndarray
        1/σ per tracker axis (1/m); (3R,) for rows of ``MeasurementModel.pose_jacobian``;
        (N, 3) per measurement and axis (robustness weights).
    idx : (k,) int ndarray, optional
        Parameter columns to keep (default all).

    Returns
    -------
    (3N, k) ndarray
        Row 3i + a is axis a of measurement i, in units of σ.
    """
    w = np.asarray(w)
    rows = (jac * (w[None, :, None] if w.ndim == 1 else w[:, :, None])).reshape(-1, jac.shape[2])
    return rows if idx is None else rows[:, idx]

