"""kpi-calib: laser-tracker calibration of industrial robots with KPI-optimal designs.

Subcommands: simulate a cell into an MCAP bag, identify a bag, design optimal
measurement poses, diagnose a calibration, validate it on a new bag, import a
table of static postures (CSV) as a bag, run a sequential campaign, replay a bag onto ROS topics, a
demo on the built-in simulated cell, and regenerate the built-in robot URDFs.
Results go to files; a summary to stdout.
"""
from __future__ import annotations

import argparse
import io
import os
import signal
import sys
import threading
from pathlib import Path
from typing import Any

from kpi_calib_ros.core.errors import ConfigError, DataError, KpiCalibError
from kpi_calib_ros.core.estimation.drift_state import (
    DAY_HOURS,
    OFFSET_SWING_RAD,
    TEMPERATURE_SWING_K,
    DriftSwing,
)
from kpi_calib_ros.core.estimation.least_squares import ITERATIONS_PER_PARAMETER
from kpi_calib_ros.core.estimation.prior import (
    DRIFT_ANGLE_PER_SQRT_HOUR,
    DRIFT_LENGTH_PER_SQRT_HOUR,
)
from kpi_calib_ros.core.measurement.recordings import stated_conditions
from kpi_calib_ros.io.names import DEFAULT_JOINT_TOPIC, DEFAULT_POINT_TOPIC, DEFAULT_POSE_TOPIC

CODE_EFFECTS_HELP = ("let the cell file's effects: name Python code ('file.py:Type:joint', "
                     "'module:Type:joint') and run it; without it only built-in and installed "
                     '(entry point) effects are used')


def _bag_topics(parser: argparse.ArgumentParser) -> None:
    parser.add_argument('--joint-topic', default=None, help='sensor_msgs/JointState topic of '
                        f"the bag (default: the cell's topics.joint_states, else "
                        f'{DEFAULT_JOINT_TOPIC})')
    parser.add_argument('--point-topic', default=None, help='geometry_msgs/PointStamped topic '
                        "of the bag (default: the cell's topics.point, else "
                        f'{DEFAULT_POINT_TOPIC})')
    parser.add_argument('--pose-topic', default=None, help='geometry_msgs/PoseStamped topic '
                        'of tracked 6-DoF bodies, read when the bag has it (default: the '
                        f"cell's topics.pose, else {DEFAULT_POSE_TOPIC})")


def _drift(text: str) -> tuple[float, ...]:
    """``--drift-per-hour LENGTH,ANGLE[,ROTATION[,PLACEMENT]]``: two to four numbers >= 0."""
    try:
        rates = tuple(float(x) for x in text.split(','))
    except ValueError:
        rates = ()
    if len(rates) not in (2, 3, 4):
        raise argparse.ArgumentTypeError(f'{text!r}: give LENGTH,ANGLE[,ROTATION[,PLACEMENT]], '
                                         'e.g. 1.2e-5,2e-5 (relative length, joint offset and '
                                         'placement rotation in rad, relative base position; '
                                         'per √hour)')
    if not all(0 <= r < float('inf') for r in rates):
        raise argparse.ArgumentTypeError(f'{text!r}: the rates must be finite and >= 0')
    return rates


def _positive_int(text: str) -> int:
    """``--max-iterations N``: a positive integer."""
    try:
        value = int(text)
    except ValueError:
        value = 0
    if value < 1:
        raise argparse.ArgumentTypeError(f'{text!r}: give a positive integer, e.g. 500')
    return value


def _level(text: str) -> float:
    """``--alpha A``: a false-alarm level, strictly between 0 and 1."""
    try:
        value = float(text)
    except ValueError:
        value = float('nan')
    if not 0.0 < value < 1.0:
        raise argparse.ArgumentTypeError(f'{text!r}: a false-alarm level is strictly between 0 '
                                         'and 1, e.g. 0.01 (1 %)')
    return value


