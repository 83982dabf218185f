"""Cell file validation in io/cell.py: sections, working poses and overrides; the cell
model (app/cell_model.py) built from it."""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import yaml

from kpi_calib_ros.app.cell_model import build_cell_model
from kpi_calib_ros.core.collision.capsules import Capsule, HalfSpace
from kpi_calib_ros.core.design.optimum import DesignSettings
from kpi_calib_ros.core.errors import ConfigError
from kpi_calib_ros.io.cell import DEFAULT_CELL, cell_from_dict, load_cell, with_overrides
from kpi_calib_ros.io.cell_sections import (
    CapsuleSpec,
    HalfSpaceSpec,
    WorkingPose,
    working_poses_from_arrays,
)
from kpi_calib_ros.io.cell_settings import DESIGN_KEYS, simulation_settings


def _doc() -> dict:
    return yaml.safe_load(DEFAULT_CELL.read_text())


def test_design_and_simulation_sections_are_typed():
    doc = _doc()
    doc['design'] = {'candidates': 123, 'weights': {'car_roof_edge': 2}}
    doc['simulation'] = {'hidden_effects': {'joint_compliance:joint_2': {'c': 4e-7}}}
    cell = cell_from_dict(doc, DEFAULT_CELL.parent)
    assert cell.design == {'candidates': 123, 'weights': {'car_roof_edge': 2.0}}
    assert build_cell_model(cell).design_settings == DesignSettings(
        candidates=123, weights={'car_roof_edge': 2.0})
    assert cell.simulation.hidden_effects == {'joint_compliance:joint_2': {'c': 4e-7}}
    assert load_cell(DEFAULT_CELL).simulation.hidden_effects == {}


def test_the_design_keys_the_file_reads_are_the_design_settings():
    """io checks ``design:`` against its own key table; the table is DesignSettings' fields
    with the kind of each default, so every checked section builds a DesignSettings."""
    defaults = DesignSettings()
    assert DESIGN_KEYS == {f.name: type(getattr(defaults, f.name))
                           for f in dataclasses.fields(DesignSettings)}


def test_obstacles_are_read_as_written_and_built_as_collision_objects():
    """The file's shapes stay as written in the Cell (plain data); the cell model builds
    the collision objects from them: a half-space normalised, a capsule in the base frame,
    robot capsules in their link frames."""
    doc = _doc()
    doc['obstacles'] = [
        {'name': 'floor', 'type': 'halfspace', 'normal': [0, 0, 2], 'offset': -1.2},
        {'name': 'box', 'a': [1, 0, 0], 'b': [1, 1, 0], 'radius': 0.2}]
    doc['collision'] = {'capsules': [{'link': 'link_3', 'a': [0, 0, 0], 'b': [0.5, 0, 0],
                                      'radius': 0.1}]}
    cell = cell_from_dict(doc, DEFAULT_CELL.parent)
    assert cell.obstacles == (HalfSpaceSpec('floor', (0.0, 0.0, 2.0), -1.2),
                              CapsuleSpec('box', 'base', (1.0, 0.0, 0.0), (1.0, 1.0, 0.0), 0.2))
    assert cell.robot_capsules == (
        CapsuleSpec('link_3', 'link_3', (0.0, 0.0, 0.0), (0.5, 0.0, 0.0), 0.1),)
    cm = build_cell_model(cell)
    assert cm.obstacles == (HalfSpace('floor', (0, 0, 1), -0.6),
                            Capsule('box', 'base', (1, 0, 0), (1, 1, 0), 0.2))
    assert cm.robot_capsules == (Capsule('link_3', 'link_3', (0, 0, 0), (0.5, 0, 0), 0.1),)
    scene = cm.collision_scene()
    assert scene.obstacles == list(cm.obstacles)
    assert scene.robot_capsules[0] == cm.robot_capsules[0]


