"""A calibration.yaml from outside (validate --calibration, identify --prior): every damaged
field is an error naming the file, the field and the fix (exit 2), before anything is
computed or written; a YAML alias bomb is refused before it expands."""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import yaml

from kpi_calib_ros.app.calibration_document import calibration_document
from kpi_calib_ros.app.cell_model import build_cell_model
from kpi_calib_ros.app.identify import identify_cell
from kpi_calib_ros.app.measurements import measurements_from_bag
from kpi_calib_ros.cli import main
from kpi_calib_ros.core.acquisition.streams import synthesize_streams
from kpi_calib_ros.core.simulation import (
    random_configurations,
    simulate_measurements,
    true_parameters,
)
from kpi_calib_ros.io.bag_writing import write_bag
from kpi_calib_ros.io.calibration_file import read_calibration_document
from kpi_calib_ros.io.cell import DEFAULT_CELL, load_cell
from kpi_calib_ros.io.results import write_calibration
from kpi_calib_ros.io.yaml_bounded import MAX_DOCUMENT_NODES, load_yaml_bounded

CELL = str(DEFAULT_CELL)
HOUR_NS = 3_600_000_000_000


@pytest.fixture(scope='module')
def made(tmp_path_factory):
    """A calibration of 30 simulated points and a new bag of 12 points one hour later."""
    tmp = tmp_path_factory.mktemp('calfile')
    cm = build_cell_model(load_cell(DEFAULT_CELL))
    rng = np.random.default_rng(5)
    p_true = true_parameters(cm.model.params, rng)

    def bag(n: int, name: str, start_ns: int) -> Path:
        q = random_configurations(cm.model, p_true, n, rng)
        eta = simulate_measurements(cm.model, p_true, q, cm.cell.sigma, rng).eta
        joints, points = synthesize_streams(q, cm.joint_names, eta, cm.cell.tracker_frame,
                                            start_ns=start_ns, rng=rng)
        return write_bag(tmp / name, joints, points)

    start = 1_700_000_000_000_000_000
    train = bag(30, 'train.mcap', start)
    new = bag(12, 'new.mcap', start + HOUR_NS)
    data, pairing = measurements_from_bag(cm, train)
    doc = calibration_document(cm, identify_cell(cm, data), pairing)
    write_calibration(tmp / 'good', doc)
    return tmp, yaml.safe_load((tmp / 'good' / 'calibration.yaml').read_text()), new


def _write(tmp: Path, name: str, doc: dict) -> Path:
    path = tmp / name / 'calibration.yaml'
    path.parent.mkdir(exist_ok=True)
    path.write_text(yaml.safe_dump(doc, sort_keys=False))
    return path


def _changed(doc: dict, field: str, value) -> dict:
    out = yaml.safe_load(yaml.safe_dump(doc))
    if field == 'parameter_value':
        out['parameters'][3]['value'] = value
    elif field == 'training_joint_ranges':
        out[field] = {**out[field], 'joint_1': value}
    else:
        out[field] = value
    return out


BAD_FIELDS = [('precision', 'x', 'precision'),
              ('training_joint_ranges', 'wide', 'training_joint_ranges.joint_1'),
              ('parameter_value', math.nan, 'parameters[3].value'),
              ('identified_at_ns', 'yesterday', 'identified_at_ns'),
              ('identified_at_ns', math.nan, 'identified_at_ns')]


@pytest.mark.parametrize('field, value, key', BAD_FIELDS)
def test_validate_names_the_file_and_field_of_a_damaged_calibration(made, tmp_path, capsys,
                                                                     field, value, key):
    tmp, doc, new = made
    path = _write(tmp_path, 'bad', _changed(doc, field, value))
    out = tmp_path / 'out'
    code = main(['validate', '--cell', CELL, '--calibration', str(path), '--bag', str(new),
                 '--out', str(out)])
    err = capsys.readouterr().err
    assert code == 2, err
    assert f'{key}:' in err and str(path) in err and 'kpi-calib identify' in err, err
    assert 'Traceback' not in err
    assert not list(out.glob('*')) if out.exists() else True  # no partial validation.json


