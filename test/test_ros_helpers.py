"""The ROS domain allocator the ROS tests share: an id is never handed out twice at once,
within one run or across processes, and is free again once released."""
from __future__ import annotations

import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

from ros_helpers import exclusive_ros_domain

HERE = Path(__file__).resolve().parent
IDS = range(40, 43)


def test_concurrent_holders_get_distinct_ids_until_none_is_left(tmp_path):
    with exclusive_ros_domain(tmp_path, IDS) as a, exclusive_ros_domain(tmp_path, IDS) as b, \
            exclusive_ros_domain(tmp_path, IDS) as c:
        assert sorted((a, b, c)) == list(IDS)
        with pytest.raises(RuntimeError, match='held by another test run'):
            with exclusive_ros_domain(tmp_path, IDS):
                pass
    with exclusive_ros_domain(tmp_path, range(a, a + 1)) as again:  # released on exit
        assert again == a


@pytest.mark.slow
def test_an_id_held_by_another_process_is_skipped(tmp_path):
    holder = subprocess.Popen([sys.executable, '-c', textwrap.dedent(f'''
        import sys
        sys.path.insert(0, {str(HERE)!r})
        from ros_helpers import exclusive_ros_domain
        from pathlib import Path
        with exclusive_ros_domain(Path({str(tmp_path)!r}), range(40, 41)) as domain:
            print(domain, flush=True)
            sys.stdin.readline()  # hold it until the test says so
        ''')], stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout.readline().strip() == '40'
        with exclusive_ros_domain(tmp_path, IDS) as domain:
            assert domain in (41, 42)
        with pytest.raises(RuntimeError):
            with exclusive_ros_domain(tmp_path, range(40, 41)):
                pass
    finally:
        holder.communicate('done\n', timeout=30)
    assert holder.returncode == 0
    with exclusive_ros_domain(tmp_path, range(40, 41)) as domain:  # the holder is gone
        assert domain == 40
