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


def test_a_far_point_excluded_leaves_no_trace_in_the_campaign(tmp_path):
    """A 50 mm fault at the 15th measurement threw the warm-started estimate a wrist
    placement 0.93 m and a joint zero 7.6 rad away; excluded from the next step on, the
    estimate never came back, every later plan rested on it and the stopped campaign's
    calibration was not valid (not published, nothing said). Each step now starts from a
    robot within the tolerances and a refit after an exclusion from the fit's own start:
    the estimate stays a robot, the calibration is valid and its TCP within 4σ."""
    from kpi_calib_ros.core.estimation.plausibility import moved_beyond
    from kpi_calib_ros.core.simulation import simulate_measurements
    cm = build_cell_model(load_cell(DEFAULT_CELL))
    truth, overrides = truth_cell_model(load_cell(DEFAULT_CELL))
    rng = np.random.default_rng(1003)
    p_true = true_parameters(truth.model.params, rng, overrides=overrides)
    cell, ctx = campaign_context(cm, 0)
    campaign = new_campaign(cm, cell, ctx, CampaignSettings(target_std=1e-5,
                                                            max_measurements=200), 0)
    sent = []

    def measure(q):
        eta = simulate_measurements(truth.model, p_true, q, 2.5e-5, rng).eta
        for row in eta:
            if len(sent) == 14:
                row[0] += 0.05
            sent.append(row)
        return eta

    q = ctx.candidates.configurations[campaign.initial_design()]
    status = campaign.add(q, measure(q), stamps_ns=np.arange(len(q)))
    start = campaign.start
    while not status.stopped:
        q = status.next_configurations[:1]
        status = campaign.add(q, measure(q), stamps_ns=[len(sent)])
        if len(sent) > 16:
            assert not moved_beyond(cm.model, campaign.result.values, start), len(sent)
    assert 14 in [e['measurement'] for e in status.excluded]
    cal, doc = campaign_calibration(cm, campaign)
    assert doc['valid'], doc['invalid_reasons']
    err = cal.result.tcp[0] - truth.model.predict(p_true, truth.q_work)[0]
    assert np.all(np.abs(err) < 4 * np.sqrt(np.diag(cal.result.tcp_covariance[0])) * 1.25)


def test_a_stopped_campaign_whose_calibration_is_not_valid_says_so(tmp_path):
    """The node's step output of a stopped campaign whose calibration the gate refuses (an
    effect the fit left out): nothing to publish, and the status says why
    (``calibration_not_published``, the node's /diagnostics ERROR); it said "target met"
    or "max_measurements reached" and left calibration.failed.yaml unmentioned."""
    from kpi_calib_ros.io.campaign_io import CampaignState
    from kpi_calib_ros.ros import job_work
    cm, campaign = _campaign(tmp_path, effects=['joint_compliance:joint_1'])
    assert campaign.status.stopped
    folder = tmp_path / 'node'
    folder.mkdir()
    out = job_work._step_output(campaign, cm, CampaignState(campaign.settings, 0), folder,
                                None, None)
    assert out.calibration is None and 'joint_compliance:joint_1' in out.refused
    status = yaml.safe_load(out.text)
    assert status['calibration_not_published'] == out.refused
    assert (folder / 'calibration.failed.yaml').is_file()
