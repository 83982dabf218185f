"""The settings sections of a cell file: ``identification:``, ``design:``,
``simulation:`` and ``topics:``, each validated with the key path in every error."""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Mapping

from kpi_calib_ros.core.diagnosis.model_selection import DEFAULT_FOLDS, MODEL_CHOICES
from kpi_calib_ros.core.effects.registry import (
    ARGUMENT_EFFECTS,
    CHAIN_EFFECTS,
    BoundEffect,
    available_effects,
    parse_effect_spec,
)
from kpi_calib_ros.core.errors import ConfigError
from kpi_calib_ros.core.estimation.least_squares import (
    DEFAULT_MAX_ITERATIONS,
    ITERATIONS_PER_PARAMETER,
)
from kpi_calib_ros.core.estimation.plausibility import Tolerances
from kpi_calib_ros.core.estimation.robust import LOSSES, OutlierSettings
from kpi_calib_ros.core.model.robot import RobotModel
from kpi_calib_ros.io.cell_values import non_negative, number, text_number_hint
from kpi_calib_ros.io.names import DEFAULT_JOINT_TOPIC, DEFAULT_POINT_TOPIC, DEFAULT_POSE_TOPIC

_TOPIC_KEYS = {'joint_states': DEFAULT_JOINT_TOPIC, 'point': DEFAULT_POINT_TOPIC,
               'pose': DEFAULT_POSE_TOPIC}


@dataclass(frozen=True)
class SimulationSettings:
    """The ``simulation:`` section: what the simulated robot has beyond the model.

    ``hidden_effects`` maps effect specs to their true parameter values; it is
    checked against the robot by :func:`hidden_effects`.
    """

    hidden_effects: Mapping[str, Any] = field(default_factory=dict)


@dataclass(frozen=True)
class IdentificationSettings:
    """The model size, loss and outlier keys of ``identification:``.

    model : ``auto`` (chosen by the predicted out-of-sample error) or a level of
    :mod:`kpi_calib_ros.core.diagnosis.model_selection`; loss : ``linear``, ``huber`` or ``soft_l1``
    (:mod:`kpi_calib_ros.core.estimation.robust`); outliers : exclusion settings; cv_folds : folds
    of the cross-validated rms reported beside the model choice; prior : std (m, rad, rad)
    of the joint placement translations, rotations and joint offsets around the nominal
    (:func:`kpi_calib_ros.core.estimation.prior.tolerance_prior`), None: no prior; max_iterations :
    iteration limit of every fit (:func:`kpi_calib_ros.core.estimation.least_squares.identify`),
    None: 100 per identified parameter; tolerances : how far identified quantities may be from
    the cell's and the bounds of effect parameters
    (:class:`kpi_calib_ros.core.estimation.plausibility.Tolerances`).
    """

    model: str = 'geometric'
    loss: str = 'linear'
    outliers: OutlierSettings = field(default_factory=OutlierSettings)
    cv_folds: int = DEFAULT_FOLDS
    prior: tuple[float, float, float] | None = None
    max_iterations: int | None = DEFAULT_MAX_ITERATIONS
    # identification.tolerances and identification.bounds: the plausibility gate
    # (core.estimation.plausibility).
    tolerances: Tolerances = field(default_factory=Tolerances)


# The keys of ``design:`` and the kind of value each takes: the fields of
# core.design.optimum.DesignSettings, which the cell model builds from them.
DESIGN_KEYS: dict[str, type] = {
    'candidates': int, 'weights': dict, 'collision': bool, 'clearance': float,
    'incidence_clearance': float, 'nlp': bool, 'exchange_starts': int, 'max_iterations': int,
    'ignore_flagged': bool, 'flag_threshold': float}


