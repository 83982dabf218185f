"""Design with stock mesh URDFs (UR10 and Panda from example-robot-data): no capsules and
no ignore_pairs in the cell; the design fits capsules to the meshes, computes the collision
matrix, is verified on the meshes and gives the KPI of a design with hand-tuned capsules."""
from __future__ import annotations

from pathlib import Path

import pytest
import yaml

from kpi_calib_ros.app.cell_model import build_cell_model
from kpi_calib_ros.app.design import run_design
from kpi_calib_ros.io.cell import load_cell

DATA = Path(__file__).resolve().parent / 'data'
N = 24


def test_hand_given_capsules_win_over_fitted_ones_link_by_link():
    cell = load_cell(DATA / 'ur10_hand_cell.yaml')
    cm = build_cell_model(cell)
    assert cm.robot_geometry().fitted_links == ()
    from dataclasses import replace
    partial = build_cell_model(replace(cell, robot_capsules=cell.robot_capsules[2:3]))
    geometry = partial.robot_geometry()
    given = [c for c in geometry.capsules if c.frame == 'upper_arm_link']
    assert given == [cm.robot_capsules[2]]
    assert set(geometry.fitted_links) == set(cm.robot.link_names) - {'upper_arm_link'}
    sources = {c['link']: c['source'] for c in geometry.summary()['capsules']}
    assert sources['upper_arm_link'] == 'cell' and sources['forearm_link'] == 'fitted'


@pytest.mark.slow
@pytest.mark.parametrize('robot', ['ur10', 'panda'])
def test_stock_mesh_urdf_design_is_mesh_collision_free_and_as_good_as_hand_capsules(
        robot, tmp_path, capsys):
    rc = run_design(DATA / f'{robot}_mesh_cell.yaml', N, 'kpi', tmp_path / 'mesh.yaml')
    out = capsys.readouterr().out
    assert rc == 0, out
    mesh = yaml.safe_load((tmp_path / 'mesh.yaml').read_text())
    geometry = mesh['geometry']
    check = geometry['mesh_check']
    assert check['run'] and check['configurations'] == N and check['in_collision'] == 0
    assert mesh['verification']['ok'] and check['pairs_checked'] > 10
    assert all(c['source'] == 'fitted' for c in geometry['capsules'])
    classes = {p['class'] for p in geometry['skipped_pairs']}
    assert 'adjacent' in classes and classes <= {'adjacent', 'default', 'always', 'fixed'}
    # Every skipped pair is listed on stdout with its class.
    for pair in geometry['skipped_pairs']:
        assert f"{pair['links'][0]} ~ {pair['links'][1]}: {pair['class']}" in out
    assert f'mesh check: 0/{N} configurations in mesh collision' in out

    # Hand capsules need not enclose the meshes: its mesh check is reported, not required.
    run_design(DATA / f'{robot}_hand_cell.yaml', N, 'kpi', tmp_path / 'hand.yaml')
    hand_out = capsys.readouterr().out
    hand = yaml.safe_load((tmp_path / 'hand.yaml').read_text())
    # The hand-given capsules cover the chain links; links they carry (a hand, fingers)
    # are fitted in both cells.
    chain = build_cell_model(load_cell(DATA / f'{robot}_hand_cell.yaml')).robot.link_names
    assert all(c['source'] == 'cell' for c in hand['geometry']['capsules'] if c['name'] in chain)
    assert sum(c['source'] == 'cell' for c in hand['geometry']['capsules']) == len(chain)
    ratio = mesh['objective'] / hand['objective']
    print(f"{robot}: KPI trace fitted capsules {mesh['objective']:.4e} m^2, hand-tuned "
          f"{hand['objective']:.4e} m^2, ratio {ratio:.3f}; mesh collisions "
          f"{check['in_collision']}/{N} (fitted), {hand['geometry']['mesh_check']['in_collision']}"
          f'/{N} (hand)')
    print(hand_out[hand_out.find('verification'):][:1500])
    assert abs(ratio - 1.0) <= 0.10


def test_configurations_in_mesh_collision_are_violations_and_the_design_is_not_ok():
    """Random UR10 poses (some self-colliding): each pair the mesh check finds is a
    violation line and the design is not ok; collision-free poses leave it ok."""
    import numpy as np

    from kpi_calib_ros.app.design import mesh_verified
    from kpi_calib_ros.app.robot_geometry import mesh_check
    from kpi_calib_ros.core.design.constraints import DesignVerification
    from kpi_calib_ros.core.design.optimum import DesignResult

    cm = build_cell_model(load_cell(DATA / 'ur10_mesh_cell.yaml'))
    lower, upper = np.maximum(cm.robot.lower, -np.pi), np.minimum(cm.robot.upper, np.pi)
    q = np.random.default_rng(3).uniform(lower, upper, size=(120, 6))
    check, _ = mesh_check(cm.robot_geometry(), cm.robot, q)
    bad, good = check.colliding, [k for k in range(len(q)) if k not in check.colliding]
    assert bad and good

    def result(configurations):
        n = len(configurations)
        return DesignResult(configurations, tuple(cm.joint_names), 'kpi', 1.0, {}, np.zeros(0),
                            np.zeros(0), (), (), np.zeros(n), np.zeros(n), 1,
                            DesignVerification(True, (), np.zeros(n), np.zeros(n), 1), {},
                            'ok', {}, n, 1.0)

    checked, doc = mesh_verified(cm, result(q[bad[:3] + good[:3]]))
    assert not checked.verification.ok and doc['mesh_check']['in_collision'] == 3
    assert all(line.startswith(('configuration 0:', 'configuration 1:', 'configuration 2:'))
               and 'mesh collision' in line for line in checked.verification.violations)
    assert '3/6 configurations in mesh collision' in checked.status
    clean, doc = mesh_verified(cm, result(q[good[:5]]))
    assert clean.verification.ok and doc['mesh_check']['in_collision'] == 0
