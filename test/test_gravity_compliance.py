"""Compliance without link masses: the mass-free gravity_compliance effect recovers the
gravity deflection of a robot whose URDF carries no <inertial>; the missing masses are
warned; the regressor is the gravity torque of the real masses."""
from __future__ import annotations

import re
import warnings

import numpy as np
import pytest
import yaml

from kpi_calib_ros.app.cell_model import build_cell_model
from kpi_calib_ros.app.identify import identify_cell
from kpi_calib_ros.app.simulate import truth_cell_model
from kpi_calib_ros.core.effects.gravity_compliance import (
    compliance_warnings,
    massless_links,
    torque_regressor,
)
from kpi_calib_ros.core.model.robot import Payload, RobotModel
from kpi_calib_ros.core.simulation import (
    random_configurations,
    simulate_measurements,
    true_parameters,
)
from kpi_calib_ros.io.cell import DEFAULT_CELL, load_cell

SIGMA = 2.0e-5
FLOOR = SIGMA * np.sqrt(3)
# The true robot complies physically (c = -1/k, k = 1e6 and 5e5 N m/rad).
HIDDEN = {'joint_compliance:joint_2': {'c': -1.0e-6}, 'joint_compliance:joint_3': {'c': -2.0e-6}}


def _cell(tmp_path, strip: bool, effects=(), hidden=None):
    doc = yaml.safe_load(DEFAULT_CELL.read_text())
    urdf = (DEFAULT_CELL.parent / doc['robot']['urdf']).resolve()
    text = urdf.read_text()
    if strip:  # a stock industrial URDF: no <inertial>
        text = re.sub(r'\s*<inertial>.*?</inertial>', '', text, flags=re.S)
    path = tmp_path / ('stripped.urdf' if strip else 'massive.urdf')
    path.write_text(text)
    doc['robot']['urdf'] = str(path)
    doc['noise'] = {'sigma': SIGMA}
    doc['effects'] = list(effects)
    if hidden:
        doc['simulation'] = {'hidden_effects': hidden}
    out = tmp_path / f'cell_{strip}_{len(effects)}.yaml'
    out.write_text(yaml.safe_dump(doc))
    return load_cell(out)


def test_regressor_reproduces_the_gravity_torque_of_the_true_masses():
    """τ_j(q) = Y_j(q) π with π the URDF's masses and first moments (plus the payload)."""
    cell = load_cell(DEFAULT_CELL)
    robot = RobotModel(cell.urdf_xml, cell.base_frame, cell.tip_frame, Payload(0.0))
    import pinocchio as pin
    ids = robot._pin_joint_ids
    pi = []
    for jid in ids:
        inertia = robot.pin_model.inertias[jid]
        pi += [inertia.mass, *(inertia.mass * np.asarray(inertia.lever))]
    q = np.random.default_rng(0).uniform(-1, 1, (5, robot.n_joints))
    tau = robot.gravity_torques(q)
    for j in range(1, robot.n_joints):
        y = torque_regressor(robot, j)
        pred = [float(np.array(y(row)).ravel() @ np.array(pi[4 * j:])) for row in q]
        np.testing.assert_allclose(pred, tau[:, j], rtol=1e-9, atol=1e-9)
    assert pin is not None


def test_missing_masses_are_warned(tmp_path):
    with pytest.warns(UserWarning, match='no mass'):
        cm = build_cell_model(_cell(tmp_path, True, effects=['joint_compliance:joint_2']))
    assert massless_links(cm.robot) == cm.robot.link_names[1:-1]  # the payload weighs on link_6
    with warnings.catch_warnings():
        warnings.simplefilter('error')
        build_cell_model(_cell(tmp_path, True, effects=['gravity_compliance:joint_2']))
        build_cell_model(_cell(tmp_path, False, effects=['joint_compliance:joint_2']))


def test_compliance_sign_and_range_are_checked():
    names = ['joint_compliance.joint_2.c'] * 4
    notes = compliance_warnings(names, [-1e-6, 1e-6, -1e-2, -1e-6], [1e-8, 1e-8, 1e-8, 1e-5])
    assert len(notes) == 2
    assert '> 0' in notes[0] and 'stiffness' in notes[1]
    # A servo-stiff or cable-driven arm: c = -6e-4 (1.7e3 N m/rad) is named with the key that
    # states it; with the cell's bound widened to 2e-3 it is no longer warned of.
    soft = compliance_warnings(names[:1], [-6e-4], [2e-6])
    assert len(soft) == 1 and 'identification.bounds.joint_compliance' in soft[0]
    assert not compliance_warnings(names[:1], [-6e-4], [2e-6], {names[0]: 2e-3})
    assert compliance_warnings(names[:1], [-6e-3], [2e-6], {names[0]: 2e-3})


def recovery(tmp_path, seed: int, n: int = 60, fresh: int = 200) -> dict[str, float]:
    """rms on fresh poses (measured, noise included) of each model of the stripped robot."""
    truth, overrides = truth_cell_model(_cell(tmp_path, False, hidden=HIDDEN))
    rng = np.random.default_rng(seed)
    p_true = true_parameters(truth.model.params, rng, overrides=overrides)
    q = random_configurations(truth.model, truth.model.params.nominal, n + fresh, rng,
                              truth.cell.max_incidence)
    data = simulate_measurements(truth.model, p_true, q[:n], SIGMA, rng)
    test = simulate_measurements(truth.model, p_true, q[n:], SIGMA, rng)
    out = {}
    with warnings.catch_warnings():
        warnings.simplefilter('ignore')
        models = {'geometric': (), 'joint_compliance (payload torques only)':
                  ('joint_compliance:joint_2', 'joint_compliance:joint_3'),
                  'gravity_compliance': ('gravity_compliance:joint_2',
                                         'gravity_compliance:joint_3')}
        for label, effects in models.items():
            cm = build_cell_model(_cell(tmp_path, True, effects=effects))
            result = identify_cell(cm, data)
            err = test.eta - cm.model.predict(result.values, test.q)
            out[label] = float(np.sqrt(np.mean(np.sum(err ** 2, axis=1))))
    return out


@pytest.mark.slow
def test_mass_free_compliance_reaches_the_noise_floor(tmp_path):
    for seed in range(3):
        rms = recovery(tmp_path, seed)
        print(f'seed {seed}: rms on fresh poses / noise floor σ√3: ' + ', '.join(
            f'{k} {v / FLOOR:.2f}' for k, v in rms.items()))
        assert rms['gravity_compliance'] <= 1.5 * FLOOR
        assert rms['geometric'] > 1.5 * FLOOR          # the effect is there to recover
