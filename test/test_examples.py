"""Every script in examples/ runs as a user runs it, and what it prints is true: the TCP
error against the simulated truth within 3σ of the std eq. (19) predicts, the KPI design
beating the random one, the hidden effect found and its value recovered within 3σ, a work
cycle of the same robot blended and a bent one refused with the bent parameter named."""
from __future__ import annotations

import re
import runpy
from pathlib import Path

import pytest

EXAMPLES = Path(__file__).resolve().parents[1] / 'examples'
NUMBER = r'[-+]?\d+(?:\.\d+)?(?:e[-+]?\d+)?'


def _run(name: str, capsys: pytest.CaptureFixture[str]) -> str:
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


def test_kpi_design_has_less_tcp_variance_than_random(capsys):
    out = _run('design_kpi_vs_random.py', capsys)
    kpi = {m.group(1): float(m.group(2))
           for m in re.finditer(rf'^\s*(kpi|random): KPI ({NUMBER}) m²', out, flags=re.M)}
    assert set(kpi) == {'kpi', 'random'}, out
    assert kpi['kpi'] < kpi['random']
    share = re.search(r'has (\d+)% less TCP variance', out)
    assert share and int(share.group(1)) == round(100 * (1 - kpi['kpi'] / kpi['random']))


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
