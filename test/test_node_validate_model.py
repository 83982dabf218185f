"""The node's ``~/validate`` work (:func:`kpi_calib_ros.ros.job_work.validate_work`) tests the
calibration with the calibration's own model: the effects it was identified with, which the
node's cell model lacks when ``identification.model: auto`` added them."""
from __future__ import annotations

import json

import numpy as np
import pytest
import yaml

from kpi_calib_ros.app.cell_model import build_cell_model
from kpi_calib_ros.app.measurements import measurements_from_bag
from kpi_calib_ros.app.simulate import simulate_campaign, truth_cell_model
from kpi_calib_ros.cli import main
from kpi_calib_ros.core.simulation import true_parameters
from kpi_calib_ros.io.cell import DEFAULT_CELL, load_cell, read_cell_document
from kpi_calib_ros.ros.job_work import validate_work

EFFECTS = {'joint_compliance:joint_2': -3e-6, 'joint_compliance:joint_3': -4e-6}


@pytest.mark.slow
def test_the_nodes_validation_uses_the_effects_the_calibration_was_identified_with(tmp_path):
    """A robot with two joint compliances calibrated with them (as auto adds them); the
    node's cell model has none. The node's validation of a new bag gives the command line's
    verdict and figures to the bit; it stopped with an unknown parameter before."""
    doc = read_cell_document(DEFAULT_CELL)
    doc['robot']['urdf'] = str((DEFAULT_CELL.parent / doc['robot']['urdf']).resolve())
    doc.setdefault('identification', {})['model'] = 'geometric'
    doc['simulation'] = {'hidden_effects': {k: {'c': c} for k, c in EFFECTS.items()}}
    cell = tmp_path / 'cell.yaml'
    cell.write_text(yaml.safe_dump(doc))
    cm, overrides = truth_cell_model(load_cell(cell))
    p_true = true_parameters(cm.model.params, np.random.default_rng(3), overrides=overrides)
    for i, name in enumerate(('train', 'new')):
        simulate_campaign(cell, 40, tmp_path / f'{name}.mcap', 10 + i, cm=cm, p_true=p_true)
    assert main(['identify', '--cell', str(cell), '--bag', str(tmp_path / 'train.mcap'),
                 '--out', str(tmp_path / 'cal'), '--effects', ','.join(EFFECTS)]) == 0
    assert main(['validate', '--cell', str(cell), '--calibration',
                 str(tmp_path / 'cal' / 'calibration.yaml'), '--bag', str(tmp_path / 'new.mcap'),
                 '--out', str(tmp_path / 'cli')]) == 0
    cli = json.loads((tmp_path / 'cli' / 'validation.json').read_text())
    node_cm = build_cell_model(load_cell(cell))  # the node's model: the cell's, no effects
    assert not node_cm.model.effects
    data = measurements_from_bag(node_cm, tmp_path / 'new.mcap')[0]
    node, _ = validate_work(node_cm, (tmp_path / 'cal' / 'calibration.yaml').read_text(), data,
                            tmp_path / 'node')
    assert node['holds'] is True
    for key in ('chi2', 'dof', 'rms_m', 'p_value'):
        assert node[key] == cli[key], key
    assert cli['rms_m'] < 1.5 * np.sqrt(3) * 2e-5