DEFAULT_SWING = DriftSwing()  # the defaults: TEMPERATURE_SWING_K, OFFSET_SWING_RAD, DAY_HOURS
SWING_HELP = ('drift state of a daily swing (core.estimation.drift_state.DriftSwing): the rates '
              'of the prior '
              'calibration (its drift_state) extrapolate it, and this cycle\'s calibration '
              'stores them; TEMPERATURE_K: ± temperature amplitude of the links (12 µm per m '
              'and K), OFFSET_RAD: ± joint offset amplitude, PERIOD_H: its period (default '
              f'{DAY_HOURS:g}); without values {TEMPERATURE_SWING_K:g},{OFFSET_SWING_RAD:g},'
              f'{DAY_HOURS:g}; added to --drift-per-hour (give 0,0 for the swing alone)')


def _swing(text: str) -> DriftSwing:
    """``--drift-velocity TEMPERATURE_K,OFFSET_RAD[,PERIOD_H]`` (checked by
    :meth:`kpi_calib_ros.core.estimation.drift_state.DriftSwing.from_values`)."""
    try:
        return DriftSwing.from_values([float(x) for x in text.split(',')])
    except (ValueError, DataError) as exc:
        raise argparse.ArgumentTypeError(
            f'{text!r}: give TEMPERATURE_K,OFFSET_RAD[,PERIOD_H], e.g. 5,5e-5 (± daily '
            'temperature swing of the links in K >= 0, ± joint offset swing in rad >= 0, '
            f'period in hours > 0): {exc}') from None


