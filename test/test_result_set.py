"""A calibration's result files written as one unit (io.result_set, app.finish): every
way to finish a calibration writes the same set, and a full disk (a real tmpfs) leaves
the old set whole -- never a new learned_residual.yaml beside the old calibration.yaml."""
from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest
import yaml

from kpi_calib_ros.app.cell_model import build_cell_model
from kpi_calib_ros.app.measurements import measurements_from_bag
from kpi_calib_ros.cli import main
from kpi_calib_ros.core.acquisition.streams import synthesize_streams
from kpi_calib_ros.core.campaigns.settings import CampaignSettings
from kpi_calib_ros.core.errors import ConfigError
from kpi_calib_ros.core.simulation import (
    random_configurations,
    simulate_measurements,
    true_parameters,
)
from kpi_calib_ros.io import result_set
from kpi_calib_ros.io.bag_writing import write_bag
from kpi_calib_ros.io.cell import DEFAULT_CELL, load_cell
from kpi_calib_ros.io.names import (
    CALIBRATED_URDF_FILE,
    CALIBRATION_FILE,
    CALIBRATIONS_DIR,
    CAMPAIGN_PLAN_FILE,
    CAMPAIGN_STATE_FILE,
    LEARNED_RESIDUAL_FILE,
)
from kpi_calib_ros.io.result_set import PENDING_DIR, complete_pending, write_result_set
from kpi_calib_ros.ros import job_work

from full_disk import fill, small_tmpfs, snapshot

CELL = str(DEFAULT_CELL)
START_NS = 1_700_000_000_000_000_000
OLD = {CALIBRATION_FILE: 'old calibration\n', CALIBRATED_URDF_FILE: '<robot name="old"/>\n',
       LEARNED_RESIDUAL_FILE: 'old learned residual\n'}


def _old_set(folder: Path) -> None:
    folder.mkdir(parents=True, exist_ok=True)
    for name, text in OLD.items():
        (folder / name).write_text(text)


def test_a_set_replaces_the_old_one_and_removes_a_member_it_lacks(tmp_path):
    _old_set(tmp_path)
    written = write_result_set(tmp_path, {LEARNED_RESIDUAL_FILE: None,
                                          CALIBRATED_URDF_FILE: 'new urdf',
                                          f'{CALIBRATIONS_DIR}/7.yaml': 'new',
                                          CALIBRATION_FILE: 'new'})
    assert snapshot(tmp_path) == {CALIBRATED_URDF_FILE: b'new urdf', CALIBRATION_FILE: b'new',
                                  f'{CALIBRATIONS_DIR}/7.yaml': b'new'}
    assert set(written) == {CALIBRATED_URDF_FILE, f'{CALIBRATIONS_DIR}/7.yaml',
                            CALIBRATION_FILE}
    assert oct((tmp_path / CALIBRATION_FILE).stat().st_mode & 0o777) == oct(0o644 & ~_umask())


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def test_a_writer_killed_among_the_renames_is_completed_before_the_next_read(tmp_path,
                                                                            monkeypatch):
    """The renames after the commit point stopped half way (as a killed process leaves
    them): complete_pending -- run by the next write and by the node before it restores
    -- moves the rest, so the folder holds the new set, not a mix."""
    _old_set(tmp_path)
    moves = []
    real = os.replace

    def killed(src, dst):
        if moves:
            raise KeyboardInterrupt  # stands for the process dying here
        moves.append(dst)
        real(src, dst)
    monkeypatch.setattr(result_set.os, 'replace', killed)
    with pytest.raises(KeyboardInterrupt):
        write_result_set(tmp_path, {LEARNED_RESIDUAL_FILE: 'new learned',
                                    CALIBRATED_URDF_FILE: 'new urdf', CALIBRATION_FILE: 'new'})
    assert (tmp_path / PENDING_DIR).is_dir()
    assert (tmp_path / LEARNED_RESIDUAL_FILE).read_text() == 'new learned'
    assert (tmp_path / CALIBRATION_FILE).read_text() == OLD[CALIBRATION_FILE]
    monkeypatch.setattr(result_set.os, 'replace', real)
    complete_pending(tmp_path)
    assert snapshot(tmp_path) == {LEARNED_RESIDUAL_FILE: b'new learned',
                                  CALIBRATED_URDF_FILE: b'new urdf', CALIBRATION_FILE: b'new'}


