"""The keys of the cell file, described once: path, type, unit, default and meaning.

Data only: :mod:`kpi_calib_ros.io.cell` validates a cell document, this module says
what each key is for. The documentation's cell-key reference is generated from
:data:`CELL_KEYS`, and ``test/test_cell_schema.py`` checks it against what the loader
accepts (every key it accepts is described, and nothing else).

Paths: ``section.key``; ``section[].key`` is a key of every item of a list.
``example`` is a value the loader accepts there (for the tests and the reference).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any

REQUIRED = 'required'
NONE = 'none'


@dataclass(frozen=True)
class CellKey:
    """One key of the cell file.

    Attributes
    ----------
    path : str
        Key path, e.g. ``noise.sigma`` or ``reflectors[].offset``.
    type : str
        What the value is written as (``number``, ``[x, y, z]``, ``string``, …).
    unit : str
        SI unit of the value (``m``, ``rad``, ``kg``, …); empty when it has none.
    default : str
        The value used when the key is absent; :data:`REQUIRED` when it must be given,
        :data:`NONE` when absence has a meaning of its own (said in ``meaning``).
    meaning : str
        One or two sentences for the reference.
    example : Any
        A value the loader accepts at this path.
    """

    path: str
    type: str
    unit: str
    default: str
    meaning: str
    example: Any

    @property
    def section(self) -> str:
        """The top-level key the path starts with."""
        return self.path.split('.')[0].split('[')[0]


_K = CellKey

CELL_KEYS: tuple[CellKey, ...] = (
    # ------------------------------------------------------------------ robot
    _K('robot', 'mapping', '', REQUIRED, 'The robot: its URDF and the chain to calibrate.',
       {'urdf': 'robot.urdf', 'base_frame': 'base_link', 'tip_frame': 'tool0'}),
    _K('robot.urdf', 'string', '', REQUIRED, 'URDF file, relative to the cell file, or a '
       '`package://` / `file://` URI resolved as ROS does.', 'robot.urdf'),
    _K('robot.base_frame', 'string', '', REQUIRED, 'First link of the calibrated chain.',
       'base_link'),
    _K('robot.tip_frame', 'string', '', REQUIRED, 'Last link of the chain (the flange); '
       'reflector offsets are in its frame.', 'tool0'),
    _K('robot.package_dirs', 'list of string', '', '[]', 'Folders (relative to the cell file) '
       'searched first for `package://` URIs of the URDF and its meshes.', ['../src']),
    _K('robot.joint_coupling', 'mapping', '', '{} (identity)', 'Affine map from the '
       "controller's joint values to the URDF's actuated joints, `{urdf_joint: "
       "{controller_joint: factor, offset: value}}` (offset in rad or m, default 0); "
       'unlisted joints map to themselves; must be invertible; mimic joints follow from '
       'their masters by the URDF and are not listed.',
       {'joint_3': {'joint_3': 1.0, 'joint_2': 1.0}}),
    _K('robot.working_poses_in', '`controller` or `urdf`', '', 'controller', 'How the '
       'working poses are written: controller values (mapped by `joint_coupling`) or URDF '
       'values.', 'urdf'),
    # ---------------------------------------------------------------- tracker
    _K('tracker', 'mapping', '', '{}', 'The laser tracker (or motion-capture) frame.',
       {'frame_id': 'laser_tracker'}),
    _K('tracker.frame_id', 'string', '', 'laser_tracker', 'Frame id of the tracker points '
       '(`header.frame_id`).', 'laser_tracker'),
    _K('tracker.base_in_tracker', '[x, y, z, roll, pitch, yaw]', 'm, rad', NONE, 'Nominal '
       'robot base pose in the tracker frame; absent: registered from the points (a design '
       'needs it).', [2.6544, 0.2728, -0.2, 0.0, 0.0, 1.9]),
    # -------------------------------------------------------------- reflector
    _K('reflector', 'mapping', '', '{}', 'The single reflector (SMR) on the tip; with '
       '`reflectors:` it holds `axis` and `max_incidence` only.', {'offset': [0, 0, 0.03]}),
    _K('reflector.offset', '[x, y, z]', 'm', NONE, 'Reflector centre in the tip frame; '
       'absent: registered from the points.', [0.0, 0.0, 0.03]),
    _K('reflector.axis', '[x, y, z]', '', '[0, 0, 1]', 'Reflector axis in the tip frame '
       '(the incidence is measured from it).', [0.0, 0.0, 1.0]),
    _K('reflector.max_incidence', 'number', 'rad', '0.5236 (30°)', 'Largest angle between '
       'the reflector axis and the line of sight, in (0, π/2].', 0.5236),
    _K('reflectors', 'list', '', NONE, 'Several reflectors or markers per pose, instead of '
       '`reflector.offset`; the first is the KPI point.', [{'name': 'm1'}]),
    _K('reflectors[].name', 'string', '', REQUIRED, 'Unique name of letters, digits and _; '
       "in parameter names (`reflector.<name>.x`) and frame ids (`<tracker>#<name>`).", 'm1'),
    _K('reflectors[].offset', '[x, y, z]', 'm', NONE, 'Centre in the tip frame; absent: '
       'registered from the points.', [0.05, 0.0, 0.03]),
    _K('reflectors[].orientation', '{rpy: [r, p, y]} or {quaternion: [x, y, z, w]}, '
       '`identify: true` in either, or identify', 'rad',
       NONE, 'A tracked 6-DoF body: its axes in the tip frame (URDF rpy, or a unit '
       'quaternion); measured as PoseStamped; needs `noise.sigma_rotation`. `identify` (or '
       '`identify: true` beside a stated guess): identified as `reflector.<name>.r{x,y,z}`, '
       'the rotation vector after the guess (the identity without one).',
       {'rpy': [0.1, -0.2, 0.3]}),
    # ------------------------------------------------------------------ noise
    _K('noise', 'mapping', '', REQUIRED, 'Measurement noise of the tracker.', {'sigma': 2e-5}),
    _K('noise.sigma', 'number or [x, y, z]', 'm', REQUIRED, 'Tracker σ per axis, in '
       '(0, 0.01]; sets the weights, the χ² test and the stated precision.', 2.0e-5),
    _K('noise.sigma_rotation', 'number', 'rad', NONE, 'Orientation noise per axis of tracked '
       'bodies, in (0, 0.1]; required with a reflector `orientation`.', 1.0e-4),
    _K('noise.joint_sigma', 'number or mapping of joint name to number', 'rad (m for '
       'prismatic joints)', NONE, 'Joint-reading noise (a controller read-back): one σ for '
       'every joint or per joint by name, joints left out read exactly; each point then has '
       'the covariance σ²I + J_q Σ_q J_qᵀ. With mimic joints, of the actuated joints (the '
       'drive too): a mimic joint\'s reading follows its leader\'s.', 5.2e-4),
    # ---------------------------------------------------------------- payload
    _K('payload', 'mapping', '', '{}', 'Payload on the tip, for the gravity torques of the '
       'torque-driven effects.', {'mass': 5.0}),
    _K('payload.mass', 'number', 'kg', '0', 'Payload mass, ≥ 0.', 5.0),
    _K('payload.com', '[x, y, z]', 'm', '[0, 0, 0]', 'Payload centre of mass in the tip '
       'frame.', [0.0, 0.0, 0.05]),
    _K('payload.limit', 'number', 'kg', 'the mass of the robot\'s moving links in the URDF',
       'The most the robot carries (its rated payload): a measured row\'s `payload.mass`, '
       'the cell\'s `payload.mass` or a working pose\'s payload beyond it is refused as a '
       'unit slip (grams written as kg) or a fault of the '
       'controller\'s report. No serial arm carries more than its own moving links weigh '
       '(payload to arm mass: 0.2-0.5 for cobots, below for industrial arms).', 10.0),
    # ---------------------------------------------------------- working poses
    _K('working_poses', 'list', 'rad (m for prismatic joints)', NONE, 'The poses where '
       'the robot works: the KPI is the TCP covariance there. Each item is a mapping or a '
       'list of joint values in chain order. Required by `design` and the campaign; '
       '`identify` reports no TCP without them.', [[0.0, 0.45, -0.35, 0.0, 0.9, 0.0]]),
    _K('working_poses[].name', 'string', '', 'work_<i>', 'Name in outputs and '
       '`design.weights`.', 'car_roof_edge'),
    _K('working_poses[].joints', 'mapping of joint name to number', 'rad (m)', REQUIRED,
       'Joint values by name.', {'joint_1': 0.0, 'joint_2': 0.45, 'joint_3': -0.35,
                                 'joint_4': 0.0, 'joint_5': 0.9, 'joint_6': 0.0}),
    _K('working_poses[].payload', 'mapping', '', 'the cell\'s `payload`', 'The load the robot '
       'carries at this pose: its TCP is predicted with the gravity torques of this payload '
       '(torque-driven effects such as `joint_compliance`).', {'mass': 2.5}),
    _K('working_poses[].payload.mass', 'number', 'kg', REQUIRED, 'Payload mass at this pose, '
       '0 to 5000.', 2.5),
    _K('working_poses[].payload.com', '[x, y, z]', 'm', 'the cell\'s `payload.com`', 'Its centre '
       'of mass in the tip frame.', [0.0, 0.0, 0.08]),
    # -------------------------------------------------------------- obstacles
    _K('obstacles', 'list', '', '[]', 'Obstacles in the robot base frame, kept clear by the '
       'design (and the tracker beam).', [{'name': 'floor', 'type': 'halfspace',
                                          'normal': [0, 0, 1], 'offset': -0.6}]),
    _K('obstacles[].name', 'string', '', REQUIRED, 'Name in reports and `ignore_pairs`.',
       'floor'),
    _K('obstacles[].type', '`capsule` or `halfspace`', '', 'capsule', 'Shape of the '
       'obstacle.', 'halfspace'),
    _K('obstacles[].normal', '[x, y, z]', '', REQUIRED + ' (halfspace)', 'Outward normal of '
       'a half-space obstacle: the free side.', [0.0, 0.0, 1.0]),
    _K('obstacles[].offset', 'number', 'm', '0', 'Half-space boundary: the points x with '
       'normal·x = offset.', -0.6),
    _K('obstacles[].a', '[x, y, z]', 'm', REQUIRED + ' (capsule)', 'First end of the capsule '
       'axis.', [1.75, -2.0, -0.15]),
    _K('obstacles[].b', '[x, y, z]', 'm', REQUIRED + ' (capsule)', 'Second end of the capsule '
       'axis.', [1.75, 2.0, -0.15]),
    _K('obstacles[].radius', 'number', 'm', REQUIRED + ' (capsule)', 'Capsule radius, ≥ 0.',
       0.45),
    # -------------------------------------------------------------- collision
    _K('collision', 'mapping', '', '{}', 'Robot collision geometry and pairs to skip.',
       {'beam_radius': 0.005}),
    _K('collision.capsules', 'list', '', '[] (fitted to the URDF)', 'Hand-given capsules of '
       'chain links; links without them get capsules fitted to their collision geometry.',
       [{'name': 'upper_arm', 'link': 'link_2', 'a': [0, 0, 0], 'b': [0.6, 0, 0],
         'radius': 0.12}]),
    _K('collision.capsules[].name', 'string', '', 'the link name', 'Name in reports and '
       '`ignore_pairs`.', 'upper_arm'),
    _K('collision.capsules[].link', 'string', '', 'base', 'Link whose frame holds the '
       'capsule.', 'link_2'),
    _K('collision.capsules[].a', '[x, y, z]', 'm', REQUIRED, 'First end of the axis in the '
       'link frame.', [0.0, 0.0, 0.0]),
    _K('collision.capsules[].b', '[x, y, z]', 'm', REQUIRED, 'Second end of the axis in the '
       'link frame.', [0.6, 0.0, 0.0]),
    _K('collision.capsules[].radius', 'number', 'm', REQUIRED, 'Capsule radius, ≥ 0.', 0.12),
    _K('collision.ignore_pairs', 'list of [name, name]', '', '[]', 'Pairs of links, capsules '
       'or obstacles never checked (added to the computed collision matrix).',
       [['base_link', 'mounting']]),
    _K('collision.beam_radius', 'number', 'm', '0.005', 'Radius of the tracker beam kept '
       'clear of obstacles (all the way to the reflector\'s centre, half-spaces included: '
       'the reflector outside every obstacle, the tracker on the free side of every '
       'half-space) and of the links (but the last 5 cm, next to the tool carrying the '
       'reflector), ≥ 0.', 0.005),
    # --------------------------------------------------------- identification
    _K('identification', 'mapping', '', '{}', 'How the robot is identified.',
       {'method': 'pivoted'}),
    _K('identification.method', '`pivoted` or `priority`', '', 'pivoted', 'Selection of the '
       'identifiable parameters: QR with column pivoting, or preferring the names in '
       '`priority`.', 'pivoted'),
    _K('identification.priority', 'list of parameter names', '', '[]', 'Parameters '
       '`method: priority` prefers (e.g. joint offsets over base angles).', []),
    _K('identification.model', '`auto`, `registration`, `joint_offsets` or `geometric`', '',
       'geometric', 'Model size (CLI `--model`); `auto` chooses by the predicted '
       'out-of-sample error and adds the effects the data show.', 'auto'),
    _K('identification.loss', '`linear`, `huber` or `soft_l1`', '', 'linear', 'Robust loss '
       '(IRLS) of the identification.', 'huber'),
    _K('identification.outliers', 'mapping', '', '{exclude: true}', 'Outlier exclusion.',
       {'exclude': True}),
    _K('identification.outliers.exclude', 'boolean', '', 'true', 'Exclude outliers (false: '
       'report them only).', False),
    _K('identification.outliers.threshold', 'number or null', 'robust σ', 'null (Bonferroni '
       'bound √χ²₃(1 − 0.01/N))', 'Distance beyond which a point is an outlier, > 1.', 5.0),
    _K('identification.outliers.max_fraction', 'number', '', '0.05', 'Largest fraction of '
       'the points excluded as faults no replicate confirms; more are a model misfit, kept '
       'in the fit, in [0, 1).', 0.1),
    _K('identification.cv_folds', 'integer', '', '5', 'Folds of the cross-validated rms '
       "reported beside `auto`'s choice, ≥ 2.", 5),
    _K('identification.max_iterations', 'integer or null', '', 'null', 'Iteration limit of '
       'every fit (trust-region Gauss-Newton), ≥ 1; null: 100 per identified parameter '
       "(SciPy's max_nfev); `identify --max-iterations` overrides it.", 200),
    _K('identification.prior', 'mapping or null', '', 'null', 'Nominal tolerances: one std '
       'around the URDF for every joint placement and offset (a Gaussian prior).',
       {'translation': 1e-3, 'rotation': 1e-3, 'offset': 1e-3}),
    _K('identification.prior.translation', 'number', 'm', REQUIRED + ' (with prior)',
       'Std of each joint placement translation.', 1.0e-3),
    _K('identification.prior.rotation', 'number', 'rad', REQUIRED + ' (with prior)',
       'Std of each joint placement rotation.', 5.0e-3),
    _K('identification.prior.offset', 'number', 'rad (m for prismatic joints)',
       REQUIRED + ' (with prior)', 'Std of each joint zero offset.', 5.0e-2),
    _K('identification.tolerances', 'mapping', '', '{}', 'How far an identified quantity may '
       'be from what the cell states before the calibration is refused as not plausible '
       '(a std above it: undetermined). A nominal arm is off by mm and 0.1°; centimetres and '
       'degrees are a wrong model, not a calibration.', {'translation': 0.05}),
    _K('identification.tolerances.base_translation', 'number', 'm', '0.1', 'Base position in '
       'the tracker frame, from `tracker.base_in_tracker` or its registration.', 0.1),
    _K('identification.tolerances.base_rotation', 'number', 'rad', '0.1', 'Base orientation '
       'in the tracker frame, as `base_translation`.', 0.1),
    _K('identification.tolerances.reflector_offset', 'number', 'm', '0.02', 'Reflector offset '
       'from `reflector.offset` (a stated offset is a prior with this tolerance, held when the '
       'placement is registered); an offset left out must be observed by the poses (the '
       'tool turned).', 0.02),
    _K('identification.tolerances.translation', 'number', 'm', '0.05', 'Every joint placement '
       'translation (link origin) correction.', 0.05),
    _K('identification.tolerances.rotation', 'number', 'rad', '0.05', 'Every joint placement '
       'rotation correction (0.05 rad ≈ 3°).', 0.05),
    _K('identification.tolerances.offset', 'number', 'rad (m for prismatic joints)', '0.2',
       'Every joint zero offset correction: homing or mastering leaves degrees, not more '
       'than ~11°.', 0.2),
    _K('identification.bounds', 'mapping of effect (`kind`, `kind:joint` or spec) to a number '
       'or a list, one per parameter', "the effect's units", "{} (the library's plausible "
       'sizes)', 'Largest |value| of an effect parameter before the calibration is refused; '
       'widen it for an arm that is softer or looser than an industrial one: servo-stiff or '
       'cable-driven joints yield to their position servo, 1/kp ≈ 1e-3 rad/(N m) '
       '(`joint_compliance` default 2e-4, harmonic drives 1e4–1e5 N m/rad); gear cyclic '
       'errors are a few mrad (default 5e-3).', {'joint_compliance:joint_2': 2.0e-3}),
    # ---------------------------------------------------------------- effects
    _K('effects', 'list of effect specs', '', '[]', 'Physical effects in the model, '
       '`effect:joint` (see the effect library); code effects need the opt-in.',
       ['joint_compliance:joint_2']),
    # ------------------------------------------------------------- simulation
    _K('simulation', 'mapping', '', '{}', 'What `kpi-calib simulate` and `campaign '
       '--simulate` put into the simulated true robot.', {'hidden_effects': {}}),
    _K('simulation.hidden_effects', 'mapping of effect spec to its parameters', '', '{}',
       'Effects the true robot has and the model may lack.',
       {'joint_compliance:joint_2': {'c': 4.0e-7}}),
    # ----------------------------------------------------------------- design
    _K('design', 'mapping', '', '{}', 'Options of the measurement design.',
       {'candidates': 1500}),
    _K('design.candidates', 'integer', '', '4000', 'Size of the random feasible candidate '
       'set of the exchange algorithm.', 1500),
    _K('design.weights', 'mapping of working pose name to number', '', '{} (equal)',
       'Weight of each working pose in the KPI criterion, ≥ 0.', {'car_roof_edge': 2.0}),
    _K('design.collision', 'boolean', '', 'true', 'Impose the capsule constraints (false: '
       'joint limits and incidence only).', True),
    _K('design.clearance', 'number', 'm', '0.002', 'Margin the optimiser keeps from every '
       'capsule pair; verification uses 0.', 0.002),
    _K('design.incidence_clearance', 'number', 'rad', '0.002', 'Margin the optimiser keeps '
       'below `reflector.max_incidence`; verification uses 0.', 0.002),
    _K('design.nlp', 'boolean', '', 'true', 'Refine the exchange design with IPOPT.', False),
    _K('design.exchange_starts', 'integer', '', '1', 'Random restarts of the exchange '
       'algorithm; the best is kept.', 3),
    _K('design.max_iterations', 'integer', '', '300', 'IPOPT iteration limit.', 150),
    _K('design.ignore_flagged', 'boolean', '', 'false', 'Drop collision pairs violated in '
       'nearly every measurable pose (reported) instead of failing.', True),
    _K('design.flag_threshold', 'number', '', '0.98', 'Fraction of measurable random poses '
       'above which a pair is flagged, in [0, 1].', 0.9),
    # ----------------------------------------------------------------- topics
    _K('topics', 'mapping', '', '{}', 'Topics of a bag (`--joint-topic`, `--point-topic`, '
       '`--pose-topic` override them).', {'point': '/tracker/point'}),
    _K('topics.joint_states', 'string', '', '/joint_states', 'sensor_msgs/JointState topic.',
       '/arm/joint_states'),
    _K('topics.point', 'string', '', '/laser_tracker/point', 'geometry_msgs/PointStamped '
       'topic of the tracker points.', '/tracker/point'),
    _K('topics.pose', 'string', '', '/laser_tracker/pose', 'geometry_msgs/PoseStamped topic '
       'of tracked 6-DoF bodies.', '/tracker/pose'),
    # ------------------------------------------------------------ temperature
    _K('temperature', 'mapping', '', NONE, 'Temperature of the arm, read with the joint states '
       'and paired to every point by time; absent: no temperature read and no thermal '
       'effect screened.', {'sensors': ['upper_arm']}),
    _K('temperature.topic', 'string', '', '/cell/temperature', 'sensor_msgs/Temperature topic '
       '(°C; `kpi-calib import-csv` writes a table\'s temperature column there).',
       '/arm/temperature'),
    _K('temperature.sensors', '[frame id, …] or {frame id: [joint, …]}', '', '[] (every sensor)',
       'Header frame ids of the sensors whose mean is the arm\'s temperature (the covariate '
       '`delta_temperature`); every sensor is kept as `temperature.<frame_id>` and, when named '
       'here, its ΔT as `delta_temperature.<frame_id>`. As a mapping, each sensor lists the '
       'joints (URDF names) whose thermal effects read its ΔT: `thermal_link_growth:J` and '
       '`thermal_growth` grow the link before J, `thermal_zero_drift:J` drifts J\'s zero; a '
       'joint under one sensor at most, a list never empty; joints not listed read the mean.',
       {'upper_arm': ['joint_3'], 'forearm': ['joint_4', 'joint_5']}),
    _K('temperature.reference', 'number', '°C', '20.0', 'Temperature the geometry is stated '
       'at (ISO 1: 20 °C); thermal effects act on ΔT = temperature − reference.', 21.5),
    _K('temperature.max_gap', 'number', 's', '120.0', 'Largest gap between temperature samples '
       '(and beyond the first/last) bridged by interpolation; a point outside is refused.',
       300.0),
    _K('temperature.valid_range', '[low, high]', '°C', '[-50.0, 150.0]', 'Plausible readings: '
       'one outside (or not finite) is a fault of the sensor or its driver, never used '
       '(counted and warned; the node does not log it); low at or above absolute zero '
       '(-273.15), high at most 1000, low < high.', [0.0, 60.0]),
    # ----------------------------------------------------------------- inputs
    _K('inputs', 'mapping', '', '{}', 'Measured inputs beyond temperature (a tilt, a payload '
       'mass, any recorded quantity), each a covariate paired to every point by time; the '
       'named-values topic is read whenever a recording has it.', {'max_gap': 5.0}),
    _K('inputs.topic', 'string', '', '/kpi_calib/inputs', 'Named values '
       '(sensor_msgs/JointState: name = covariate, position = value, SI) that `import-csv` '
       'writes from a table\'s covariates and the node logs.', '/cell/inputs'),
    _K('inputs.max_gap', 'number', 's', '10.0', 'Largest gap between readings of an input (and '
       'beyond the first/last) bridged by interpolation; a point outside is refused. A payload '
       '(`payload.*`) is held from a reading to the next, whatever the gap.', 2.0),
    _K('inputs.expect', 'list of covariate names', '', '[]', 'Inputs the named-values topic '
       'must give every point: one that never arrives stops the identification naming the '
       'input, the topic and the fix; a point without one is refused.', ['payload.mass']),
    _K('inputs.sources', 'list', '', '[]', 'Other topics whose fields are inputs, each '
       '{topic, type, fields}.', [{'topic': '/column_tilt',
                                   'type': 'geometry_msgs/msg/Vector3Stamped',
                                   'fields': {'tilt.column.x': 'vector.x'}}]),
    _K('inputs.sources[].topic', 'string', '', REQUIRED, 'The topic (absolute name).',
       '/column_tilt'),
    _K('inputs.sources[].type', 'string', '', REQUIRED, 'Its ROS message type, a stamped one '
       '(with a header): pkg/msg/Type.', 'geometry_msgs/msg/Vector3Stamped'),
    _K('inputs.sources[].fields', 'mapping of covariate name to field path', '', REQUIRED,
       'Each input and where it is in the message: attributes joined by `.`, an element as '
       '`[i]` or `[name]` (of the message\'s `name` list). Tilts `tilt.<sensor>.x/.y` in rad '
       'feed `measured_tilt`; `payload.mass` (kg) and `payload.com.x/.y/.z` (m) the rows\' '
       'gravity torques.', {'tilt.column.x': 'vector.x', 'tilt.column.y': 'vector.y'}),
    # ------------------------------------------------------------- compliance
    _K('compliance', 'mapping', '', '{}', 'Which torques the torque-driven effects read.',
       {'torque_source': 'model'}),
    _K('compliance.torque_source', '`model` or `measured`', '', 'model', '`model`: the gravity '
       'torques of the URDF with each row\'s payload; `measured`: the joint states\' effort '
       '(every chain joint named, one finite effort each), paired to every point by time as '
       '`effort.<joint>` (N m).', 'measured'),
)


def cell_key(path: str) -> CellKey:
    """The description of ``path``; KeyError naming the path when there is none."""
    for key in CELL_KEYS:
        if key.path == path:
            return key
    raise KeyError(f'{path!r} is not a cell key; see kpi_calib_ros.io.cell_schema.CELL_KEYS')