def build_parser() -> argparse.ArgumentParser:
    """The `kpi-calib` parser with every subcommand (also the source of the CLI
    reference page of the documentation)."""
    parser = argparse.ArgumentParser(prog='kpi-calib', description=__doc__)
    sub = parser.add_subparsers(dest='command', required=True)

    sim = sub.add_parser('simulate', help='simulate a measurement campaign into an MCAP bag')
    sim.add_argument('--cell', required=True, help='cell YAML file')
    sim.add_argument('--n', type=int, default=60, help='number of measurement poses')
    sim.add_argument('--out', required=True, help='output .mcap file')
    sim.add_argument('--seed', type=int, default=0)
    sim.add_argument('--poses', help='design.yaml whose configurations to measure '
                     '(default: random measurable, collision-free poses)')
    sim.add_argument('--allow-code-effects', action='store_true', help=CODE_EFFECTS_HELP)

    ide = sub.add_parser('identify', help='identify parameters from a bag; exit 0 valid, 1 '
                         'not valid, 2 error, 3 (with --prior) a change beyond the drift '
                         'model: not blended')
    ide.add_argument('--cell', required=True)
    _recordings(ide)
    ide.add_argument('--out', required=True, help='output folder')
    ide.add_argument('--effects', default='', metavar='EFFECT:JOINT,...',
                     help="physical effects added to the cell file's effects: (e.g. "
                     'joint_compliance:joint_2); the summary compares with the geometric model')
    ide.add_argument('--model', choices=['auto', 'registration', 'joint_offsets', 'geometric'],
                     help="model size (overrides the cell's identification.model; auto: a "
                     'larger level only when it lowers the misfit beyond noise (F-test), from '
                     'the smallest up; then the significant, plausible effects that predict '
                     'held-out regions of joint space better)')
    ide.add_argument('--max-iterations', type=_positive_int, metavar='N',
                     help="iteration limit of every fit (overrides the cell's "
                     f'identification.max_iterations; default {ITERATIONS_PER_PARAMETER} '
                     'per identified parameter)')
    ide.add_argument('--prior', metavar='OLD/calibration.yaml',
                     help="a previous calibration as Gaussian prior (its values and "
                     "parameter_covariance; replaces the cell's identification.prior)")
    ide.add_argument('--drift-per-hour', type=_drift, metavar='LENGTH,ANGLE[,ROTATION[,PLACEMENT]]',
                     default=(DRIFT_LENGTH_PER_SQRT_HOUR, DRIFT_ANGLE_PER_SQRT_HOUR),
                     help='random-walk drift that widens --prior per √hour since its '
                     'identified_at_ns: relative length change (thermal growth), joint offset '
                     'angle (rad), placement rotation (rad, default: ANGLE) and relative base '
                     'position change (default: LENGTH); default '
                     f'{DRIFT_LENGTH_PER_SQRT_HOUR:g},{DRIFT_ANGLE_PER_SQRT_HOUR:g}')
    ide.add_argument('--drift-model', choices=['thermal', 'isotropic'], default='thermal',
                     help='thermal (default): each translation grows along its nominal '
                     'vector (thermal expansion); isotropic: every axis independently')
    ide.add_argument('--keep-placement', action='store_true',
                     help='tracker and reflector nest not moved since --prior: keep the base '
                     'and reflector placement in the prior (default: identified anew)')
    ide.add_argument('--drift-velocity', type=_swing, nargs='?', const=DEFAULT_SWING,
                     metavar='TEMPERATURE_K,OFFSET_RAD[,PERIOD_H]', help=SWING_HELP)
    ide.add_argument('--learned-residual', action='store_true',
                     help='also learn what the physical model leaves as a Gaussian process '
                     'over joint space; written as learned_residual.yaml beside '
                     'calibration.yaml only when it lowers the cross-validated error')
    _bag_topics(ide)
    ide.add_argument('--allow-code-effects', action='store_true', help=CODE_EFFECTS_HELP)

    dia = sub.add_parser('diagnose', help='residual report, model adequacy and the most likely '
                         'missing physical effect; exit 0, 1 when the TCP is not estimable '
                         'from the measurements (as identify)')
    dia.add_argument('--cell', required=True)
    _recordings(dia)
    dia.add_argument('--out', required=True, help='output folder: diagnosis.json, report.md, plots')
    dia.add_argument('--effects', default='', metavar='EFFECT:JOINT,...',
                     help='effects already in the model, as for identify')
    dia.add_argument('--folds', type=int, default=0, help='cross-validation folds over poses; '
                     '0 (default): leave one pose out')
    dia.add_argument('--model', choices=['auto', 'registration', 'joint_offsets', 'geometric'],
                     help="model level the effects are screened against (overrides the cell's "
                     'identification.model)')
    dia.add_argument('--alpha', type=_level, default=None,
                     help='family-wise false-alarm level of the effect tests (default: the '
                     'adequacy level, 0.01)')
    _bag_topics(dia)
    dia.add_argument('--allow-code-effects', action='store_true', help=CODE_EFFECTS_HELP)

    val = sub.add_parser('validate', help='predict a new recording with a calibration; exit 0 '
                         'when it holds, 1 when it does not')
    val.add_argument('--cell', required=True)
    val.add_argument('--calibration', required=True, help='calibration.yaml of identify')
    val.add_argument('--bag', required=True, help='new MCAP bag (not used for the calibration)')
    val.add_argument('--out', required=True, help='output folder: validation.json, plot')
    val.add_argument('--allow-code-effects', action='store_true', help=CODE_EFFECTS_HELP)
    val.add_argument('--register', nargs='?', const='base',
                     choices=['base', 'base+reflector', 'reflector'],
                     help='the tracker (or probe) was set up again: re-fit the base pose '
                     '(base+reflector: and the reflector offsets; reflector: the offsets '
                     'alone, the probe remounted; an identified body orientation with them) '
                     'on the new recording alone first; the rms '
                     'after it is the figure to compare, chi2 loses its dof; a learned '
                     'residual is carried into the registered set-up')
    val.add_argument('--recording', metavar='NAME',
                     help='the new bag was measured from the set-up of this recording of the '
                     "calibration (its recordings: section): placed as the calibration placed "
                     "it (its base pose, its reflector offsets when remounted), not as the "
                     'first recording')
    val.add_argument('--covariate', action='append', default=[], metavar='NAME=VALUE',
                     help='a condition every new row was measured under, in its SI unit '
                     '(e.g. payload.mass=2.5); repeat per condition; with --recording it '
                     "replaces that recording's own; needed when the calibration's "
                     'recordings each stated it')
    _bag_topics(val)

    imp = sub.add_parser('import-csv', help='a table of static postures (CSV) into an MCAP bag')
    imp.add_argument('csv', nargs='+', help='one row per posture: joint values and marker '
                     'points; several tables (sessions) go into one bag')
    imp.add_argument('--out', required=True, help='output .mcap file')
    imp.add_argument('--mapping', help='YAML: frame_id, joints, markers, stamp_columns, units')
    imp.add_argument('--frame', help='frame of the points (mapping frame_id)')
    imp.add_argument('--joints', help='comma-separated joint columns (named as the joints)')
    imp.add_argument('--marker', action='append', default=[], metavar='NAME=X,Y,Z',
                     help='a marker and its three columns; repeat per marker')
    imp.add_argument('--stamp-columns', default='', help='comma-separated Unix-second '
                     'columns whose mean stamps a row (default: the row order)')
    imp.add_argument('--delimiter', choices=[',', ';', 'tab', '|'], default=None,
                     help='column separator (default: the mapping\'s, else detected)')
    imp.add_argument('--decimal', choices=['.', ','], default=None,
                     help="decimal mark (default: the mapping's, else detected)")

    des = sub.add_parser('design', help='optimal measurement configurations')
    des.add_argument('--cell', required=True)
    des.add_argument('--n', type=int, default=60)
    des.add_argument('--criterion', choices=['kpi', 'A', 'D', 'random'], default='kpi')
    des.add_argument('--out', required=True, help='output design.yaml')
    des.add_argument('--seed', type=int, default=0)
    des.add_argument('--prior', metavar='OLD/calibration.yaml',
                     help='design the poses of a re-identification: the KPI criterion with '
                     "this calibration's information (prior precision) added")
    des.add_argument('--hours', type=float, default=1.0,
                     help='drift time from the --prior calibration to the measurement '
                     '(default 1 h)')
    des.add_argument('--drift-per-hour', type=_drift, metavar='LENGTH,ANGLE[,ROTATION[,PLACEMENT]]',
                     default=(DRIFT_LENGTH_PER_SQRT_HOUR, DRIFT_ANGLE_PER_SQRT_HOUR),
                     help='drift rates as for identify --prior')
    des.add_argument('--drift-model', choices=['thermal', 'isotropic'], default='thermal')
    des.add_argument('--keep-placement', action='store_true',
                     help='as for identify --prior: base and reflector placement in the prior')
    des.add_argument('--drift-velocity', type=_swing, nargs='?', const=DEFAULT_SWING,
                     metavar='TEMPERATURE_K,OFFSET_RAD[,PERIOD_H]',
                     help='drift state as for identify --prior')
    des.add_argument('--allow-code-effects', action='store_true', help=CODE_EFFECTS_HELP)

    cam = sub.add_parser('campaign', help='sequential campaign: each next pose from what has '
                         'been measured, stop when the TCP std reaches the target')
    cam.add_argument('--cell', required=True)
    cam.add_argument('--target-std', type=float, required=True, metavar='M',
                     help='target of the largest per-axis TCP std over the working poses (m)')
    cam.add_argument('--simulate', action='store_true', help='run the loop against a '
                     "simulated true robot (the cell's simulation.hidden_effects included); "
                     'without it: write and print the initial plan')
    cam.add_argument('--seed', type=int, default=0)
    cam.add_argument('--max', type=int, default=200, dest='max_measurements',
                     help='largest number of measurements (default 200)')
    cam.add_argument('--out', required=True, help='output folder')
    cam.add_argument('--allow-code-effects', action='store_true', help=CODE_EFFECTS_HELP)

    rep = sub.add_parser('replay', help='publish a bag onto the live ROS topics with its timing')
    rep.add_argument('bag', help='MCAP bag with joint states and tracker points')
    rep.add_argument('--rate', type=float, default=1.0, help='playback speed factor')
    rep.add_argument('--joint-topic', default=DEFAULT_JOINT_TOPIC)
    rep.add_argument('--point-topic', default=DEFAULT_POINT_TOPIC)
    rep.add_argument('--pose-topic', default=DEFAULT_POSE_TOPIC,
                     help='geometry_msgs/PoseStamped topic of tracked 6-DoF bodies')
    rep.add_argument('--wait-for-subscribers', type=float, default=10.0, metavar='SEC',
                     help='wait this long for a subscriber on both topics before playing')

    demo = sub.add_parser('demo', help='simulate, identify and report on the built-in cell')
    demo.add_argument('--out', default='demo_out')
    demo.add_argument('--seed', type=int, default=7)

    rob = sub.add_parser('robots', help='regenerate the URDFs of the built-in robot library')
    rob.add_argument('--out', help='target folder (default: the package data folder)')
    return parser


