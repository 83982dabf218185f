"""Several recordings (tracker set-ups) in one identification: simulated and real.

Simulated (the built-in KR15-class cell, σ = 20 µm): one robot, three set-ups whose base poses
are 1.9–2.1 m and 29–34° apart (ground tilts of 36–41 mrad), 40 poses each, the third with its
probe remounted by 1.1 cm; each set-up's placement started from its own registration on the
nominal robot. The joint identification (geometric model) is compared with the equivalent
truth (the true robot in the kept parameters: a noise-free fit to 300 fresh poses of each
set-up): the worst |error|/σ over every identified parameter (placements included), and the
error's χ² with the fit's covariance (χ² of as many dof as parameters when the covariance
is right: of 42 parameters, one beyond 3σ in 11 % of fits). A fourth
set-up (another station, 40 poses) is registered on 6 of its points (the base pose re-fitted,
the calibration held: its first 6 poses, random, or 6 spread over its points by
farthest-point selection, as one places registration points) and its other 34 points
predicted: rms against the noise floor √3·σ (the rms distance pure noise gives); the same
with set-up A alone calibrated (40 poses), and with the true robot (what the registration on
6 points costs by itself). The tool's own way to the next station is a third: the 6 poses
designed for it (``kpi-calib design --cell CELL_d.yaml --prior calibration.yaml``, KPI
criterion, the joint calibration as prior, D's cell file placing the base where the station
puts it roughly, 400 candidates, no NLP refinement), measured, registered on and the same 34
random poses predicted.

Real (../shared/data/ipa_ur10): 400 poses of Series A (random, seed 0) and half of Series D
(316 poses, random, seed 0: months later, tracker set up again and the probe remounted)
identified together, D's reflector its own, at the geometric and the joint-offset level;
the other 316 poses of D predicted after registration (base and probe offset re-fitted on
them, ``validate --register base+reflector``), against the same prediction from A alone.

Writes bench/results/recordings.md.

    .venv/bin/python bench/recordings.py [SEEDS] [DATA_DIR]
"""
from __future__ import annotations

import dataclasses
import sys
import time
from pathlib import Path

import numpy as np
import scipy.stats
import yaml

from kpi_calib_ros.app.calibration_document import calibration_document
from kpi_calib_ros.app.cell_model import build_cell_model
from kpi_calib_ros.app.design import design_free, design_point
from kpi_calib_ros.app.identify import calibrate_cell
from kpi_calib_ros.app.measurements import with_recordings
from kpi_calib_ros.app.reidentify import cycle_prior
from kpi_calib_ros.app.validate import validate_calibration
from kpi_calib_ros.core.design.optimum import (
    DesignSettings,
    design_context,
    design_measurements,
)
from kpi_calib_ros.core.estimation.least_squares import identify
from kpi_calib_ros.core.estimation.registration import reregister
from kpi_calib_ros.core.measurement import recordings as rec
from kpi_calib_ros.core.measurement.data import Measurements
from kpi_calib_ros.core.simulation import (
    random_configurations,
    simulate_measurements,
    true_parameters,
)
from kpi_calib_ros.io.cell import DEFAULT_CELL, cell_from_dict, load_cell
from kpi_calib_ros.io.csv_import import read_postures
from kpi_calib_ros.io.csv_mapping import mapping_from_dict

ROOT = Path(__file__).resolve().parents[1]
SIGMA = 2e-5
POSES = 40
REGISTER_ON = 6
MOVES = {'b': np.array([-1.2, 1.5, 0.1, 0.02, -0.03, 0.6]),
         'c': np.array([0.8, -1.9, -0.2, -0.04, 0.01, -0.5]),
         'd': np.array([1.5, 1.0, 0.15, 0.01, 0.03, -0.55])}
REMOUNT = np.array([0.004, -0.003, 0.01])
RECORDINGS = [rec.Recording('a'), rec.Recording('b'), rec.Recording('c', True)]
BASE = [f'base.{c}' for c in ('x', 'y', 'z', 'roll', 'pitch', 'yaw')]
LEVELS = ('geometric', 'joint_offsets')  # model levels of the real calibrations


