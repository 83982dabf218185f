"""Resident memory of kpi_calib_node (a separate process) under floods of absurd joint states.

Three floods on /joint_states once the robot model is known, each paced by the
node's ``received.joint_states`` count so every message is handled:
  arrays  30 joint states with 1e6-element arrays (the chain's joints plus 999 994 more);
  names   10 joint states with 2e5 distinct names each, never repeated;
  churn   20 000 joint states with the chain and one never-seen name each.
VmRSS (and the peak VmHWM) from /proc/<pid>/status before, after each flood, and
after 5 s of calm. ``--code DIR`` runs the node from another checkout (to compare).
Writes bench/results/node_memory.md.

    python bench/node_memory.py [--code /path/to/checkout]
"""
from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

from rclpy.duration import Duration
from rclpy.qos import QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import JointState
from std_msgs.msg import Header

import kpi_calib_ros  # noqa: F401  (single-threaded BLAS before numpy loads)
from kpi_calib_ros.app.cell_model import build_cell_model
from kpi_calib_ros.io.cell import DEFAULT_CELL, load_cell
from kpi_calib_ros.ros import conversions as cv

from _live_node import LiveNode

OUT = Path(__file__).resolve().parent / 'results' / 'node_memory.md'
CHAIN = build_cell_model(load_cell(DEFAULT_CELL)).joint_names


def floods():
    """(name, list of message factories): built lazily so the bench stays small itself."""
    def arrays(k):
        names = list(CHAIN) + [f'x_{i}' for i in range(1_000_000 - len(CHAIN))]
        return lambda stamp: JointState(header=Header(stamp=cv.time_msg(stamp)), name=names,
                                        position=[0.0] * len(names))

    def distinct(k):
        names = list(CHAIN) + [f'n{k}_{i}' for i in range(200_000)]
        return lambda stamp: JointState(header=Header(stamp=cv.time_msg(stamp)), name=names,
                                        position=[0.0] * len(names))

    def churn(k):
        names = list(CHAIN) + [f'c_{k}']
        return lambda stamp: JointState(header=Header(stamp=cv.time_msg(stamp)), name=names,
                                        position=[0.0] * len(names))
    return [('arrays', 30, arrays), ('names', 10, distinct), ('churn', 20_000, churn)]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument('--code', help='run the node from this checkout (PYTHONPATH)')
    args = parser.parse_args(argv)
    if args.code:
        os.environ['PYTHONPATH'] = str(Path(args.code).resolve())
    live = LiveNode('auto_identify:=false')
    pub = live.node.create_publisher(JointState, '/joint_states', QoSProfile(
        depth=100, reliability=ReliabilityPolicy.RELIABLE))
    live.spin_until(lambda: pub.get_subscription_count() > 0, 30, 'the subscription')
    rows = [('start', *live.rss_kb(), 0, 0)]
    print(f'start: VmRSS {rows[0][1] / 1024:.0f} MB', flush=True)
    stamp = 1_700_000_000_000_000_000
    try:
        for name, count, make in floods():
            base = live.count('received.joint_states')
            started = time.monotonic()
            for k in range(count):
                stamp += 1_000_000
                pub.publish(make(k)(stamp))
                if count < 100:   # large messages: one at a time, acknowledged
                    pub.wait_for_all_acked(Duration(seconds=30))
                elif k % 50 == 49:   # small ones: at most ~100 ahead of the node
                    live.spin_until(lambda base=base, k=k: live.count('received.joint_states')
                                    - base >= k - 50, 60, 'the node')
            live.spin_until(lambda base=base, count=count: live.count('received.joint_states')
                            - base >= count, 120, f'the node to handle the {name} flood')
            rss, peak = live.rss_kb()
            got = live.count('received.joint_states') - base
            rows.append((f'after {name} ({count} msgs)', rss, peak, got,
                         live.count('rejected.oversized_joint_state')))
            print(f'after {name}: {got} of {count} received in {time.monotonic() - started:.1f} '
                  f's; VmRSS {rss / 1024:.0f} MB, peak {peak / 1024:.0f} MB; '
                  f'oversized rejected {rows[-1][4]}', flush=True)
        live.spin_until(lambda: False, 5.0, '')
        rows.append(('5 s later', *live.rss_kb(), 0, live.count('rejected.oversized_joint_state')))
        print(f'5 s later: VmRSS {rows[-1][1] / 1024:.0f} MB, peak {rows[-1][2] / 1024:.0f} MB')
    finally:
        code = live.close()
    lines = ['# kpi_calib_node memory under floods of absurd joint states', '',
             f'`python bench/node_memory.py{" --code " + args.code if args.code else ""}`, '
             f'measured {time.strftime("%Y-%m-%d")}; node exit code {code}', '',
             '| when | VmRSS (MB) | VmHWM (MB) | received | rejected oversized |',
             '|---|---|---|---|---|']
    lines += [f'| {w} | {r / 1024:.0f} | {p / 1024:.0f} | {g} | {o} |' for w, r, p, g, o in rows]
    if not args.code:
        OUT.parent.mkdir(exist_ok=True)
        OUT.write_text('\n'.join(lines) + '\n')
        print(f'wrote {OUT}')
    else:
        print('\n'.join(lines))
    return 0


if __name__ == '__main__':
    sys.exit(main())