# What each subcommand's --out names: a folder of results or the one file written
# (with an example name for the message).
OUT_FOLDER = ''
OUTPUTS = {'identify': OUT_FOLDER, 'diagnose': OUT_FOLDER, 'validate': OUT_FOLDER,
           'campaign': OUT_FOLDER, 'demo': OUT_FOLDER, 'robots': OUT_FOLDER,
           'simulate': 'bag.mcap', 'import-csv': 'bag.mcap', 'design': 'design.yaml'}


def check_output(command: str, out: str | None) -> None:
    """The one check of a subcommand's ``--out``, before anything is computed: a folder
    of results must be writable and not a file system's root
    (:func:`~kpi_calib_ros.io.results.writable_folder`), a file must not be a folder
    (:func:`~kpi_calib_ros.io.results.writable_file`). ConfigError names ``--out``."""
    if out is None or command not in OUTPUTS:
        return
    from kpi_calib_ros.io.results import writable_file, writable_folder
    if OUTPUTS[command] == OUT_FOLDER:
        writable_folder(out, '--out')
    else:
        writable_file(out, '--out', OUTPUTS[command])


class Stopped(KeyboardInterrupt):
    """SIGTERM, raised as SIGINT's KeyboardInterrupt is: what a command was writing is
    removed on the way out (temporary files of atomic writes, a bag's ``.partial``)."""

    def __init__(self, signum: int) -> None:
        super().__init__(signum)
        self.signum = signum


