"""Sphinx configuration of the kpi_calib_ros documentation (`make doc`, in `make test`)."""
from __future__ import annotations

import re
import sys
from pathlib import Path

DOC = Path(__file__).resolve().parent
REPO = DOC.parent
sys.path.insert(0, str(DOC / '_ext'))
sys.path.insert(0, str(REPO))

project = 'kpi_calib_ros'
author = 'kpi_calib_ros maintainers'
copyright = '2026, kpi_calib_ros maintainers'
# One version, from package.xml (test/test_version.py checks setup.py and CHANGELOG.rst).
version = release = re.search(r'<version>([^<]+)</version>',
                              (REPO / 'package.xml').read_text()).group(1)

extensions = ['myst_parser', 'sphinx.ext.autodoc', 'numpydoc', 'reference_pages']
source_suffix = {'.md': 'markdown', '.rst': 'restructuredtext'}
exclude_patterns = ['_build']
myst_heading_anchors = 3
numpydoc_show_class_members = False
numpydoc_class_members_toctree = False
autodoc_member_order = 'bysource'
# Furo: a theme made for technical documentation (pinned in requirements.txt); the code
# blocks show 88 characters without scrolling (test/test_doc_pictures.py keeps them so).
html_theme = 'furo'
html_title = f'kpi_calib_ros {release}'
# The pictures (doc/_static/pictures/, `make pictures`) reach the site through the pages'
# figures, which Sphinx copies; no other static file is published.
html_static_path: list[str] = []


def _absolute_values(app, what, name, obj, options, lines) -> None:
    """|x| in a docstring is an absolute value, not a reST substitution."""
    lines[:] = [re.sub(r'(?<!\\)\|([^|\s`][^|`]*?)\|', r'\\|\1\\|', line) for line in lines]


def setup(app) -> None:
    app.connect('autodoc-process-docstring', _absolute_values, priority=400)
