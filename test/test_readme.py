"""The README is the short entry point (at most 200 lines): what the package is, the two
commands, the demo, and where to go next; every file it points to exists."""
from __future__ import annotations

import re
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
README = (REPO / 'README.md').read_text()


def test_readme_is_at_most_200_lines():
    assert len(README.splitlines()) <= 200


def test_every_path_the_readme_names_exists():
    paths = set(re.findall(r'`((?:doc|examples|bench/results|config)/[^`\s]*)`', README))
    paths |= set(re.findall(r'\]\(((?:doc)/[^)\s]+)\)', README))
    paths |= {p for p in re.findall(r'`([A-Za-z_.]+\.(?:rst|txt|md))`', README)}
    assert len(paths) >= 10
    missing = sorted(p for p in paths if not (REPO / p).exists())
    assert missing == [], f'the README points to files that do not exist: {missing}'


def test_the_two_commands_are_make_targets():
    makefile = (REPO / 'Makefile').read_text()
    for target in re.findall(r'^make (\w+)', README, flags=re.M) + ['check', 'doc']:
        assert re.search(rf'^{target}:', makefile, flags=re.M), target


def test_ci_runs_the_readme_test_command_then_the_slow_studies():
    """CI calls the README's test command, so a missing install step fails there, and then
    the tests marked slow that `make test` leaves out."""
    ci = [line.strip() for line in (REPO / '.ci' / 'run').read_text().splitlines()
          if line.strip().startswith('make ')]
    assert ci == ['make test', 'make test-slow']
    makefile = (REPO / 'Makefile').read_text()
    recipe = re.search(r'^test-slow:.*\n\t(.*)$', makefile, flags=re.M).group(1)
    assert recipe.endswith('-m slow test')


@pytest.mark.slow
def test_the_demo_summary_the_readme_quotes_is_what_the_demo_prints(tmp_path, capsys):
    from kpi_calib_ros.app.demo import run_demo
    assert run_demo(tmp_path, seed=7) == 0
    printed = capsys.readouterr().out.splitlines()
    block = README.split('Lines\nof its summary (seed 7):\n\n```text\n', 1)[1].split('```', 1)[0]
    quoted = [line for line in block.splitlines() if line.strip()]
    assert len(quoted) >= 10
    assert [line for line in quoted if line not in printed] == []
    assert (tmp_path / 'diagnosis' / 'before_after.png').is_file()