def design_settings(raw: Mapping[str, Any] | None) -> dict[str, Any]:
    """Validate the ``design:`` mapping of a cell file; errors name the key. Returns the
    given keys with their checked values (the rest take DesignSettings' defaults)."""
    raw = dict(raw or {})
    known = set(DESIGN_KEYS)
    for key in raw:
        if key not in known:
            raise ConfigError(f'design.{key}', f'unknown key; allowed: {sorted(known)}')
    values: dict[str, Any] = {}
    for key, value in raw.items():
        kind = DESIGN_KEYS[key]
        path = f'design.{key}'
        if key == 'weights':
            if not isinstance(value, Mapping) or not all(
                    isinstance(v, (int, float)) and v >= 0 for v in value.values()):
                raise ConfigError(path, 'must map working pose names to weights >= 0')
            values[key] = {str(k): float(v) for k, v in value.items()}
        elif kind is bool:
            if not isinstance(value, bool):
                raise ConfigError(path, f'must be true or false, got {value!r}')
            values[key] = value
        elif kind is int:
            if not isinstance(value, int) or isinstance(value, bool) or value < 1:
                raise ConfigError(path, f'must be a positive integer, got {value!r}')
            values[key] = value
        else:
            values[key] = non_negative(number(raw, key, 'design'), path, '')
    if values.get('flag_threshold', 0.5) > 1:
        raise ConfigError('design.flag_threshold', 'must be a fraction in [0, 1]')
    return values


_IDENT_KEYS = {'method', 'priority', 'model', 'loss', 'outliers', 'cv_folds', 'prior',
               'max_iterations', 'tolerances', 'bounds'}

PRIOR_KEYS = ('translation', 'rotation', 'offset')
# identification.tolerances: the fields of core.estimation.plausibility.Tolerances but its
# bounds (identification.bounds).
TOLERANCE_KEYS = ('base_translation', 'base_rotation', 'reflector_offset', 'translation',
                  'rotation', 'offset')


def identification_settings(raw: Mapping[str, Any]) -> IdentificationSettings:
    """Validate the model-size, loss and outlier keys of ``identification:``."""
    unknown = set(raw) - _IDENT_KEYS
    if unknown:
        raise ConfigError(f'identification.{sorted(unknown)[0]}',
                          f'unknown key; allowed: {sorted(_IDENT_KEYS)}')
    model = raw.get('model', 'geometric')
    if model not in MODEL_CHOICES:
        raise ConfigError('identification.model', f'must be one of {list(MODEL_CHOICES)}, '
                          f'got {model!r}')
    loss = raw.get('loss', 'linear')
    if loss not in LOSSES:
        raise ConfigError('identification.loss', f'must be one of {list(LOSSES)}, got {loss!r}')
    folds = raw.get('cv_folds', DEFAULT_FOLDS)
    if isinstance(folds, bool) or not isinstance(folds, int) or folds < 2:
        raise ConfigError('identification.cv_folds', f'must be an integer >= 2, got {folds!r}')
    out = raw.get('outliers') or {}
    if not isinstance(out, dict):
        raise ConfigError('identification.outliers', 'must be a mapping {exclude: true, '
                          'threshold: null}')
    bad = set(out) - {'exclude', 'threshold', 'max_fraction'}
    if bad:
        raise ConfigError(f'identification.outliers.{sorted(bad)[0]}', 'unknown key; allowed: '
                          "['exclude', 'max_fraction', 'threshold']")
    exclude = out.get('exclude', True)
    if not isinstance(exclude, bool):
        raise ConfigError('identification.outliers.exclude', f'must be true or false, got '
                          f'{exclude!r}')
    threshold = out.get('threshold')
    if threshold is not None and (isinstance(threshold, bool) or
                                  not isinstance(threshold, (int, float)) or threshold <= 1):
        raise ConfigError('identification.outliers.threshold', 'must be a distance in units of '
                          f'the robust σ greater than 1 (e.g. 5.0), or null; got {threshold!r}')
    fraction = out.get('max_fraction', OutlierSettings().max_fraction)
    if isinstance(fraction, bool) or not isinstance(fraction, (int, float)) or \
            not 0 <= fraction < 1:
        raise ConfigError('identification.outliers.max_fraction', f'must be in [0, 1), got '
                          f'{fraction!r}')
    limit = raw.get('max_iterations', DEFAULT_MAX_ITERATIONS)
    if limit is not None and (isinstance(limit, bool) or not isinstance(limit, int)
                              or limit < 1):
        raise ConfigError('identification.max_iterations', 'must be a positive integer (the '
                          'iteration limit of every fit) or null (the default: '
                          f'{ITERATIONS_PER_PARAMETER} per identified parameter), got '
                          f'{limit!r}')
    return IdentificationSettings(model, loss, OutlierSettings(
        exclude, None if threshold is None else float(threshold), float(fraction)), folds,
        _tolerance_prior(raw.get('prior')), limit,
        _tolerances(raw.get('tolerances'), raw.get('bounds')))


