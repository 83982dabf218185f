"""Reflector frame ids: how a tracker point names the reflector it was measured on.

Several reflectors per pose: every reflector (or mocap marker) point is its own
``PointStamped`` with ``header.frame_id = '<tracker_frame>#<reflector name>'`` (the
point is expressed in ``<tracker_frame>``; the part after ``#``, a character no ROS
frame name contains, names the reflector of the cell's ``reflectors:`` list). One
topic, one log and one replay carry every reflector, and points of one pose may share
a stamp. A plain ``<tracker_frame>`` is the single ``reflector:`` of a cell.
"""
from __future__ import annotations

from typing import Sequence

__all__ = ['REFLECTOR_SEPARATOR', 'reflector_frame', 'split_frame', 'unknown_reflector']

REFLECTOR_SEPARATOR = '#'


def reflector_frame(tracker_frame: str, name: str) -> str:
    """Return the frame id ``'<tracker_frame>#<name>'`` of reflector ``name``'s points.

    ``tracker_frame`` itself for the single unnamed reflector (``name`` '').
    """
    return f'{tracker_frame}{REFLECTOR_SEPARATOR}{name}' if name else tracker_frame


def split_frame(frame_id: str) -> tuple[str, str]:
    """Split a point's frame id ``'<frame>#<name>'`` into ``(frame, reflector name)``.

    The name is '' when there is no ``#``; a leading '/' of the frame is dropped.
    """
    frame, _, name = frame_id.partition(REFLECTOR_SEPARATOR)
    return frame.strip('/'), name


def unknown_reflector(frame_id: str, tracker_frame: str, reflectors: Sequence[str]) -> str:
    """Return why the point's ``frame_id`` names none of ``reflectors``, and the fix.

    ``tracker_frame`` and ``reflectors`` (names, '' the single one) are the cell's; the
    text lists the frame ids expected and says what to change, in the points or the cell.
    """
    expected = [reflector_frame(tracker_frame, r) for r in reflectors]
    _, name = split_frame(frame_id)
    if not name:
        fix = (f"send the points with frame_id '{expected[0]}', or their reflector name "
               "after the '#'")
    elif tuple(reflectors) == ('',):
        fix = (f'the cell has one reflector: (no names); name it as the points do: '
               f'reflectors: [{{name: {name}}}] (offset and orientation as in reflector:)')
    else:
        fix = (f"add {{name: {name}}} to the cell's reflectors: list, or send the points "
               'with one of the names above')
    return (f"point frame_id '{frame_id}' names a reflector the cell does not have; "
            f"frame ids are '<tracker_frame>{REFLECTOR_SEPARATOR}<reflector name>' for the cell's "
            f'reflectors: list (a plain tracker frame for a single reflector:), expected one '
            f'of {expected}; {fix}')