def _raise_stopped(signum: int, frame: object) -> None:
    raise Stopped(signum)


class _PipeSafe(io.TextIOBase):
    """Standard output that a reader closing the pipe (``| head``) does not stop.

    The command's output is its summary; its result is the files it writes. A write to a
    pipe whose reader has gone raises BrokenPipeError in the middle of the work (a
    traceback, exit 1, the files after that print unwritten); from then on the rest of
    the output goes to the null device and the work goes on.
    """

    def __init__(self, stream: Any) -> None:
        self._stream = stream

    def _closed_pipe(self) -> None:
        null = os.open(os.devnull, os.O_WRONLY)
        try:  # the real descriptor too: the interpreter flushes it at exit
            os.dup2(null, self._stream.fileno())
        finally:
            os.close(null)

    def write(self, text: str) -> int:
        try:
            return self._stream.write(text)
        except BrokenPipeError:
            self._closed_pipe()
            return len(text)

    def flush(self) -> None:
        try:
            self._stream.flush()
        except BrokenPipeError:
            self._closed_pipe()

    def writable(self) -> bool:
        return True

    def isatty(self) -> bool:
        return self._stream.isatty()

    def fileno(self) -> int:
        return self._stream.fileno()

    @property
    def encoding(self) -> str:  # type: ignore[override]
        return self._stream.encoding


def main(argv: list[str] | None = None) -> int:
    if argv is None and not isinstance(sys.stdout, _PipeSafe):  # run as the program
        sys.stdout = _PipeSafe(sys.stdout)
    parser = build_parser()
    args = parser.parse_args(argv)
    # Only the main thread may set a handler (main() is also called from tests' threads).
    installed = threading.current_thread() is threading.main_thread()
    previous = signal.signal(signal.SIGTERM, _raise_stopped) if installed else None
    try:
        check_output(args.command, getattr(args, 'out', None))
        return _COMMANDS[args.command](args)
    except (KpiCalibError, ValueError, FileNotFoundError) as exc:
        print(f'kpi-calib {args.command}: error: {exc}', file=sys.stderr)
        return 2
    except KeyboardInterrupt as exc:
        signum = exc.signum if isinstance(exc, Stopped) else signal.SIGINT
        print(f'kpi-calib {args.command}: stopped by {signal.Signals(signum).name}; the '
              'temporary files it was writing are removed', file=sys.stderr)
        return 128 + signum
    finally:
        if installed:
            signal.signal(signal.SIGTERM, previous if previous is not None else signal.SIG_DFL)


