"""The package's layers, checked on its source: core < io < app < ros < cli.

Every ``import`` of every module is read with :mod:`ast` (function-level imports
included), so a lower layer importing a higher one fails here whether or not the
import ever runs. Two rules beyond the order: io reads and writes files and topics but
builds no design or collision problem (it imports neither ``core.design`` nor
``core.collision``), and core computes but writes no file.
"""
from __future__ import annotations

import ast
import functools
import importlib
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parent.parent / 'kpi_calib_ros'
# The front door (api) gathers the app layer's jobs for scripts; the node and CLI use app.
LAYERS = {'core': 0, 'io': 1, 'app': 2, 'api': 2.5, 'ros': 3, 'cli': 4}
# Message, service and middleware packages: never in the numerical core.
ROS_ROOTS = ('rclpy', 'rosbag2_py', 'builtin_interfaces', 'rcl_interfaces')
ROS_SUFFIXES = ('_msgs', '_srvs', '_interfaces')


@functools.lru_cache(maxsize=None)
def _parse(text: str, filename: str) -> ast.Module:
    """The syntax tree of ``text``, parsed once: some 300 checks read the same modules."""
    return ast.parse(text, filename)


def _module_name(path: Path) -> str:
    rel = path.relative_to(PACKAGE.parent).with_suffix('')
    parts = list(rel.parts)
    if parts[-1] == '__init__':
        parts = parts[:-1]
    return '.'.join(parts)


def _layer(module: str) -> int | None:
    """Layer of a ``kpi_calib_ros`` module; None for the package root (no code but env)."""
    parts = module.split('.')
    if parts[0] != 'kpi_calib_ros' or len(parts) < 2:
        return None
    if parts[1] not in LAYERS:
        raise AssertionError(f'{module} is in no layer; place it under one of {sorted(LAYERS)}')
    return LAYERS[parts[1]]


