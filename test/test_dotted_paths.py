"""Every module path the prose names exists: dotted paths (``core.estimation.precision``,
``kpi_calib_ros.io.cell.load_cell``) and file paths (``core/model/robot.py``) in doc/, the
README, the package's docstrings and comments, the examples, the benches and ``--help``.

A module moved or renamed leaves its old name in the prose; this test finds it."""
from __future__ import annotations

import argparse
import importlib
import inspect
import io
import re
from pathlib import Path

import pytest

from kpi_calib_ros import cli
from kpi_calib_ros.core.effects.registry import ENTRY_POINT_GROUP

ROOT = Path(__file__).resolve().parents[1]
PACKAGE = ROOT / 'kpi_calib_ros'
LAYERS = ('core', 'io', 'app', 'ros', 'cli')

# A dotted path starts at the package or at one of its layers; it is not the tail of a
# longer name (``foo.core.x``) or of a file path (``test/core.x``).
DOTTED = re.compile(r'(?<![\w./-])((?:kpi_calib_ros|%s)(?:\.[A-Za-z_]\w*)+)' % '|'.join(LAYERS))
# Dotted names that are not module paths: the entry point group of user effects.
NOT_MODULES = {ENTRY_POINT_GROUP}
FILE = re.compile(r'(?<![\w./-])((?:kpi_calib_ros/)?(?:core|io|app|ros)/[\w/]+\.py)\b')


def _resolves(dotted: str) -> bool:
    """Whether ``dotted`` names a module of the package, or an attribute, a dataclass field
    or an annotated attribute of one."""
    parts = ('kpi_calib_ros.' + dotted if not dotted.startswith('kpi_calib_ros.')
             else dotted).split('.')
    for i in range(len(parts), 1, -1):
        try:
            obj = importlib.import_module('.'.join(parts[:i]))
        except ModuleNotFoundError:
            continue
        for name in parts[i:]:
            if hasattr(obj, name):
                obj = getattr(obj, name)
            elif name in getattr(obj, '__dataclass_fields__', {}) or \
                    name in getattr(obj, '__annotations__', {}) or _instance_attribute(obj, name):
                obj = None
            else:
                return False
        return True
    return False


def _instance_attribute(obj: object, name: str) -> bool:
    """Whether the class ``obj`` sets ``self.<name>`` in one of its methods."""
    if not inspect.isclass(obj):
        return False
    return re.search(rf'\bself\.{name}\s*(:[^=]*)?=', inspect.getsource(obj)) is not None


def broken_paths(text: str) -> list[str]:
    """The dotted and file paths in ``text`` that name nothing in the package."""
    bad = []
    for match in DOTTED.finditer(text):
        dotted = match.group(1)
        head, _, name = dotted.partition('.')
        if dotted.endswith('.py') or dotted in NOT_MODULES:
            continue  # a file name (``cli.py``): the file pattern's, or a bare name
        if head == 'io' and hasattr(io, name.split('.')[0]):
            continue  # the standard library's io (``io.StringIO``)
        if not _resolves(dotted):
            bad.append(dotted)
    for match in FILE.finditer(text):
        path = match.group(1)
        if not (ROOT / path).exists() and not (PACKAGE / path).exists():
            bad.append(path)
    return bad


def _sources() -> list[Path]:
    # doc/_generated holds the build's copies of bench/results/*.md: their sources are read.
    pages = [p for p in ROOT.glob('doc/**/*.md') if '_generated' not in p.parts]
    return sorted([*pages, ROOT / 'README.md', *PACKAGE.rglob('*.py'),
                   *ROOT.glob('examples/*.py'), *ROOT.glob('bench/*.py'),
                   *ROOT.glob('bench/results/*.md')])


def _help_texts() -> dict[str, str]:
    parser = cli.build_parser()
    texts = {'kpi-calib --help': parser.format_help()}
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for name, sub in action.choices.items():
                texts[f'kpi-calib {name} --help'] = sub.format_help()
    return texts


def test_the_checker_finds_a_moved_module_and_passes_the_real_ones():
    assert broken_paths('see core.drift_state.DriftSwing and core/precision.py') == [
        'core.drift_state.DriftSwing', 'core/precision.py']
    assert broken_paths('core.estimation.drift_state.DriftSwing, io.StringIO, cli.py, '
                        'kpi_calib_ros.io.bag.BagContents.point_sigma, '
                        'core/estimation/precision.py') == []
    assert broken_paths('kpi_calib_ros.core.estimation.precision.no_such_name') == [
        'kpi_calib_ros.core.estimation.precision.no_such_name']


@pytest.mark.parametrize('path', _sources(), ids=lambda p: str(p.relative_to(ROOT)))
def test_every_module_path_in_the_prose_and_code_exists(path):
    assert broken_paths(path.read_text(encoding='utf-8')) == []


def test_every_module_path_in_help_exists():
    bad = {cmd: found for cmd, text in _help_texts().items() if (found := broken_paths(text))}
    assert bad == {}
