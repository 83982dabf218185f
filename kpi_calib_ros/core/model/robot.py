"""Robot model: the serial chain between a base frame and a tip frame of any URDF.

Pinocchio parses the URDF; this module extracts the chain as plain numbers that
the symbolic kinematics can build on (nominal joint placements, joint axes,
joint types and limits) and keeps the Pinocchio model for what Pinocchio does
best: reference forward kinematics and gravity torques (with the payload).

Conventions: SI units, a joint value is one scalar per chain joint (rad for
revolute/continuous, m for prismatic), in chain order from base to tip.
"""
from __future__ import annotations

import re
from dataclasses import dataclass
from typing import Sequence

import numpy as np
import pinocchio as pin

from kpi_calib_ros.core.errors import ConfigError

__all__ = ['MAX_URDF_ELEMENTS', 'ChainJoint', 'Payload', 'RobotModel']

_REVOLUTE = {'JointModelRX', 'JointModelRY', 'JointModelRZ', 'JointModelRevoluteUnaligned'}
_CONTINUOUS = {'JointModelRUBX', 'JointModelRUBY', 'JointModelRUBZ',
               'JointModelRevoluteUnboundedUnaligned'}
_PRISMATIC = {'JointModelPX', 'JointModelPY', 'JointModelPZ', 'JointModelPrismaticUnaligned'}
# Links and joints a URDF may have: real robots have tens (a mobile manipulator with
# hands about 100); Pinocchio needs ~0.4 ms per link (20 000 fixed links: 7.9 s), so a
# bound far above any robot keeps a generated or hostile file from hanging the tool.
MAX_URDF_ELEMENTS = 5000
_ELEMENT = re.compile(r'<\s*(link|joint)[\s/>]')


@dataclass(frozen=True)
class ChainJoint:
    """One actuated joint of the chain.

    Attributes
    ----------
    name : str
        URDF joint name.
    kind : str
        ``'revolute'``, ``'continuous'`` or ``'prismatic'``.
    placement : (4, 4) ndarray
        Nominal pose of this joint's frame in the previous chain joint's frame
        (the base frame for the first joint).
    axis : (3,) ndarray
        Unit joint axis in this joint's frame.
    lower, upper : float
        Joint limits (rad or m); +-inf for continuous joints.
    child_link : str
        Name of the link this joint moves.
    """

    name: str
    kind: str
    placement: np.ndarray
    axis: np.ndarray
    lower: float
    upper: float
    child_link: str


@dataclass(frozen=True)
class Payload:
    """Point-mass-like payload rigidly attached to the tip frame.

    mass in kg, com (3,) in the tip frame in m.
    """

    mass: float = 0.0
    com: tuple[float, float, float] = (0.0, 0.0, 0.0)


