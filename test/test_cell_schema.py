"""io/cell_schema.py describes exactly the cell keys io/cell.py accepts: in every section
the loader checks for unknown keys, the keys it allows are the keys described; every
described key, set to its example, is accepted; every described key is one the loader
reads; and the stated defaults are the loader's."""
from __future__ import annotations

import copy
import re
from dataclasses import fields
from pathlib import Path
from typing import Any

import pytest

from kpi_calib_ros.core.design.optimum import DesignSettings
from kpi_calib_ros.core.errors import ConfigError
from kpi_calib_ros.io import (
    cell,
    cell_inputs,
    cell_sections,
    cell_settings,
    cell_temperature,
    cell_values,
)
from kpi_calib_ros.io.cell import DEFAULT_CELL, cell_from_dict, read_cell_document
from kpi_calib_ros.io.cell_schema import CELL_KEYS, REQUIRED, cell_key

UNKNOWN = 'zz_not_a_key'
# Sections whose unknown keys the loader refuses, and where to put an unknown key.
STRICT = {'': (), 'identification': ('identification',),
          'identification.outliers': ('identification', 'outliers'),
          'identification.prior': ('identification', 'prior'),
          'identification.tolerances': ('identification', 'tolerances'),
          'simulation': ('simulation',), 'topics': ('topics',), 'design': ('design',),
          'reflectors[]': ('reflectors', 0), 'robot': ('robot',), 'tracker': ('tracker',),
          'reflector': ('reflector',), 'noise': ('noise',), 'payload': ('payload',),
          'collision': ('collision',), 'collision.capsules[]': ('collision', 'capsules', 0),
          'inputs': ('inputs',)}


def _base() -> dict[str, Any]:
    doc = read_cell_document(DEFAULT_CELL)
    doc['robot']['urdf'] = str((DEFAULT_CELL.parent / doc['robot']['urdf']).resolve())
    return doc


def _load(doc: dict[str, Any]) -> None:
    cell_from_dict(doc, DEFAULT_CELL.parent)


def _children(prefix: str) -> set[str]:
    """Leaf names of the described keys directly under ``prefix`` ('' = top level)."""
    out = set()
    for key in CELL_KEYS:
        if not prefix and '.' not in key.path and '[' not in key.path:
            out.add(key.path)
        elif prefix and key.path.startswith(prefix + '.') and \
                '.' not in key.path[len(prefix) + 1:]:
            out.add(key.path[len(prefix) + 1:])
    return out


def _allowed_from_error(exc: ConfigError) -> set[str]:
    message = str(exc)
    listed = re.search(r"\[([^\]]*)\]", message.split('unknown', 1)[-1])
    if listed:
        return set(re.findall(r"'([^']+)'", listed.group(1)))
    return {w.strip() for w in message.split('allowed:', 1)[1].split(',')}


def _section_doc(where: tuple, key: str) -> dict[str, Any]:
    doc = _base()
    if where and where[0] == 'reflectors':
        doc['reflector'].pop('offset', None)
        doc['reflectors'] = [{'name': 'm1'}]
    if where[:2] == ('collision', 'capsules'):
        doc.setdefault('collision', {})['capsules'] = [
            dict(cell_key('collision.capsules').example[0])]
    if where == ('identification', 'prior'):
        doc.setdefault('identification', {})['prior'] = dict(
            cell_key('identification.prior').example)
    target = doc
    for step in where:
        if isinstance(target, dict):
            target = target.setdefault(step, {})
        else:
            target = target[step]
    target[key] = 1
    return doc


@pytest.mark.parametrize('section', sorted(STRICT))
def test_the_keys_a_strict_section_allows_are_the_keys_described(section):
    with pytest.raises(ConfigError) as exc:
        _load(_section_doc(STRICT[section], UNKNOWN))
    assert UNKNOWN in str(exc.value) or 'unknown' in str(exc.value)
    assert _allowed_from_error(exc.value) == _children(section)


def _set(doc: dict[str, Any], path: str, value: Any) -> None:
    parts = path.split('.')
    target: Any = doc
    for i, part in enumerate(parts):
        name, is_item = part.rstrip('[]'), part.endswith('[]')
        last = i == len(parts) - 1
        if is_item:
            items = target.get(name)
            if not isinstance(items, list) or not items or not isinstance(items[0], dict):
                target[name] = copy.deepcopy(cell_key(name if not i else
                                                      '.'.join(parts[:i] + [name])).example)
            target = target[name][0]
        elif last:
            target[name] = copy.deepcopy(value)
        else:
            if not isinstance(target.get(name), dict):
                target[name] = copy.deepcopy(cell_key('.'.join(parts[:i + 1])).example)
            target = target[name]


