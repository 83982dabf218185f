"""Real cells: package:// robot descriptions, chain-order working poses, optional placement
(registered from the data before identification), geometry needed by design only."""
from __future__ import annotations

import copy
from pathlib import Path

import numpy as np
import pytest
import yaml

from kpi_calib_ros.app.cell_model import build_cell_model
from kpi_calib_ros.app.identify import identify_cell, run_identify
from kpi_calib_ros.app.placement import REGISTER_ABOVE_M, registered_start
from kpi_calib_ros.core.acquisition.streams import synthesize_streams
from kpi_calib_ros.core.errors import ConfigError, DataError
from kpi_calib_ros.core.simulation import (
    random_configurations,
    simulate_measurements,
    true_parameters,
)
from kpi_calib_ros.io.bag import write_bag
from kpi_calib_ros.io.cell import DEFAULT_CELL, cell_from_dict, read_cell_document

DATA = DEFAULT_CELL.parent  # relative paths of the default cell resolve here
SIGMA = 2.0e-5
BASE_KEYS = ('x', 'y', 'z', 'roll', 'pitch', 'yaw')


def _doc() -> dict:
    return copy.deepcopy(read_cell_document(DEFAULT_CELL))


def _model(doc: dict):
    return build_cell_model(cell_from_dict(doc, DATA))


# ------------------------------------------------------------------ cell keys
def test_working_poses_in_chain_order_equal_the_named_form_and_their_length_is_checked():
    doc = _doc()
    named = _model(doc)
    doc['working_poses'] = [list(row) for row in named.q_work.tolist()]
    plain = _model(doc)
    np.testing.assert_array_equal(plain.q_work, named.q_work)
    assert plain.working_pose_names == tuple(f'work_{i + 1}' for i in range(len(named.q_work)))
    doc['working_poses'] = [[0.0, 0.4, -0.3, 0.0, 0.9]]
    with pytest.raises(ConfigError, match=r'working_poses\[0\].*5 joint values.*6 joints'):
        _model(doc)
    doc['working_poses'] = [[0.0, 0.4, 'x', 0.0, 0.9, 0.0]]
    with pytest.raises(ConfigError, match=r'working_poses\[0\]\[2\]'):
        _model(doc)


def test_robot_urdf_may_be_a_package_uri_and_package_dirs_are_relative_to_the_cell(tmp_path):
    package = tmp_path / 'pkgs' / 'my_robot'
    (package / 'urdf').mkdir(parents=True)
    (package / 'package.xml').write_text('<package><name>my_robot</name></package>')
    (package / 'urdf' / 'arm.urdf').write_text((DATA.parent / 'robots' / 'kr15_class.urdf')
                                               .read_text())
    doc = _doc()
    doc['robot'].update(urdf='package://my_robot/urdf/arm.urdf', package_dirs=['pkgs'])
    cell = cell_from_dict(doc, tmp_path)
    assert cell.package_dirs == ('pkgs',)
    assert cell.urdf_path == str((package / 'urdf' / 'arm.urdf').resolve())
    doc['robot']['package_dirs'] = ['elsewhere']
    with pytest.raises(ConfigError, match="robot.urdf.*my_robot.*tried.*elsewhere") as info:
        cell_from_dict(doc, tmp_path)
    assert info.value.key == 'robot.urdf'
    doc['robot']['package_dirs'] = 'pkgs'
    with pytest.raises(ConfigError, match='robot.package_dirs'):
        cell_from_dict(doc, tmp_path)


def test_placement_keys_are_optional_but_a_design_needs_the_tracker_pose():
    doc = _doc()
    del doc['tracker']['base_in_tracker']
    del doc['reflector']['offset']
    cm = _model(doc)
    assert not cm.cell.base_in_tracker_given and not cm.cell.reflector_offset_given
    with pytest.raises(ConfigError, match='a design needs to know where the tracker') as info:
        cm.design_cell()
    assert info.value.key == 'tracker.base_in_tracker'


# Two-joint arm whose collision meshes exist nowhere.
MISSING_MESH_URDF = (Path(__file__).resolve().parent / 'data' / 'missing_mesh_arm.urdf').read_text()


def test_identification_needs_no_geometry_and_design_names_what_it_could_not_find(tmp_path):
    """Meshes that cannot be found: identification works, design says which files and where."""
    cell = tmp_path / 'cell.yaml'
    (tmp_path / 'arm.urdf').write_text(MISSING_MESH_URDF)
    cell.write_text(yaml.safe_dump({
        'robot': {'urdf': 'arm.urdf', 'base_frame': 'base', 'tip_frame': 'tip',
                  'package_dirs': ['my_pkgs']},
        'tracker': {'base_in_tracker': [2.0, 0.0, 0.0, 0.0, 0.0, 3.0]},
        'reflector': {'offset': [0.0, 0.02, 0.03]}, 'noise': {'sigma': SIGMA},
        'working_poses': [[0.5, 0.3]]}))
    cm = build_cell_model(cell_from_dict(yaml.safe_load(cell.read_text()), tmp_path))
    rng = np.random.default_rng(4)
    q = random_configurations(cm.model, cm.geometric.nominal, 20, rng)
    data = simulate_measurements(cm.model, cm.geometric.nominal, q, SIGMA, rng)
    assert identify_cell(cm, data).converged
    with pytest.raises(ConfigError, match=r'package://no_such_pkg/meshes/base.stl.*arm.urdf.*'
                       r'tried.*my_pkgs') as info:
        cm.design_cell()
    assert info.value.key == 'robot.package_dirs'