@pytest.mark.parametrize('field, value, key', BAD_FIELDS)
def test_identify_prior_names_the_file_and_field_of_a_damaged_prior(made, tmp_path, capsys,
                                                                     monkeypatch, field, value,
                                                                     key):
    from kpi_calib_ros.app import reidentify

    def no_fit(*args, **kwargs):
        raise AssertionError('a damaged prior reached the identification')
    monkeypatch.setattr(reidentify, 'reidentify', no_fit)
    tmp, doc, new = made
    path = _write(tmp_path, 'bad', _changed(doc, field, value))
    code = main(['identify', '--cell', CELL, '--bag', str(new), '--out', str(tmp_path / 'o'),
                 '--prior', str(path)])
    err = capsys.readouterr().err
    assert code == 2, err
    assert f'{key}:' in err and str(path) in err and '--prior' in err, err
    assert not (tmp_path / 'o' / 'calibration.yaml').exists()


def _bomb(levels: int, width: int) -> str:
    """A 'billion laughs' matrix: ``width ** levels`` numbers from a few hundred bytes."""
    lines = ['l0: &l0 [' + ', '.join(['1.0'] * width) + ']']
    for i in range(1, levels):
        lines.append(f'l{i}: &l{i} [' + ', '.join([f'*l{i - 1}'] * width) + ']')
    return '\n'.join(lines) + '\n'


def test_a_yaml_alias_bomb_in_the_matrix_is_refused_before_it_expands(made, tmp_path, capsys):
    """7 levels of 11: 19.5 million numbers (> MAX_DOCUMENT_NODES) from 400 bytes; read
    unbounded, np.array(matrix) expands it (a 9-level one: 7.45 GiB)."""
    tmp, doc, new = made
    assert 11 ** 7 > MAX_DOCUMENT_NODES
    placeholder = yaml.safe_load(yaml.safe_dump(doc))
    placeholder['parameter_covariance']['matrix'] = 'BOMB'
    text = yaml.safe_dump(placeholder, sort_keys=False).replace('matrix: BOMB', 'matrix: *l6')
    path = tmp_path / 'bomb' / 'calibration.yaml'
    path.parent.mkdir()
    path.write_text(_bomb(7, 11) + text)
    for command in (['validate', '--calibration', str(path), '--bag', str(new)],
                    ['identify', '--prior', str(path), '--bag', str(new)]):
        code = main(command + ['--cell', CELL, '--out', str(tmp_path / 'o')])
        err = capsys.readouterr().err
        assert code == 2, err
        assert 'aliases' in err and str(path) in err and str(MAX_DOCUMENT_NODES) in err, err


def test_benign_aliases_are_read_and_a_recursive_one_is_refused():
    assert load_yaml_bounded('a: &x [1, 2]\nb: *x\n', 'f.yaml', 'k') == {'a': [1, 2],
                                                                       'b': [1, 2]}
    with pytest.raises(ValueError, match='refers to itself'):
        load_yaml_bounded('a: &x [1, *x]\n', 'f.yaml', 'k')


def test_a_mangled_drift_state_is_refused_like_the_covariance(made, tmp_path, capsys,
                                                             monkeypatch):
    """Negative variances or names out of the covariance's order: identify --prior
    --drift-velocity names the field (exit 2) instead of carrying the state on."""
    from kpi_calib_ros.app import reidentify

    def no_fit(*args, **kwargs):
        raise AssertionError('a mangled drift state reached the identification')
    monkeypatch.setattr(reidentify, 'reidentify', no_fit)
    _, doc, new = made
    names = [n for n in doc['parameter_covariance']['names']
             if not n.startswith(('base.', 'reflector.'))][:3]
    k = len(names)
    state = {'names': names, 'values': [0.0] * (2 * k),
             'covariance': np.diag(np.full(2 * k, 1e-8)).tolist(),
             'cross_covariance': np.zeros((k, 2 * k)).tolist()}
    good = _write(tmp_path, 'good', {**doc, 'drift_state': state})
    assert read_calibration_document(good)['drift_state']['names'] == names
    negative = np.diag(np.full(2 * k, 1e-8))
    negative[1, 1] = -1e-8
    for change, field in (({'covariance': negative.tolist()}, 'drift_state.covariance'),
                          ({'names': names[::-1]}, 'drift_state.names')):
        path = _write(tmp_path, 'bad', {**doc, 'drift_state': {**state, **change}})
        code = main(['identify', '--cell', CELL, '--bag', str(new), '--out',
                     str(tmp_path / 'o'), '--prior', str(path), '--drift-velocity'])
        err = capsys.readouterr().err
        assert code == 2 and f'{field}: in --prior {path}' in err, err