def _positive(value: Any, key: str, unit: str, example: str) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) \
            or not 0 < value < float('inf'):
        raise ConfigError(key, f'must be a positive number in {unit} (e.g. {example})'
                          f'{text_number_hint(value)}; got {value!r}')
    return float(value)


def _tolerances(raw: Any, bounds: Any) -> Tolerances:
    """``identification.tolerances`` ({base_translation, base_rotation, reflector_offset,
    translation, rotation}: m or rad, each optional) and ``identification.bounds`` (effect spec,
    ``kind:joint`` or kind -> a bound or a list of one per parameter); joints are checked
    against the chain when the cell model is built."""
    raw = {} if raw is None else raw
    if not isinstance(raw, dict):
        raise ConfigError('identification.tolerances', 'must be a mapping, e.g. '
                          '{translation: 0.05, rotation: 0.05, reflector_offset: 0.02}')
    unknown = set(raw) - set(TOLERANCE_KEYS)
    if unknown:
        raise ConfigError(f'identification.tolerances.{sorted(unknown)[0]}',
                          f'unknown key; allowed: {list(TOLERANCE_KEYS)}')
    values = {k: _positive(v, f'identification.tolerances.{k}',
                           'm' if k.endswith(('translation', 'reflector_offset')) else 'rad',
                           '0.05')
              for k, v in raw.items()}
    bounds = {} if bounds is None else bounds
    if not isinstance(bounds, dict):
        raise ConfigError('identification.bounds', 'must map effects to bounds, e.g. '
                          '{joint_compliance:joint_2: 2.0e-3}')
    known = available_effects()
    every = set(known) | set(CHAIN_EFFECTS) | set(ARGUMENT_EFFECTS)
    parsed: dict[str, tuple[float, ...]] = {}
    for spec, value in bounds.items():
        key = f'identification.bounds.{spec}'
        kind = str(spec).split(':')[0]
        if kind not in every:
            raise ConfigError(key, f'unknown effect {kind!r}; write kind or kind:joint with a '
                              f'kind of {sorted(every)}')
        items = value if isinstance(value, list) else [value]
        n = len(known[kind].parameters) if kind in known else None
        if not items or (n is not None and len(items) not in (1, n)):
            raise ConfigError(key, f'give one bound (every parameter) or {n}, one per '
                              f'parameter {list(known[kind].parameters)}')
        parsed[str(spec)] = tuple(_positive(v, key, 'the effect\'s units', '2.0e-3')
                                  for v in items)
    return Tolerances(**values, bounds=parsed)


def _tolerance_prior(raw: Any) -> tuple[float, float, float] | None:
    """``identification.prior``: {translation, rotation, offset} std (m, rad), or null."""
    if raw is None:
        return None
    fix = ('a mapping {translation: 1.0e-3, rotation: 1.0e-3, offset: 1.0e-3} of the '
           'tolerance std (m, rad, rad) of the joint placements and offsets, or null')
    if not isinstance(raw, dict):
        raise ConfigError('identification.prior', f'must be {fix}; got {raw!r}')
    bad = set(raw) ^ set(PRIOR_KEYS)
    if bad:
        raise ConfigError(f'identification.prior.{sorted(bad)[0]}',
                          f'unknown or missing key: give exactly {list(PRIOR_KEYS)}')
    values = []
    for key in PRIOR_KEYS:
        v = raw[key]
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not 0 < v < float('inf'):
            raise ConfigError(f'identification.prior.{key}', 'must be a positive std in m '
                              f'or rad (e.g. 1.0e-3){text_number_hint(v)}; got {v!r}')
        values.append(float(v))
    return values[0], values[1], values[2]


def simulation_settings(raw: Any) -> SimulationSettings:
    """Validate the ``simulation:`` mapping of a cell file."""
    if raw is None:
        return SimulationSettings()
    if not isinstance(raw, dict):
        raise ConfigError('simulation', 'must be a mapping, e.g. {hidden_effects: '
                          '{joint_compliance:joint_2: {c: 5.0e-7}}}')
    unknown = set(raw) - {'hidden_effects'}
    if unknown:
        raise ConfigError(f'simulation.{sorted(unknown)[0]}', "unknown key; allowed: "
                          "['hidden_effects']")
    hidden = raw.get('hidden_effects') or {}
    if not isinstance(hidden, dict):
        raise ConfigError('simulation.hidden_effects', 'must map effect specs to their '
                          'parameters, e.g. {joint_compliance:joint_2: {c: 5.0e-7}}')
    return SimulationSettings(dict(hidden))


