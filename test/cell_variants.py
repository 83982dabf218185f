"""The default cell measured by one reflector, by three reflectors, or by a tracked 6-DoF
body: the cell documents tests of the design and the campaign share."""
from __future__ import annotations

from typing import Any

from kpi_calib_ros.io.cell import DEFAULT_CELL, read_cell_document

KINDS = ('one point', 'three reflectors', 'tracked pose')


def cell_document(kind: str) -> dict[str, Any]:
    """The default cell's document with ``kind`` of :data:`KINDS` as its measurement: a
    tracked pose is a probe whose orientation the tracker reports at σ_rot = 0.1 mrad."""
    doc = read_cell_document(DEFAULT_CELL)
    if kind == 'three reflectors':
        del doc['reflector']['offset']
        doc['reflectors'] = [{'name': 'a', 'offset': [0.0, 0.0, 0.03]},
                             {'name': 'b', 'offset': [0.06, 0.0, 0.03]},
                             {'name': 'c', 'offset': [0.0, 0.05, 0.02]}]
    elif kind == 'tracked pose':
        del doc['reflector']['offset']
        doc['reflectors'] = [{'name': 'probe', 'offset': [0.0, 0.02, 0.03],
                              'orientation': {'rpy': [0.1, -0.2, 0.3]}}]
        doc['noise']['sigma_rotation'] = 1e-4
    elif kind != 'one point':
        raise ValueError(f'kind must be one of {KINDS}, got {kind!r}')
    return doc