# ------------------------------------------------------------------ registration
@pytest.fixture(scope='module')
def campaign():
    """A true robot (geometric errors, reflector off-axis) measured in 40 postures."""
    cm = _model(_doc())
    params = cm.model.params
    rng = np.random.default_rng(21)
    p_true = true_parameters(params, rng)
    refl = [params.index(f'reflector.{c}') for c in 'xyz']
    p_true[refl] = [0.02, -0.01, 0.09]
    q = random_configurations(cm.model, p_true, 40, rng)
    return p_true, simulate_measurements(cm.model, p_true, q, SIGMA, rng)


def _placed(p_true: np.ndarray, base_delta=(0, 0, 0, 0, 0, 0), offset=None, drop=False) -> dict:
    cm = _model(_doc())
    params = cm.model.params
    doc = _doc()
    base = [p_true[params.index(f'base.{c}')] for c in BASE_KEYS]
    doc['tracker']['base_in_tracker'] = [float(b + d) for b, d in zip(base, base_delta)]
    doc['reflector']['offset'] = [float(p_true[params.index(f'reflector.{c}')]) for c in 'xyz'] \
        if offset is None else list(offset)
    if drop:
        del doc['tracker']['base_in_tracker']
        del doc['reflector']['offset']
    return doc


@pytest.mark.parametrize('delta', [(1.0, -0.4, 0.2, 0.0, 0.0, np.pi),
                                   (0.5, 0.5, -0.3, 0.0, 0.0, np.pi / 2), 'missing'])
def test_unknown_placement_is_registered_and_gives_the_true_nominal_result(campaign, delta):
    """Base off by up to 1 m / 180° yaw and reflector unknown (zeros), or both keys left
    out: identification equals the one started at the true placement. Compared where any
    gauge agrees (the identifiable subset may differ with the start): the predicted points
    at the measured and the working poses, the TCP points and their covariance, and rms."""
    p_true, data = campaign
    truth = _model(_placed(p_true))
    assert registered_start(truth, data)[1] is None  # the true nominal needs no registration
    doc = _placed(p_true, drop=True) if delta == 'missing' else _placed(
        p_true, delta, offset=[0.0, 0.0, 0.0])
    off = _model(doc)
    p0, reg = registered_start(off, data)
    assert reg is not None and reg.rms_m < REGISTER_ABOVE_M
    ref, got = identify_cell(truth, data), identify_cell(off, data)
    assert ref.converged and got.converged
    assert len(got.estimated) == len(ref.estimated)
    for q in (data.q, truth.q_work):
        a, b = truth.model.predict(ref.values, q), off.model.predict(got.values, q)
        assert np.max(np.abs(a - b)) < 1e-9 * np.max(np.abs(a))  # 1e-9 relative (points ~1 m)
    np.testing.assert_allclose(got.tcp, ref.tcp, rtol=0, atol=1e-9 * np.abs(ref.tcp).max())
    np.testing.assert_allclose(got.tcp_covariance, ref.tcp_covariance, rtol=0,
                               atol=1e-9 * np.abs(ref.tcp_covariance).max())
    assert got.rms_m == pytest.approx(ref.rms_m, rel=1e-9)


def test_points_the_registered_nominal_still_misses_are_refused_with_the_causes(campaign):
    p_true, data = campaign
    cm = _model(_placed(p_true))
    scaled = type(data)(q=data.q, eta=data.eta * 1000.0, stamps_ns=data.stamps_ns)
    with pytest.raises(DataError, match=r'misses the measured points by .* m rms.*units'):
        identify_cell(cm, scaled)
    shuffled = type(data)(q=data.q[:, ::-1], eta=data.eta, stamps_ns=data.stamps_ns)
    with pytest.raises(DataError, match='joint values in the wrong order'):
        identify_cell(cm, shuffled)


def test_identify_command_reports_the_registered_placement(campaign, tmp_path, capsys):
    p_true, data = campaign
    doc = _placed(p_true, drop=True)
    doc['robot']['urdf'] = str((DATA / doc['robot']['urdf']).resolve())
    cell = tmp_path / 'cell.yaml'
    cell.write_text(yaml.safe_dump(doc))
    cm = _model(doc)
    joints, points = synthesize_streams(data.q, cm.joint_names, data.eta, cm.cell.tracker_frame,
                                        joint_noise_rad=0.0, rng=np.random.default_rng(1))
    bag = write_bag(tmp_path / 'run.mcap', joints, points)
    assert run_identify(cell, bag, tmp_path / 'out') == 0
    out = capsys.readouterr().out
    assert 'placement registered from the points (left out of the cell)' in out
