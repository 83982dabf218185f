"""The stamps of the measurements the node's published calibration was fitted to.

``~/validate`` tests the calibration on the measurements accepted since it was identified:
every stored one not among those it was fitted to. A restarted node reads the calibration
back from calibration.yaml, which does not list them; this file beside it does, with the
SHA-256 of the calibration's text, so that it is used only for that calibration. Without it
(or for another calibration) the restored node takes the measurements stamped up to the
calibration's last one as fitted, which drops later-accepted poses stamped inside the
training span (rows drawn from one table, a tracker clock set back).
"""
from __future__ import annotations

import hashlib
import json
from pathlib import Path
from typing import Iterable

from kpi_calib_ros.io.results import write_atomic

__all__ = ['read_fitted_stamps', 'write_fitted_stamps']


def _digest(text: str) -> str:
    return hashlib.sha256(text.encode('utf-8')).hexdigest()


def write_fitted_stamps(path: str | Path, calibration_text: str, stamps: Iterable[int]) -> None:
    """Write the ``stamps`` (ns) a calibration (its YAML ``calibration_text``) was fitted to.

    Raises
    ------
    OSError
        Not written (the previous file is left as it was).
    """
    doc = {'calibration_sha256': _digest(calibration_text),
           'stamps_ns': sorted({int(t) for t in stamps})}
    write_atomic(Path(path), json.dumps(doc))


def read_fitted_stamps(path: str | Path, calibration_text: str) -> set[int] | None:
    """Return the stamps the calibration ``calibration_text`` was fitted to, or None.

    None when the file is missing, unreadable, not of the written form, or written for
    another calibration.
    """
    try:
        doc = json.loads(Path(path).read_text())
    except (OSError, ValueError):
        return None
    if not isinstance(doc, dict) or doc.get('calibration_sha256') != _digest(calibration_text):
        return None
    stamps = doc.get('stamps_ns')
    if not isinstance(stamps, list) or not all(
            isinstance(t, int) and not isinstance(t, bool) for t in stamps):
        return None
    return set(stamps)
