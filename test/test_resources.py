"""package:// and file:// resolution: package_dirs, ROS_PACKAGE_PATH, ament index, cmeel."""
from pathlib import Path

import pytest

from kpi_calib_ros.core.errors import ConfigError
from kpi_calib_ros.io.resources import (
    cmeel_prefixes,
    find_package,
    mesh_uris,
    resolve_mesh_uris,
    resolve_uri,
)

UR10 = 'package://example-robot-data/robots/ur_description/urdf/ur10_robot.urdf'


@pytest.fixture
def no_ros_env(monkeypatch):
    monkeypatch.delenv('AMENT_PREFIX_PATH', raising=False)
    monkeypatch.delenv('ROS_PACKAGE_PATH', raising=False)


def _package(root: Path, name: str, folder: str | None = None) -> Path:
    pkg = root / (folder or name)
    (pkg / 'meshes').mkdir(parents=True)
    (pkg / 'package.xml').write_text(f'<package format="3"><name>{name}</name></package>')
    (pkg / 'meshes' / 'link.stl').write_text('solid x\nendsolid x\n')
    return pkg


def test_pip_installed_example_robot_data_resolves_with_no_configuration(no_ros_env):
    path = resolve_uri(UR10)
    assert path.is_file() and path.parts[-4:] == ('robots', 'ur_description', 'urdf',
                                                  'ur10_robot.urdf')
    # Found through the cmeel prefix's ament index marker, not through a guess.
    prefix = path.parents[5]
    assert prefix in cmeel_prefixes()
    assert (prefix / 'share/ament_index/resource_index/packages/example-robot-data').is_file()


def test_every_collision_mesh_of_the_stock_urdf_becomes_an_existing_absolute_path(no_ros_env):
    resolved = resolve_mesh_uris(resolve_uri(UR10).read_text())
    collision = [u for u in mesh_uris(resolved) if '/collision/' in u]
    assert len(collision) == 7
    assert all(Path(u).is_absolute() and Path(u).is_file() for u in collision)
    # Visual meshes are left alone: a computation on collisions never needs them.
    assert any(u.startswith('package://') for u in mesh_uris(resolved))


def test_package_dirs_win_over_the_environment_and_accept_the_package_or_its_parent(
        tmp_path, monkeypatch):
    first = _package(tmp_path / 'a', 'my_robot_description', folder='checkout')
    second = _package(tmp_path / 'b', 'my_robot_description')
    monkeypatch.setenv('ROS_PACKAGE_PATH', str(tmp_path / 'b'))
    uri = 'package://my_robot_description/meshes/link.stl'
    assert resolve_uri(uri) == (second / 'meshes/link.stl').resolve()
    # The package directory itself, named differently but declared by package.xml.
    assert resolve_uri(uri, [first]) == (first / 'meshes/link.stl').resolve()
    assert resolve_uri(uri, [tmp_path / 'a']) == resolve_uri(uri)  # parent has no such folder
    # Relative entries are relative to base_dir (the cell file's folder), not the cwd.
    assert resolve_uri(uri, ['a/checkout'], base_dir=tmp_path) == (first / 'meshes/link.stl'
                                                                   ).resolve()


def test_ament_prefix_path_is_read_through_the_index(tmp_path, monkeypatch):
    prefix = tmp_path / 'install'
    share = _package(prefix / 'share', 'cell_description')
    marker = prefix / 'share/ament_index/resource_index/packages/cell_description'
    marker.parent.mkdir(parents=True)
    marker.write_text('')
    monkeypatch.setenv('AMENT_PREFIX_PATH', str(prefix))
    monkeypatch.delenv('ROS_PACKAGE_PATH', raising=False)
    assert find_package('cell_description')[0].resolve() == share.resolve()


def test_file_uris_and_relative_paths(tmp_path):
    mesh = _package(tmp_path, 'p') / 'meshes/link.stl'
    assert resolve_uri(f'file://{mesh}') == mesh.resolve()
    assert resolve_uri('p/meshes/link.stl', base_dir=tmp_path) == mesh.resolve()


def test_missing_package_or_file_names_the_uri_the_file_and_every_path_tried(
        tmp_path, no_ros_env, monkeypatch):
    monkeypatch.setenv('ROS_PACKAGE_PATH', str(tmp_path / 'ros'))
    with pytest.raises(ConfigError) as err:
        resolve_uri('package://nowhere/arm.stl', [tmp_path / 'extra'], referenced_by='cell.urdf')
    text = str(err.value)
    assert text.startswith('robot.package_dirs:')
    for expected in ('package://nowhere/arm.stl', 'cell.urdf', str(tmp_path / 'extra'),
                     str(tmp_path / 'extra' / 'nowhere'), str(tmp_path / 'ros' / 'nowhere'),
                     'resource_index/packages/nowhere'):
        assert expected in text
    with pytest.raises(ConfigError, match='no file .*missing.stl'):
        resolve_uri('package://example-robot-data/missing.stl')
    with pytest.raises(ConfigError, match='no file'):
        resolve_uri(f'file://{tmp_path}/none.stl')
