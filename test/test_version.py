"""setup.py, package.xml and CHANGELOG.rst (the ROS changelog format `catkin_generate_changelog`
and bloom read) state one version: the newest changelog section is the package's version."""
from __future__ import annotations

import ast
import re
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
VERSION = r'(\d+\.\d+\.\d+)'


def _setup_version() -> str:
    tree = ast.parse((REPO / 'setup.py').read_text())
    call = next(n for n in ast.walk(tree) if isinstance(n, ast.Call)
                and getattr(n.func, 'id', '') == 'setup')
    return next(k.value.value for k in call.keywords if k.arg == 'version')


def _package_xml_version() -> str:
    return re.search(rf'<version>{VERSION}</version>', (REPO / 'package.xml').read_text()).group(1)


def _changelog_sections() -> list[tuple[str, str]]:
    text = (REPO / 'CHANGELOG.rst').read_text()
    return re.findall(rf'^{VERSION} \((\d{{4}}-\d{{2}}-\d{{2}})\)\n-+\n', text, flags=re.M)


def test_setup_py_package_xml_and_changelog_agree():
    sections = _changelog_sections()
    assert sections, 'CHANGELOG.rst has no "X.Y.Z (YYYY-MM-DD)" section'
    assert _setup_version() == _package_xml_version() == sections[0][0]


def test_changelog_is_in_the_ros_format_newest_first():
    text = (REPO / 'CHANGELOG.rst').read_text().splitlines()
    assert text[:3] == ['^' * 35, 'Changelog for package kpi_calib_ros', '^' * 35]
    sections = _changelog_sections()
    versions = [tuple(int(x) for x in v.split('.')) for v, _ in sections]
    assert versions == sorted(versions, reverse=True) and len(set(versions)) == len(versions)
    dates = [d for _, d in sections]
    assert dates == sorted(dates, reverse=True)
