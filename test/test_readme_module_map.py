"""The module map of the documentation (doc/architecture.md) lists every module of the
package exactly once, and nothing that does not exist: a newcomer finds each concept where
the map says."""
from __future__ import annotations

import re
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
PACKAGE = REPO / 'kpi_calib_ros'


def _map_rows() -> list[str]:
    text = (REPO / 'doc' / 'architecture.md').read_text()
    section = text.split('| concept | module |', 1)[1]
    return re.findall(r'^\|[^|]+\| `([^`]+)` \|$', section, flags=re.M)


def _normalised(path: str) -> str:
    return path if path.startswith('kpi_calib_ros/') else f'kpi_calib_ros/{path}'


def test_every_module_is_in_the_map_once_and_every_entry_exists():
    listed = [_normalised(p) for p in _map_rows()]
    modules = sorted(str(p.relative_to(REPO)) for p in PACKAGE.rglob('*.py')
                     if p.name != '__init__.py')
    duplicates = sorted({p for p in listed if listed.count(p) > 1})
    assert duplicates == [], f'listed more than once: {duplicates}'
    assert sorted(set(modules) - set(listed)) == [], 'modules missing from doc/architecture.md'
    assert sorted(set(listed) - set(modules)) == [], 'doc/architecture.md entries with no module'
