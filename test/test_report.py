"""`kpi-calib diagnose` and `identify --effects` end to end on a simulated bag."""
from __future__ import annotations

import json

import pytest
import yaml

from kpi_calib_ros.app.measurements import load_measurements
from kpi_calib_ros.cli import main
from kpi_calib_ros.io.cell import DEFAULT_CELL
from kpi_calib_ros.io.names import DIAGNOSIS_DIR
from kpi_calib_ros.ros.job_work import diagnose_work

HIDDEN = 'joint_compliance:shoulder_lift_joint'


@pytest.fixture(scope='module')
def campaign(tmp_path_factory):
    """A UR-class cell whose simulated robot bends at the shoulder; the bag of 80 poses."""
    folder = tmp_path_factory.mktemp('hidden')
    doc = yaml.safe_load((DEFAULT_CELL.parent / 'ur_cell.yaml').read_text())
    doc['robot']['urdf'] = str((DEFAULT_CELL.parent / doc['robot']['urdf']).resolve())
    doc['simulation'] = {'hidden_effects': {HIDDEN: {'c': 4e-6}}}
    cell = folder / 'cell.yaml'
    cell.write_text(yaml.safe_dump(doc))
    bag = folder / 'run.mcap'
    assert main(['simulate', '--cell', str(cell), '--n', '80', '--out', str(bag),
                 '--seed', '3']) == 0
    truth = yaml.safe_load(bag.with_name('run.truth.yaml').read_text())
    assert truth['parameters'][f'{HIDDEN.replace(":", ".")}.c'] == 4e-6
    return cell, bag


@pytest.mark.slow
def test_diagnose_writes_ranked_json_report_and_plots(campaign, tmp_path, capsys):
    cell, bag = campaign
    assert main(['diagnose', '--cell', str(cell), '--bag', str(bag), '--out', str(tmp_path)]) == 0
    def refuse(constant):
        raise ValueError(f'diagnosis.json holds {constant}: not valid JSON')
    doc = json.loads((tmp_path / 'diagnosis.json').read_text(), parse_constant=refuse)
    # A joint play's transition, held at a grid value in the screen, has its std (the full
    # Jacobian there); one the data do not determine is null with the reason.
    plays = [c for c in doc['candidates'] if c['effect'] == 'joint_play']
    assert plays
    for p in (p for c in plays for p in c['parameters']):
        assert p['std'] is not None or 'not determined' in p['std_reason'], p
    assert doc['model_adequate'] is False and doc['rms_m'] > 1.5 * doc['noise_floor_m']
    top = doc['candidates'][0]
    assert (top['effect'], top['joint']) == ('joint_compliance', 'shoulder_lift_joint')
    assert set(top) >= {'effect', 'joint', 'rms_after_m', 'p_value', 'explanation'}
    assert top['p_value'] < 0.01 and 'correlates' in top['explanation']
    assert doc['candidates'][1]['validation_rms_after_m'] >= top['validation_rms_after_m']
    assert 'tracker_scale' in {c['spec'] for c in doc['not_distinguishable']}
    added = doc['added_effect']
    assert added['effects'] == [HIDDEN]
    assert added['validation_rms_after_m'] < 0.5 * added['validation_rms_before_m']
    report = (tmp_path / 'report.md').read_text()
    for png in ('residuals_vs_joints', 'residuals_vs_torque', 'residuals_vs_time_distance',
                'measured_vs_predicted_3d', 'joint_errors', 'before_after', 'periodogram'):
        assert (tmp_path / f'{png}.png').stat().st_size > 10_000
        assert f'({png}.png)' in report
    # χ² rejects the geometric model: the learned residual it fitted is drawn too.
    assert (tmp_path / 'learned_residual.png').stat().st_size > 10_000
    out = capsys.readouterr().out
    assert f'Add it with --effects {HIDDEN}' in out and 'validation rms' in out


