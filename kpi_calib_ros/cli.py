"""kpi-calib: laser-tracker calibration of industrial robots with KPI-optimal designs.

Subcommands: simulate a cell into an MCAP bag, identify a bag, design optimal
measurement poses, diagnose a calibration, replay a bag onto ROS topics, and a
demo on the built-in simulated cell. Results go to files; a summary to stdout.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
import yaml

from kpi_calib_ros.core.errors import KpiCalibError


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog='kpi-calib', description=__doc__)
    sub = parser.add_subparsers(dest='command', required=True)

    sim = sub.add_parser('simulate', help='simulate a measurement campaign into an MCAP bag')
    sim.add_argument('--cell', required=True, help='cell YAML file')
    sim.add_argument('--n', type=int, default=60, help='number of measurement poses')
    sim.add_argument('--out', required=True, help='output .mcap file')
    sim.add_argument('--seed', type=int, default=0)
    sim.add_argument('--poses', help='design.yaml whose configurations to measure '
                     '(default: random measurable, collision-free poses)')

    ide = sub.add_parser('identify', help='identify parameters from a bag')
    ide.add_argument('--cell', required=True)
    ide.add_argument('--bag', required=True, help='MCAP bag with joint states and tracker points')
    ide.add_argument('--out', required=True, help='output folder')
    ide.add_argument('--effects', default='', metavar='EFFECT:JOINT,...',
                     help="physical effects added to the cell file's effects: (e.g. "
                     'joint_compliance:joint_2); the summary compares with the geometric model')

    dia = sub.add_parser('diagnose', help='residual report, model adequacy and the most likely '
                         'missing physical effect')
    dia.add_argument('--cell', required=True)
    dia.add_argument('--bag', required=True, help='MCAP bag with joint states and tracker points')
    dia.add_argument('--out', required=True, help='output folder: diagnosis.json, report.md, plots')
    dia.add_argument('--effects', default='', metavar='EFFECT:JOINT,...',
                     help='effects already in the model, as for identify')
    dia.add_argument('--folds', type=int, default=5, help='cross-validation folds over poses')
    dia.add_argument('--alpha', type=float, default=0.01,
                     help='family-wise false-alarm level of the effect tests')

    des = sub.add_parser('design', help='optimal measurement configurations')
    des.add_argument('--cell', required=True)
    des.add_argument('--n', type=int, default=60)
    des.add_argument('--criterion', choices=['kpi', 'A', 'D', 'random'], default='kpi')
    des.add_argument('--out', required=True, help='output design.yaml')
    des.add_argument('--seed', type=int, default=0)

    rep = sub.add_parser('replay', help='publish a bag onto the live ROS topics with its timing')
    rep.add_argument('bag', help='MCAP bag with joint states and tracker points')
    rep.add_argument('--rate', type=float, default=1.0, help='playback speed factor')
    rep.add_argument('--joint-topic', default='/joint_states')
    rep.add_argument('--point-topic', default='/laser_tracker/point')
    rep.add_argument('--wait-for-subscribers', type=float, default=10.0, metavar='SEC',
                     help='wait this long for a subscriber on both topics before playing')

    demo = sub.add_parser('demo', help='simulate, identify and report on the built-in cell')
    demo.add_argument('--out', default='demo_out')
    demo.add_argument('--seed', type=int, default=7)

    args = parser.parse_args(argv)
    try:
        return _COMMANDS[args.command](args)
    except (KpiCalibError, ValueError, FileNotFoundError) as exc:
        print(f'kpi-calib {args.command}: error: {exc}', file=sys.stderr)
        return 2


def _simulate(args: argparse.Namespace) -> int:
    from kpi_calib_ros.io.simulate import simulate_campaign
    poses = None
    if args.poses:
        doc = yaml.safe_load(Path(args.poses).read_text())
        poses = (doc['joint_names'], np.asarray(doc['configurations'], float))
    summary = simulate_campaign(args.cell, args.n, args.out, args.seed, poses=poses)
    print(summary)
    return 0


def _identify(args: argparse.Namespace) -> int:
    from kpi_calib_ros.core.effects import split_specs
    from kpi_calib_ros.io.cell import build_cell_model, load_cell
    from kpi_calib_ros.io.results import summary_text, write_calibration
    from kpi_calib_ros.pipeline import (calibration_document, identify_cell,
                                        measurements_from_bag)
    cm = build_cell_model(load_cell(args.cell), effects=tuple(split_specs(args.effects)))
    data, pairing = measurements_from_bag(cm, args.bag)
    for reason, count in sorted(pairing.rejections.items()):
        print(f'rejected {count} sample(s): {reason}', file=sys.stderr)
    result = identify_cell(cm, data)
    doc = calibration_document(cm, result, pairing)
    comparison = ''
    if cm.model.effects:
        from kpi_calib_ros.io.report import add_effect_comparison
        comparison = add_effect_comparison(doc, cm, data, result)
    path = write_calibration(args.out, doc)
    print(summary_text(doc))
    if comparison:
        print(comparison)
    print(f'written: {path}')
    return 0 if result.converged else 1


def _design(args: argparse.Namespace) -> int:
    from kpi_calib_ros.io.design_io import run_design_command
    return run_design_command(args)


def _replay(args: argparse.Namespace) -> int:
    from kpi_calib_ros.ros.replay import run_replay_command  # ROS only when replaying
    return run_replay_command(args)


def _diagnose(args: argparse.Namespace) -> int:
    from kpi_calib_ros.io.report import run_diagnose_command
    return run_diagnose_command(args)


def _demo(args: argparse.Namespace) -> int:
    from kpi_calib_ros.io.demo import run_demo
    return run_demo(args.out, args.seed)


_COMMANDS = {'simulate': _simulate, 'identify': _identify, 'design': _design,
             'diagnose': _diagnose, 'replay': _replay, 'demo': _demo}

if __name__ == '__main__':
    sys.exit(main())