def _imports(path: Path) -> list[tuple[int, str]]:
    """(line, absolute module name) of every import in ``path``."""
    tree = _parse(path.read_text(), str(path))
    package = _module_name(path).rsplit('.', 0 if path.name == '__init__.py' else 1)[0]
    found = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            found += [(node.lineno, alias.name) for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split('.')
                base = base[:len(base) - node.level + 1]
                name = '.'.join(base + ([node.module] if node.module else []))
            else:
                name = node.module or ''
            found.append((node.lineno, name))
            # ``from kpi_calib_ros import io`` or ``from kpi_calib_ros.core import design``
            # names a sub-package or module of a package, not just the package.
            if (PACKAGE.parent / name.replace('.', '/')).is_dir():
                found += [(node.lineno, f'{name}.{a.name}') for a in node.names]
    return found


def _sources() -> list[Path]:
    return sorted(PACKAGE.rglob('*.py'))


def test_every_module_is_in_a_layer():
    for path in _sources():
        _layer(_module_name(path))  # raises for a module outside the layers


@pytest.mark.parametrize('path', _sources(), ids=lambda p: str(p.relative_to(PACKAGE)))
def test_no_module_imports_a_higher_layer(path):
    own = _layer(_module_name(path))
    if own is None:
        return
    upward = [f'line {line}: {name}' for line, name in _imports(path)
              if name.startswith('kpi_calib_ros.') and (_layer(name) or 0) > own]
    assert not upward, f'{path.name} (layer {own}) imports a higher layer: {upward}'


# Inside core, each family may import only from those before it (and from itself).
CORE_ORDER = {'errors': 0, 'model': 1, 'measurement': 2, 'effects': 3, 'acquisition': 4,
              'collision': 5, 'estimation': 6, 'simulation': 7, 'diagnosis': 8, 'design': 9,
              'campaigns': 10}


def _core_rank(module: str) -> int | None:
    """Rank of a ``kpi_calib_ros.core`` module in :data:`CORE_ORDER`; None outside core."""
    parts = module.split('.')
    if parts[:2] != ['kpi_calib_ros', 'core'] or len(parts) < 3:
        return None
    if parts[2] not in CORE_ORDER:
        raise AssertionError(f'{module} is in no core family; add it to a sub-package of core '
                             f'(and to CORE_ORDER if it is a new family)')
    return CORE_ORDER[parts[2]]


@pytest.mark.parametrize('path', sorted((PACKAGE / 'core').rglob('*.py')),
                         ids=lambda p: str(p.relative_to(PACKAGE / 'core')))
def test_core_families_import_only_earlier_ones(path):
    own = _core_rank(_module_name(path))
    if own is None:
        return
    later = [f'line {line}: {name}' for line, name in _imports(path)
             if (_core_rank(name) or 0) > own]
    assert not later, f'{path.name} (core rank {own}) imports a later core family: {later}'


def test_the_core_order_checker_sees_a_later_family():
    assert _core_rank('kpi_calib_ros.core.estimation.robust') > _core_rank(
        'kpi_calib_ros.core.model.robot')
    with pytest.raises(AssertionError, match='no core family'):
        _core_rank('kpi_calib_ros.core.stray_module')


@pytest.mark.parametrize('path', sorted((PACKAGE / 'core').rglob('*.py')),
                         ids=lambda p: str(p.relative_to(PACKAGE / 'core')))
def test_every_core_module_declares_its_public_names(path):
    """``__all__`` in every core module and family package, and every name in it exists."""
    if path == PACKAGE / 'core' / '__init__.py':
        return
    tree = _parse(path.read_text(), str(path))
    declared = [node for node in tree.body if isinstance(node, ast.Assign)
                and any(isinstance(t, ast.Name) and t.id == '__all__' for t in node.targets)]
    assert declared, f'{path.name} declares no __all__'
    module = importlib.import_module(_module_name(path))
    missing = [name for name in module.__all__ if not hasattr(module, name)]
    assert not missing, f'{path.name}: __all__ names what it does not have: {missing}'


@pytest.mark.parametrize('path', sorted((PACKAGE / 'core').rglob('*.py')),
                         ids=lambda p: p.name)
def test_core_never_imports_ros(path):
    ros = [f'line {line}: {name}' for line, name in _imports(path)
           if name.split('.')[0] in ROS_ROOTS or name.split('.')[0].endswith(ROS_SUFFIXES)]
    assert not ros, f'core module {path.name} imports ROS: {ros}'


def test_argparse_only_in_the_cli():
    users = [str(p.relative_to(PACKAGE)) for p in _sources()
             if p.name != 'cli.py' and any(n == 'argparse' for _, n in _imports(p))]
    assert not users, f'argparse outside cli.py: {users}'


# Private helpers still shared across modules; each is to become public in its home module
# (or stop being shared). The list may only shrink.
KNOWN_PRIVATE: set[str] = set()


def test_no_private_names_imported_across_modules():
    private = []
    for path in _sources():
        for node in ast.walk(_parse(path.read_text(), str(path))):
            if isinstance(node, ast.ImportFrom) and (node.module or '').startswith('kpi_calib_ros'):
                private += [f'{path.name}: {node.module}.{a.name}' for a in node.names
                            if a.name.startswith('_')]
    new = sorted(set(private) - KNOWN_PRIVATE)
    assert not new, f'private names imported from another module: {new}'


def test_the_checker_sees_upward_and_relative_imports(tmp_path, monkeypatch):
    """The checker itself can fail: absolute and relative upward imports are both seen."""
    fake = PACKAGE / 'io' / 'zz_fake_module.py'
    monkeypatch.setattr(Path, 'read_text', lambda self, *a, **k: (
        'from kpi_calib_ros.app.identify import run_identify\n'
        'def f():\n    from ..ros import node\n'))
    names = [n for _, n in _imports(fake)]
    assert names == ['kpi_calib_ros.app.identify', 'kpi_calib_ros.ros', 'kpi_calib_ros.ros.node']
    assert all(_layer(n) > _layer(_module_name(fake)) for n in names)


def _module_graph() -> dict[str, set[str]]:
    """Module -> the package modules it imports (a sub-module import names its module)."""
    modules = {_module_name(p): p for p in _sources()}
    graph = {}
    for name, path in modules.items():
        targets = set()
        for _, imported in _imports(path):
            while imported and imported not in modules:
                imported = imported.rpartition('.')[0]
            if imported and imported != name and imported != 'kpi_calib_ros':
                targets.add(imported)
        graph[name] = targets
    return graph


def _cycle(graph: dict[str, set[str]]) -> list[str]:
    state: dict[str, int] = {}
    stack: list[str] = []

    def visit(node: str) -> list[str]:
        state[node] = 1
        stack.append(node)
        for nxt in sorted(graph.get(node, ())):
            if state.get(nxt) == 1:
                return stack[stack.index(nxt):] + [nxt]
            if nxt not in state and (found := visit(nxt)):
                return found
        stack.pop()
        state[node] = 2
        return []

    for node in sorted(graph):
        if node not in state and (found := visit(node)):
            return found
    return []


def test_no_import_cycles():
    cycle = _cycle(_module_graph())
    assert not cycle, f'import cycle: {" -> ".join(cycle)}'


def test_the_cycle_finder_finds_a_cycle():
    assert _cycle({'a': {'b'}, 'b': {'c'}, 'c': {'a'}}) == ['a', 'b', 'c', 'a']
    assert _cycle({'a': {'b'}, 'b': set(), 'c': {'a', 'b'}}) == []


# A module says one thing: at most MODULE_LINES lines. The modules still over it, each at
# most its present length, until it is split (they may shrink, never grow).
MODULE_LINES = 600
OVER_THE_LIMIT: dict[str, int] = {}


def test_no_module_grows_past_its_limit():
    """Every module is at most 600 lines, or at most its length when it was last counted
    over the limit; a module split below the limit leaves the list."""
    lengths = {str(path.relative_to(PACKAGE.parent)): len(path.read_text().splitlines())
               for path in PACKAGE.rglob('*.py')}
    too_long = {name: n for name, n in lengths.items()
                if n > OVER_THE_LIMIT.get(name, MODULE_LINES)}
    assert too_long == {}, f'modules over their line limit (split them): {too_long}'
    split = sorted(name for name in OVER_THE_LIMIT if lengths.get(name, 0) <= MODULE_LINES)
    assert split == [], f'now within {MODULE_LINES} lines, drop from OVER_THE_LIMIT: {split}'


# io turns files into plain data and back; the design and collision objects are built in app.
MODEL_BUILDING = {'kpi_calib_ros.core.design', 'kpi_calib_ros.core.collision'}


def _builds_models(module: str) -> bool:
    return '.'.join(module.split('.')[:3]) in MODEL_BUILDING


@pytest.mark.parametrize('path', sorted((PACKAGE / 'io').rglob('*.py')),
                         ids=lambda p: str(p.relative_to(PACKAGE / 'io')))
def test_io_imports_no_design_or_collision_code(path):
    found = [f'line {line}: {name}' for line, name in _imports(path) if _builds_models(name)]
    assert not found, f'io module {path.name} imports design/collision code (build those ' \
                      f'objects in app): {found}'


def test_the_io_checker_sees_a_design_import(monkeypatch):
    fake = PACKAGE / 'io' / 'zz_fake_module.py'
    monkeypatch.setattr(Path, 'read_text', lambda self, *a, **k: (
        'from kpi_calib_ros.core import collision\n'
        'def f():\n    from ..core.design.cell import DesignCell\n'))
    names = [n for _, n in _imports(fake) if _builds_models(n)]
    assert names == ['kpi_calib_ros.core.collision', 'kpi_calib_ros.core.design.cell']


# What writes a file, read off the call: the rule core is checked against.
# ``open(...)`` / ``<path>.open(...)`` with a mode holding w, a, x or + (or a mode not
# written out); these module functions; these methods (Path's and matplotlib's writers);
# yaml's dumpers given a stream; and importing tempfile or shutil at all.
WRITING_FUNCTIONS = {
    'os.replace', 'os.rename', 'os.remove', 'os.unlink', 'os.mkdir', 'os.makedirs',
    'os.rmdir', 'os.truncate', 'os.symlink', 'os.link', 'os.open', 'os.fdopen',
    'numpy.save', 'numpy.savez', 'numpy.savez_compressed', 'numpy.savetxt',
    'json.dump', 'pickle.dump', 'io.open'}
WRITING_METHODS = {'write_text', 'write_bytes', 'savefig', 'mkdir', 'touch', 'unlink', 'rmdir',
                   'rename', 'symlink_to', 'hardlink_to', 'tofile', 'to_csv'}
YAML_DUMPERS = {'yaml.dump', 'yaml.safe_dump', 'yaml.dump_all', 'yaml.safe_dump_all'}
WRITING_MODULES = ('tempfile', 'shutil')


def _dotted(node: ast.AST, aliases: dict[str, str]) -> str:
    """``np.save`` as ``numpy.save`` (import aliases resolved); '' when not a plain name."""
    parts = []
    while isinstance(node, ast.Attribute):
        parts.append(node.attr)
        node = node.value
    if not isinstance(node, ast.Name):
        return ''
    parts.append(aliases.get(node.id, node.id))
    return '.'.join(reversed(parts))


def _writes_mode(mode: ast.AST | None) -> bool:
    if mode is None:
        return False
    if isinstance(mode, ast.Constant) and isinstance(mode.value, str):
        return any(c in mode.value for c in 'wax+')
    return True  # a mode computed at run time may write


def _file_writes(tree: ast.AST) -> list[str]:
    """``line N: what`` for every file write in ``tree`` by the rule above."""
    aliases: dict[str, str] = {}
    found = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            aliases.update({a.asname or a.name: a.name for a in node.names})
            found += [f'line {node.lineno}: import {a.name}' for a in node.names
                      if a.name.split('.')[0] in WRITING_MODULES]
        elif isinstance(node, ast.ImportFrom) and not node.level:
            aliases.update({a.asname or a.name: f'{node.module}.{a.name}' for a in node.names})
            if (node.module or '').split('.')[0] in WRITING_MODULES:
                found.append(f'line {node.lineno}: from {node.module} import')
    for node in ast.walk(tree):
        if not isinstance(node, ast.Call):
            continue
        name = _dotted(node.func, aliases)
        keywords = {k.arg: k.value for k in node.keywords}
        if name in ('open', 'builtins.open'):
            mode = node.args[1] if len(node.args) > 1 else keywords.get('mode')
            writes = _writes_mode(mode)
        elif isinstance(node.func, ast.Attribute) and node.func.attr == 'open' \
                and name not in WRITING_FUNCTIONS:
            writes = _writes_mode(node.args[0] if node.args else keywords.get('mode'))
        elif name in YAML_DUMPERS:
            writes = len(node.args) > 1 or keywords.get('stream') is not None
        else:
            writes = name in WRITING_FUNCTIONS or (
                isinstance(node.func, ast.Attribute) and node.func.attr in WRITING_METHODS)
        if writes:
            found.append(f'line {node.lineno}: {name or ast.unparse(node.func)}(...)')
    return found


@pytest.mark.parametrize('path', sorted((PACKAGE / 'core').rglob('*.py')),
                         ids=lambda p: str(p.relative_to(PACKAGE / 'core')))
def test_core_writes_no_file(path):
    writes = _file_writes(_parse(path.read_text(), str(path)))
    assert not writes, f'core module {path.name} writes a file (do that in io): {writes}'


def test_the_write_checker_sees_every_kind_of_write():
    source = '\n'.join([
        'import numpy as np, yaml, json',
        'import tempfile',
        'from os import replace as swap',
        'from pathlib import Path',
        'def f(p, doc, fig, a, mode):',
        '    open(p, "w"); open(p, mode=mode); Path(p).open("a")',
        '    Path(p).write_text("x"); fig.savefig(p); np.savez(p, a=a)',
        '    yaml.safe_dump(doc, stream=p); json.dump(doc, p); swap(p, p)',
        # reads and text: none of these writes
        '    open(p); open(p, "rb"); Path(p).open(); Path(p).read_text()',
        '    yaml.safe_dump(doc); json.dumps(doc); "ab".replace("a", "b")',
    ])
    found = _file_writes(ast.parse(source))
    assert [w.split(': ', 1)[1] for w in found] == [
        'import tempfile', 'open(...)', 'open(...)', 'Path(p).open(...)',
        'Path(p).write_text(...)', 'fig.savefig(...)', 'numpy.savez(...)',
        'yaml.safe_dump(...)', 'json.dump(...)', 'os.replace(...)']
