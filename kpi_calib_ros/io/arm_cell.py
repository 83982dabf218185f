"""The cell document of an arm in a simulated tracker cell: any URDF's chain, no cell file.

The robot base 2.5 m from the tracker, turned to face it; the reflector off the last joint's
axis; no working poses (a diagnosis or an identification needs none). The cell the general
effects are tried on with the stock arms of example-robot-data
(``bench/general_effects_stock.py`` and its test), read by
:func:`~kpi_calib_ros.io.cell.cell_from_dict` as a cell file would be.
"""
from __future__ import annotations

from typing import Any

BASE_IN_TRACKER = (2.5, 0.3, -0.3, 0.0, 0.0, 3.0)  # x, y, z (m), roll, pitch, yaw (rad)
REFLECTOR_OFFSET = (0.03, 0.02, 0.05)  # m in the tip frame: off the last joint's axis


def arm_cell_document(urdf: str, base_frame: str, tip_frame: str,
                      sigma: float) -> dict[str, Any]:
    """Return the cell document of the chain ``base_frame`` → ``tip_frame`` of ``urdf``
    (a path or a ``package://`` URI) measured by a tracker of σ ``sigma`` (m per axis),
    placed as the module docstring says; a new dict each call, to extend (working poses,
    identification settings) before it is read."""
    return {'robot': {'urdf': urdf, 'base_frame': base_frame, 'tip_frame': tip_frame},
            'tracker': {'frame_id': 'laser_tracker', 'base_in_tracker': list(BASE_IN_TRACKER)},
            'reflector': {'offset': list(REFLECTOR_OFFSET), 'axis': [0, 0, 1]},
            'noise': {'sigma': sigma}}


__all__ = ['arm_cell_document']
