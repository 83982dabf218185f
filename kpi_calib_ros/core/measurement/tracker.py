"""Measurement model of a laser tracker, eq. (3), and its incidence angle, eq. (4).

``h(p, q) = T_tracker_base(p) · TCP(p, q) · r(p)``: the reflector centre in the
tracker frame. Physical effects (joint compliance, cyclic gear errors, …) plug
in as corrections of the joint values or of the measured point; their
parameters are appended to the geometric ones so every derivative stays exact.

Several reflectors (or motion-capture markers) on one tool are one model: each
measurement row is a (pose, reflector) pair, ``Measurements.reflector`` holds the
reflector index of every row, and every numeric method takes that index array
(``None``: reflector 0 throughout).

A tracked 6-DoF pose (a body on the tool whose orientation the tracker also reports)
adds a rotation row per pose (:mod:`kpi_calib_ros.core.measurement.pose`): its
reflector index is ``n_reflectors + k`` for reflector ``k``, its ``eta`` is zero and
``Measurements.rotation`` holds the measured body rotation that its prediction takes.

Joint readings are not exact either: with a joint-reading noise Σ_q = diag(σ_q²) stated
(``joint_sigma``), measurement i has the covariance Σ_i = diag(σ²) + J_q,i Σ_q J_q,iᵀ
(J_q,i = ∂h/∂q at the measurement), no longer diagonal and dependent on p. Its rows are
whitened with W_i = L_i⁻¹, L_i L_iᵀ = Σ_i (:meth:`MeasurementModel.whitening`), evaluated at
the current estimate. Rows of one pose measured by several reflectors share that pose's
joint readings; their correlation is not modelled (each row carries its own J_q Σ_q J_qᵀ).

A tracker states its uncertainty per point: each row's own σ
(:mod:`kpi_calib_ros.core.measurement.data`) is σ in the covariance above and in every weight
(:mod:`kpi_calib_ros.core.measurement.weighting`).

Covariates: a cause the joint state does not carry (temperature of the arm, time into a
shift) reaches an effect as a per-row input. ``Measurements.covariates`` maps a covariate
name to its value (N,) per row (``temperature.<frame_id>`` in °C, ``delta_temperature`` in K,
:mod:`kpi_calib_ros.core.measurement.covariates`); an effect names the covariates it reads in its
``inputs`` and receives them, in that order, as a fourth argument of its corrections
(``joint_correction(q, tau, theta, z)``, ``placement_correction(theta, z)``). The model's
CasADi functions take them as one more input ``z`` (n_z,) after ``(p, q, tau)``
(:attr:`MeasurementModel.inputs` gives the order). Every input is 0 where no covariates are
given (the design, the KPI at the working poses, fresh poses): an input is a deviation from
a reference condition (ΔT from the cell's reference temperature), so 0 is that condition.

The KPI point of a working pose is ``h(p, q_work)`` of reflector 0 (the first
reflector of the cell): the reflector/TCP centre at
the working configuration expressed in the tracker frame. Unlike a TCP "in the
base frame", this point is observable and does not depend on which redundant
parameters the identifiability analysis keeps (a gauge-free quantity).
"""
from __future__ import annotations

import dataclasses
from typing import Any, Mapping, Sequence, cast

import casadi as ca
import numpy as np

from kpi_calib_ros.core.measurement.buffers import Mapped, call_mapped
from kpi_calib_ros.core.measurement.data import Measurements, joint_noise
from kpi_calib_ros.core.measurement.deflection import deflected_torque, torque_input, torque_width
from kpi_calib_ros.core.measurement.effect_protocol import (
    Effect,
    bound_arguments,
    effect_inputs,
    optional_correction,
)
from kpi_calib_ros.core.measurement.payload import cell_payload_inputs, payload_torques
from kpi_calib_ros.core.measurement.pose import (
    body_orientation,
    measured_rotation_input,
    rotation_residual_expression,
)
from kpi_calib_ros.core.model.kinematics import Expr, SymbolicChain, pose6, reflector_point
from kpi_calib_ros.core.model.parameters import (
    BASE_COMPONENTS,
    RECORDING_PREFIX,
    ParameterSet,
    recording_names,
    reflector_prefixes,
)
from kpi_calib_ros.core.model.robot import RobotModel

