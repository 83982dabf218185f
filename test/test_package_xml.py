"""package.xml declares every dependency the code imports (what rosdep installs is all
that a ROS install of the package has)."""
from __future__ import annotations

import ast
import sys
import xml.etree.ElementTree as ET
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
PACKAGE = 'kpi_calib_ros'

# Imported top-level module -> its rosdep key. A ROS package's Python module has the
# package's name; the others are rosdep's python3-* keys, '-pip' where rosdep knows the
# module only from PyPI.
ROSDEP_KEYS = {
    **{name: name for name in (
        'rclpy', 'rcl_interfaces', 'builtin_interfaces', 'std_msgs', 'std_srvs',
        'sensor_msgs', 'geometry_msgs', 'trajectory_msgs', 'visualization_msgs',
        'diagnostic_msgs', 'launch', 'launch_ros', 'ament_index_python', 'pinocchio',
        'coal')},
    'numpy': 'python3-numpy',
    'scipy': 'python3-scipy',
    'yaml': 'python3-yaml',
    'matplotlib': 'python3-matplotlib',
    'casadi': 'python3-casadi-pip',
    'mcap': 'python3-mcap-pip',
    'mcap_ros2': 'python3-mcap-ros2-support-pip',
    'pytest': 'python3-pytest',
    'hypothesis': 'python3-hypothesis',
    'lz4': 'python3-lz4',
    'zstandard': 'python3-zstandard',
    'sklearn': 'python3-sklearn',
}


def imported_modules(paths: list[Path]) -> dict[str, set[str]]:
    """Top-level modules imported anywhere in ``paths`` (also inside functions), each
    with the files that import it; the standard library and relative imports left out."""
    found: dict[str, set[str]] = {}
    for path in paths:
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if isinstance(node, ast.Import):
                names = [alias.name for alias in node.names]
            elif isinstance(node, ast.ImportFrom) and not node.level:
                names = [node.module]
            else:
                continue
            for name in names:
                top = name.split('.')[0]
                if top not in sys.stdlib_module_names and top != '__future__':
                    found.setdefault(top, set()).add(str(path.relative_to(REPO)))
    return found


def declared(*tags: str) -> set[str]:
    root = ET.parse(REPO / 'package.xml').getroot()
    return {e.text.strip() for tag in tags for e in root.iter(tag)}


def undeclared(modules: dict[str, set[str]], keys: set[str]) -> dict[str, str]:
    problems = {}
    for module, files in sorted(modules.items()):
        key = ROSDEP_KEYS.get(module)
        if key is None:
            problems[module] = (f'imported by {sorted(files)}: add its rosdep key to '
                                f'ROSDEP_KEYS here and to package.xml')
        elif key not in keys:
            problems[module] = f'imported by {sorted(files)}: package.xml lacks {key!r}'
    return problems


def test_every_module_the_package_imports_is_an_exec_depend():
    files = sorted((REPO / PACKAGE).rglob('*.py')) + sorted((REPO / 'launch').glob('*.py'))
    modules = imported_modules(files)
    modules.pop(PACKAGE)
    assert {'rclpy', 'numpy', 'coal', 'launch_ros'} <= set(modules)  # the scan sees them
    keys = declared('exec_depend', 'depend')
    assert undeclared(modules, keys) == {}


def test_every_module_the_tests_import_is_declared():
    files = sorted((REPO / 'test').glob('*.py'))
    # The tests' helpers and the benches a test reuses (sys.path) are ours, not packages.
    local = {p.stem for p in files} | {p.stem for p in (REPO / 'bench').glob('*.py')}
    modules = {m: f for m, f in imported_modules(files).items()
               if m != PACKAGE and m not in local}
    assert 'pytest' in modules
    keys = declared('exec_depend', 'depend', 'test_depend')
    assert undeclared(modules, keys) == {}


def test_the_check_names_a_missing_dependency():
    problems = undeclared({'numpy': {'a.py'}, 'left_pad': {'b.py'}}, keys=set())
    assert "lacks 'python3-numpy'" in problems['numpy']
    assert 'add its rosdep key' in problems['left_pad']
