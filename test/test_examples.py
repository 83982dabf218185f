"""Every script in examples/ runs as a user runs it, and what it prints is true: the TCP
error against the simulated truth within 3σ of the std eq. (19) predicts, the KPI design
beating the random one, the hidden effect found and its value recovered within 3σ, a work
cycle of the same robot blended and a bent one refused with the bent parameter named."""
from __future__ import annotations

import re
import runpy
import sys
from pathlib import Path

import pytest

EXAMPLES = Path(__file__).resolve().parents[1] / 'examples'
NUMBER = r'[-+]?\d+(?:\.\d+)?(?:e[-+]?\d+)?'


def _run(name: str, capsys: pytest.CaptureFixture[str]) -> str:
    # As a user runs it: no arguments (not pytest's own, which a script would read as its).
    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(sys, 'argv', [str(EXAMPLES / name)])
        runpy.run_path(str(EXAMPLES / name), run_name='__main__')
    return capsys.readouterr().out


def _vector(line: str, label: str) -> list[float]:
    inside = re.search(rf'{label} \[([^\]]*)\]', line)
    assert inside, f'no {label} [...] in {line!r}'
    return [float(v) for v in inside.group(1).split(',')]


def test_every_example_is_tested_and_shown_in_a_tutorial():
    scripts = sorted(p.name for p in EXAMPLES.glob('*.py'))
    tested = set(re.findall(r"_run\('([a-z_]+\.py)'", Path(__file__).read_text()))
    shown = ' '.join(p.read_text() for p in (EXAMPLES.parent / 'doc').rglob('*.md'))
    assert scripts and set(scripts) <= tested, f'examples without a test: {set(scripts) - tested}'
    missing = [s for s in scripts if f'examples/{s}' not in shown]
    assert missing == [], f'examples no doc page includes: {missing}'


def test_first_calibration_tcp_error_within_3_sigma_of_its_predicted_std(capsys):
    out = _run('first_calibration.py', capsys)
    lines = [line for line in out.splitlines() if line.startswith('TCP ')]
    assert lines, out
    for line in lines:
        error, std, z = (_vector(line, label) for label in ('error', 'std', 'z'))
        # The printed z is the printed error over the printed std (rounding of 0.1 µm).
        assert [e / s for e, s in zip(error, std)] == pytest.approx(z, abs=0.02)
        assert max(abs(v) for v in z) < 3.0, line
        # 60 poses at σ = 20 µm: the TCP is known to ~10 µm, not to σ or to a millimetre.
        assert all(2.0 < s < 20.0 for s in std), line


@pytest.mark.slow
def test_kpi_design_has_less_tcp_variance_than_random(capsys):
    out = _run('design_kpi_vs_random.py', capsys)
    kpi = {m.group(1): float(m.group(2))
           for m in re.finditer(rf'^\s*(kpi|random): KPI ({NUMBER}) m²', out, flags=re.M)}
    assert set(kpi) == {'kpi', 'random'}, out
    assert kpi['kpi'] < kpi['random']
    share = re.search(r'has (\d+)% less TCP variance', out)
    assert share and int(share.group(1)) == round(100 * (1 - kpi['kpi'] / kpi['random']))


@pytest.mark.slow
def test_the_hidden_compliance_is_found_and_recovered(capsys):
    out = _run('find_missing_effect.py', capsys)
    assert 'geometric model adequate: False' in out
    assert 'top candidate: joint_compliance:joint_2 ' in out
    before = float(re.search(rf'rms ({NUMBER}) µm', out).group(1))
    after = float(re.search(rf'rms after adding it: ({NUMBER}) µm', out).group(1))
    # σ = 20 µm per axis: a point's rms is about √3·20 = 35 µm once nothing is missing.
    assert after < before / 3 and after < 45.0
    c, c_std, c_true = (float(v) for v in re.search(
        rf'identified c = ({NUMBER}) ± ({NUMBER}) rad/\(N m\), true ({NUMBER})', out).groups())
    assert abs(c - c_true) < 3 * c_std