def test_a_full_file_system_leaves_the_old_set_and_no_temporary_file(tmp_path):
    with small_tmpfs(tmp_path / 'disk', '1m') as disk:
        folder = disk / 'out'
        _old_set(folder)
        before = snapshot(folder)
        fill(disk, 8192)
        with pytest.raises(ConfigError) as info:
            write_result_set(folder, {LEARNED_RESIDUAL_FILE: 'x' * 4000,
                                      CALIBRATED_URDF_FILE: 'u' * 20000,
                                      CALIBRATION_FILE: 'c' * 20000})
        assert str(folder) in str(info.value) and 'No space left on device' in str(info.value)
        assert 'intact' in str(info.value) and info.value.key == '--out'
        assert snapshot(folder) == before
        assert sorted(p.name for p in folder.iterdir()) == sorted(OLD)


def _bag(cm, path: Path, n: int, seed: int, start_ns: int) -> Path:
    rng = np.random.default_rng(seed)
    p_true = true_parameters(cm.model.params, np.random.default_rng(1))
    q = random_configurations(cm.model, p_true, n, rng)
    eta = simulate_measurements(cm.model, p_true, q, cm.cell.sigma, rng).eta
    joints, points = synthesize_streams(q, cm.joint_names, eta, cm.cell.tracker_frame,
                                        start_ns=start_ns, rng=rng)
    return write_bag(path, joints, points)


def _result_names(folder: Path) -> set[str]:
    """The files a finished calibration left (an archived copy as calibrations/*); the
    plots the CLI draws beside them (identification.png, change_test.png) are reports, not
    part of the result set."""
    names = set()
    for name in snapshot(folder):
        if name in (CAMPAIGN_PLAN_FILE, CAMPAIGN_STATE_FILE) or name.endswith('.png'):
            continue
        names.add(f'{CALIBRATIONS_DIR}/*' if name.startswith(CALIBRATIONS_DIR) else name)
    return names


@pytest.mark.slow
def test_every_way_to_finish_a_calibration_writes_the_same_set(tmp_path, capsys):
    """CLI identify, identify --prior, the node's ~/identify and its sequential campaign,
    each into a folder holding an older set with a learned_residual.yaml: each leaves
    calibration.yaml and the calibrated URDF (the node's two also the archived copy,
    equal to calibration.yaml), and no path keeps the stale learned residual."""
    cm = build_cell_model(load_cell(DEFAULT_CELL))
    bag = _bag(cm, tmp_path / 'a.mcap', 40, 2, START_NS)
    later = _bag(cm, tmp_path / 'b.mcap', 40, 3, START_NS + 3_600_000_000_000)
    folders = {k: tmp_path / k for k in ('identify', 'prior', 'node', 'campaign')}
    for folder in folders.values():
        _old_set(folder)
    assert main(['identify', '--cell', CELL, '--bag', str(bag),
                 '--out', str(folders['identify'])]) == 0
    prior = folders['identify'] / CALIBRATION_FILE
    assert main(['identify', '--cell', CELL, '--bag', str(later), '--prior', str(prior),
                 '--out', str(folders['prior'])]) == 0
    capsys.readouterr()
    data, pairing = measurements_from_bag(cm, bag)
    out = job_work.identify_work(cm, data, pairing, folders['node'])
    assert out.calibration is not None and out.calibration.valid
    campaign, initial, _, _ = job_work.sequential_start_work(
        cm, CampaignSettings(target_std=1.0, max_measurements=60), 0, folders['campaign'])
    q = cm.joint_coupling.to_urdf(initial)
    rng = np.random.default_rng(5)
    p_true = true_parameters(cm.model.params, np.random.default_rng(1))
    eta = simulate_measurements(cm.model, p_true, q, cm.cell.sigma, rng).eta
    from kpi_calib_ros.core.measurement.data import Measurements
    from kpi_calib_ros.io.campaign_io import CampaignState
    step = job_work.sequential_step_work(
        campaign, cm, Measurements(q=q, eta=eta, stamps_ns=START_NS + 10 ** 9 * np.arange(
            1, len(q) + 1)), CampaignState(campaign.settings, 0), folders['campaign'])
    assert step.status.stopped and step.calibration is not None
    cli = {CALIBRATION_FILE, CALIBRATED_URDF_FILE}
    node = cli | {f'{CALIBRATIONS_DIR}/*'}
    assert {k: _result_names(f) for k, f in folders.items()} == {
        'identify': cli, 'prior': cli, 'node': node, 'campaign': node}
    for key in ('node', 'campaign'):
        folder = folders[key]
        text = (folder / CALIBRATION_FILE).read_text()
        stamp = yaml.safe_load(text)['identified_at_ns']
        assert (folder / CALIBRATIONS_DIR / f'{stamp}.yaml').read_text() == text
    for folder in folders.values():
        assert not (folder / LEARNED_RESIDUAL_FILE).exists()
        assert not list(folder.glob('.result_set*'))