@pytest.mark.parametrize('section, key', [
    ({'design': {'candidates': 0}}, 'design.candidates'),
    ({'design': {'colision': False}}, 'design.colision'),
    ({'simulation': [1, 2]}, 'simulation'),
    ({'simulation': {'hiden_effects': {}}}, 'simulation.hiden_effects'),
    ({'simulation': {'hidden_effects': ['joint_compliance:joint_2']}},
     'simulation.hidden_effects'),
])
def test_bad_sections_name_the_key(section, key):
    doc = _doc()
    doc.update(section)
    with pytest.raises(ConfigError) as info:
        cell_from_dict(doc, DEFAULT_CELL.parent)
    assert info.value.key == key


def test_simulation_section_may_be_absent():
    assert simulation_settings(None).hidden_effects == {}


def test_flat_working_poses_become_named_poses():
    poses = working_poses_from_arrays(['a', 'b'], [0.1, 0.2, 0.3, 0.4])
    assert poses == (WorkingPose('work_1', {'a': 0.1, 'b': 0.2}),
                     WorkingPose('work_2', {'a': 0.3, 'b': 0.4}))


@pytest.mark.parametrize('names, values, key', [
    ([], [0.0], 'working_joint_names'),
    (['a', 'a'], [0.0, 0.0], 'working_joint_names'),
    (['a', 'b'], [0.0, 0.0, 0.0], 'working_poses'),
    (['a', 'b'], [0.0, float('nan')], 'working_poses[1]'),
])
def test_flat_working_poses_are_validated(names, values, key):
    with pytest.raises(ConfigError) as info:
        working_poses_from_arrays(names, values)
    assert info.value.key == key


def test_overrides_replace_urdf_and_working_poses():
    cell = load_cell(DEFAULT_CELL, urdf_xml='')
    with pytest.raises(ConfigError, match='robot.urdf'):
        build_cell_model(cell)
    urdf = load_cell(DEFAULT_CELL).urdf_xml
    q = [0.1, -0.2, 0.3, 0.0, 0.5, -0.1]
    names = [f'joint_{i}' for i in range(1, 7)]
    poses = working_poses_from_arrays(names, q)
    cm = build_cell_model(with_overrides(cell, urdf_xml=urdf, working_poses=poses))
    assert cm.cell.urdf_path == '<robot_description>'
    np.testing.assert_array_equal(cm.q_work, [q])
    assert cm.working_pose_names == ('work_1',)
    # Joint names are checked against the robot when the model is built.
    wrong = working_poses_from_arrays(['a'] + names[1:], q)
    with pytest.raises(ConfigError, match='working_poses'):
        build_cell_model(with_overrides(cell, urdf_xml=urdf, working_poses=wrong))


def _set(doc: dict, dotted: str, value) -> dict:
    node = doc
    *path, last = dotted.split('.')
    for key in path:
        node = node.setdefault(key, {})
    node[last] = value
    return doc


# Every numeric key of a cell file, given a word: the error names exactly that key.
NUMERIC_KEYS = ['collision.beam_radius', 'reflector.max_incidence', 'payload.mass',
                'noise.sigma', 'design.candidates', 'design.flag_threshold']


@pytest.mark.parametrize('key', NUMERIC_KEYS)
def test_a_word_where_a_number_belongs_names_the_key(key):
    with pytest.raises(ConfigError) as info:
        cell_from_dict(_set(_doc(), key, 'wide'), DEFAULT_CELL.parent)
    assert info.value.key == key
    assert 'wide' in str(info.value)


@pytest.mark.parametrize('item, key', [
    ({'name': 'box', 'type': 'capsule', 'a': [0, 0, 0], 'b': [1, 0, 0], 'radius': 'wide'},
     'obstacles[0].radius'),
    ({'name': 'floor', 'type': 'halfspace', 'normal': [0, 0, 1], 'offset': 'low'},
     'obstacles[0].offset'),
    ({'name': 'box', 'type': 'capsule', 'a': [0, 0, 'x'], 'b': [1, 0, 0], 'radius': 0.1},
     'obstacles[0].a'),
])
def test_numbers_inside_lists_name_their_item(item, key):
    doc = _doc()
    doc['obstacles'] = [item]
    with pytest.raises(ConfigError) as info:
        cell_from_dict(doc, DEFAULT_CELL.parent)
    assert info.value.key == key