def test_a_work_cycle_blends_the_same_robot_and_refuses_a_bent_one(capsys):
    out = _run('work_cycle.py', capsys)
    cycle = next(line for line in out.splitlines() if line.startswith('cycle 1:'))
    assert 'consistent: True' in cycle
    assert max(abs(v) for v in _vector(cycle, 'z')) < 3.0
    bent = next(line for line in out.splitlines() if line.startswith('cycle 2:'))
    assert 'consistent: False' in bent
    name, shift, std = re.search(rf'moved most: (\S+) by ({NUMBER}) ± ({NUMBER}) mm',
                                 out).groups()
    assert name == 'joint_2.placement.tx'            # the bent parameter, named first
    assert abs(float(shift) - 1.0) < 3 * float(std)  # by the 1 mm it was bent


def test_the_examples_index_lists_every_script_by_task():
    """examples/README.md and doc/examples.md each name every script once, in a table row
    that says its task."""
    scripts = sorted(p.name for p in EXAMPLES.glob('*.py'))
    for index in (EXAMPLES / 'README.md', EXAMPLES.parent / 'doc' / 'examples.md'):
        rows = [line for line in index.read_text().splitlines() if line.startswith('| ')]
        listed = [m for line in rows for m in re.findall(r'examples/([a-z_]+\.py)', line)]
        assert sorted(set(listed)) == scripts, f'{index.name}: {set(scripts) ^ set(listed)}'


@pytest.mark.slow
def test_a_bag_written_and_read_back_calibrates_the_tcp_within_3_sigma(capsys):
    out = _run('calibrate_from_bag.py', capsys)
    paired = re.search(r'(\d+) measurements paired, valid: True', out)
    assert paired and int(paired.group(1)) == 50, out    # every point paired
    z = float(re.search(rf'largest \|z\| ({NUMBER})', out).group(1))
    assert z < 3.0


@pytest.mark.slow
def test_the_sequential_campaign_stops_at_its_target_with_the_tcp_within_3_sigma(capsys):
    out = _run('sequential_campaign.py', capsys)
    poses, initial, std = re.search(
        rf'(\d+) poses \((\d+) initial\), stopped: target met; largest TCP std ({NUMBER})',
        out).groups()
    assert int(initial) < int(poses) <= 200 and float(std) < 15.0
    assert float(re.search(rf'largest \|z\| ({NUMBER})', out).group(1)) < 3.0


@pytest.mark.slow
def test_the_learned_residual_brings_fresh_poses_to_the_noise(capsys):
    out = _run('learned_residual.py', capsys)
    assert out.startswith('learned residual chosen'), out
    physical, learned = (float(v) for v in re.search(
        rf'rms ({NUMBER}) µm physical, ({NUMBER}) µm with the learned', out).groups())
    # σ = 20 µm per axis: a point's rms is √3·20 = 35 µm; the 0.2 mm field is well above.
    assert physical > 100.0 and learned < 70.0 and learned < physical / 2


@pytest.mark.slow
def test_a_moved_tracker_fails_validation_as_is_and_holds_re_registered(capsys):
    out = _run('validate_new_recording.py', capsys)
    holds = dict(re.findall(r'^\s*(.+?): holds (True|False)', out, flags=re.M))
    assert holds == {'same set-up': 'True', 'set up again, as is': 'False',
                     'set up again, registered': 'True'}, out


@pytest.mark.slow
def test_two_tracker_stations_give_the_tcp_within_3_sigma_and_better_than_one(capsys):
    out = _run('several_recordings.py', capsys)
    assert 'recording.b.base.yaw = ' in out                 # station b's own placement
    z, both, alone = (float(v) for v in re.search(
        rf'within ({NUMBER})σ; largest TCP std ({NUMBER}) µm \(station a alone: ({NUMBER})',
        out).groups())
    assert z < 3.0 and both < alone


@pytest.mark.slow
def test_a_payload_recorded_per_row_recovers_the_compliance(capsys):
    out = _run('measured_inputs.py', capsys)
    c, c_std, c_true = (float(v) for v in re.search(
        rf'c = ({NUMBER}) ± ({NUMBER}) rad/\(N m\), true ({NUMBER})', out).groups())
    assert abs(c - c_true) < 3 * c_std
    rms = float(re.search(rf'rms ({NUMBER}) µm\n', out).group(1))
    blind = float(re.search(rf'one payload: rms ({NUMBER})', out).group(1))
    assert rms < 45.0 < 2 * rms < blind