def set_up_rows(cm, p_robot: np.ndarray, name: str, n: int, rng, sigma: float = SIGMA,
                remounted: bool = False) -> tuple[Measurements, np.ndarray]:
    """``n`` poses of set-up ``name`` measured with the cell's one-placement model."""
    single = p_robot.copy()
    single[:6] += MOVES.get(name, 0.0)
    if remounted:
        single[-3:] += REMOUNT
    q = random_configurations(cm.model, single, n, rng)
    return simulate_measurements(cm.model, single, q, sigma, rng), single


def spread(eta: np.ndarray, k: int) -> np.ndarray:
    """Indices of ``k`` points spread over ``eta`` (N, 3): farthest-point selection from the
    point farthest from the centroid, as one places registration points."""
    picked = [int(np.argmax(np.linalg.norm(eta - eta.mean(axis=0), axis=1)))]
    while len(picked) < k:
        gap = np.min(np.linalg.norm(eta[:, None] - eta[picked][None], axis=2), axis=1)
        picked.append(int(np.argmax(gap)))
    return np.array(picked)


def predict_registered(model, p: np.ndarray, new: Measurements, spread_points: bool = False
                       ) -> float:
    """Rms (m) of ``new``'s points after REGISTER_ON of them re-register the base pose: the
    first REGISTER_ON (random poses), or REGISTER_ON spread ones (:func:`spread`)."""
    on = spread(new.eta, REGISTER_ON) if spread_points else np.arange(REGISTER_ON)
    first = new.subset(on)
    rest = new.subset(np.setdiff1d(np.arange(len(new)), on))
    index = model.params.indices(BASE)
    reg = reregister(model, p, first, index, np.full(3, SIGMA), np.zeros(0, int),
                     np.zeros((0, 0)))
    miss = rest.eta - model.predict(reg.p, rest.q)
    return float(np.sqrt(np.mean(np.sum(miss ** 2, axis=1))))


def station_cell(move: np.ndarray):
    """The default cell seen from another tracker station: its base moved by ``move``; the
    robot stands elsewhere in the hall, so of the obstacles only its floor and mounting
    remain (the default cell's wall and car would stand between it and this tracker)."""
    doc = yaml.safe_load(DEFAULT_CELL.read_text())
    doc['tracker']['base_in_tracker'] = (np.array(doc['tracker']['base_in_tracker'])
                                         + move).tolist()
    doc['obstacles'] = [o for o in doc['obstacles'] if o['name'] in ('floor', 'mounting')]
    return build_cell_model(cell_from_dict(doc, DEFAULT_CELL.parent))


def predict_designed(cm, placed, result, p_robot: np.ndarray, rest: Measurements, rng,
                     prior_doc: dict | None = None) -> tuple[float, float]:
    """Rms (m) of ``rest`` (the fourth set-up's random poses) after registering on
    REGISTER_ON poses the tool designs for station D with ``result`` (of ``placed``) as
    prior, measured there; and the same with the true robot registered on them."""
    station = station_cell(MOVES['d'])
    doc = prior_doc if prior_doc is not None else calibration_document(placed, result)
    cp = cycle_prior(station, doc, None, hours=0.0)
    free = design_free(station, cp.allowed)
    cell = station.design_cell()
    settings = DesignSettings(candidates=400, nlp=False)
    ctx = design_context(cell, rng, settings, prior=cp.prior, p=design_point(station, cp),
                         free=free)
    q = design_measurements(cell, REGISTER_ON, 'kpi', rng, settings, context=ctx).configurations
    single = p_robot.copy()
    single[:6] += MOVES['d']
    on = simulate_measurements(cm.model, single, q, SIGMA, rng)
    out = []
    for model, p in ((placed.model, result.values), (cm.model, p_robot)):
        reg = reregister(model, p, on, model.params.indices(BASE), np.full(3, SIGMA),
                         np.zeros(0, int), np.zeros((0, 0)))
        miss = rest.eta - model.predict(reg.p, rest.q)
        out.append(float(np.sqrt(np.mean(np.sum(miss ** 2, axis=1)))))
    return out[0], out[1]