@pytest.mark.parametrize('key, value', [
    ('tracker.base_in_tracker', [2654.4, 272.8, -200.0, 0.0, 0.0, 1.9]),   # millimetres
    ('tracker.base_in_tracker', [2.6544, 0.2728, -0.2, 0.0, 0.0, 108.9]),  # degrees
    ('reflector.offset', [0, 0, 30]),                                       # millimetres
])
def test_values_in_other_units_are_caught_at_load_with_a_units_hint(key, value):
    with pytest.raises(ConfigError) as info:
        cell_from_dict(_set(_doc(), key, value), DEFAULT_CELL.parent)
    assert info.value.key == key
    assert 'SI metres' in str(info.value) or 'radians' in str(info.value)


def test_the_largest_plausible_values_still_load():
    doc = _set(_doc(), 'tracker.base_in_tracker', [30.0, -20.0, 5.0, 3.1, -1.5, 6.2])
    cell = cell_from_dict(_set(doc, 'reflector.offset', [0.0, 0.5, 1.2]), DEFAULT_CELL.parent)
    assert cell.reflector_offset.tolist() == [0.0, 0.5, 1.2]


def test_bag_topics_come_from_the_cell_or_their_defaults():
    assert (load_cell(DEFAULT_CELL).joint_topic, load_cell(DEFAULT_CELL).point_topic) == (
        '/joint_states', '/laser_tracker/point')
    doc = _set(_doc(), 'topics', {'joint_states': '/arm/joint_states'})
    cell = cell_from_dict(doc, DEFAULT_CELL.parent)
    assert (cell.joint_topic, cell.point_topic) == ('/arm/joint_states', '/laser_tracker/point')
    for topics, key in (({'joints': '/x'}, 'topics.joints'), ({'point': 'a b'}, 'topics.point'),
                        ({'point': '/joint_states'}, 'topics.point')):
        with pytest.raises(ConfigError) as info:
            cell_from_dict(_set(_doc(), 'topics', topics), DEFAULT_CELL.parent)
        assert info.value.key == key


def test_identification_priority_names_are_checked_against_the_model():
    doc = _set(_doc(), 'identification', {'method': 'priority',
                                          'priority': ['joint_1.offset', 'joint_1.ofset']})
    with pytest.raises(ConfigError) as info:
        build_cell_model(cell_from_dict(doc, DEFAULT_CELL.parent))
    assert info.value.key == 'identification.priority'
    assert "['joint_1.ofset']" in str(info.value) and "'joint_1.offset'" in str(info.value)
    doc = _set(_doc(), 'identification', {'priority': ['joint_1.offset']})  # method pivoted
    with pytest.raises(ConfigError, match='only with method: priority'):
        cell_from_dict(doc, DEFAULT_CELL.parent)


def test_a_priority_of_joint_parameters_holds_at_every_model_level():
    """``method: priority`` naming joint offsets: every level fits, the smaller ones (the
    registration, which moves the placement alone) with those names held. Before, any
    joint name was refused as unknown there (exit 2, naming base.* and reflector.* as the
    valid ones) and priority could not be used at all."""
    from kpi_calib_ros.app.identify import calibrate_cell
    from kpi_calib_ros.core.simulation import (
        random_configurations,
        simulate_measurements,
        true_parameters,
    )
    doc = _set(_doc(), 'identification', {'method': 'priority',
                                          'priority': ['joint_1.offset', 'joint_2.offset']})
    cm = build_cell_model(cell_from_dict(doc, DEFAULT_CELL.parent))
    rng = np.random.default_rng(2)
    q = random_configurations(cm.model, cm.model.params.nominal, 40, rng)
    data = simulate_measurements(cm.model, true_parameters(cm.model.params, rng), q,
                                 cm.cell.sigma, rng)
    for level in ('registration', 'auto', 'geometric'):
        cal = calibrate_cell(cm, data, model=level)
        assert cal.result.converged, level
    assert {'joint_1.offset', 'joint_2.offset'} <= set(cal.result.estimated)