def test_out_at_the_file_system_root_is_refused_before_computing(made, monkeypatch, capsys):
    from kpi_calib_ros.app import measurements as app_measurements
    from kpi_calib_ros.app import validate as app_validate

    def no_computing(*args, **kwargs):
        raise AssertionError('the bag was read before --out was checked')
    monkeypatch.setattr(app_measurements, 'measurements_from_bag', no_computing)
    monkeypatch.setattr(app_validate, 'measurements_from_bag', no_computing)
    tmp, _, new = made
    for command in (['identify'], ['validate', '--calibration',
                                   str(tmp / 'good' / 'calibration.yaml')]):
        code = main(command + ['--cell', CELL, '--bag', str(new), '--out', '/'])
        err = capsys.readouterr().err
        assert code == 2 and '--out' in err and 'root of a file system' in err, err


def test_a_prior_dated_after_the_data_or_years_before_warns_naming_the_clocks(made, cm):
    """Δt = −2 h (the prior after the data) and 55 554 h: each a warning that names the
    clocks; the prior is widened by |Δt| all the same (never narrowed)."""
    from kpi_calib_ros.app.reidentify import cycle_prior
    tmp, doc, new = made
    data, _ = measurements_from_bag(cm, new)
    first = int(np.min(data.stamps_ns))
    honest = cycle_prior(cm, doc, data)
    assert honest.warnings == () and 0.9 < honest.hours < 1.0  # 30 points end before
    for hours, words in ((-2.0, 'AFTER the first new measurement'), (55_554.0, 'years')):
        stamp = first - int(hours * HOUR_NS)
        cp = cycle_prior(cm, {**doc, 'identified_at_ns': stamp}, data)
        assert cp.hours == pytest.approx(hours)
        assert len(cp.warnings) == 1 and words in cp.warnings[0], cp.warnings
        assert f'identified_at_ns {stamp}' in cp.warnings[0] and 'clock' in cp.warnings[0]
        assert np.all(np.diag(cp.prior.covariance) >= np.diag(honest.prior.covariance))


def test_an_overstated_sigma_is_a_verdict_beside_the_adequacy(made, capsys):
    """σ stated 250× too large: χ² ≈ dof / 62 500 — `adequate` stays true (the model is
    not contradicted), and the lower tail says 'sigma overstated' in the file and the
    summary; with the true σ the verdict is 'sigma consistent'."""
    import dataclasses

    from kpi_calib_ros.io.results import summary_text
    tmp, doc, _ = made
    assert doc['model_adequacy']['noise_verdict'] == 'sigma consistent'
    cm = build_cell_model(load_cell(DEFAULT_CELL))
    data, pairing = measurements_from_bag(cm, tmp / 'train.mcap')
    loud = dataclasses.replace(cm, cell=dataclasses.replace(
        cm.cell, sigma=np.asarray(cm.cell.sigma, float) * 250))
    over = calibration_document(loud, identify_cell(loud, data), pairing)
    adequacy = over['model_adequacy']
    assert adequacy['adequate'] is True and adequacy['p_value'] > 0.99
    assert adequacy['chi2'] < adequacy['dof'] / 1000
    assert adequacy['noise_verdict'] == 'sigma overstated' and adequacy['lower_tail_p'] < 0.01
    assert 'WARNING: sigma overstated' in summary_text(over)
    assert 'noise.sigma' in summary_text(over)