__all__ = ['MeasurementModel']


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
    orientations : mapping {reflector index: (3, 3) rotation}, optional
        Orientation in the tip frame of the tracked body whose origin is that
        reflector; each gets a rotation row (channel ``n_reflectors + index``).
    rotation_scale : (3,) array, optional
        σ / σ_rot per axis (m/rad): rotation rows are in metres at the stated σ.
    joint_sigma : (n,) or (n, k) array, optional
        Standard deviation of each joint reading (rad, m for prismatic joints) in chain
        order, independent; or the map S (n, k) of k independent unit noises onto the chain
        readings (``q + S ε``: a drive's reading noise that its mimic joints follow);
        None (default): exact joint readings, every row weighted by 1/σ alone.
    joint_temperatures : mapping {joint name: covariate name}, optional
        The temperature each joint's thermal effects read, where it is not the arm's mean
        ``delta_temperature`` (the cell's ``temperature.sensors`` mapping, e.g.
        ``{'joint_3': 'delta_temperature.upper_arm'}``). The model keeps it so that effects
        bound later for it (the diagnosis's candidates, an effect added by name) read the same
        sensors as its own; its effects are bound with it already
        (:func:`kpi_calib_ros.core.effects.registry.bind_effect`).
    """

    def __init__(self, robot: RobotModel, geometric: ParameterSet,
                 effects: Sequence[Effect] = (),
                 reflector_axis: np.ndarray | Sequence[float] = (0.0, 0.0, 1.0),
                 orientations: Mapping[int, np.ndarray] | None = None,
                 rotation_scale: np.ndarray | Sequence[float] | None = None,
                 joint_sigma: np.ndarray | Sequence[float] | None = None,
                 joint_temperatures: Mapping[str, str] | None = None) -> None:
        self.robot = robot
        self.joint_temperatures: dict[str, str] = dict(joint_temperatures or {})
        unknown = sorted(set(self.joint_temperatures) - set(robot.joint_names))
        if unknown:
            raise ValueError(f'joint_temperatures name joints {unknown} not on the chain '
                             f'{robot.joint_names}')
        # The joint-reading noise map S (chain readings q + S ε) and each reading's std.
        self.joint_noise_map, self.joint_sigma = joint_noise(joint_sigma, robot.n_joints)
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
        # Recordings after the first with their own placement (core.measurement.recordings):
        # each row selects its recording's by the one-hot covariate recording.<name>.
        self.recordings: tuple[str, ...] = tuple(recording_names(params))
        # Covariates the effects read, then the recordings', in the order of the functions'
        # input z.
        self.inputs: tuple[str, ...] = tuple(dict.fromkeys(
            [name for e in self.effects for name in effect_inputs(e)]
            + [f'{RECORDING_PREFIX}{r}' for r in self.recordings]))
        n = robot.n_joints
        p = ca.SX.sym('p', len(params))
        q = ca.SX.sym('q', n)
        tau = ca.SX.sym('tau', torque_width(n, self.uses_torque))
        z = ca.SX.sym('z', len(self.inputs))
        # One tool pose for every reflector; ∂h/∂q and the incidence cosine are built on
        # first use (a model made for one Jacobian, as the diagnosis screen makes one per
        # candidate effect, never needs them).
        world, thetas = self._tool_pose(p, q, tau, z)
        self._points = [self._reflector_point(world, thetas, p, k, z)
                        for k in range(self.chain.n_reflectors)]
        self._symbols = (p, q, tau, z)
        self._h = [ca.Function('h', [p, q, tau, z], [point]) for point in self._points]
        self._hj = [ca.Function('hj', [p, q, tau, z], [point, ca.jacobian(point, p)])
                    for point in self._points]
        self._hq_built: list[ca.Function] | None = None
        self._cos_built: ca.Function | None = None
        self._mapped: dict[tuple[int, int, int], Mapped] = {}
        self.orientations = {int(k): np.asarray(r, float).reshape(3, 3)
                             for k, r in (orientations or {}).items()}
        if any(not 0 <= k < self.chain.n_reflectors for k in self.orientations):
            raise ValueError(f'orientations name reflectors {sorted(self.orientations)}; the '
                             f'model has {self.chain.n_reflectors}')
        if self.orientations and rotation_scale is None:
            raise ValueError('orientations need rotation_scale (σ / σ_rot per axis, m/rad)')
        self.rotation_scale = (None if rotation_scale is None
                               else np.broadcast_to(np.asarray(rotation_scale, float), 3).copy())
        measured = ca.SX.sym('rotation', 9)
        self._rot: dict[int, tuple[ca.Function, ca.Function, ca.Function, ca.Function]] = {}
        for k in self.orientations:
            body = self.body_rotation_expression(p, q, tau, k, z)
            row = rotation_residual_expression(measured, body, self.rotation_scale)
            self._rot[k] = (ca.Function('hr', [p, q, tau, measured, z], [row]),
                            ca.Function('hrj', [p, q, tau, measured, z],
                                        [row, ca.jacobian(row, p)]),
                            ca.Function('hrq', [p, q, tau, measured, z], [ca.jacobian(row, q)]),
                            ca.Function('body', [p, q, tau, z], [body]))

    @property
    def n_reflectors(self) -> int:
        """Reflectors (or markers) on the tool; index 0 is the KPI reflector."""
        return self.chain.n_reflectors

    def rotation_channel(self, reflector: int) -> int:
        """Row index (``Measurements.reflector``) of reflector ``reflector``'s rotation row."""
        if reflector not in self.orientations:
            raise ValueError(f'reflector {reflector} has no orientation: it measures no '
                             'rotation (give its orientation in the cell)')
        return self.n_reflectors + reflector

    # ------------------------------------------------------------ symbolic API
    def _tool_pose(self, p: Expr, q: Expr, tau: Expr, z: Expr = None
                   ) -> tuple[Expr, list[Expr]]:
        """Tip pose (4x4) in the tracker frame with the effects applied, and their parameter slices.

        The joint and placement corrections and the frame deflections (link bending) of the
        effects are applied; also returns each effect's parameter slice. ``z`` (len(inputs),)
        the covariates (None: 0, the reference condition).
        """
        q_eff = q
        if z is None:
            z = ca.DM.zeros(len(self.inputs))
        placement = None
        deflections: dict[int, Expr] = {}
        tilts: dict[int, Expr] = {}
        bound = bound_arguments(self.effects, p, len(self.geometric), z, self.inputs)
        thetas = [theta for _, theta, _ in bound]
        tau = deflected_torque(tau, q, [b for b in bound if b[0].uses_torque])
        for effect, theta, extra in bound:
            correction = cast(Any, effect).joint_correction(q, tau, theta, *extra)
            moves = optional_correction(effect, 'placement_correction')
            for joint, delta in (moves(theta, *extra) if moves is not None else ()):
                placement = placement if placement is not None else ca.SX.zeros(p.shape[0])
                idx = self.chain.placement_indices(joint)
                placement[idx] = placement[idx] + delta
            if correction is not None:
                q_eff = q_eff + correction
            frame = optional_correction(effect, 'frame_correction')
            bent = frame(q, tau, theta, *extra) if frame is not None else None
            if bent is not None:
                index, rotation = bent
                deflections[index] = (deflections[index] @ rotation if index in deflections
                                      else rotation)
            tilt = optional_correction(effect, 'tilt_correction')
            turned = tilt(theta, *extra) if tilt is not None else None
            if turned is not None:
                index, rotation = turned
                tilts[index] = tilts[index] @ rotation if index in tilts else rotation
        tip = self.chain.tip_transform(p if placement is None else p + placement, q_eff,
                                       deflections, tilts)
        return self._base_pose(p, z) @ tip, thetas

    def _recording_selects(self, name: str, z: Expr) -> Expr:
        """Whether a row belongs to recording ``name`` (its one-hot covariate in ``z``)."""
        return z[self.inputs.index(f'{RECORDING_PREFIX}{name}')] > 0.5

    def _base_pose(self, p: Expr, z: Expr) -> Expr:
        """Return the base pose (4x4) in the tracker frame of the row's recording.

        The first recording's is ``base.*``; selected exactly (``if_else``), so every
        derivative is that recording's own.
        """
        base = self.chain.base_in_tracker(p)
        for name in self.recordings:
            own = pose6(p[self.params.indices(
                [f'{RECORDING_PREFIX}{name}.base.{c}' for c in BASE_COMPONENTS]).tolist()])
            base = ca.if_else(self._recording_selects(name, z), own, base)
        return base

    def _reflector_offset(self, p: Expr, reflector: int, z: Expr) -> Expr:
        """Reflector ``reflector``'s centre (3,) in the tip frame for the row's recording.

        A recording with its probe remounted has its own offsets; the others the first's.
        """
        offset = self.chain.reflector(p, reflector)
        if not self.recordings:
            return offset
        prefix = reflector_prefixes(self.params)[reflector]
        for name in self.recordings:
            names = [f'{RECORDING_PREFIX}{name}.{prefix}.{c}' for c in 'xyz']
            if names[0] in self.params.names:
                offset = ca.if_else(self._recording_selects(name, z),
                                    p[self.params.indices(names).tolist()], offset)
        return offset

    def body_rotation_expression(self, p: Expr, q: Expr, tau: Expr, reflector: int,
                                 z: Expr = None) -> Expr:
        """Rotation (3x3) of reflector ``reflector``'s tracked body in the tracker frame."""
        prefix = reflector_prefixes(self.params)[reflector]  # a remount: its own turn
        own = [(self._recording_selects(r, z), f'{RECORDING_PREFIX}{r}.{prefix}')
               for r in (self.recordings if z is not None else ())]
        return self._tool_pose(p, q, tau, z)[0][0:3, 0:3] @ body_orientation(
            self.params.names, p, self.orientations[reflector], prefix, own)

    def point_expression(self, p: Expr, q: Expr, tau: Expr = None,
                         reflector: int = 0, z: Expr = None) -> Expr:
        """Centre of reflector ``reflector`` in the tracker frame, CasADi expression (3,).

        ``z`` the covariates :attr:`inputs` (None: 0).
        """
        world, thetas = self._tool_pose(p, q, tau, z)
        return self._reflector_point(world, thetas, p, reflector, z)

    def _reflector_point(self, world: Expr, thetas: list, p: Expr, reflector: int,
                         z: Expr = None) -> Expr:
        """Reflector ``reflector``'s centre from the tool pose ``world`` (4x4).

        ``thetas`` are the effects' parameters of :meth:`_tool_pose`; ``z`` the covariates
        (None: 0, the first recording's reflector).
        """
        if z is None:
            z = ca.DM.zeros(len(self.inputs))
        point = reflector_point(world, self._reflector_offset(p, reflector, z))
        for effect, theta in zip(self.effects, thetas):
            corrected = effect.point_correction(point, theta)
            if corrected is not None:
                point = corrected
        return point

    def incidence_cos_expression(self, p: Expr, q: Expr) -> Expr:
        """Cosine of β between the reflector axis and the beam towards the tracker, eq. (4)."""
        world = self.chain.base_in_tracker(p) @ self.chain.tip_transform(p, q)
        point = reflector_point(world, self.chain.reflector(p))
        axis = world[0:3, 0:3] @ ca.DM(self.reflector_axis)
        beam = -point / ca.norm_2(point)  # the tracker sits at the tracker-frame origin
        return ca.dot(axis, beam) / ca.norm_2(axis)

    # ------------------------------------------------------------- numerics
    def _torques(self, q: np.ndarray, tau: np.ndarray | None,
                 covariates: Mapping[str, np.ndarray] | None = None) -> np.ndarray:
        n = self.robot.n_joints
        if tau is not None:
            return torque_input(tau, n, self.uses_torque)
        if self.uses_torque:
            return payload_torques(self.robot, q, covariates, gradient=True)
        return np.zeros_like(np.atleast_2d(q))

    def input_values(self, n: int, covariates: Mapping[str, np.ndarray] | None) -> np.ndarray:
        """Return the covariates the effects read, (n, len(inputs)) in :attr:`inputs` order.

        Zeros (the reference condition) where ``covariates`` is None; a payload input
        (:data:`~kpi_calib_ros.core.measurement.payload.PAYLOAD_MASS`, ``PAYLOAD_COM``) the
        cell's payload where the covariates do not state it.

        Raises
        ------
        ValueError
            A covariate the effects read is missing, of another length or not finite.
        """
        # A row's payload is the cell's where it states none, as its gravity torques are
        # (core.measurement.payload): its reference condition.
        stated = cell_payload_inputs(self.robot.payload)
        out = np.tile([stated.get(name, 0.0) for name in self.inputs], (n, 1))
        for i, name in enumerate(self.inputs):
            if covariates is None or (name in stated and name not in covariates):
                continue
            if name not in covariates:
                raise ValueError(f'the effects read the covariate {name!r}; the measurements '
                                 f'carry {sorted(covariates)}: record it (e.g. the cell\'s '
                                 'temperature topic) or drop the effect')
            values = np.asarray(covariates[name], float).reshape(-1)
            if values.shape != (n,) or not np.all(np.isfinite(values)):
                raise ValueError(f'covariate {name!r} must hold {n} finite values, one per row')
            out[:, i] = values
        return out

    def _groups(self, n: int, reflector: np.ndarray | None) -> list[tuple[int, np.ndarray]]:
        """(row channel, rows) pairs covering rows 0..n-1.

        A row channel is a reflector index, or ``n_reflectors + k`` for the rotation row of
        reflector ``k``.
        """
        if reflector is None:
            return [(0, np.arange(n))]
        ref = np.asarray(reflector, dtype=int).reshape(-1)
        if len(ref) != n:
            raise ValueError(f'reflector must hold one index per row ({n}), got {len(ref)}')
        valid = set(range(self.n_reflectors)) | {self.n_reflectors + k for k in self.orientations}
        bad = sorted(set(ref.tolist()) - valid)
        if bad:
            raise ValueError(f'reflector indices must be in [0, {self.n_reflectors}) or a '
                             f'rotation row {sorted(valid - set(range(self.n_reflectors)))}, '
                             f'got {bad}')
        return [(int(k), np.flatnonzero(ref == k)) for k in np.unique(ref)]

    def __getstate__(self) -> dict:
        """Picklable state (a job's result crosses a process boundary).

        The functions built on first use are built now; CasADi expressions and the mapped
        functions stay behind.
        """
        return dict(self.__dict__, _hq_built=self._hq, _cos_built=self._cos, _symbols=None,
                    _points=None, _mapped={})

    @property
    def _hq(self) -> list[ca.Function]:
        """∂h/∂q of each reflector (built on first use)."""
        if self._hq_built is None:
            p, q, tau, z = self._symbols
            self._hq_built = [ca.Function('hq', [p, q, tau, z], [ca.jacobian(point, q)])
                              for point in self._points]
        return self._hq_built

    @property
    def _cos(self) -> ca.Function:
        """Cosine of the incidence angle (built on first use)."""
        if self._cos_built is None:
            p, q, _, _ = self._symbols
            self._cos_built = ca.Function('cos_incidence', [p, q],
                                          [self.incidence_cos_expression(p, q)])
        return self._cos_built

    def _map(self, which: int, channel: int, m: int) -> Mapped:
        """Return function ``which`` of a row channel mapped over ``m`` rows (built once per m)."""
        key = (which, channel, m)
        if key not in self._mapped:
            if channel < self.n_reflectors:
                fn = (self._h, self._hj, self._hq)[which][channel]
            else:
                fn = self._rot[channel - self.n_reflectors][which]
            self._mapped[key] = Mapped.of(fn.map(m))
        return self._mapped[key]

    def _evaluate(self, which: int, channel: int, rows: np.ndarray, p: np.ndarray,
                  q: np.ndarray, tau: np.ndarray, rotation: np.ndarray | None,
                  z: np.ndarray) -> list:
        """Evaluate function ``which`` of a row channel over ``rows``.

        ``which`` 0: h, 1: h and ∂h/∂p, 2: ∂h/∂q. A rotation row takes its measured rotation as
        an input; ``z`` (N, n_z) the covariates (:meth:`input_values`).
        """
        m = len(rows)
        if channel < self.n_reflectors:
            args = [p, q[rows].T, tau[rows].T, z[rows].T]
        else:
            if rotation is None:
                raise ValueError('rotation rows need the measured rotations (rotation=)')
            measured = measured_rotation_input(np.asarray(rotation)[rows])
            args = [p, q[rows].T, tau[rows].T, measured.T, z[rows].T]
        return call_mapped(self._map(which, channel, m), args)

    def predict(self, p: np.ndarray, q: np.ndarray, tau: np.ndarray | None = None,
                reflector: np.ndarray | None = None,
                rotation: np.ndarray | None = None,
                covariates: Mapping[str, np.ndarray] | None = None) -> np.ndarray:
        """Predicted points (N, 3) in the tracker frame for joint values ``q`` (N, n).

        ``reflector`` (N,) the reflector indices (None: reflector 0); rotation rows (see
        :class:`Measurements`) need ``rotation`` (N, 3, 3); ``covariates`` the rows' covariates
        (:meth:`input_values`; None: the reference condition).
        """
        q = np.atleast_2d(q)
        tau = self._torques(q, tau, covariates)
        z = self.input_values(len(q), covariates)
        out = np.zeros((len(q), 3))
        for k, rows in self._groups(len(q), reflector):
            if len(rows):
                out[rows] = self._evaluate(0, k, rows, p, q, tau, rotation, z)[0].T
        return out

    def jacobian(self, p: np.ndarray, q: np.ndarray, tau: np.ndarray | None = None,
                 reflector: np.ndarray | None = None,
                 rotation: np.ndarray | None = None,
                 covariates: Mapping[str, np.ndarray] | None = None
                 ) -> tuple[np.ndarray, np.ndarray]:
        """Predicted points (N, 3) and their Jacobian (N, 3, n_p) w.r.t. p."""
        q = np.atleast_2d(q)
        tau = self._torques(q, tau, covariates)
        z = self.input_values(len(q), covariates)
        n_p = len(self.params)
        pts, jac = np.zeros((len(q), 3)), np.zeros((len(q), 3, n_p))
        for k, rows in self._groups(len(q), reflector):
            if len(rows):
                h, j = self._evaluate(1, k, rows, p, q, tau, rotation, z)
                pts[rows] = h.T
                jac[rows] = j.reshape(3, len(rows), n_p).transpose(1, 0, 2)
        return pts, jac

    def joint_jacobian(self, p: np.ndarray, q: np.ndarray, tau: np.ndarray | None = None,
                       reflector: np.ndarray | None = None,
                       rotation: np.ndarray | None = None,
                       covariates: Mapping[str, np.ndarray] | None = None) -> np.ndarray:
        """Jacobian (N, 3, n) of the predicted points w.r.t. the joint values."""
        q = np.atleast_2d(q)
        tau = self._torques(q, tau, covariates)
        z = self.input_values(len(q), covariates)
        out = np.zeros((len(q), 3, q.shape[1]))
        for k, rows in self._groups(len(q), reflector):
            if len(rows):
                jac = self._evaluate(2, k, rows, p, q, tau, rotation, z)[0]
                out[rows] = jac.reshape(3, len(rows), q.shape[1]).transpose(1, 0, 2)
        return out

    def whitening(self, p: np.ndarray, q: np.ndarray, sigma: np.ndarray,
                  tau: np.ndarray | None = None, reflector: np.ndarray | None = None,
                  rotation: np.ndarray | None = None,
                  point_weights: np.ndarray | None = None,
                  covariates: Mapping[str, np.ndarray] | None = None) -> np.ndarray:
        """Weights of the residual rows at parameters ``p``, for :func:`weighted_rows`.

        Without joint-reading noise (``joint_sigma`` None): (N, 3) per-axis weights
        √ω_i / σ_i,a. With it: (N, 3, 3) W_i = √ω_i L_i⁻¹, L_i the Cholesky factor of
        Σ_i = diag(σ_i²) + J_q,i diag(joint_sigma²) J_q,iᵀ, so W_i Σ_i W_iᵀ = ω_i I.

        Parameters
        ----------
        sigma : (3,) or (N, 3) ndarray
            Tracker noise per axis, m, for every row or per row (:func:`row_sigma`)
            (rotation rows are in metres at this σ).
        point_weights : (N,) ndarray, optional
            Robustness weights ω_i in [0, 1]; default 1.
        """
        q = np.atleast_2d(q)
        sigma = np.broadcast_to(np.asarray(sigma, float), (len(q), 3))
        omega = np.ones(len(q)) if point_weights is None else np.asarray(point_weights, float)
        if omega.shape != (len(q),) or not np.all(np.isfinite(omega)) or np.any(omega < 0):
            raise ValueError(f'point_weights must be {len(q)} finite numbers >= 0, got shape '
                             f'{omega.shape}')
        if self.joint_sigma is None:
            return np.sqrt(omega)[:, None] / sigma
        jq = self.joint_jacobian(p, q, tau, reflector, rotation, covariates) @ self.joint_noise_map
        cov = np.einsum('nak,nbk->nab', jq, jq) + sigma[:, :, None] ** 2 * np.eye(3)
        chol = np.linalg.cholesky(cov)
        inverse = np.linalg.solve(chol, np.broadcast_to(np.eye(3), chol.shape))
        return inverse * np.sqrt(omega)[:, None, None]

    def body_rotations(self, p: np.ndarray, q: np.ndarray, reflector: int,
                       tau: np.ndarray | None = None) -> np.ndarray:
        """Rotations (N, 3, 3) of reflector ``reflector``'s tracked body in the tracker frame.

        At joint values ``q`` (N, n): what a 6-DoF tracker reports, noise-free.
        """
        q = np.atleast_2d(q)
        tau = self._torques(q, tau)
        fn = self._rot[reflector][3].map(len(q))
        # (3, 3N), one 3x3 block per row; at the reference condition (no covariates)
        out = np.array(fn(p, q.T, tau.T, np.zeros((len(self.inputs), len(q)))))
        return out.reshape(3, len(q), 3).transpose(1, 0, 2)

    @property
    def pose_channels(self) -> tuple[int, ...]:
        """Row channels every measured pose gives (``Measurements.reflector`` values).

        Each reflector's point, then each tracked body's rotation row.
        """
        return (tuple(range(self.n_reflectors))
                + tuple(self.n_reflectors + k for k in sorted(self.orientations)))

    @property
    def rows_per_pose(self) -> int:
        """Rows of three residuals a measured pose gives (:attr:`pose_channels`)."""
        return len(self.pose_channels)

    def pose_measurements(self, p: np.ndarray, q: np.ndarray,
                          tau: np.ndarray | None = None) -> Measurements:
        """Return the rows measuring configurations ``q`` (N, n) gives, noise-free at ``p``.

        For every pose, :attr:`pose_channels` in turn (pose ``i``, channel ``c`` in row
        ``i·B + c``); a rotation row carries the body rotation at ``p`` as measured, so its
        residual is zero and its Jacobian the one identification takes there.
        """
        rows = self._pose_rows(p, q, tau)
        eta = self.predict(p, rows.q, rows.tau, rows.reflector, rows.rotation)
        return dataclasses.replace(rows, eta=eta)

    def _pose_rows(self, p: np.ndarray, q: np.ndarray,
                   tau: np.ndarray | None) -> Measurements:
        """:meth:`pose_measurements` without the predicted points (eta zero)."""
        q = np.atleast_2d(q)
        channels = np.array(self.pose_channels)
        rows_q = np.repeat(q, len(channels), axis=0)
        rows_tau = None if tau is None else np.repeat(np.atleast_2d(tau), len(channels), axis=0)
        reflector = np.tile(channels, len(q))
        rotation = None
        if self.orientations:
            rotation = np.broadcast_to(np.eye(3), (len(rows_q), 3, 3)).copy()
            for k in self.orientations:
                rotation[reflector == self.n_reflectors + k] = self.body_rotations(p, q, k, tau)
        return Measurements(q=rows_q, eta=np.zeros((len(rows_q), 3)), tau=rows_tau,
                            reflector=reflector, rotation=rotation)

    def pose_jacobian(self, p: np.ndarray, q: np.ndarray,
                      tau: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Every row a measured pose gives, as the design sees a pose (:meth:`pose_measurements`).

        Predictions (N, 3B) and Jacobian (N, 3B, n_p), channel ``c`` of :attr:`pose_channels` in
        rows 3c..3c+2 (B = 1 for a single reflector).
        """
        q = np.atleast_2d(q)
        rows = self._pose_rows(p, q, tau)
        pts, jac = self.jacobian(p, rows.q, rows.tau, rows.reflector, rows.rotation)
        b = self.rows_per_pose
        return pts.reshape(len(q), 3 * b), jac.reshape(len(q), 3 * b, -1)

    def pose_point_expression(self, p: Expr, q: Expr, tau: Expr = None,
                              p_measured: Expr = None) -> Expr:
        """Every row of a pose stacked (:attr:`pose_channels`), CasADi expression (3B,).

        A rotation row takes the body rotation at ``p_measured`` as the measured one (its
        Jacobian in ``p`` at ``p = p_measured`` is the design's; required with tracked bodies).
        """
        rows = [self.point_expression(p, q, tau, k) for k in range(self.n_reflectors)]
        if self.orientations and p_measured is None:
            raise ValueError('p_measured is needed for the rotation rows of tracked bodies')
        for k in sorted(self.orientations):
            measured = self.body_rotation_expression(p_measured, q, tau, k)
            rows.append(rotation_residual_expression(
                ca.reshape(measured, 9, 1), self.body_rotation_expression(p, q, tau, k),
                self.rotation_scale))
        return ca.vertcat(*rows)

    def incidence_cos(self, p: np.ndarray, q: np.ndarray) -> np.ndarray:
        """Cosine of the incidence angle (N,) at joint values ``q`` (N, n)."""
        q = np.atleast_2d(q)
        return np.array(self._cos.map(len(q))(p, q.T)).ravel()
