"""A job's forked child never finalises objects it inherited from the node.

The node's objects include rclpy handles; a child that collected and finalised them
acted on DDS entities that exist only in the parent and died with SIGSEGV now and then.
Here an unreachable cycle with a finaliser stands in for such a handle: the child's
collector must leave it alone, the parent's must still reclaim it afterwards.
"""
from __future__ import annotations

import gc
from pathlib import Path

from kpi_calib_ros.ros.child_process import run_in_child


class _Handle:
    """A cycle with a finaliser that leaves a trace of the process that ran it."""

    def __init__(self, trace: Path) -> None:
        self.trace = trace
        self.me = self

    def __del__(self) -> None:
        with open(self.trace, 'a') as stream:
            stream.write('finalised\n')


def _collect_everything() -> int:
    return gc.collect()


def test_the_child_never_collects_what_it_inherited_and_the_parent_still_does(tmp_path):
    trace = tmp_path / 'finalised.txt'
    was_enabled = gc.isenabled()
    gc.disable()  # the parent must not reclaim the cycle before the fork
    try:
        _Handle(trace)  # unreachable at once, kept alive by its cycle
        run_in_child(_collect_everything)
        assert not trace.exists(), 'the child finalised an object of the parent'
        gc.collect()  # the parent's collector still reclaims it: the test can fail
        assert trace.read_text() == 'finalised\n'
    finally:
        if was_enabled:
            gc.enable()
