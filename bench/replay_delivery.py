"""Messages delivered into kpi_calib_node (a separate process) by `kpi-calib replay`.

Replays a simulated KR15-class campaign (joint states at 50 Hz, one point per pose)
at rates 1, 100 and 1000 and compares what replay sent with what the node counted
(``received.*`` on its /diagnostics, read by this script, not by replay). Rate 1
uses a 10-pose bag (40 s); 100 and 1000 a 60-pose bag (12001 joint states, as in
the report of the loss). Writes bench/results/replay_delivery.md.

    python bench/replay_delivery.py [--rates 1 100 1000] [--replay-code DIR]

``--replay-code DIR`` runs `kpi-calib replay` from another checkout (to compare
with an earlier replay); the node always runs from this one.
"""
from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import kpi_calib_ros  # noqa: F401  (single-threaded BLAS before numpy loads)
from kpi_calib_ros.app.simulate import simulate_campaign
from kpi_calib_ros.io.bag import read_bag
from kpi_calib_ros.io.cell import DEFAULT_CELL

from _live_node import BIN, LiveNode

OUT = Path(__file__).resolve().parent / 'results' / 'replay_delivery.md'


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument('--rates', type=float, nargs='+', default=[1.0, 100.0, 1000.0])
    parser.add_argument('--replay-code', help='run the replay from this checkout (PYTHONPATH)')
    args = parser.parse_args(argv)
    code = {'PYTHONPATH': str(Path(args.replay_code).resolve())} if args.replay_code else {}
    folder = Path(tempfile.mkdtemp(prefix='kpi_replay_bench_'))
    bags = {}
    for n in (10, 60):
        bags[n] = folder / f'run_{n}.mcap'
        simulate_campaign(DEFAULT_CELL, n, bags[n], seed=3)
    live = LiveNode('auto_identify:=false')
    rows = []
    try:
        for rate in args.rates:
            bag = bags[10 if rate < 10 else 60]
            joints, points = read_bag(bag)
            live.spin_until(lambda: False, 1.5, '')  # settle: latest counts
            before = (live.count('received.joint_states'), live.count('received.points'))
            started = time.monotonic()
            replay = subprocess.Popen([str(BIN / 'kpi-calib'), 'replay', str(bag), '--rate',
                                       str(rate)], stdout=subprocess.PIPE,
                                      stderr=subprocess.STDOUT, text=True,
                                      env={**os.environ, **code})  # domain set by LiveNode
            live.spin_until(lambda replay=replay: replay.poll() is not None, 900, 'the replay')
            seconds = time.monotonic() - started
            output = replay.stdout.read().strip()
            live.spin_until(lambda before=before, joints=joints: live.count(
                'received.joint_states') - before[0] >= len(joints), 5, 'the last counts')
            got = (live.count('received.joint_states') - before[0],
                   live.count('received.points') - before[1])
            rows.append((rate, len(joints), got[0], len(points), got[1], replay.returncode,
                         seconds))
            print(f'rate {rate:g}: sent {len(joints)} joint states / {len(points)} points, node '
                  f'received {got[0]} / {got[1]}; replay rc {replay.returncode}, '
                  f'{seconds:.1f} s wall\n  replay said: ' + output.replace('\n', '\n  '),
                  flush=True)
    finally:
        live.close()
    lines = ['# Replay delivery into kpi_calib_node (separate process)', '',
             f'`python bench/replay_delivery.py --rates {" ".join(f"{r:g}" for r in args.rates)}'
             + (f' --replay-code {args.replay_code}`' if args.replay_code else '`')
             + f', measured {time.strftime("%Y-%m-%d")}', '',
             '| rate | joint states sent | received by node | points sent | received | '
             'replay rc | wall time (s) |', '|---|---|---|---|---|---|---|']
    lines += [f'| {r:g} | {js} | {jr} | {ps} | {pr} | {rc} | {s:.1f} |'
              for r, js, jr, ps, pr, rc, s in rows]
    if args.replay_code:
        print('\n'.join(lines))
    else:
        OUT.parent.mkdir(exist_ok=True)
        OUT.write_text('\n'.join(lines) + '\n')
        print(f'wrote {OUT}')
    return 0 if all(jr == js and pr == ps for _, js, jr, ps, pr, _, _ in rows) else 1


if __name__ == '__main__':
    sys.exit(main())
