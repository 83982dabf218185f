"""kpi_calib_node parameters: names, defaults, descriptions and their validation.

Pure functions over plain values (no node needed), so validation is tested with
data and the same code checks start-up values and runtime changes.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

from rcl_interfaces.msg import ParameterDescriptor
from rclpy.exceptions import (
    InvalidParameterTypeException,
    InvalidParameterValueException,
    InvalidTopicNameException,
    ParameterUninitializedException,
)
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.validate_topic_name import validate_topic_name

from kpi_calib_ros.app.validate import REGISTER
from kpi_calib_ros.core.design.optimum import DESIGN_CRITERIA
from kpi_calib_ros.core.errors import ConfigError, DataError
from kpi_calib_ros.core.estimation.drift_state import DriftSwing
from kpi_calib_ros.core.measurement.recordings import NAME_PATTERN
from kpi_calib_ros.io.cell import DEFAULT_CELL
from kpi_calib_ros.io.cell_sections import WorkingPose, working_poses_from_arrays
from kpi_calib_ros.io.names import (
    DEFAULT_JOINT_TOPIC,
    DEFAULT_POINT_TOPIC,
    DEFAULT_POSE_TOPIC,
    ROBOT_DESCRIPTION_TOPIC,
)


@dataclass(frozen=True)
class NodeSettings:
    """Validated node parameters (see :data:`PARAMETERS` for meaning and units)."""

    robot_description: str
    robot_description_topic: str
    cell_file: str
    working_poses: tuple[float, ...]
    working_joint_names: tuple[str, ...]
    num_measurements: int
    criterion: str
    design_seed: int
    joint_states_topic: str
    point_topic: str
    min_measurements: int
    auto_identify: bool
    data_dir: str
    allow_code_effects: bool = False
    pose_topic: str = DEFAULT_POSE_TOPIC
    campaign: str = 'fixed'
    target_tcp_std: float = 1.0e-5
    max_measurements: int = 200
    reidentify_with_prior: bool = True
    drift_velocity: tuple[float, ...] = ()
    validate_register: str = ''
    identify_learned_residual: bool = False
    station: str = ''
    station_reflector_remounted: bool = False


CAMPAIGNS = ('fixed', 'sequential')

# name: (default or parameter type when empty, read only, description)
PARAMETERS: dict[str, tuple[Any, bool, str]] = {
    'robot_description': ('', True, 'URDF document; empty: taken from the latched '
                          'robot_description_topic (as robot_state_publisher provides it)'),
    'robot_description_topic': (ROBOT_DESCRIPTION_TOPIC, True,
                                'latched std_msgs/String topic with the URDF'),
    'cell_file': ('', True, 'cell YAML (tracker, reflector, noise, working poses, obstacles); '
                  'empty: the built-in simulated cell'),
    'working_poses': (Parameter.Type.DOUBLE_ARRAY, True,
                      'working poses overriding the cell file: flat list, one block of '
                      'len(working_joint_names) joint values (rad) per pose'),
    'working_joint_names': (Parameter.Type.STRING_ARRAY, True,
                            'joint order of working_poses'),
    'num_measurements': (30, False, 'number of measurement poses ~/design computes'),
    'criterion': ('kpi', False, f'design criterion, one of {list(DESIGN_CRITERIA)}'),
    'design_seed': (0, False, 'seed of the design random generator'),
    'joint_states_topic': (DEFAULT_JOINT_TOPIC, True, 'sensor_msgs/JointState topic'),
    'point_topic': (DEFAULT_POINT_TOPIC, True, 'geometry_msgs/PointStamped tracker topic'),
    'pose_topic': (DEFAULT_POSE_TOPIC, True, 'geometry_msgs/PoseStamped topic of tracked 6-DoF '
                   "bodies (reflectors with an orientation in the cell)"),
    'min_measurements': (20, False, 'accepted measurements before automatic identification'),
    'auto_identify': (True, False, 'identify when min_measurements is reached, and again '
                      'as more measurements arrive'),
    'data_dir': ('~/.ros/kpi_calib', True, 'measurement log and results (created if missing)'),
    'campaign': ('fixed', False, "'fixed': ~/design publishes num_measurements poses; "
                 "'sequential': ~/design publishes a small initial design, and after every "
                 'accepted measurement the node re-identifies and publishes the updated plan '
                 '(next pose first) until the target is met'),
    'target_tcp_std': (1.0e-5, False, 'sequential campaign: target of the largest per-axis '
                       'TCP std over the working poses (m)'),
    'max_measurements': (200, False, 'sequential campaign: stop after this many '
                         'measurements'),
    'reidentify_with_prior': (True, False, 'identify with the last calibration of an earlier '
                              'cycle (data_dir/calibrations/) as prior, widened by the '
                              'default drift model; a change beyond it is not blended'),
    'drift_velocity': (Parameter.Type.DOUBLE_ARRAY, False,
                       'drift state of re-identifications (as identify --drift-velocity): '
                       '[temperature_K, offset_rad] or [temperature_K, offset_rad, period_h], '
                       'the daily swing of the links\' temperature and of the joint offsets, '
                       'e.g. [5.0, 5.0e-5]; the rates are stored in each calibration for the '
                       'next cycle; empty (default): the random-walk drift model only'),
    'validate_register': ('', False, "~/validate with the tracker (or probe) set up again "
                          "since the calibration: 'base' re-fits the base pose, "
                          "'base+reflector' also the reflector offsets, 'reflector' the offsets "
                          "alone, on the new measurements "
                          "alone (as validate --register); '' (default): none"),
    'identify_learned_residual': (False, False, '~/identify also learns what the physical '
                                  'model leaves as a Gaussian process over joint space (as '
                                  'identify --learned-residual): written as '
                                  'data_dir/learned_residual.yaml, which ~/tcp_query uses, '
                                  'only when it predicts held-out poses better; not with a '
                                  'prior calibration (reidentify_with_prior)'),
    'station': ('', False, 'the tracker station (set-up) the measurements arriving now are '
                'taken from: setting a new name starts a new station (the tracker was moved, '
                'or the robot), each with its own base placement in one identification; '
                "letters, digits, _ or -, starting with a letter; '' (default): the station "
                'of the last measurement log in data_dir (a restart continues it), else '
                'station_1'),
    'station_reflector_remounted': (False, False, 'the probe was remounted for this station: '
                                    'its reflector offsets are identified for it alone; set '
                                    'it with station, before the station\'s first '
                                    'measurement'),
    'allow_code_effects': (False, True, "run the Python code a cell file's effects: name "
                           "('file.py:Type:joint', 'module:Type:joint'); off: only built-in "
                           'and installed (entry point) effects'),
}

# What a value of each declared type is written as on the command line.
_TYPE_WORDS = {Parameter.Type.BOOL: 'true or false', Parameter.Type.INTEGER: 'an integer',
               Parameter.Type.DOUBLE: 'a number', Parameter.Type.STRING: 'a string',
               Parameter.Type.DOUBLE_ARRAY: 'a list of numbers, e.g. [0.0, 1.2]',
               Parameter.Type.STRING_ARRAY: "a list of strings, e.g. ['a', 'b']"}


def parameter_type(name: str) -> Parameter.Type:
    """The declared type of parameter ``name`` (from its default)."""
    default = PARAMETERS[name][0]
    if isinstance(default, Parameter.Type):
        return default
    return Parameter.Type.from_parameter_value(default)


def type_error(name: str, value: Any) -> ConfigError:
    """The error for a parameter given with the wrong type (``-p auto_identify:=maybe``
    arrives as the string 'maybe'), naming the parameter and the type it takes."""
    return ConfigError(name, f'must be {_TYPE_WORDS[parameter_type(name)]}, got {value!r}')


def settings_from_parameters(values: dict[str, Any]) -> NodeSettings:
    """Validate raw parameter values; ConfigError names the parameter and the fix."""
    def text(key: str, allow_empty: bool = False) -> str:
        value = values[key]
        if not isinstance(value, str) or (not allow_empty and not value.strip()):
            raise ConfigError(key, f'must be a non-empty string, got {value!r}')
        return value

    def integer(key: str, minimum: int) -> int:
        value = values[key]
        if isinstance(value, bool) or not isinstance(value, int) or value < minimum:
            raise ConfigError(key, f'must be an integer >= {minimum}, got {value!r}')
        return value

    def topic(key: str) -> str:
        name = text(key)
        try:
            validate_topic_name(name)
        except InvalidTopicNameException as exc:  # its message points at the bad character
            raise ConfigError(key, f'{name!r} is not a valid ROS topic name: '
                              f'{str(exc).splitlines()[0].split(": ", 1)[-1]} '
                              "(e.g. '/joint_states')") from None
        return name

    poses = tuple(float(v) for v in values['working_poses'] or ())
    names = tuple(str(v) for v in values['working_joint_names'] or ())
    if poses or names:
        working_poses_from_arrays(names, poses)  # the cell's validation, keys named as here
    if values['criterion'] not in DESIGN_CRITERIA:
        raise ConfigError('criterion', f'must be one of {list(DESIGN_CRITERIA)}, '
                          f'got {values["criterion"]!r}')
    if values['campaign'] not in CAMPAIGNS:
        raise ConfigError('campaign', f'must be one of {list(CAMPAIGNS)}, '
                          f'got {values["campaign"]!r}')
    target = values['target_tcp_std']
    if isinstance(target, bool) or not isinstance(target, (int, float)) or not (
            0 < float(target) < float('inf')):
        raise ConfigError('target_tcp_std', f'must be a positive length in m (e.g. 1.0e-5), '
                          f'got {target!r}')
    register = values.get('validate_register', '')
    if register not in ('', *REGISTER):
        raise ConfigError('validate_register', f"must be '' or one of {list(REGISTER)}, "
                          f'got {register!r}')
    station = values.get('station', '')
    if station != '' and (not isinstance(station, str) or not NAME_PATTERN.match(station)):
        raise ConfigError('station', f"must be '' or a name that starts with a letter and holds "
                          f"letters, digits, _ or - only (e.g. 'station_2'), got {station!r}")
    for key in ('auto_identify', 'allow_code_effects', 'reidentify_with_prior',
                'identify_learned_residual', 'station_reflector_remounted'):
        if not isinstance(values[key], bool):
            raise ConfigError(key, f'must be true or false, got {values[key]!r}')
    swing: tuple[float, ...] = ()
    if values.get('drift_velocity'):
        try:
            swing = DriftSwing.from_values(values['drift_velocity']).values()
        except (TypeError, ValueError, DataError) as exc:
            raise ConfigError('drift_velocity', 'must be empty or [temperature_K, offset_rad'
                              '(, period_h)] with finite swings >= 0 and a period > 0 h, e.g. '
                              f"[5.0, 5.0e-5], got {values['drift_velocity']!r} ({exc})"
                              ) from None
    topics = {k: topic(k) for k in ('robot_description_topic', 'joint_states_topic',
                                    'point_topic', 'pose_topic')}
    if topics['joint_states_topic'] == topics['point_topic']:
        raise ConfigError('point_topic', 'must differ from joint_states_topic')
    if topics['pose_topic'] in (topics['joint_states_topic'], topics['point_topic']):
        raise ConfigError('pose_topic', 'must differ from joint_states_topic and point_topic')
    cell_file = text('cell_file', allow_empty=True) or str(DEFAULT_CELL)
    if not Path(cell_file).expanduser().is_file():
        raise ConfigError('cell_file', f'file {cell_file!r} does not exist')
    return NodeSettings(
        robot_description=text('robot_description', allow_empty=True),
        cell_file=str(Path(cell_file).expanduser()), working_poses=poses,
        working_joint_names=names, num_measurements=integer('num_measurements', 1),
        criterion=values['criterion'], design_seed=integer('design_seed', 0),
        min_measurements=integer('min_measurements', 1),
        auto_identify=values['auto_identify'], allow_code_effects=values['allow_code_effects'],
        data_dir=str(Path(text('data_dir')).expanduser()), campaign=values['campaign'],
        target_tcp_std=float(target), max_measurements=integer('max_measurements', 1),
        reidentify_with_prior=values['reidentify_with_prior'], drift_velocity=swing,
        validate_register=register,
        identify_learned_residual=values['identify_learned_residual'], station=station,
        station_reflector_remounted=values['station_reflector_remounted'], **topics)


def working_poses(settings: NodeSettings) -> tuple[WorkingPose, ...] | None:
    """The ``working_poses`` parameters as working poses (None: keep the cell file's); their
    joint names and limits are checked when the cell model is built."""
    if not settings.working_poses:
        return None
    return working_poses_from_arrays(settings.working_joint_names, settings.working_poses)



def declare_parameters(node: Node) -> None:
    """Declare every parameter on ``node``; a start-up value of the wrong type (``-p
    auto_identify:=maybe`` arrives as a string) is a ConfigError naming it."""
    for name, (default, read_only, description) in PARAMETERS.items():
        try:
            node.declare_parameter(name, default, ParameterDescriptor(
                description=description, read_only=read_only))
        except (InvalidParameterTypeException, InvalidParameterValueException) as exc:
            given = getattr(node, '_parameter_overrides', {}).get(name)
            raise type_error(name, exc if given is None else given.value) from None


def parameter_values(node: Node, changes: dict[str, Any] | None = None) -> dict[str, Any]:
    """Every parameter's value on ``node`` (an empty array parameter: []), with
    ``changes`` applied."""
    values = {}
    for name in PARAMETERS:
        try:
            values[name] = node.get_parameter(name).value
        except ParameterUninitializedException:  # an array parameter left empty
            values[name] = []
    values.update(changes or {})
    return values

__all__ = ['NodeSettings', 'PARAMETERS', 'declare_parameters', 'parameter_type',
           'parameter_values', 'settings_from_parameters', 'type_error', 'working_poses']