def _recordings(parser: argparse.ArgumentParser) -> None:
    """``--bag`` (once, or once per recording), ``--remounted`` and ``--recordings``."""
    parser.add_argument('--bag', action='append', default=[],
                        help='MCAP bag with joint states and tracker points; repeated: several '
                        'recordings (tracker set-ups) identified together, each with its own '
                        'base placement, named by its file stem')
    parser.add_argument('--remounted', action='append', default=[], metavar='NAME',
                        help='a recording (file stem of a --bag after the first) whose probe '
                        'was mounted again: its reflector offset is identified for it alone')
    parser.add_argument('--recordings', metavar='MANIFEST.yaml',
                        help='the recordings as a manifest instead of --bag: a list of {bag, '
                        'name, reflector_remounted, covariates: {name: value}}')


def _sources(args: argparse.Namespace) -> Any:
    """The bag (one, as before) or the recordings of ``--bag`` / ``--recordings``."""
    from kpi_calib_ros.io.recordings_manifest import read_manifest, sources_from_bags
    if args.recordings and args.bag:
        raise ConfigError('--recordings', 'give the recordings either as --bag or in a '
                          'manifest, not both')
    if args.recordings:
        if args.remounted:
            raise ConfigError('--remounted', 'with --recordings, state reflector_remounted in '
                              'the manifest')
        return read_manifest(args.recordings)
    if not args.bag:
        raise ConfigError('--bag', 'give the MCAP bag (--bag FILE, repeated for several '
                          'recordings) or a manifest (--recordings FILE)')
    if len(args.bag) == 1 and not args.remounted:
        return args.bag[0]
    return sources_from_bags(args.bag, args.remounted)


def _simulate(args: argparse.Namespace) -> int:
    from kpi_calib_ros.app.simulate import run_simulate
    return run_simulate(args.cell, args.n, args.out, args.seed, poses_path=args.poses,
                        allow_code_effects=args.allow_code_effects)


def _identify(args: argparse.Namespace) -> int:
    options = {'joint_topic': args.joint_topic, 'point_topic': args.point_topic,
               'pose_topic': args.pose_topic,
               'allow_code_effects': args.allow_code_effects}
    bags = _sources(args)
    if args.prior:
        if not isinstance(bags, str):
            raise ConfigError('--prior', 'a previous calibration as prior takes one recording '
                              '(--bag once); identify several recordings without --prior')
        if args.learned_residual:
            raise ValueError('--learned-residual is not available with --prior: identify '
                             'without --prior to learn the residual')
        from kpi_calib_ros.app.reidentify import run_reidentify
        return run_reidentify(args.cell, bags, args.out, args.prior, effects=args.effects,
                              model=args.model, drift=args.drift_per_hour,
                              keep_placement=args.keep_placement,
                              drift_model=args.drift_model, swing=args.drift_velocity,
                              max_iterations=args.max_iterations, **options)
    from kpi_calib_ros.app.identify import run_identify
    return run_identify(args.cell, bags, args.out, effects=args.effects, model=args.model,
                        max_iterations=args.max_iterations,
                        learned_residual=args.learned_residual, **options)


def _design(args: argparse.Namespace) -> int:
    from kpi_calib_ros.app.design import run_design
    if not (args.hours >= 0 and args.hours < float('inf')):
        raise ValueError(f'--hours must be finite and >= 0, got {args.hours}')
    return run_design(args.cell, args.n, args.criterion, args.out, seed=args.seed,
                      allow_code_effects=args.allow_code_effects, prior_path=args.prior,
                      hours=args.hours, drift=args.drift_per_hour,
                      keep_placement=args.keep_placement, drift_model=args.drift_model,
                      swing=args.drift_velocity)


