"""Robot model: the serial chain between a base frame and a tip frame of any URDF.

Pinocchio parses the URDF; this module extracts the chain as plain numbers that
the symbolic kinematics can build on (nominal joint placements, joint axes,
joint types and limits) and keeps the Pinocchio model for what Pinocchio does
best: reference forward kinematics and gravity torques (with the payload).

Conventions: SI units, a joint value is one scalar per chain joint (rad for
revolute/continuous, m for prismatic), in chain order from base to tip.

Mimic joints (``<mimic joint="master" multiplier="m" offset="o"/>``) are chain joints
like any other here (each keeps its own placement and error parameters), but they are
not independent: their value is ``m · q_master + o`` (URDF semantics). The robot's
*actuated* joints are the independent ones: the chain's non-mimic joints and the
masters of its mimic joints (a master may lie off the chain, e.g. the drive of a
lifting column whose two stages both mimic it). :attr:`RobotModel.mimic_matrix` and
:attr:`RobotModel.mimic_offset` map actuated values to chain values; configurations
are drawn in the actuated joints (:meth:`RobotModel.sample_configurations`), so
every chain configuration the tool makes respects the relation.
"""
from __future__ import annotations

import re
import xml.etree.ElementTree as ET
from dataclasses import dataclass
from typing import Sequence

import numpy as np
import pinocchio as pin

from kpi_calib_ros.core.errors import ConfigError