def simulated(seed: int, cm) -> dict:
    rng = np.random.default_rng(seed)
    p_robot = true_parameters(cm.model.params, rng)
    parts, truths = [], {}
    for r in RECORDINGS:
        rows, truths[r.name] = set_up_rows(cm, p_robot, r.name, POSES, rng,
                                           remounted=r.reflector_remounted)
        parts.append(rows)
    data = rec.combine(parts, RECORDINGS)
    placed = with_recordings(cm, RECORDINGS)
    truth = np.concatenate([p_robot, np.zeros(len(placed.model.params) - len(p_robot))])
    for r in RECORDINGS[1:]:
        truth[placed.model.params.indices(rec.base_names(r.name))] = truths[r.name][:6]
        if r.reflector_remounted:
            truth[placed.model.params.indices(rec.reflector_names(r.name, 'reflector'))] = \
                truths[r.name][-3:]
    start = time.perf_counter()
    joint = calibrate_cell(placed, data, model='geometric')
    seconds = time.perf_counter() - start
    result = joint.result
    dense_parts = [set_up_rows(cm, p_robot, r.name, 300, rng, 1e-300, r.reflector_remounted)[0]
                   for r in RECORDINGS]
    dense = rec.combine(dense_parts, RECORDINGS)
    dense = dataclasses.replace(dense, eta=placed.model.predict(truth, dense.q,
                                                                covariates=dense.covariates))
    equivalent = identify(placed.model, dense, SIGMA, cm.q_work, p0=result.values,
                          free=list(result.estimated))
    idx = placed.model.params.indices(list(result.estimated))
    error = result.values[idx] - equivalent.values[idx]
    z = error / result.std
    chi2 = float(error @ np.linalg.solve(result.covariance, error))
    worst = int(np.argmax(np.abs(z)))
    placement = [i for i, n in enumerate(result.estimated)
                 if n.startswith(('base.', 'reflector.', 'recording.'))]
    # the fourth set-up, and set-up A alone
    fourth, _ = set_up_rows(cm, p_robot, 'd', POSES, rng)
    alone = calibrate_cell(cm, parts[0], model='geometric').result
    designed, truth_designed = predict_designed(
        cm, placed, result, p_robot, fourth.subset(np.arange(REGISTER_ON, POSES)), rng)
    return {'seed': seed, 'valid': joint.valid, 'implausible': len(joint.implausible),
            'parameters': len(result.estimated), 'worst_z': float(abs(z[worst])),
            'chi2': chi2, 'chi2_p': float(scipy.stats.chi2.sf(chi2, len(z))),
            'worst_name': result.estimated[worst],
            'worst_placement_z': float(np.max(np.abs(z[placement]))), 'z': z.tolist(),
            'equivalent_rms_m': equivalent.rms_m, 'seconds': seconds,
            'joint_rms_m': predict_registered(placed.model, result.values, fourth),
            'alone_rms_m': predict_registered(cm.model, alone.values, fourth),
            'truth_rms_m': predict_registered(cm.model, p_robot, fourth),
            'joint_spread_m': predict_registered(placed.model, result.values, fourth, True),
            'alone_spread_m': predict_registered(cm.model, alone.values, fourth, True),
            'joint_designed_m': designed, 'truth_designed_m': truth_designed}


def ur10_series(path: Path) -> Measurements:
    """One series' joint readings and probe origins, without stamps (D's are not usable)."""
    doc = yaml.safe_load((ROOT / 'test' / 'data' / 'ipa_ur10_mapping.yaml').read_text())
    for key in ('stamp_columns', 'stamp_format', 'stamp_timezone'):
        doc.pop(key, None)
    rows = list(read_postures(path, mapping_from_dict(doc)))
    return Measurements(q=np.array([r.q for r in rows]),
                        eta=np.array([r.points[0][1] for r in rows]),
                        reflector=np.zeros(len(rows), int))