@pytest.mark.parametrize('key, value', [
    ('payload.com', [0, 0, 80]),                       # millimetres
    ('payload.mass', 12000.0),                         # grams
    ('working_poses.0.payload', {'mass': 5.0, 'com': [0, 0, 80]}),
])
def test_payload_values_in_other_units_are_caught_at_load(key, value):
    doc = _doc()
    if key.startswith('working_poses'):
        doc['working_poses'][0]['payload'] = value
        key = 'working_poses[0].payload.com'
    else:
        doc = _set(doc, key, value)
    with pytest.raises(ConfigError) as info:
        cell_from_dict(doc, DEFAULT_CELL.parent)
    assert info.value.key == key
    assert 'SI' in str(info.value)


@pytest.mark.parametrize('path, key, named', [
    (('payload',), 'cog', 'payload.cog'),
    (('robot',), 'joint_couplng', 'robot.joint_couplng'),
    (('tracker',), 'frame', 'tracker.frame'),
    (('reflector',), 'max_incidense', 'reflector.max_incidense'),
    (('noise',), 'sigma_joint', 'noise.sigma_joint'),
    (('collision',), 'beamradius', 'collision.beamradius'),
    (('obstacles', 0), 'ofset', 'obstacles[0].ofset'),
])
def test_a_misspelled_key_is_refused_not_ignored(path, key, named):
    """Before, each of these loaded with the key's default in place of the stated value."""
    doc = _doc()
    target = doc
    for step in path:
        target = target.setdefault(step, {}) if isinstance(target, dict) else target[step]
    target[key] = 1.0
    with pytest.raises(ConfigError, match='unknown key') as info:
        cell_from_dict(doc, DEFAULT_CELL.parent)
    assert info.value.key == named


def test_an_obstacle_takes_only_its_own_shapes_keys():
    """A capsule with an ``offset`` or a ``frame`` (obstacles are in the base frame) would
    be built without it; a half-space with a capsule's radius likewise."""
    capsule = {'name': 'pillar', 'type': 'capsule', 'a': [1.0, 0, 0], 'b': [1.0, 0, 1.0],
               'radius': 0.1}
    for extra, named in (({'offset': 0.2}, 'obstacles[0].offset'),
                         ({'frame': 'link_3'}, 'obstacles[0].frame')):
        doc = _doc()
        doc['obstacles'] = [{**capsule, **extra}]
        with pytest.raises(ConfigError) as info:
            cell_from_dict(doc, DEFAULT_CELL.parent)
        assert info.value.key == named
    doc = _doc()
    doc['obstacles'] = [{'name': 'floor', 'type': 'halfspace', 'normal': [0, 0, 1],
                         'radius': 0.3}]
    with pytest.raises(ConfigError) as info:
        cell_from_dict(doc, DEFAULT_CELL.parent)
    assert info.value.key == 'obstacles[0].radius'


@pytest.mark.parametrize('key, value, field', [
    ('payload.mass', 500.0, 'payload.mass'),
    ('working_poses.0.payload', {'mass': 500.0}, 'working_poses[0].payload'),
])
def test_a_payload_beyond_what_the_arm_carries_is_refused_at_load(key, value, field):
    """A cell payload (or a working pose's) beyond the arm's rating, or without one the mass of
    its moving links, is refused as a row's is: 500 kg on a Baxter arm was accepted."""
    def cell(limit=None):
        doc = _doc()
        if key.startswith('working_poses'):
            doc['working_poses'][0]['payload'] = value
        else:
            doc = _set(doc, key, value)
        if limit is not None:
            doc = _set(doc, 'payload.limit', limit)
        return cell_from_dict(doc, DEFAULT_CELL.parent)
    with pytest.raises(ConfigError) as caught:
        build_cell_model(cell())
    assert caught.value.key == field and 'payload.limit' in str(caught.value)
    build_cell_model(cell(600.0))  # its rating stated