__all__ = ['MAX_URDF_ELEMENTS', 'ChainJoint', 'Mimic', 'Payload', 'RobotModel', 'frame_id',
           'urdf_mimics']

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
class Mimic:
    """A URDF ``<mimic>``: the joint's value is ``multiplier · q_master + offset``.

    ``offset`` in the joint's unit (rad or m); ``multiplier`` in its unit per the
    master's.
    """

    master: str
    multiplier: float = 1.0
    offset: float = 0.0


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
    mimic : Mimic or None
        The URDF's mimic relation of this joint; None for an independent joint.
    """

    name: str
    kind: str
    placement: np.ndarray
    axis: np.ndarray
    lower: float
    upper: float
    child_link: str
    mimic: Mimic | None = None


@dataclass(frozen=True)
class Payload:
    """Point-mass-like payload rigidly attached to the tip frame.

    mass in kg, com (3,) in the tip frame in m.
    """

    mass: float = 0.0
    com: tuple[float, float, float] = (0.0, 0.0, 0.0)


def frame_id(model: pin.Model, name: str) -> int:
    """Return the Pinocchio id of the frame ``name``: the link (body) of that name first.

    A URDF may name a joint like a link (the stock SO-100's ``gripper``): Pinocchio then
    holds two frames of the name and refuses to pick one.
    """
    if model.existFrame(name, pin.BODY):
        return int(model.getFrameId(name, pin.BODY))
    return int(model.getFrameId(name))


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
        base = model.frames[frame_id(model, base_frame)]
        tip = model.frames[frame_id(model, tip_frame)]
        path = _joint_path(model, base.parentJoint, tip.parentJoint)
        if path is None:
            raise ConfigError('robot.tip_frame', f'{tip_frame!r} is not downstream of base frame '
                              f'{base_frame!r}; choose a tip on the chain below the base')
        if not path:
            raise ConfigError('robot.tip_frame', f'no actuated joint between {base_frame!r} '
                              f'and {tip_frame!r}')
        self._pin_joint_ids = path
        # A <mimic> naming a joint the URDF does not have states no relation (stock hand
        # descriptions ship such tags, and urdfdom reads them): the joint stays independent.
        mimics = {name: m for name, m in urdf_mimics(urdf_xml).items()
                  if model.existJointName(m.master)}
        self._urdf_mimics = mimics
        self.joints = tuple(self._chain_joint(jid, first=(i == 0), base=base,
                                              mimic=mimics.get(model.names[jid]))
                            for i, jid in enumerate(path))
        self._actuated()
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
    def moving_mass_kg(self) -> float:
        """The mass (kg) of the links the chain's joints move.

        The cell's payload left out; 0 when the URDF states no inertias.
        """
        model, first, tip = self.pin_model, self._pin_joint_ids[0], self._pin_joint_ids[-1]
        return float(sum(self._bare_tip.mass if j == tip else model.inertias[j].mass
                         for j in model.subtrees[first]))

    @property
    def has_mimic(self) -> bool:
        """Whether a chain joint mimics another (its value follows the master's)."""
        return any(j.mimic is not None for j in self.joints)

    @property
    def actuated_names(self) -> tuple[str, ...]:
        """The independent joints, base to tip.

        Each non-mimic chain joint at its place on the chain, and each master off the chain
        at its first mimic joint's place; the chain's joint names when nothing mimics.
        """
        return self._actuated_names

    @property
    def actuated_lower(self) -> np.ndarray:
        """Lower limits (m,) of the actuated joints.

        Their own, narrowed by the limits of the joints that mimic them (through the
        relation).
        """
        return self._actuated_bounds[0].copy()

    @property
    def actuated_upper(self) -> np.ndarray:
        """Upper limits (m,) of the actuated joints (see :attr:`actuated_lower`)."""
        return self._actuated_bounds[1].copy()

    @property
    def mimic_matrix(self) -> np.ndarray:
        """(n, m) map of actuated joint values to chain values: ``q = M @ x + d``."""
        return self._mimic_matrix.copy()

    @property
    def mimic_offset(self) -> np.ndarray:
        """(n,) offsets ``d`` of :attr:`mimic_matrix` (the URDF mimic offsets, else 0)."""
        return self._mimic_offset.copy()

    def chain_values(self, x: np.ndarray) -> np.ndarray:
        """Chain joint values (n,) or (N, n) of actuated values ``x`` ((m,) or (N, m))."""
        x = np.asarray(x, dtype=float)
        return x if not self.has_mimic else x @ self._mimic_matrix.T + self._mimic_offset

    def actuated_values(self, q: np.ndarray) -> np.ndarray:
        """Actuated values (m,) or (N, m) of chain values ``q``.

        A master off the chain is read from its first mimic joint (exact for
        configurations that respect the relation).
        """
        q = np.asarray(q, dtype=float)
        if not self.has_mimic:
            return q
        return (q - self._mimic_offset) @ self._recover.T

    def mimic_residual(self, q: np.ndarray) -> np.ndarray:
        """Return |q − (M x + d)| (n,) or (N, n).

        How far chain values ``q`` are from respecting every mimic relation (0 when they
        do).
        """
        q = np.asarray(q, dtype=float)
        return np.abs(q - self.chain_values(self.actuated_values(q)))

    def sampling_bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """Actuated joint ranges (m,) to draw configurations from.

        The limits, continuous joints on [-π, π].
        """
        lower, upper = self._actuated_bounds
        return np.where(np.isfinite(lower), lower, -np.pi), np.where(np.isfinite(upper),
                                                                      upper, np.pi)

    def middle_configuration(self) -> np.ndarray:
        """Return the (n,) chain configuration with every actuated joint mid-range.

        Mid-range of :meth:`sampling_bounds`.
        """
        lower, upper = self.sampling_bounds()
        return self.chain_values(0.5 * (lower + upper))

    def sample_configurations(self, rng: np.random.Generator, size: int) -> np.ndarray:
        """Return (size, n) chain configurations uniform in the actuated joints' ranges.

        Ranges of :meth:`sampling_bounds`; mimic joints follow their masters.
        """
        lower, upper = self.sampling_bounds()
        return self.chain_values(rng.uniform(lower, upper, size=(size, len(lower))))

    @property
    def link_names(self) -> list[str]:
        """Links moved by each chain joint, base to tip (the base link first)."""
        model = self.pin_model
        base_link = model.frames[frame_id(model, self.base_frame)].name
        return [base_link] + [j.child_link for j in self.joints]

    def _actuated(self) -> None:
        """Find the actuated joints and the map from their values to the chain's."""
        model = self.pin_model
        by_name = {j.name: i for i, j in enumerate(self.joints)}
        names: list[str] = []
        for joint in self.joints:
            source = joint.mimic.master if joint.mimic is not None else joint.name
            if joint.mimic is not None:
                # On the chain or off it (a middle joint off the chain was taken as free).
                if source in self._urdf_mimics:
                    raise ConfigError('robot.urdf', f'joint {joint.name!r} mimics {source!r}, '
                                      'which mimics another joint itself; let it mimic the '
                                      'independent joint directly')
                if joint.mimic.multiplier == 0.0:
                    raise ConfigError('robot.urdf', f'joint {joint.name!r}: <mimic '
                                      'multiplier="0"> makes it a fixed joint; write it as '
                                      'type="fixed" with its origin')
            # A master on the chain takes its own place (an unnamed working pose lists the
            # independent joints in chain order); one off it, its first mimic's.
            if joint.mimic is not None and source in by_name:
                continue
            if source not in names:
                names.append(source)
        self._actuated_names = tuple(names)
        n, m = len(self.joints), len(names)
        matrix, offset = np.zeros((n, m)), np.zeros(n)
        lower = np.full(m, -np.inf)
        upper = np.full(m, np.inf)
        recover = np.zeros((m, n))
        for i, joint in enumerate(self.joints):
            if joint.mimic is None:
                k = names.index(joint.name)
                matrix[i, k] = 1.0
                lower[k], upper[k] = max(lower[k], joint.lower), min(upper[k], joint.upper)
                recover[k] = 0.0
                recover[k, i] = 1.0
                continue
            k = names.index(joint.mimic.master)
            mult, off = joint.mimic.multiplier, joint.mimic.offset
            matrix[i, k], offset[i] = mult, off
            # The mimic joint's own limits bound its master through the relation.
            ends = sorted(((joint.lower - off) / mult, (joint.upper - off) / mult))
            lower[k], upper[k] = max(lower[k], ends[0]), min(upper[k], ends[1])
            if not recover[k].any():
                recover[k, i] = 1.0 / mult
        for k, name in enumerate(names):
            if name in by_name:
                continue
            jmodel = model.joints[model.getJointId(name)]  # an off-chain master's own limits
            if jmodel.nq == 1:
                lower[k] = max(lower[k], float(model.lowerPositionLimit[jmodel.idx_q]))
                upper[k] = min(upper[k], float(model.upperPositionLimit[jmodel.idx_q]))
        lower, upper = lower + 0.0, upper + 0.0  # no -0.0 bound
        bad = [names[k] for k in range(m) if not lower[k] <= upper[k]]
        if bad:
            raise ConfigError('robot.urdf', f'joint(s) {bad}: the limits of the joints that '
                              'mimic them leave no value; check the <limit> and <mimic> tags')
        # A leader whose mimics' limits leave one value cannot move: a mimic's limits or
        # multiplier written wrong (the PR2's right gripper finger), not a joint to draw.
        narrowed = {names.index(j.mimic.master) for j in self.joints
                    if j.mimic is not None and j.upper > j.lower}
        single = [k for k in sorted(narrowed) if not lower[k] < upper[k]]
        if single:
            raise ConfigError('robot.urdf', f'joint(s) {[names[k] for k in single]}: the '
                              'limits of the joints that mimic them leave the single value '
                              f'{lower[single[0]]:g}: '
                              'the joint could not move; check the <limit> and <mimic> '
                              '(multiplier sign, offset) tags')
        self._mimic_matrix, self._mimic_offset = matrix, offset
        self._actuated_bounds = (lower, upper)
        self._recover = recover
        # Off-chain masters, set in Pinocchio configurations as the relation gives them:
        # (idx_q, nq, actuated index); plain numbers, so the model pickles (worker jobs).
        self._off_chain = [(int(j.idx_q), int(j.nq), k) for k, j in (
            (k, model.joints[model.getJointId(name)]) for k, name in enumerate(names)
            if name not in by_name)]

    def _chain_joint(self, jid: int, first: bool, base: pin.Frame,
                     mimic: Mimic | None = None) -> ChainJoint:
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
        return ChainJoint(name, kind, placement, axis, lower, upper, child, mimic)

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

        Joints outside the chain stay at their neutral value, except the masters of
        mimic joints, which take the value the relation gives.
        """
        q = np.asarray(q, dtype=float)
        q_pin = pin.neutral(self.pin_model)
        if self._off_chain:
            x = self.actuated_values(q)
            for idx, nq, k in self._off_chain:
                if nq == 1:
                    q_pin[idx] = x[k]
                elif nq == 2:  # continuous
                    q_pin[idx:idx + 2] = np.cos(x[k]), np.sin(x[k])
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
        base_inv = data.oMf[frame_id(model, self.base_frame)].inverse()
        poses = {link: np.array((base_inv * data.oMf[model.getFrameId(link, pin.BODY)])
                                .homogeneous) for link in self.link_names}
        tip = np.array((base_inv * data.oMf[frame_id(model, self.tip_frame)]).homogeneous)
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
            root frame taken as level (gravity along its -z). A chain joint that other
            chain joints mimic carries their load too: its force is that of its actuated
            coordinate, Σ_i M_ij τ_i over the chain joints i it drives (itself included,
            :attr:`mimic_matrix`), the virtual work of the drive (as Pinocchio's
            ``mimic=True`` model gives it); a mimic joint keeps its own.

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
        if self.has_mimic:
            drives = [i for i, j in enumerate(self.joints) if j.mimic is None]
            columns = np.argmax(np.abs(self._mimic_matrix[drives]), axis=1)
            out[:, drives] = (out @ self._mimic_matrix)[:, columns]
        return out[0] if single else out

    def within_limits(self, q: np.ndarray, margin: float = 0.0) -> np.ndarray:
        """Boolean mask: rows of ``q`` (N, n) strictly inside the limits shrunk by ``margin``."""
        q = np.atleast_2d(q)
        return np.all((q >= self.lower + margin) & (q <= self.upper - margin), axis=1)


def urdf_mimics(urdf_xml: str) -> dict[str, Mimic]:
    """Return {joint name: its :class:`Mimic`} of every ``<joint>`` with a ``<mimic>``.

    Multiplier 1 and offset 0 by default, as the URDF specification says.

    Raises
    ------
    ConfigError
        A ``<mimic>`` without a ``joint`` or with a multiplier/offset that is not a
        finite number.
    """
    try:
        root = ET.fromstring(urdf_xml)
    except ET.ParseError as exc:
        raise ConfigError('robot.urdf', f'not a valid URDF ({exc}); check the file with '
                          'check_urdf') from exc
    out: dict[str, Mimic] = {}
    for element in root.findall('joint'):
        tag = element.find('mimic')
        if tag is None:
            continue
        name = str(element.get('name'))
        master = tag.get('joint')
        if not master:
            raise ConfigError('robot.urdf', f'joint {name!r}: <mimic> names no joint; write '
                              '<mimic joint="master" multiplier="1" offset="0"/>')
        values = []
        for attr, default in (('multiplier', 1.0), ('offset', 0.0)):
            text = tag.get(attr)
            try:
                value = default if text is None else float(text)
            except ValueError:
                value = float('nan')
            if not np.isfinite(value):
                raise ConfigError('robot.urdf', f'joint {name!r}: <mimic {attr}="{text}"> is '
                                  'not a finite number')
            values.append(value)
        out[name] = Mimic(master, values[0], values[1])
    return out


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