@pytest.mark.parametrize('key', [k for k in CELL_KEYS if k.path not in ('robot', 'robot.urdf')],
                         ids=lambda k: k.path)
def test_every_described_key_set_to_its_example_is_accepted(key):
    doc = _base()
    if key.path.startswith('reflectors'):
        doc['reflector'].pop('offset', None)
    if key.path == 'reflectors[].orientation':
        doc['noise']['sigma_rotation'] = 1.0e-4
    if key.path in ('obstacles[].a', 'obstacles[].b', 'obstacles[].radius'):
        # a capsule's keys, on a capsule (a half-space refuses them)
        doc['obstacles'] = [{'name': 'pillar', 'type': 'capsule', 'a': [1.75, -2.0, -0.15],
                             'b': [1.75, 2.0, -0.15], 'radius': 0.45}]
    if key.path == 'identification.priority':
        doc.setdefault('identification', {})['method'] = 'priority'
        key_example: Any = ['joint_1.offset']
    else:
        key_example = key.example
    _set(doc, key.path, key_example)
    _load(doc)


def test_an_undescribed_value_in_a_described_key_is_still_refused():
    """The acceptance test above can fail: a wrong value at a described key is refused."""
    doc = _base()
    _set(doc, 'collision.beam_radius', 'wide')
    with pytest.raises(ConfigError, match='collision.beam_radius'):
        _load(doc)


def test_every_described_key_is_read_by_the_loader():
    # io/cell.py and the section readers it delegates to
    source = ''.join(Path(m.__file__).read_text()
                     for m in (cell, cell_sections, cell_settings, cell_values, cell_temperature,
                               cell_inputs))
    design = {f.name for f in fields(DesignSettings)}
    for key in CELL_KEYS:
        leaf = key.path.split('.')[-1].rstrip('[]')
        assert f"'{leaf}'" in source or (key.section == 'design' and leaf in design), \
            f'{key.path}: the cell loader reads no key {leaf!r}'


def test_every_key_has_type_meaning_and_a_default_or_required():
    paths = [k.path for k in CELL_KEYS]
    assert len(paths) == len(set(paths))
    for key in CELL_KEYS:
        assert key.type and key.meaning and key.default, key.path
        parent = key.path.rsplit('.', 1)[0].rstrip('[]') if '.' in key.path else None
        assert parent is None or parent in paths, f'{key.path}: its section is not described'


def test_stated_defaults_are_the_loaders():
    design = DesignSettings()
    for f in fields(DesignSettings):
        if f.name == 'weights':
            continue
        stated = cell_key(f'design.{f.name}').default
        assert stated == str(getattr(design, f.name)).lower(), f.name
    ident = cell_settings.identification_settings({})
    assert cell_key('identification.model').default == ident.model
    assert cell_key('identification.loss').default == ident.loss
    assert cell_key('identification.cv_folds').default == str(ident.cv_folds)
    assert cell_key('identification.outliers.exclude').default == \
        str(ident.outliers.exclude).lower()
    assert cell_key('identification.outliers.max_fraction').default == \
        str(ident.outliers.max_fraction)
    loaded = cell_from_dict(_base(), DEFAULT_CELL.parent)
    for key, attribute in (('joint_states', 'joint_topic'), ('point', 'point_topic'),
                           ('pose', 'pose_topic')):
        doc = _base()
        doc.pop('topics', None)
        assert cell_key(f'topics.{key}').default == getattr(
            cell_from_dict(doc, DEFAULT_CELL.parent), attribute)
    doc = _base()
    for section in ('collision', 'payload'):
        doc.pop(section, None)
    doc['reflector'] = {'offset': doc['reflector']['offset']}
    bare = cell_from_dict(doc, DEFAULT_CELL.parent)
    assert float(cell_key('collision.beam_radius').default) == bare.beam_radius
    assert float(cell_key('payload.mass').default) == bare.payload_mass
    assert float(cell_key('reflector.max_incidence').default.split()[0]) == \
        pytest.approx(bare.max_incidence, abs=1e-4)
    assert cell_key('tracker.frame_id').default == loaded.tracker_frame
    required = {k.path for k in CELL_KEYS if k.default == REQUIRED}
    assert {'robot', 'noise', 'noise.sigma'} <= required
    assert 'working_poses' not in required  # identify needs none; design refuses without
    doc = _base()
    doc.pop('noise')
    with pytest.raises(ConfigError, match='noise'):
        _load(doc)
    doc = _base()
    doc.pop('working_poses')
    assert cell_from_dict(doc, DEFAULT_CELL.parent).working_poses == ()