def _misfit_cell(tmp_path: Path) -> Path:
    doc = yaml.safe_load(DEFAULT_CELL.read_text())
    doc['robot']['urdf'] = str((DEFAULT_CELL.parent / doc['robot']['urdf']).resolve())
    doc['simulation'] = {'hidden_effects': {'cyclic_joint_error_h2:joint_2':
                                            {'a': 4e-4, 'b': 2e-4}}}
    cell = tmp_path / 'misfit.yaml'
    cell.write_text(yaml.safe_dump(doc))
    return cell


@pytest.mark.slow
def test_identify_on_a_full_disk_exits_2_and_keeps_the_old_set_whole(tmp_path, capsys):
    """A real full file system (tmpfs) under --out with a calibration and its learned
    residual: identify --learned-residual again, with room left for a new learned
    residual but not for the rest. Exit 2 naming the folder and that the old result is
    intact; every file as it was, no temporary file left (the old code put the new
    learned_residual.yaml beside the old calibration.yaml and ended with a traceback)."""
    cell = _misfit_cell(tmp_path)
    bags = []
    for seed in (4, 6):
        bags.append(tmp_path / f'{seed}.mcap')
        assert main(['simulate', '--cell', str(cell), '--n', '90', '--out', str(bags[-1]),
                     '--seed', str(seed)]) == 0

    def identify(bag: Path, out: Path) -> int:
        return main(['identify', '--cell', str(cell), '--bag', str(bag), '--out', str(out),
                     '--model', 'geometric', '--learned-residual'])
    # The second identification's files, written where there is room: their sizes.
    assert identify(bags[1], tmp_path / 'roomy') == 0
    new = snapshot(tmp_path / 'roomy')
    assert LEARNED_RESIDUAL_FILE in new and len(new[CALIBRATION_FILE]) > 48 * 1024
    with small_tmpfs(tmp_path / 'disk', '16m') as disk:
        out = disk / 'out'
        assert identify(bags[0], out) == 0
        before = snapshot(out)
        assert LEARNED_RESIDUAL_FILE in before
        # Room for the new learned residual once the old one is gone, not for the rest.
        fill(disk, max(len(new[LEARNED_RESIDUAL_FILE]) - len(before[LEARNED_RESIDUAL_FILE]),
                       0) + 32 * 1024)
        capsys.readouterr()
        code = identify(bags[1], out)
        err = capsys.readouterr().err
        assert code == 2, err
        assert f'cannot write the results to {out}' in err and 'No space left' in err, err
        assert 'intact' in err and 'Traceback' not in err, err
        assert snapshot(out) == before
        assert sorted(p.name for p in out.iterdir()) == sorted(before)


@pytest.mark.slow
def test_the_nodes_calibration_has_the_command_lines_sections(tmp_path, capsys):
    """With the cell's tolerance prior and an effect, ~/identify's calibration.yaml holds
    the ``prior:`` and ``effects_comparison:`` sections identify writes, equal to them;
    before, the node's had neither."""
    doc = yaml.safe_load(DEFAULT_CELL.read_text())
    doc['robot']['urdf'] = str((DEFAULT_CELL.parent / doc['robot']['urdf']).resolve())
    doc['identification'] = {'prior': {'translation': 1e-3, 'rotation': 1e-3, 'offset': 1e-3}}
    doc['effects'] = ['joint_compliance:joint_2']
    cell = tmp_path / 'cell.yaml'
    cell.write_text(yaml.safe_dump(doc))
    cm = build_cell_model(load_cell(cell))
    bag = _bag(cm, tmp_path / 'a.mcap', 40, 2, START_NS)
    assert main(['identify', '--cell', str(cell), '--bag', str(bag),
                 '--out', str(tmp_path / 'cli')]) == 0
    capsys.readouterr()
    data, pairing = measurements_from_bag(cm, bag)
    out = job_work.identify_work(cm, data, pairing, tmp_path / 'node')
    assert out.calibration is not None and out.calibration.valid
    cli, node = (yaml.safe_load((tmp_path / k / CALIBRATION_FILE).read_text())
                 for k in ('cli', 'node'))
    assert 'joint_compliance.joint_2.c' in {p['name'] for p in node['parameters']}
    for section in ('prior', 'effects_comparison'):
        assert section in cli and node.get(section) == cli[section], section
    assert set(node) == set(cli)