def _campaign(args: argparse.Namespace) -> int:
    from kpi_calib_ros.app.campaign import run_campaign
    return run_campaign(args.cell, args.target_std, args.out, simulate=args.simulate,
                        seed=args.seed, max_measurements=args.max_measurements,
                        allow_code_effects=args.allow_code_effects)


def _replay(args: argparse.Namespace) -> int:
    from kpi_calib_ros.ros.replay import run_replay  # ROS only when replaying
    return run_replay(args.bag, args.rate, args.joint_topic, args.point_topic,
                      args.wait_for_subscribers, args.pose_topic)


def _diagnose(args: argparse.Namespace) -> int:
    from kpi_calib_ros.app.diagnose import run_diagnose
    from kpi_calib_ros.core.estimation.residuals import ADEQUACY_ALPHA
    alpha = ADEQUACY_ALPHA if args.alpha is None else args.alpha
    return run_diagnose(args.cell, _sources(args), args.out, effects=args.effects,
                        folds=args.folds,
                        alpha=alpha, model=args.model, joint_topic=args.joint_topic,
                        point_topic=args.point_topic, pose_topic=args.pose_topic,
                        allow_code_effects=args.allow_code_effects)


def _validate(args: argparse.Namespace) -> int:
    from kpi_calib_ros.app.validate import run_validate
    return run_validate(args.cell, args.calibration, args.bag, args.out, args.register,
                        allow_code_effects=args.allow_code_effects,
                        joint_topic=args.joint_topic, point_topic=args.point_topic,
                        pose_topic=args.pose_topic, recording=args.recording,
                        conditions=_conditions(args.covariate))


def _conditions(given: list[str]) -> dict[str, float]:
    """``--covariate NAME=VALUE`` repeated, checked as a recording's conditions are."""
    values: dict[str, Any] = {}
    for item in given:
        name, sep, text = item.partition('=')
        try:
            value = float(text)
        except ValueError:
            value = None
        if not sep or not name or value is None:
            raise ConfigError('--covariate', f'{item!r}: give NAME=VALUE, a number in the '
                              "covariate's SI unit, e.g. payload.mass=2.5")
        if name in values:
            raise ConfigError('--covariate', f'{name!r} given twice')
        values[name] = value
    return stated_conditions(values, '--covariate')


def _import_csv(args: argparse.Namespace) -> int:
    from kpi_calib_ros.io.csv_import import import_csv, load_mapping, mapping_from_dict
    if args.mapping:
        mapping = load_mapping(args.mapping)
    else:
        markers = {}
        for item in args.marker:
            name, _, cols = item.partition('=')
            markers[name] = cols.split(',')
        mapping = mapping_from_dict({
            'frame_id': args.frame, 'joints': [j for j in (args.joints or '').split(',') if j],
            'markers': markers,
            'stamp_columns': [c for c in args.stamp_columns.split(',') if c]})
    summary = import_csv(args.csv, args.out, mapping,
                         delimiter='\t' if args.delimiter == 'tab' else args.delimiter,
                         decimal=args.decimal)
    print('\n'.join(summary.lines()))
    return 0


def _demo(args: argparse.Namespace) -> int:
    from kpi_calib_ros.app.demo import run_demo
    return run_demo(args.out, args.seed)


def _robots(args: argparse.Namespace) -> int:
    from kpi_calib_ros.core.model.robot_library import DATA_DIR
    from kpi_calib_ros.io.shipped_robots import write_shipped
    for path in write_shipped(Path(args.out) if args.out else DATA_DIR):
        print(path)
    return 0


_COMMANDS = {'simulate': _simulate, 'identify': _identify, 'design': _design,
             'diagnose': _diagnose, 'validate': _validate, 'import-csv': _import_csv,
             'replay': _replay, 'campaign': _campaign, 'demo': _demo, 'robots': _robots}

if __name__ == '__main__':
    sys.exit(main())
