"""colcon builds the package into a ROS install tree: executables, package.xml, config, launch."""
from __future__ import annotations

import ast
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from kpi_calib_ros.ros.parameters import PARAMETERS

REPO = Path(__file__).resolve().parents[1]
BIN = Path(sys.executable).parent
PACKAGE_FILES = ('package.xml', 'setup.py', 'setup.cfg', 'resource', 'config', 'launch',
                 'kpi_calib_ros')


@pytest.mark.slow
def test_colcon_build_installs_the_ros_package(tmp_path):
    source = tmp_path / 'ws' / 'src' / 'kpi_calib_ros'
    source.mkdir(parents=True)
    for name in PACKAGE_FILES:
        path = REPO / name
        if path.is_dir():
            shutil.copytree(path, source / name,
                            ignore=shutil.ignore_patterns('__pycache__', '*.egg-info'))
        else:
            shutil.copy2(path, source / name)
    env = {**os.environ, 'PATH': f'{BIN}{os.pathsep}{os.environ.get("PATH", "")}'}
    build = subprocess.run([str(BIN / 'colcon'), 'build'], cwd=tmp_path / 'ws', env=env,
                           capture_output=True, text=True, timeout=300)
    assert build.returncode == 0, build.stdout + build.stderr

    prefix = tmp_path / 'ws' / 'install' / 'kpi_calib_ros'
    share = prefix / 'share' / 'kpi_calib_ros'
    for path in (prefix / 'lib' / 'kpi_calib_ros' / 'kpi_calib_node',
                 prefix / 'lib' / 'kpi_calib_ros' / 'kpi-calib',
                 share / 'package.xml', share / 'config' / 'kpi_calib.params.yaml',
                 share / 'launch' / 'kpi_calib.launch.py',
                 prefix / 'share' / 'ament_index' / 'resource_index' / 'packages' /
                 'kpi_calib_ros'):
        assert path.is_file(), f'{path.relative_to(prefix)} missing from the install tree'
    assert os.access(prefix / 'lib' / 'kpi_calib_ros' / 'kpi_calib_node', os.X_OK)
    site = next(prefix.glob('lib/python3*/site-packages'))
    assert (site / 'kpi_calib_ros' / 'data' / 'robots' / 'kr15_class.urdf').is_file()
    assert (site / 'kpi_calib_ros' / 'data' / 'cells' / 'default_cell.yaml').is_file()

    # The installed CLI runs from the install tree (what `ros2 run` would start).
    run = subprocess.run([str(prefix / 'lib' / 'kpi_calib_ros' / 'kpi-calib'), '--help'],
                         env={**env, 'PYTHONPATH': str(site)}, cwd=tmp_path,
                         capture_output=True, text=True, timeout=60)
    assert run.returncode == 0 and 'replay' in run.stdout, run.stdout + run.stderr
    where = subprocess.run([sys.executable, '-c',
                            'import kpi_calib_ros; print(kpi_calib_ros.__file__)'],
                           env={**env, 'PYTHONPATH': str(site)}, cwd=tmp_path,
                           capture_output=True, text=True)
    assert where.stdout.startswith(str(site)), where.stdout


def test_launch_and_params_file_agree_with_the_node():
    """The params file sets only parameters the node declares; the launch file is the
    standard launch_ros form starting the installed executable with it."""
    doc = yaml.safe_load((REPO / 'config' / 'kpi_calib.params.yaml').read_text())
    params = doc['kpi_calib_node']['ros__parameters']
    assert set(params) <= set(PARAMETERS), set(params) - set(PARAMETERS)
    source = (REPO / 'launch' / 'kpi_calib.launch.py').read_text()
    tree = ast.parse(source)
    calls = [n for n in ast.walk(tree) if isinstance(n, ast.Call)
             and getattr(n.func, 'id', '') == 'Node']
    assert len(calls) == 1
    keywords = {k.arg: k.value for k in calls[0].keywords}
    assert ast.literal_eval(keywords['package']) == 'kpi_calib_ros'
    assert ast.literal_eval(keywords['executable']) == 'kpi_calib_node'
    assert 'kpi_calib.params.yaml' in source and 'parameters' in keywords
