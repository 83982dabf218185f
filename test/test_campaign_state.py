"""The node's sequential campaign across restarts and its published calibration, without
ROS: the campaign state file, the rebuild from it, and the calibration a stopped campaign
publishes (the node only calls these jobs and publishes what they return)."""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import yaml

from kpi_calib_ros.app.campaign import campaign_context, new_campaign
from kpi_calib_ros.app.cell_model import build_cell_model
from kpi_calib_ros.core.acquisition.outcomes import PairingResult
from kpi_calib_ros.core.campaigns.settings import MODEL_INADEQUATE, TARGET_MET, CampaignSettings
from kpi_calib_ros.core.errors import DataError
from kpi_calib_ros.core.measurement.data import Measurements
from kpi_calib_ros.core.simulation import simulate_measurements, true_parameters
from kpi_calib_ros.io.campaign_io import CampaignState, read_campaign_state, write_campaign_state
from kpi_calib_ros.io.cell import DEFAULT_CELL, load_cell
from kpi_calib_ros.io.cell_settings import hidden_effects
from kpi_calib_ros.io.names import CALIBRATIONS_DIR, CAMPAIGN_STATE_FILE
from kpi_calib_ros.ros import job_work

SECOND = 1_000_000_000
TARGET = 16e-6


@pytest.fixture(scope='module')
def campaign_run(tmp_path_factory):
    """A node campaign as the node's jobs run it, to its stop: start, the initial design
    in one step, then one measurement per step. Returns the cell model, data_dir, the
    output of every step and all measurements (stamped, URDF joint values)."""
    cm = build_cell_model(load_cell(DEFAULT_CELL))
    data_dir = tmp_path_factory.mktemp('campaign') / 'data'
    settings = CampaignSettings(target_std=TARGET, max_measurements=60)
    campaign, initial, _, _ = job_work.sequential_start_work(cm, settings, 0, data_dir)
    state = read_campaign_state(data_dir / CAMPAIGN_STATE_FILE)
    assert state == CampaignState(settings, 0)
    rng = np.random.default_rng(4)
    p_true = true_parameters(cm.model.params, rng)
    sigma = float(cm.cell.sigma[0])
    batches: list[Measurements] = []

    def measure(q: np.ndarray) -> Measurements:
        start = int(batches[-1].stamps_ns[-1]) if batches else 0
        eta = cm.model.predict(p_true, q) + rng.normal(scale=sigma, size=(len(q), 3))
        batches.append(Measurements(q=q, eta=eta,
                                    stamps_ns=start + SECOND * np.arange(1, len(q) + 1)))
        return batches[-1]
    outs = [job_work.sequential_step_work(campaign, cm, measure(cm.joint_coupling.to_urdf(initial)),
                                          state, data_dir)]
    while not outs[-1].status.stopped:
        q_next = cm.joint_coupling.to_urdf(outs[-1].plan[:1])
        outs.append(job_work.sequential_step_work(campaign, cm, measure(q_next), outs[-1].state,
                                                  data_dir))
    return cm, data_dir, outs, batches


def _through(batches: list[Measurements], k: int) -> Measurements:
    """The measurements of steps 0..k."""
    part = batches[:k + 1]
    return Measurements(q=np.vstack([b.q for b in part]), eta=np.vstack([b.eta for b in part]),
                        stamps_ns=np.concatenate([b.stamps_ns for b in part]))


@pytest.mark.slow
def test_a_restarted_campaign_plans_the_same_next_pose(campaign_run, tmp_path):
    """A restart after step k: the campaign rebuilt from its state file and the restored
    measurements has the plan and status the running campaign had (next pose to 1e-9);
    the measurement of step k+1 (accepted, not yet added when the node was killed) then
    gives the plan the uninterrupted campaign made."""
    cm, _, outs, batches = campaign_run
    assert len(outs) >= 4, 'the campaign must plan a few poses for this test'
    k = 2
    state = outs[k].state
    assert len(state.steps) == k + 1
    rebuilt, _, out = job_work.sequential_resume_work(cm, state, _through(batches, k + 1), tmp_path)
    assert out is not None and out.calibration is None
    np.testing.assert_allclose(out.plan[0], outs[k].plan[0], atol=1e-9)
    assert out.status.statistic == pytest.approx(outs[k].status.statistic, rel=1e-12)
    assert yaml.safe_load(out.text)['resumed'] is True
    assert read_campaign_state(tmp_path / CAMPAIGN_STATE_FILE).steps == state.steps
    after = job_work.sequential_step_work(rebuilt, cm, batches[k + 1], out.state, tmp_path)
    np.testing.assert_allclose(after.plan[0], outs[k + 1].plan[0], atol=1e-9)
    assert after.state.steps == outs[k + 1].state.steps


@pytest.mark.slow
def test_a_state_whose_measurements_are_gone_is_refused_by_name(campaign_run, tmp_path):
    cm, _, outs, batches = campaign_run
    data = _through(batches, 1)
    with pytest.raises(DataError, match='campaign_state.yaml: steps: .*~/reset'):
        job_work.sequential_resume_work(cm, outs[1].state, data.subset(np.arange(len(data)) > 0),
                                        tmp_path)
    (tmp_path / CAMPAIGN_STATE_FILE).write_text('version: 1\nsettings: {}\n')
    with pytest.raises(DataError, match='campaign_state.yaml: field .*~/reset'):
        read_campaign_state(tmp_path / CAMPAIGN_STATE_FILE)