def real(data_dir: Path) -> dict:
    doc = {'robot': {'urdf': 'package://example-robot-data/robots/ur_description/urdf/'
                             'ur10_robot.urdf', 'base_frame': 'base_link', 'tip_frame': 'tool0'},
           'tracker': {'frame_id': 'laser_tracker'}, 'reflectors': [{'name': 'probe'}],
           'noise': {'sigma': SIGMA},
           'working_poses': [[0.0, -1.2, 1.7, -2.07, -1.57, 0.0]]}
    cm = build_cell_model(cell_from_dict(doc, data_dir))
    a = ur10_series(data_dir / 'Series_A' / 'measurements_grid.csv')
    d = ur10_series(data_dir / 'Series_D' / 'measurements_iso_cubes.csv')
    a_train = a.subset(np.random.default_rng(0).choice(len(a), 400, replace=False))
    order = np.random.default_rng(0).permutation(len(d))
    d_train, d_test = d.subset(order[:len(d) // 2]), d.subset(order[len(d) // 2:])
    out: dict = {'a': len(a_train), 'd_train': len(d_train), 'd_test': len(d_test)}
    both = [rec.Recording('A'), rec.Recording('D', True)]
    for level in LEVELS:
        for label, cal_cm, data in (
                ('A alone', cm, a_train),
                ('A and half of D', with_recordings(cm, both),
                 rec.combine([a_train, d_train], both))):
            start = time.perf_counter()
            cal = calibrate_cell(cal_cm, data, model=level)
            seconds = time.perf_counter() - start
            calibration = calibration_document(cal_cm, cal.result)
            v = validate_calibration(cal_cm, cal.result.values, calibration, d_test,
                                     'base+reflector')
            out[(level, label)] = {'valid': cal.valid, 'training_rms_m': cal.result.rms_m,
                                   'implausible': list(cal.implausible), 'd_rms_m': v.rms_m,
                                   'seconds': seconds}
    return out


def main(argv: list[str]) -> int:
    seeds = int(argv[0]) if argv else 5
    data_dir = Path(argv[1]) if len(argv) > 1 else Path('/work/shared/data/ipa_ur10')
    cm = build_cell_model(load_cell(DEFAULT_CELL))
    floor = np.sqrt(3) * SIGMA
    rows = []
    for seed in range(seeds):
        r = simulated(seed, cm)
        rows.append(r)
        print(r, flush=True)
    ur10 = real(data_dir)
    print(ur10, flush=True)
    lines = ['# Several recordings (tracker set-ups) in one identification', '',
             'Command: `.venv/bin/python bench/recordings.py '
             f'{seeds}` (figures exactly as measured; see the module docstring).', '',
             '## Simulated: three set-ups of 40 poses, a fourth predicted', '',
             f'KR15-class cell, σ = {SIGMA * 1e6:g} µm per axis, noise floor √3·σ = '
             f'{floor * 1e6:.1f} µm (rms distance of pure noise). Set-ups B and C are '
             '1.9 m / 2.1 m and 34° / 29° from A (tilts 36 / 41 mrad), C with the probe '
             'remounted (11 mm); the fourth set-up D 1.8 m and 32° from A (tilt 32 mrad), '
             f'registered on {REGISTER_ON} points, its other {POSES - REGISTER_ON} predicted.', '',
             '| seed | valid | gate violations | identified | χ² of the error (p) | '
             'worst \\|error\\|/σ (which) | '
             'worst over placements | D, 6 random points: joint (µm, × floor) | A alone | '
             'true robot | '
             'D, 6 spread points: joint | A alone | D, 6 designed poses: joint | '
             'true robot | joint fit (s) |',
             '|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|']
    for r in rows:
        lines.append(
            f"| {r['seed']} | {r['valid']} | {r['implausible']} | {r['parameters']} | "
            f"{r['chi2']:.1f} ({r['chi2_p']:.2f}) | "
            f"{r['worst_z']:.2f} ({r['worst_name']}) | {r['worst_placement_z']:.2f} | "
            f"{r['joint_rms_m'] * 1e6:.1f} ({r['joint_rms_m'] / floor:.3f}) | "
            f"{r['alone_rms_m'] * 1e6:.1f} ({r['alone_rms_m'] / floor:.3f}) | "
            f"{r['truth_rms_m'] * 1e6:.1f} ({r['truth_rms_m'] / floor:.3f}) | "
            f"{r['joint_spread_m'] * 1e6:.1f} ({r['joint_spread_m'] / floor:.3f}) | "
            f"{r['alone_spread_m'] * 1e6:.1f} ({r['alone_spread_m'] / floor:.3f}) | "
            f"{r['joint_designed_m'] * 1e6:.1f} ({r['joint_designed_m'] / floor:.3f}) | "
            f"{r['truth_designed_m'] * 1e6:.1f} ({r['truth_designed_m'] / floor:.3f}) | "
            f"{r['seconds']:.1f} |")
    def mean(key: str) -> float:
        return float(np.mean([r[key] for r in rows]))
    # Is "every parameter within 3σ" the truth of a right covariance? With k parameters,
    # one beyond 3σ in 1 − 0.9973^k of fits; the χ² p-values of the seeds (independent)
    # are uniform when the covariance is right.
    n_par = rows[0]['parameters']
    beyond = sum(r['worst_z'] > 3 for r in rows)
    expected = 1 - (1 - 2 * scipy.stats.norm.sf(3)) ** n_par
    at_least = float(scipy.stats.binom.sf(beyond - 1, len(rows), expected))
    pooled = np.concatenate([r['z'] for r in rows])
    uniform_p = float(scipy.stats.kstest([r['chi2_p'] for r in rows], 'uniform').pvalue)
    lines += ['', f'Some parameter beyond 3σ in {beyond} of {len(rows)} seeds; with a right '
              f'covariance, one of {n_par} parameters is beyond 3σ in {expected:.1%} of fits '
              f'(P(≥ {beyond} of {len(rows)}) = {at_least:.2f}). The χ² of the error: p-values '
              f'uniform (Kolmogorov-Smirnov p = {uniform_p:.2f} over the {len(rows)} seeds); '
              f'|error|/σ of every parameter of every seed ({len(pooled)}): std '
              f'{np.std(pooled):.3f}, beyond 3σ {np.mean(np.abs(pooled) > 3):.2%} (0.27 % '
              'for N(0, 1); the parameters of one seed are correlated).']
    lines += ['', f"Worst |error|/σ over every seed: {max(r['worst_z'] for r in rows):.2f}; "
              f"over the placements: {max(r['worst_placement_z'] for r in rows):.2f}. "
              'Fourth set-up, mean over the seeds, registered on 6 random points: joint '
              f"{mean('joint_rms_m') * 1e6:.1f} µm ({mean('joint_rms_m') / floor:.3f} × "
              f"floor), A alone {mean('alone_rms_m') * 1e6:.1f} µm "
              f"({mean('alone_rms_m') / floor:.3f} × floor), the true robot "
              f"{mean('truth_rms_m') * 1e6:.1f} µm ({mean('truth_rms_m') / floor:.3f} × floor: "
              'what the registration on 6 points alone costs); on 6 spread points: joint '
              f"{mean('joint_spread_m') * 1e6:.1f} µm ({mean('joint_spread_m') / floor:.3f} × "
              f"floor), A alone {mean('alone_spread_m') * 1e6:.1f} µm "
              f"({mean('alone_spread_m') / floor:.3f} × floor); on 6 poses designed for "
              f"station D with the joint calibration as prior: joint "
              f"{mean('joint_designed_m') * 1e6:.1f} µm "
              f"({mean('joint_designed_m') / floor:.3f} × floor; worst seed "
              f"{max(r['joint_designed_m'] for r in rows) / floor:.3f}, above 1.2 × in "
              f"{sum(r['joint_designed_m'] > 1.2 * floor for r in rows)} of {len(rows)}), "
              f"the true robot on them {mean('truth_designed_m') * 1e6:.1f} µm "
              f"({mean('truth_designed_m') / floor:.3f} × floor).", '',
              '## Real: UR10 Series A and D in one identification', '',
              f"{ur10['a']} poses of Series A and {ur10['d_train']} of Series D (probe "
              f"remounted, its own reflector offset) identified together, at two model levels; "
              f"the other {ur10['d_test']} poses of D predicted after registration (base "
              'and probe offset re-fitted on them).', '',
              '| model level | calibration | valid | training rms (µm) | D predicted (µm) | '
              'plausibility gate | fit (s) |',
              '|---|---|---|---|---|---|---|']
    for level in LEVELS:
        for label in ('A alone', 'A and half of D'):
            r = ur10[(level, label)]
            lines.append(f"| {level} | {label} | {r['valid']} | "
                         f"{r['training_rms_m'] * 1e6:.1f} | {r['d_rms_m'] * 1e6:.1f} | "
                         f"{'; '.join(v.split(';')[0] for v in r['implausible']) or 'passes'} "
                         f"| {r['seconds']:.1f} |")
    (ROOT / 'bench' / 'results' / 'recordings.md').write_text('\n'.join(lines) + '\n')
    print('\n'.join(lines))
    return 0


if __name__ == '__main__':
    sys.exit(main(sys.argv[1:]))