def parse_topics(raw: Any) -> dict[str, str]:
    """The ``topics:`` section: which topics of a bag carry the joint states, the
    tracker points and the tracked 6-DoF poses (``--joint-topic`` / ``--point-topic`` /
    ``--pose-topic`` override it)."""
    if raw is None:
        raw = {}
    if not isinstance(raw, dict):
        raise ConfigError('topics', f'must be a mapping with keys {sorted(_TOPIC_KEYS)}')
    unknown = set(raw) - set(_TOPIC_KEYS)
    if unknown:
        raise ConfigError(f'topics.{sorted(unknown)[0]}', f'unknown key; allowed: '
                          f'{sorted(_TOPIC_KEYS)}')
    names = {}
    for key, default in _TOPIC_KEYS.items():
        value = raw.get(key, default)
        if not isinstance(value, str) or not value.strip() or ' ' in value:
            raise ConfigError(f'topics.{key}', f'must be a topic name such as {default!r}, '
                              f'got {value!r}')
        names[key] = value
    keys = list(names)
    for i, key in enumerate(keys):
        same = [k for k in keys[:i] if names[k] == names[key]]
        if same:
            raise ConfigError(f'topics.{key}', f'must differ from topics.{same[0]}')
    return {'joint_topic': names['joint_states'], 'point_topic': names['point'],
            'pose_topic': names['pose']}


def parse_priority(ident: dict, method: str) -> tuple[str, ...]:
    """``identification.priority``: parameter names, used only by ``method: priority``
    (their existence is checked against the model in
    :func:`~kpi_calib_ros.app.cell_model.build_cell_model`)."""
    raw = ident.get('priority')
    if raw is None:
        return ()
    if not isinstance(raw, list) or not all(isinstance(n, str) for n in raw):
        raise ConfigError('identification.priority', 'must be a list of parameter names, e.g. '
                          '[joint_1.offset, joint_2.offset]')
    if method != 'priority':
        raise ConfigError('identification.priority', "is used only with method: priority; "
                          'set it or remove the list')
    return tuple(raw)


# ----------------------------------------------------------------- simulation
def hidden_effects(doc: Any, robot: RobotModel, key: str = 'simulation.hidden_effects',
                   base_dir: str | Path | None = None, allow_code: bool = False,
                   temperatures: Mapping[str, str] | None = None
                   ) -> tuple[tuple[BoundEffect, ...], dict[str, float]]:
    """Effects the simulated "true" robot has and the model lacks.

    ``doc`` maps specs to parameter values, as in a cell file::

        simulation:
          hidden_effects:
            joint_compliance:joint_2: {c: 8.0e-7}
            tracker_scale: {s: 5.0e-6}

    A parameter left out takes the effect's typical size. ``temperatures``: the temperature
    each joint's thermal effects read (the cell model's ``joint_temperatures``, see
    :func:`~kpi_calib_ros.core.effects.registry.bind_effect`).

    Returns
    -------
    effects : tuple of BoundEffect
    overrides : dict
        Parameter name -> true value, for :func:`~kpi_calib_ros.core.simulation.true_parameters`.
    """
    if not doc:
        return (), {}
    if not isinstance(doc, dict):
        raise ConfigError(key, 'must be a mapping {effect:joint: {parameter: value}}')
    effects, overrides = [], {}
    for spec, values in doc.items():
        effect = parse_effect_spec(str(spec), robot, f'{key}.{spec}', base_dir, allow_code,
                                   temperatures)
        values = values or {}
        if not isinstance(values, dict):
            raise ConfigError(f'{key}.{spec}',
                              f'must map parameters {list(effect.kind.parameters)} to values')
        unknown = set(values) - set(effect.kind.parameters)
        if unknown:
            raise ConfigError(f'{key}.{spec}.{sorted(unknown)[0]}', 'unknown parameter; '
                              f'{effect.kind.name} has {list(effect.kind.parameters)}')
        for suffix, name, typical in zip(effect.kind.parameters, effect.parameter_names,
                                         effect.typical):
            value = values.get(suffix, typical)
            if not isinstance(value, (int, float)) or isinstance(value, bool):
                raise ConfigError(f'{key}.{spec}.{suffix}', f'must be a number, got {value!r}')
            overrides[name] = float(value)
        effects.append(effect)
    return tuple(effects), overrides