def test_identify_with_effects_reports_before_and_after(campaign, tmp_path, capsys):
    cell, bag = campaign
    assert main(['identify', '--cell', str(cell), '--bag', str(bag), '--out', str(tmp_path),
                 '--effects', HIDDEN]) == 0
    doc = yaml.safe_load((tmp_path / 'calibration.yaml').read_text())
    cmp = doc['effects_comparison']
    assert cmp['rms_after_m'] < 0.6 * cmp['rms_before_m']
    (param,) = cmp['effect_parameters']
    assert param['name'] == 'joint_compliance.shoulder_lift_joint.c'
    assert abs(param['value'] - 4e-6) < 3 * param['std']
    assert {p['name'] for p in doc['parameters']} >= {param['name']}
    out = capsys.readouterr().out
    assert 'validation rms' in out and 'joint_compliance.shoulder_lift_joint.c' in out


def test_the_effects_are_compared_at_the_level_they_were_fitted(campaign, tmp_path):
    """Fitted at ``joint_offsets``, the model with the effect is compared with the
    ``joint_offsets`` model without it: before, with the geometric model, which the
    identification did not publish (a real UR10 region read "NOT recommended" of the
    effects ``auto`` published at its smaller level)."""
    cell, bag = campaign
    assert main(['identify', '--cell', str(cell), '--bag', str(bag), '--out',
                 str(tmp_path / 'with'), '--effects', HIDDEN, '--model', 'joint_offsets']) == 0
    assert main(['identify', '--cell', str(cell), '--bag', str(bag), '--out',
                 str(tmp_path / 'without'), '--model', 'joint_offsets']) == 0
    assert main(['identify', '--cell', str(cell), '--bag', str(bag), '--out',
                 str(tmp_path / 'geometric'), '--model', 'geometric']) == 0
    with_, without, geometric = (
        yaml.safe_load((tmp_path / k / 'calibration.yaml').read_text())
        for k in ('with', 'without', 'geometric'))
    assert with_['model']['level'] == without['model']['level'] == 'joint_offsets'
    cmp = with_['effects_comparison']
    # The same fit as the published joint_offsets calibration without the effect, and not
    # the geometric one (a different rms on these poses).
    assert cmp['rms_before_m'] == pytest.approx(without['rms_m'], rel=1e-6)
    assert abs(geometric['rms_m'] - without['rms_m']) > 0.05 * without['rms_m']


def test_bad_effect_spec_exits_with_the_choices(campaign, tmp_path, capsys):
    cell, bag = campaign
    code = main(['identify', '--cell', str(cell), '--bag', str(bag), '--out', str(tmp_path),
                 '--effects', 'joint_compliance:elbow'])
    assert code == 2
    err = capsys.readouterr().err
    assert "'joint_compliance:elbow'" in err and 'elbow_joint' in err


@pytest.mark.slow
def test_the_nodes_diagnosis_is_the_command_lines(campaign, tmp_path, capsys):
    """~/diagnose (job_work.diagnose_work, run in the node's worker) gives the document,
    the learned residual's decision and its plot that ``kpi-calib diagnose`` gives: before,
    the node never asked the learned residual (no remedy of it, no decision, no plot)."""
    cell, bag = campaign
    assert main(['diagnose', '--cell', str(cell), '--bag', str(bag), '--out',
                 str(tmp_path / 'cli')]) == 0
    said = capsys.readouterr().out
    cm, data, _ = load_measurements(cell, bag)
    doc, text, verdict, report = diagnose_work(cm, data, tmp_path / 'node')
    assert json.loads(text) == doc
    assert doc == json.loads((tmp_path / 'cli' / 'diagnosis.json').read_text())
    assert (report.parent / 'learned_residual.png').stat().st_size > 10_000
    assert report.parent == tmp_path / 'node' / DIAGNOSIS_DIR
    reason = next(line for line in said.splitlines() if line.startswith('learned residual'))
    assert reason.split(';')[0] in verdict