def test_excluded_points_read_the_same_number_in_the_log_and_the_file(made, cm):
    """A point moved 2 mm: the summary (and the node's log, the same text) states the
    distance_sigma that calibration.yaml stores, and the reason adds no other figure."""
    import re

    from kpi_calib_ros.app.calibration_document import add_robust_sections, robust_summary
    from kpi_calib_ros.app.identify import calibrate_cell
    tmp, _, _ = made
    data, pairing = measurements_from_bag(cm, tmp / 'train.mcap')
    eta = np.array(data.eta)
    eta[7] += [2e-3, 0.0, 0.0]
    moved = dataclasses_replace(data, eta=eta)
    cal = calibrate_cell(cm, moved)
    doc = add_robust_sections(calibration_document(cm, cal.result, pairing), cal)
    excluded = doc['robust']['excluded']
    assert [e['index'] for e in excluded] == [7]
    line = next(x for x in robust_summary(doc).splitlines() if 'measurement 7 ' in x)
    assert f"distance_sigma {excluded[0]['distance_sigma']:.2f} σ̂" in line
    figures = {float(x) for x in re.findall(r'([\d.]+) σ̂', line)}
    assert figures == {round(excluded[0]['distance_sigma'], 2),
                       round(doc['robust']['outlier_threshold_sigma'], 2)}, line


def dataclasses_replace(obj, **changes):
    import dataclasses
    return dataclasses.replace(obj, **changes)


def test_validate_takes_the_code_effects_opt_in_it_advises(made, tmp_path, capsys):
    """validate's error for a cell naming code advises --allow-code-effects: validate
    accepts it (and runs the code only then)."""
    tmp, _, new = made
    marker = tmp_path / 'ran.marker'
    (tmp_path / 'sag.py').write_text(
        f'from pathlib import Path\nPath({str(marker)!r}).write_text("ran")\n'
        'from kpi_calib_ros.core.effects.registry import EffectType\n'
        "SAG = EffectType('sag', ('g',), ('rad',), joint_function=lambda q, t, th: th[0] * q)\n")
    cell = yaml.safe_load(DEFAULT_CELL.read_text())
    cell['robot']['urdf'] = str((DEFAULT_CELL.parent / cell['robot']['urdf']).resolve())
    cell['effects'] = ['sag.py:SAG:joint_2']
    (tmp_path / 'cell.yaml').write_text(yaml.safe_dump(cell))
    args = ['validate', '--cell', str(tmp_path / 'cell.yaml'), '--calibration',
            str(tmp / 'good' / 'calibration.yaml'), '--bag', str(new), '--out',
            str(tmp_path / 'out')]
    assert main(args) == 2
    err = capsys.readouterr().err
    assert '--allow-code-effects' in err and not marker.exists()
    code = main(args + ['--allow-code-effects'])
    err = capsys.readouterr().err
    # Ran: the calibration lacks the effect's parameter, which validate names.
    assert marker.exists() and code == 2 and 'sag' in err, err


def test_validate_says_sigma_overstated_when_chi2_is_far_below_its_dof(made, tmp_path,
                                                                        capsys):
    """The same calibration with noise_sigma_m 250x: the new points 'hold' (p = 1) and
    validation.json and the summary say 'sigma overstated'; as written: consistent."""
    import json
    tmp, doc, new = made
    loud = {**doc, 'noise_sigma_m': [s * 250 for s in doc['noise_sigma_m']]}
    for name, calibration, verdict in (('honest', doc, 'sigma consistent'),
                                       ('loud', loud, 'sigma overstated')):
        path = _write(tmp_path, name, calibration)
        out = tmp_path / f'out_{name}'
        code = main(['validate', '--cell', CELL, '--calibration', str(path), '--bag', str(new),
                     '--out', str(out)])
        text = capsys.readouterr().out
        result = json.loads((out / 'validation.json').read_text())
        assert code == 0 and result['holds'], text
        assert result['noise_verdict'] == verdict, result['lower_tail_p']
        assert ('WARNING: sigma overstated' in text) == (name == 'loud')


def _inline_bomb(levels: int, width: int) -> str:
    """The bomb as one flow sequence whose anchors are defined at their first use, so it
    fits under any key: ``[&l1 [&l0 [1.0, ...], *l0, ...], *l1, ...]``."""
    text = '&l0 [' + ', '.join(['1.0'] * width) + ']'
    for i in range(1, levels):
        text = f'&l{i} [' + ', '.join([text] + [f'*l{i - 1}'] * (width - 1)) + ']'
    return text


