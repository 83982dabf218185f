"""Joint states kpi_calib_node (a separate process) receives at 1 kHz while it identifies.

A driver-like publisher in this process streams a simulated KR15-class campaign in
real time (joint states at 1 kHz, one tracker point per pose), not paced by the node
(a real joint_state_broadcaster is not). The node identifies automatically after
``min_measurements`` and again after every new measurement, so identification jobs
compete with pairing for most of the stream. Afterwards the node's counts
(/diagnostics: ``received.joint_states``, ``lost.joint_states``, ``accepted``) are
compared with what was published. Writes bench/results/node_load.md.

    python bench/node_load.py [--poses 16] [--rate-hz 1000] [--label TEXT]
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np
from geometry_msgs.msg import PointStamped
from rclpy.qos import QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import JointState

import kpi_calib_ros  # noqa: F401  (single-threaded BLAS before numpy loads)
from kpi_calib_ros.app.cell_model import build_cell_model
from kpi_calib_ros.core.acquisition.streams import synthesize_streams
from kpi_calib_ros.core.simulation import (
    random_configurations,
    simulate_measurements,
    true_parameters,
)
from kpi_calib_ros.io.cell import DEFAULT_CELL, load_cell
from kpi_calib_ros.ros.conversions import joint_state_msg, point_stamped_msg

from _live_node import LiveNode

OUT = Path(__file__).resolve().parent / 'results' / 'node_load.md'


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument('--poses', type=int, default=16)
    parser.add_argument('--rate-hz', type=float, default=1000.0)
    parser.add_argument('--min-measurements', type=int, default=10)
    parser.add_argument('--label', default='', help='a note for the results table')
    args = parser.parse_args(argv)
    cm = build_cell_model(load_cell(DEFAULT_CELL))
    rng = np.random.default_rng(4)
    q = random_configurations(cm.model, cm.model.params.nominal, args.poses, rng)
    data = simulate_measurements(cm.model, true_parameters(cm.model.params, rng), q,
                                 cm.cell.sigma, rng)
    joints, points = synthesize_streams(q, cm.joint_names, data.eta, cm.cell.tracker_frame,
                                        rate_hz=args.rate_hz, move_time_s=1.0,
                                        hold_time_s=1.0, rng=rng)
    stream = sorted([(s.stamp_ns, 0, joint_state_msg(s)) for s in joints]
                    + [(p.stamp_ns, 1, point_stamped_msg(p)) for p in points],
                    key=lambda item: item[:2])
    live = LiveNode('auto_identify:=true', f'min_measurements:={args.min_measurements}')
    qos = QoSProfile(depth=len(stream), reliability=ReliabilityPolicy.RELIABLE)
    pubs = [live.node.create_publisher(JointState, '/joint_states', qos),
            live.node.create_publisher(PointStamped, '/laser_tracker/point', qos)]
    try:
        live.spin_until(lambda: all(p.get_subscription_count() for p in pubs), 30, 'the node')
        live.spin_until(lambda: False, 1.0, '')
        identified_before = live.count('identified_with')
        start, first = time.monotonic(), stream[0][0]
        states, behind_max, backlog = set(), 0.0, 0
        sent_joints = 0
        for i, (stamp, kind, msg) in enumerate(stream):
            delay = start + (stamp - first) * 1e-9 - time.monotonic()
            if delay > 0:
                time.sleep(delay)  # a driver's clock
            behind_max = max(behind_max, -delay)
            pubs[kind].publish(msg)
            sent_joints += kind == 0
            if not i % 200:
                for _ in range(20):  # take every diagnostics message waiting (10 Hz)
                    live.executor.spin_once(timeout_sec=0.0)
                states.add(live.values.get('state', ''))
                # Joint states published but not yet handled by the node (its count is
                # up to one diagnostics period, 0.1 s, old): the executor's lag.
                backlog = max(backlog, sent_joints - live.count('received.joint_states'))
        seconds = time.monotonic() - start
        live.spin_until(lambda: live.count('received.joint_states') >= len(joints)
                        and live.values.get('state') == 'idle', 120, 'the node to settle')
        live.spin_until(lambda: False, 1.5, '')
        values = dict(live.values)
    finally:
        live.close()
    received = int(values.get('received.joint_states', -1))
    lost = int(values.get('lost.joint_states', -1))
    accepted = int(values.get('accepted', -1))
    jobs = int(values.get('identifications', -1))
    lag_ms = values.get('max_lag_ms.joint_states', '-')
    identifying = sorted(s for s in states if s.startswith('identifying'))
    print(f'published {len(joints)} joint states at {args.rate_hz:g} Hz and {len(points)} '
          f'points in {seconds:.1f} s (publisher at most {behind_max * 1e3:.1f} ms late); node '
          f'received {received} joint states ({len(joints) - received} missing, lost counted '
          f'{lost}), accepted {accepted} of {len(points)} points; identifications '
          f'{jobs} (identified_with {values.get("identified_with")}, before '
          f'{identified_before}); states seen {identifying}; largest backlog {backlog} joint '
          f'states; largest lag publication -> callback {lag_ms} ms')
    row = (f'| {args.label or "-"} | {args.rate_hz:g} | {len(joints)} | {received} | '
           f'{len(joints) - received} | {lost} | {len(points)} | {accepted} | {jobs} | '
           f'{backlog} | {lag_ms} |')
    header = ['# Joint states received by kpi_calib_node while it identifies', '',
              '`python bench/node_load.py` (2 shared cores); one row per run.', '',
              '| code | rate (Hz) | joint states published | received | missing | counted '
              'lost | points | accepted | identifications | largest backlog | largest lag (ms) |',
              '|---|---|---|---|---|---|---|---|---|---|---|']
    lines = OUT.read_text().splitlines() if OUT.exists() else header
    OUT.write_text('\n'.join(lines + [row]) + '\n')
    print(f'wrote {OUT}')
    return 0 if received == len(joints) and accepted == len(points) else 1


if __name__ == '__main__':
    sys.exit(main())