def test_state_round_trip(tmp_path):
    state = CampaignState(CampaignSettings(target_std=7e-6, max_measurements=40), 3,
                          ((1, 2, 3), (4,)), {'stop_reason': 'running'})
    assert read_campaign_state(write_campaign_state(tmp_path / 's.yaml', state)) == state
    stopped = dataclasses.replace(state, status={'stop_reason': TARGET_MET})
    assert stopped.stopped and not state.stopped
    # A campaign at a later station keeps its station and where it plans from.
    far = dataclasses.replace(state, station='far',
                              base_in_tracker=(2.5, -2.0, 0.15, 0.03, -0.02, 0.7))
    assert read_campaign_state(write_campaign_state(tmp_path / 'f.yaml', far)) == far
    doc = yaml.safe_load((tmp_path / 'f.yaml').read_text())
    doc['base_in_tracker'] = [1.0, 2.0]
    (tmp_path / 'bad.yaml').write_text(yaml.safe_dump(doc))
    with pytest.raises(DataError, match='base_in_tracker must be 6 finite numbers'):
        read_campaign_state(tmp_path / 'bad.yaml')


@pytest.mark.slow
def test_the_published_calibration_states_the_precision_the_campaign_stopped_on(campaign_run):
    """One statistic: the stopped campaign's calibration states per-axis TCP std equal to
    the campaign's (σ upper limit), its largest is the stop statistic, the document says
    which σ and that the target was met; it is the one calibration archived."""
    _, data_dir, outs, _ = campaign_run
    final = outs[-1]
    assert final.status.stop_reason == TARGET_MET and final.calibration is not None
    assert all(o.calibration is None for o in outs[:-1])
    doc = yaml.safe_load(final.calibration[0])
    std = np.array([t['std'] for t in doc['tcp']])
    np.testing.assert_allclose(std, final.status.tcp_std, rtol=1e-9)
    assert std.max() == pytest.approx(final.status.statistic, rel=1e-9)
    assert std.max() <= final.status.target_std
    assert doc['campaign']['target_met'] is True
    assert 'upper 97.5 % confidence limit of sigma' in doc['precision']['basis']
    assert doc['valid'] is True
    assert len(list((data_dir / CALIBRATIONS_DIR).glob('*.yaml'))) == 1
    assert read_campaign_state(data_dir / CAMPAIGN_STATE_FILE).stopped


@pytest.mark.slow
def test_a_campaign_stopped_model_inadequate_publishes_and_archives_nothing(tmp_path):
    """Hidden joint compliance the model lacks: the campaign stops 'model inadequate'; the
    step gives no calibration to publish, nothing is archived as the next cycle's prior,
    and an identification of the same data afterwards (~/identify) is not archived."""
    cell_doc = load_cell(DEFAULT_CELL)
    cm = build_cell_model(cell_doc)
    effects, overrides = hidden_effects({'joint_compliance:joint_2': {'c': 4.0e-7}}, cm.robot)
    truth = build_cell_model(cell_doc, effects=effects)
    cell, ctx = campaign_context(cm, 3, candidates=1000)
    settings = CampaignSettings(target_std=10e-6, max_measurements=80)
    campaign = new_campaign(cm, cell, ctx, settings, seed=1)
    rng = np.random.default_rng(7)
    p_true = true_parameters(truth.model.params, rng, overrides=overrides)
    sigma = float(cm.cell.sigma[0])
    state = CampaignState(settings, 1)
    q = ctx.candidates.configurations[campaign.initial_design()]
    n = 0
    while True:
        eta = simulate_measurements(truth.model, p_true, q, sigma, rng).eta
        stamps = SECOND * np.arange(n + 1, n + len(q) + 1)
        n += len(q)
        out = job_work.sequential_step_work(campaign, cm, Measurements(q=q, eta=eta,
                                                                       stamps_ns=stamps),
                                            state, tmp_path)
        state = out.state
        if out.status.stopped:
            break
        q = out.status.next_configurations[:1]
    assert out.status.stop_reason == MODEL_INADEQUATE
    assert out.calibration is None and out.result is None
    assert not (tmp_path / CALIBRATIONS_DIR).exists()
    data = Measurements(q=campaign.q, eta=campaign.eta, stamps_ns=campaign.stamps)
    pairing = PairingResult(tuple(cm.joint_names), cm.cell.tracker_frame, campaign.q,
                            campaign.eta, campaign.stamps)
    out = job_work.identify_work(cm, data, pairing, tmp_path, archive=False)
    cal, text = out.calibration, out.text
    assert cal is not None and cal.valid and yaml.safe_load(text)['identified_at_ns'] > 0
    assert not (tmp_path / CALIBRATIONS_DIR).exists()


def test_a_damaged_or_hostile_state_file_is_refused_by_name(tmp_path):
    """The state file lies in data_dir, where a damaged disk or another writer may leave
    anything: a NUL byte, nested aliases that expand to billions of nodes, text that is not
    UTF-8. Each is a DataError naming the file and ~/reset (the aliases refused by their
    count before they are expanded)."""
    path = tmp_path / CAMPAIGN_STATE_FILE
    laughs = 'a: &a [x, x, x, x, x, x, x, x, x, x]\n' + ''.join(
        f'{chr(98 + i)}: &{chr(98 + i)} [*{chr(97 + i)}, *{chr(97 + i)}, *{chr(97 + i)}, '
        f'*{chr(97 + i)}, *{chr(97 + i)}, *{chr(97 + i)}, *{chr(97 + i)}, *{chr(97 + i)}, '
        f'*{chr(97 + i)}, *{chr(97 + i)}]\n' for i in range(9))
    for content in (b'version: 1\nsettings: {\x00}\n', laughs.encode(), b'version: \xff\xfe\n'):
        path.write_bytes(content)
        with pytest.raises(DataError, match=r'campaign_state.yaml.*~/reset'):
            read_campaign_state(path)