def test_a_cell_file_or_design_with_an_alias_bomb_is_refused_at_once(tmp_path, capsys):
    """The cell file and a design.yaml given to simulate --poses are read with the same
    bounds (a cell is a few kB: 1e6 expanded nodes at most), exit 2 naming the file."""
    cell_doc = yaml.safe_load(Path(CELL).read_text())
    cell_doc['robot']['urdf'] = str(Path(CELL).parent.parent / 'robots' / 'kr15_class.urdf')
    cell_doc['obstacles'] = 'BOMB'
    cell = tmp_path / 'cell.yaml'
    cell.write_text(yaml.safe_dump(cell_doc).replace('obstacles: BOMB',
                                                    'obstacles: ' + _inline_bomb(7, 11)))
    code = main(['simulate', '--cell', str(cell), '--n', '5', '--out', str(tmp_path / 'a.mcap')])
    err = capsys.readouterr().err
    assert code == 2 and 'aliases' in err and str(cell) in err, err
    design = tmp_path / 'design.yaml'
    design.write_text('joint_names: [joint_1]\nconfigurations: ' + _inline_bomb(8, 11) + '\n')
    code = main(['simulate', '--cell', CELL, '--n', '5', '--poses', str(design),
                 '--out', str(tmp_path / 'b.mcap')])
    err = capsys.readouterr().err
    assert code == 2 and 'aliases' in err and str(design) in err, err
    assert not (tmp_path / 'a.mcap').exists() and not (tmp_path / 'b.mcap').exists()


def test_a_column_mapping_with_an_alias_bomb_is_refused(tmp_path, capsys):
    mapping = tmp_path / 'mapping.yaml'
    mapping.write_text('frame_id: laser_tracker\njoints: ' + _inline_bomb(6, 11) + '\n')
    table = tmp_path / 't.csv'
    table.write_text('a,b\n1,2\n')
    code = main(['import-csv', str(table), '--mapping', str(mapping),
                 '--out', str(tmp_path / 'o.mcap')])
    err = capsys.readouterr().err
    assert code == 2 and 'aliases' in err and str(mapping) in err, err


def _with_nul(source: Path, target: Path) -> Path:
    """``source`` copied to ``target`` with a NUL byte (a damaged disk block) inside."""
    text = source.read_text()
    target.parent.mkdir(parents=True, exist_ok=True)
    target.write_text(text[:len(text) // 2] + '\x00' + text[len(text) // 2:])
    return target


def test_a_control_character_in_any_yaml_file_is_a_named_error(made, tmp_path, capsys):
    """A NUL byte in the cell, a calibration, a --prior, a column mapping or a learned
    residual: exit 2 naming the file and the fix, never a yaml ReaderError traceback."""
    tmp, _, new = made
    good = tmp / 'good' / 'calibration.yaml'
    cell = _with_nul(Path(CELL), tmp_path / 'cell' / 'cell.yaml')
    calibration = _with_nul(good, tmp_path / 'cal' / 'calibration.yaml')
    beside = tmp_path / 'learned' / 'calibration.yaml'
    beside.parent.mkdir()
    beside.write_text(good.read_text())
    learned = beside.parent / 'learned_residual.yaml'
    learned.write_text('version: 1\n\x00\n')
    mapping = tmp_path / 'mapping.yaml'
    mapping.write_text('frame_id: laser_tracker\n\x00joints: [a]\n')
    table = tmp_path / 't.csv'
    table.write_text('a,b\n1,2\n')
    out = str(tmp_path / 'out')
    cases = [(cell, ['identify', '--cell', str(cell), '--bag', str(new), '--out', out]),
             (calibration, ['validate', '--cell', CELL, '--calibration', str(calibration),
                            '--bag', str(new), '--out', out]),
             (calibration, ['identify', '--cell', CELL, '--prior', str(calibration),
                            '--bag', str(new), '--out', out]),
             (mapping, ['import-csv', str(table), '--mapping', str(mapping),
                        '--out', str(tmp_path / 'o.mcap')]),
             (learned, ['validate', '--cell', CELL, '--calibration', str(beside),
                        '--bag', str(new), '--out', out])]
    for path, command in cases:
        code = main(command)
        err = capsys.readouterr().err
        assert code == 2, (command, err)
        assert f'{path} holds a character YAML does not allow (#x0000' in err, err
        assert 'give a' in err.splitlines()[-1], err
