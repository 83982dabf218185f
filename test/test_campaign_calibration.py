"""The calibration a stopped sequential campaign publishes (app.campaign.campaign_calibration)
is judged as identify judges its rows: every row the poses gave (each reflector's point),
the parameters the fit was asked for, the rows' torques."""
from __future__ import annotations

import numpy as np
import yaml

from kpi_calib_ros.app.campaign import (
    campaign_calibration,
    campaign_context,
    new_campaign,
    simulate_sequential,
)
from kpi_calib_ros.app.cell_model import build_cell_model
from kpi_calib_ros.app.simulate import truth_cell_model
from kpi_calib_ros.core.campaigns.settings import CampaignSettings
from kpi_calib_ros.core.simulation import true_parameters
from kpi_calib_ros.io.cell import DEFAULT_CELL, load_cell, read_cell_document


def _campaign(tmp_path, **changes):
    doc = read_cell_document(DEFAULT_CELL)
    doc['robot']['urdf'] = str((DEFAULT_CELL.parent / doc['robot']['urdf']).resolve())
    doc.update(changes)
    if 'reflectors' in changes:
        doc['reflector'].pop('offset', None)
    path = tmp_path / 'cell.yaml'
    path.write_text(yaml.safe_dump(doc))
    cm = build_cell_model(load_cell(path))
    truth, overrides = truth_cell_model(load_cell(path))
    rng = np.random.default_rng(4)
    p_true = true_parameters(truth.model.params, rng, overrides=overrides)
    cell, ctx = campaign_context(cm, 0, candidates=400)
    campaign = new_campaign(cm, cell, ctx, CampaignSettings(target_std=2.5e-5,
                                                            max_measurements=45), 0)
    simulate_sequential(campaign, truth, p_true, float(cm.cell.sigma[0]), rng)
    return cm, campaign


def test_an_effect_the_campaign_left_out_of_the_fit_is_not_valid(tmp_path):
    """joint_1's axis is vertical: gravity never loads it, the fit leaves its compliance
    out. The campaign's calibration was published as valid; identify refuses it."""
    cm, campaign = _campaign(tmp_path, effects=['joint_compliance:joint_1'])
    cal, doc = campaign_calibration(cm, campaign)
    assert 'joint_compliance.joint_1.c' not in cal.result.estimated
    assert not doc['valid']
    assert any('joint_compliance:joint_1: undetermined' in r and 'left out of the fit' in r
               for r in doc['invalid_reasons']), doc['invalid_reasons']


def test_a_campaign_over_two_reflectors_is_judged_on_every_row(tmp_path):
    """Two reflectors: two rows a pose. The calibration indexed the poses with the rows'
    kept mask."""
    cm, campaign = _campaign(tmp_path, reflectors=[
        {'name': 'a', 'offset': [0.0, 0.0, 0.06]}, {'name': 'b', 'offset': [0.05, 0.0, 0.06]}])
    assert len(campaign.rows) == 2 * len(campaign.q)
    cal, doc = campaign_calibration(cm, campaign)
    assert doc['valid'], doc['invalid_reasons']
    assert cal.estimability.all_estimable
