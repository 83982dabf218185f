"""The built-in robot URDFs written to files (``kpi-calib robots``).

:mod:`kpi_calib_ros.core.model.robot_library` generates their text; this module writes it.
"""
from __future__ import annotations

from pathlib import Path

from kpi_calib_ros.core.model.robot_library import DATA_DIR, shipped_urdfs


def write_shipped(directory: Path = DATA_DIR) -> list[Path]:
    """Regenerate the shipped URDF files into ``directory``; returns the written paths."""
    directory.mkdir(parents=True, exist_ok=True)
    paths = []
    for stem, text in shipped_urdfs().items():
        path = directory / f'{stem}.urdf'
        path.write_text(text, encoding='utf-8')
        paths.append(path)
    return paths