class RobotModel:
    """A serial chain from ``base_frame`` to ``tip_frame`` of a URDF.

    Parameters
    ----------
    urdf_xml : str
        URDF document.
    base_frame, tip_frame : str
        Frame (link) names; ``tip_frame`` must be downstream of ``base_frame``.
    payload : Payload, optional
        Added to the body carrying the tip frame for gravity torques.

    Raises
    ------
    ConfigError
        Malformed URDF, unknown frame, a tip not downstream of the base, or a
        joint in the chain that is not 1-DoF revolute/continuous/prismatic.
    """

    def __init__(self, urdf_xml: str, base_frame: str, tip_frame: str,
                 payload: Payload | None = None) -> None:
        # Counted on the text, before Pinocchio parses it (a tag inside a comment counts
        # too: an overestimate of a bound).
        elements = sum(1 for _ in _ELEMENT.finditer(urdf_xml))
        if elements > MAX_URDF_ELEMENTS:
            raise ConfigError('robot.urdf', f'{elements} <link>/<joint> elements, more than '
                              f'the {MAX_URDF_ELEMENTS} a robot description may have here; '
                              'give the URDF of the robot (not a scene or a generated '
                              'file)')
        try:
            self.pin_model = pin.buildModelFromXML(urdf_xml)
        except (ValueError, RuntimeError) as exc:
            raise ConfigError('robot.urdf', f'not a valid URDF ({exc}); check the file '
                              'with check_urdf') from exc
        self.base_frame = base_frame
        self.tip_frame = tip_frame
        self.payload = payload or Payload()
        model = self.pin_model
        for key, frame in (('robot.base_frame', base_frame), ('robot.tip_frame', tip_frame)):
            if not model.existFrame(frame):
                links = sorted({f.name for f in model.frames if f.type == pin.FrameType.BODY})
                raise ConfigError(key, f'frame {frame!r} is not in the URDF; links are {links}')
        base = model.frames[model.getFrameId(base_frame)]
        tip = model.frames[model.getFrameId(tip_frame)]
        path = _joint_path(model, base.parentJoint, tip.parentJoint)
        if path is None:
            raise ConfigError('robot.tip_frame', f'{tip_frame!r} is not downstream of base frame '
                              f'{base_frame!r}; choose a tip on the chain below the base')
        if not path:
            raise ConfigError('robot.tip_frame', f'no actuated joint between {base_frame!r} '
                              f'and {tip_frame!r}')
        self._pin_joint_ids = path
        self.joints = tuple(self._chain_joint(jid, first=(i == 0), base=base)
                            for i, jid in enumerate(path))
        self.tip_placement = np.array(tip.placement.homogeneous)
        self._pin_data = model.createData()
        self._add_payload(tip)

    # ------------------------------------------------------------------ structure
    @property
    def joint_names(self) -> list[str]:
        """Chain joint names, base to tip."""
        return [j.name for j in self.joints]

    @property
    def n_joints(self) -> int:
        """Number of chain joints n."""
        return len(self.joints)

    @property
    def lower(self) -> np.ndarray:
        """Lower joint limits (n,) (rad or m), chain order."""
        return np.array([j.lower for j in self.joints])

    @property
    def upper(self) -> np.ndarray:
        """Upper joint limits (n,) (rad or m), chain order."""
        return np.array([j.upper for j in self.joints])

    @property
    def link_names(self) -> list[str]:
        """Links moved by each chain joint, base to tip (the base link first)."""
        model = self.pin_model
        base_link = model.frames[model.getFrameId(self.base_frame)].name
        return [base_link] + [j.child_link for j in self.joints]

    def _chain_joint(self, jid: int, first: bool, base: pin.Frame) -> ChainJoint:
        model = self.pin_model
        jmodel = model.joints[jid]
        kind_name = jmodel.shortname()
        name = model.names[jid]
        if kind_name in _REVOLUTE:
            kind = 'revolute'
        elif kind_name in _CONTINUOUS:
            kind = 'continuous'
        elif kind_name in _PRISMATIC:
            kind = 'prismatic'
        else:
            raise ConfigError('robot.urdf', f'joint {name!r} ({kind_name}) in the chain is not a '
                              '1-DoF revolute, continuous or prismatic joint')
        jdata = jmodel.createData()
        jmodel.calc(jdata, pin.neutral(model))
        subspace = np.array(jdata.S).reshape(6)
        axis = subspace[3:] if kind != 'prismatic' else subspace[:3]
        axis = axis / np.linalg.norm(axis)
        placement = np.array(model.jointPlacements[jid].homogeneous)
        if first:
            # The chain starts at the base frame, which may sit anywhere on its joint's body.
            placement = np.linalg.inv(np.array(base.placement.homogeneous)) @ placement
        if kind == 'continuous':
            lower, upper = -np.inf, np.inf
        else:
            lower = float(model.lowerPositionLimit[jmodel.idx_q])
            upper = float(model.upperPositionLimit[jmodel.idx_q])
        child = next(f.name for f in model.frames
                     if f.parentJoint == jid and f.type == pin.FrameType.BODY)
        return ChainJoint(name, kind, placement, axis, lower, upper, child)

    def _add_payload(self, tip: pin.Frame) -> None:
        jid = self._pin_joint_ids[-1]
        # the tip body without payload, and the tip frame in its joint: other payloads
        # (:meth:`gravity_torques` per row) are added to it
        self._bare_tip = pin.Inertia(self.pin_model.inertias[jid])
        self._tip_in_joint = pin.SE3(tip.placement)
        self._loaded: dict[Payload, tuple[pin.Model, pin.Data]] = {}
        if self.payload.mass <= 0.0:
            return
        self.pin_model.inertias[jid] = self._bare_tip + self._payload_inertia(self.payload)

    def _payload_inertia(self, payload: Payload) -> pin.Inertia:
        com_in_joint = self._tip_in_joint.act(np.asarray(payload.com, dtype=float))
        return pin.Inertia(float(payload.mass), com_in_joint, np.zeros((3, 3)))

    def _model_with(self, payload: Payload) -> tuple[pin.Model, pin.Data]:
        """Return the Pinocchio model (and its data) with ``payload`` in place of the cell's."""
        if payload == self.payload:
            return self.pin_model, self._pin_data
        loaded = self._loaded.get(payload)
        if loaded is None:
            model = pin.Model(self.pin_model)
            model.inertias[self._pin_joint_ids[-1]] = (
                self._bare_tip + self._payload_inertia(payload) if payload.mass > 0.0
                else pin.Inertia(self._bare_tip))
            loaded = model, model.createData()
            if len(self._loaded) < 64:  # a campaign has a few loads, not one per row
                self._loaded[payload] = loaded
        return loaded

    # ------------------------------------------------------------------ numerics
    def pin_configuration(self, q: np.ndarray) -> np.ndarray:
        """Pinocchio configuration vector for chain joint values ``q`` (n,).

        Joints outside the chain stay at their neutral value.
        """
        q = np.asarray(q, dtype=float)
        q_pin = pin.neutral(self.pin_model)
        for jid, value, joint in zip(self._pin_joint_ids, q, self.joints):
            idx = self.pin_model.joints[jid].idx_q
            if joint.kind == 'continuous':
                q_pin[idx:idx + 2] = np.cos(value), np.sin(value)
            else:
                q_pin[idx] = value
        return q_pin

    def pin_link_poses(self, q: np.ndarray) -> tuple[dict[str, np.ndarray], np.ndarray]:
        """Nominal link poses {link name: (4, 4)} and tip pose (4, 4) in the base frame.

        Computed by Pinocchio from the URDF, independently of the CasADi chain of
        :mod:`kinematics` (the design verification relies on that independence).
        """
        model = self.pin_model
        data = model.createData()  # own data: callers may run in several threads
        pin.framesForwardKinematics(model, data, self.pin_configuration(q))
        base_inv = data.oMf[model.getFrameId(self.base_frame)].inverse()
        poses = {link: np.array((base_inv * data.oMf[model.getFrameId(link, pin.BODY)])
                                .homogeneous) for link in self.link_names}
        tip = np.array((base_inv * data.oMf[model.getFrameId(self.tip_frame)]).homogeneous)
        return poses, tip

    def pin_tip_pose(self, q: np.ndarray) -> np.ndarray:
        """Nominal tip pose (4, 4) in the base frame, computed by Pinocchio."""
        return self.pin_link_poses(q)[1]

    def gravity_torques(self, q: np.ndarray,
                        payloads: Sequence[Payload] | None = None) -> np.ndarray:
        """Gravity torque (N m, or N for prismatic) of each chain joint.

        Parameters
        ----------
        q : (n,) or (N, n) ndarray
            Chain joint values.
        payloads : sequence of N Payload, optional
            The payload each row carries on the tip in place of the cell's (a campaign that
            mixes loads); None: the cell's payload on every row.

        Returns
        -------
        (n,) or (N, n) ndarray
            Generalised gravity forces including the payload, with the URDF
            root frame taken as level (gravity along its -z).

        Raises
        ------
        ValueError
            ``payloads`` not one per row, or a mass that is negative or not finite.
        """
        q = np.asarray(q, dtype=float)
        single = q.ndim == 1
        rows = np.atleast_2d(q)
        if payloads is not None:
            payloads = list(payloads)
            if len(payloads) != len(rows):
                raise ValueError(f'payloads must give one payload per row ({len(rows)}), got '
                                 f'{len(payloads)}')
            bad = [p for p in payloads if not (np.isfinite(p.mass) and p.mass >= 0.0
                                               and np.all(np.isfinite(p.com)))]
            if bad:
                raise ValueError(f'a payload mass must be finite and >= 0 kg with a finite '
                                 f'centre of mass, got {bad[0]}')
        v_idx = [self.pin_model.joints[j].idx_v for j in self._pin_joint_ids]
        out = np.empty_like(rows)
        for k, row in enumerate(rows):
            model, data = ((self.pin_model, self._pin_data) if payloads is None
                           else self._model_with(payloads[k]))
            tau = pin.computeGeneralizedGravity(model, data, self.pin_configuration(row))
            out[k] = np.asarray(tau)[v_idx]
        return out[0] if single else out

    def within_limits(self, q: np.ndarray, margin: float = 0.0) -> np.ndarray:
        """Boolean mask: rows of ``q`` (N, n) strictly inside the limits shrunk by ``margin``."""
        q = np.atleast_2d(q)
        return np.all((q >= self.lower + margin) & (q <= self.upper - margin), axis=1)


def _joint_path(model: pin.Model, base_joint: int, tip_joint: int) -> list[int] | None:
    """Joint ids from just below ``base_joint`` down to ``tip_joint``; None if not an ancestor."""
    path = []
    jid = tip_joint
    while jid != base_joint:
        if jid == 0:
            return None
        path.append(jid)
        jid = model.parents[jid]
    return path[::-1]
