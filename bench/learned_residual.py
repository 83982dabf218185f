"""The learned residual (core.diagnosis.learned_residual): simulated maps, false alarms, coverage,
and the real UR10 and TIAGo splits.

1. Smooth unknown map of two joints (joint_2, joint_3; 100 µm, 5 σ) on the built-in KR15
   cell: 200 training poses with joint_2 in the lower half of its range, 200 fresh poses
   inside (same half) and 200 outside (upper half), per seed. Chosen?, fresh-pose
   measurement rms / noise floor (sqrt(3) σ), and the share of fresh poses whose true TCP
   error lies in the 95 % ellipsoid (χ²₃), inside and outside.
2. Clean data (no map), 150 poses: how often the learned residual is chosen (false alarms).
3. UR10 Series A (real, laser tracker): a geometric calibration on 300 poses of the first
   quarter of Series A with shoulder_pan below its median; held-out: later poses in the
   same region, and poses of the other region; rms of the physical model and with the
   learned residual (also on the poses of the same quarter and region not trained on), and
   the share of held-out measurements in their 95 % ellipsoid
   (TCP covariance plus the noise the learned residual estimates).
4. TIAGo mocap (real): calibrated on the 37-posture session (2021-11-30), validated on
   2021-11-26.

Every held-out set is also tested against its joint statement (its poses share the
parameters' error and the learned field; core.diagnosis.shared_error): the range the 95 %
share takes over recordings that agree with the statement, the independent points the set
is worth, and p; in simulation the p-values over seeds should be uniform.

    .venv/bin/python bench/learned_residual.py [n_smooth_seeds [n_clean_seeds]]

Writes bench/results/learned_residual.md.
"""
from __future__ import annotations

import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import scipy.stats

from kpi_calib_ros.app.cell_model import build_cell_model
from kpi_calib_ros.app.identify import calibrate_cell
from kpi_calib_ros.app.learned_residual import (
    choose_residual,
    field_covariance,
    physical_covariance,
    point_rows,
    predict_tcp,
)
from kpi_calib_ros.app.measurements import load_measurements
from kpi_calib_ros.app.placement import registered_start
from kpi_calib_ros.cli import main as cli
from kpi_calib_ros.core.diagnosis.corrected_tcp import corrected_tcp
from kpi_calib_ros.core.diagnosis.learned_residual import fit_learned_residual
from kpi_calib_ros.core.diagnosis.shared_error import (
    joint_test_points,
    shared_error_test,
    statement_covariance,
)
from kpi_calib_ros.core.estimation.least_squares import identify
from kpi_calib_ros.core.estimation.precision import expected_tcp_error, honest_precision
from kpi_calib_ros.core.measurement.data import Measurements
from kpi_calib_ros.core.simulation import (
    random_configurations,
    simulate_measurements,
    smooth_joint_map,
    true_parameters,
)
from kpi_calib_ros.io.cell import DEFAULT_CELL, cell_from_dict, load_cell
from kpi_calib_ros.io.csv_import import read_postures
from kpi_calib_ros.io.csv_mapping import load_mapping

ROOT = Path(__file__).resolve().parents[1]
SHARED = ROOT.parent / 'shared' / 'data'
UR10 = SHARED / 'ipa_ur10' if (SHARED / 'ipa_ur10').is_dir() else Path('/work/shared/data/ipa_ur10')
TIAGO = Path(os.environ.get('TIAGO_MOCAP_DIR') or (
    SHARED / 'tiago_mocap' if (SHARED / 'tiago_mocap').is_dir()
    else '/work/shared/data/tiago_mocap'))
OUT = ROOT / 'bench' / 'results' / 'learned_residual.md'
AMPLITUDE_M = 1e-4
N_TRAIN = 200
N_FRESH = 200
N_CLEAN = 150
UR10_TRAIN = 300
UR10_SIGMA = 20e-6
CHI2_95 = float(scipy.stats.chi2.ppf(0.95, 3))


def physical_misfit(model, data: Measurements, result) -> float:
    """b (m): the physical model's held-out misfit, 0 when χ² accepts it."""
    misfit = expected_tcp_error(model, data, result).misfit_m
    return float(misfit) if np.isfinite(misfit) else 0.0


def rms(e: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.sum(np.atleast_2d(e) ** 2, axis=1))))


def mahalanobis(e: np.ndarray, cov: np.ndarray) -> np.ndarray:
    """(M,) squared Mahalanobis distance of the errors e (M, 3) under ``cov`` (M, 3, 3)."""
    return np.einsum('mi,mij,mj->m', e, np.linalg.inv(cov), e)


def covered(e: np.ndarray, cov: np.ndarray) -> float:
    """Share of the errors e (M, 3) inside their 95 % ellipsoid of ``cov`` (M, 3, 3)."""
    return float(np.mean(mahalanobis(e, cov) <= CHI2_95))


def joint_check(e: np.ndarray, jac: np.ndarray, cov: np.ndarray, q: np.ndarray, model,
                outside: np.ndarray | None, noise: np.ndarray | None) -> str:
    """The errors e (M, 3) against their joint statement (points sharing the parameters'
    error and the learned field; core.diagnosis.shared_error) as table cells: the range of
    the 95 % share over recordings that agree with it, the independent points the tested
    ones are worth, and p."""
    idx = joint_test_points(len(e))
    joint = statement_covariance(jac[idx], cov, q[idx], model, outside, noise)
    out = shared_error_test(e[idx], joint)
    return (f'{out.share_range[0]:.3f}-{out.share_range[1]:.3f} | '
            f'{out.effective_points:.1f} of {out.points} | {out.p_value:.2g}')


def physical_coverage(e: np.ndarray, jac: np.ndarray, result, misfit: float,
                      sigma: np.ndarray) -> float:
    """Coverage of the physical model's own statement: its (χ²-scaled) TCP covariance, its
    held-out misfit b²/3 per axis and the noise σ² · χ²/dof of a measurement."""
    cov = np.einsum('mik,kl,mjl->mij', jac, result.covariance, jac)
    noise = float(np.mean(np.broadcast_to(sigma, (3,)) ** 2)) * result.covariance_scale
    return covered(e, cov + (misfit ** 2 / 3.0 + noise) * np.eye(3))


def smooth_seed(cm, seed: int, amplitude: float, n_train: int) -> dict:
    rng = np.random.default_rng(seed)
    p = true_parameters(cm.model.params, rng)
    phase = rng.uniform(0, 2 * np.pi, 6)
    pool = random_configurations(cm.model, p, 3 * n_train + 6 * N_FRESH, rng)
    mid = 0.5 * (cm.model.robot.lower[1] + cm.model.robot.upper[1])
    low, high = pool[pool[:, 1] < mid], pool[pool[:, 1] >= mid]
    q, fresh_in, fresh_out = low[:n_train], low[n_train:n_train + N_FRESH], high[:N_FRESH]
    clean = simulate_measurements(cm.model, p, q, cm.cell.sigma, rng)
    data = Measurements(q=q, eta=clean.eta + smooth_joint_map(q, (1, 2), amplitude, phase))
    result = honest_precision(identify(cm.model, data, cm.cell.sigma, cm.q_work))
    choice = fit_learned_residual(q, result.residuals, cm.cell.sigma, tuple(cm.joint_names),
                                  seed=seed)
    out = {'chosen': choice.chosen, 'p': choice.p_value}
    if amplitude == 0:
        return out
    cov = physical_covariance(result, choice.model, cm.cell.sigma)
    outside = field_covariance(cm.model, data, result, choice.model, cm.cell.sigma)
    floor = float(np.sqrt(np.sum(np.broadcast_to(cm.cell.sigma, (3,)) ** 2)))
    for name, fresh in (('in', fresh_in), ('out', fresh_out)):
        truth = cm.model.predict(p, fresh) + smooth_joint_map(fresh, (1, 2), amplitude, phase)
        tcp = predict_tcp(cm.model, result.values, result.estimated, cov, choice.model, fresh,
                          outside)
        measured = truth + rng.normal(size=truth.shape) * cm.cell.sigma
        physical = tcp.position - tcp.correction.mean
        out[f'{name}_phys'] = rms(measured - physical) / floor
        out[f'{name}_learned'] = rms(measured - tcp.position) / floor
        out[f'{name}_cover'] = covered(truth - tcp.position, tcp.covariance)
        out[f'{name}_m2'] = mahalanobis(truth - tcp.position, tcp.covariance)
        _, jac = cm.model.jacobian(result.values, fresh)
        joint = statement_covariance(jac[:, :, cm.model.params.indices(list(result.estimated))],
                                     cov, fresh, choice.model, outside)
        out[f'{name}_joint'] = shared_error_test(truth - tcp.position, joint)
        out[f'{name}_inside'] = float(np.mean(tcp.correction.inside))
    return out


def simulated(n_smooth: int, n_clean: int, lines: list[str]) -> None:
    cm = build_cell_model(load_cell(DEFAULT_CELL))
    t0 = time.perf_counter()
    rows = [smooth_seed(cm, seed, AMPLITUDE_M, N_TRAIN) for seed in range(n_smooth)]
    lines += ['## 1. Smooth unknown map of two joints (KR15 cell, σ = 20 µm, map 100 µm)', '',
              f'{N_TRAIN} training poses (joint_2 in the lower half), {N_FRESH} fresh poses '
              'inside and outside per seed. Error: rms of fresh measurements / noise floor '
              '(sqrt(3) σ = 34.6 µm); coverage: share of true TCP errors in the 95 % '
              'ellipsoid.', '',
              '| seed | chosen | inside: physical | inside: learned | coverage inside | '
              'outside: physical | outside: learned | coverage outside | share inside region '
              '(fresh in / out) |', '|' + '---|' * 9]
    for seed, r in enumerate(rows):
        lines.append(f"| {seed} | {r['chosen']} | {r['in_phys']:.2f}x | {r['in_learned']:.2f}x "
                     f"| {r['in_cover']:.3f} | {r['out_phys']:.2f}x | {r['out_learned']:.2f}x | "
                     f"{r['out_cover']:.3f} | {r['in_inside']:.2f} / {r['out_inside']:.2f} |")
    worst = max(r['in_learned'] for r in rows)
    lines += ['', f"Chosen in {sum(r['chosen'] for r in rows)} of {n_smooth} seeds; fresh-pose "
              f'error inside the region {min(r["in_learned"] for r in rows):.2f}-{worst:.2f}x '
              'the noise floor (acceptance <= 1.5x); coverage inside '
              f"{min(r['in_cover'] for r in rows):.3f}-{max(r['in_cover'] for r in rows):.3f}, "
              f"outside {min(r['out_cover'] for r in rows):.3f}-"
              f"{max(r['out_cover'] for r in rows):.3f} (acceptance 0.90-0.98); over all "
              f'{n_smooth * N_FRESH} fresh poses of the seeds '
              f"{np.mean(np.concatenate([r['in_m2'] for r in rows]) <= CHI2_95):.3f} inside, "
              f"{np.mean(np.concatenate([r['out_m2'] for r in rows]) <= CHI2_95):.3f} outside "
              '(one calibration\'s poses share its errors, so one seed\'s share spreads '
              f'around the pooled one); {time.perf_counter() - t0:.0f} s.', '']
    for where, label in (('in', 'inside'), ('out', 'outside')):
        tests = [r[f'{where}_joint'] for r in rows if f'{where}_joint' in r]
        p = [t.p_value for t in tests]
        held = sum(t.share_range[0] <= t.share <= t.share_range[1] for t in tests)
        lines.append(f'Joint statement (the poses share the parameters\' error and the field), '
                     f'{label}: share of the true errors in their 95 % ellipsoids within the '
                     f'range the statement gives it in {held} of {len(tests)} seeds (range '
                     f'{min(t.share_range[0] for t in tests):.3f}-'
                     f'{max(t.share_range[1] for t in tests):.3f}); {N_FRESH} poses worth '
                     f'{np.median([t.effective_points for t in tests]):.0f} independent ones '
                     f'(median); p per seed {", ".join(f"{x:.2f}" for x in p)} '
                     f'(below 0.05 in {sum(x < 0.05 for x in p)}; Kolmogorov-Smirnov against '
                     f'uniform p = {scipy.stats.kstest(p, "uniform").pvalue:.2f}).')
        lines.append('')
    print('\n'.join(lines[-8:]), flush=True)
    t0 = time.perf_counter()
    clean = [smooth_seed(cm, 1000 + seed, 0.0, N_CLEAN) for seed in range(n_clean)]
    alarms = [1000 + s for s, r in enumerate(clean) if r['chosen']]
    lines += ['## 2. Clean data: false alarms', '',
              f'{n_clean} seeds, {N_CLEAN} poses each, no map: the learned residual was chosen '
              f'in {len(alarms)} ({alarms}); smallest p of the paired test '
              f"{min(r['p'] for r in clean):.3g}; {time.perf_counter() - t0:.0f} s.", '']
    print(lines[-2], flush=True)


def ur10(lines: list[str]) -> None:
    rows = list(read_postures(UR10 / 'Series_A' / 'measurements_grid.csv',
                              load_mapping(ROOT / 'test' / 'data' / 'ipa_ur10_mapping.yaml')))
    stamps = np.array([r.stamp_ns for r in rows], dtype=float)
    q_all = np.array([r.q for r in rows])
    eta_all = np.array([r.points[0][1] for r in rows])
    order = np.argsort(stamps, kind='stable')
    early, late = order[:len(order) // 4], order[len(order) // 4:]
    pan_median = float(np.median(q_all[:, 0]))
    region = q_all[:, 0] < pan_median
    rng = np.random.default_rng(0)
    candidates = early[region[early]]
    train = rng.choice(candidates, UR10_TRAIN, replace=False)
    same_time = np.setdiff1d(candidates, train)
    later_same = rng.choice(late[region[late]], 1000, replace=False)
    other = rng.choice(np.flatnonzero(~region), 1000, replace=False)
    doc = {'robot': {'urdf': 'package://example-robot-data/robots/ur_description/urdf/'
                             'ur10_robot.urdf', 'base_frame': 'base_link', 'tip_frame': 'tool0'},
           'tracker': {'frame_id': 'tracker'}, 'noise': {'sigma': UR10_SIGMA},
           'working_poses': [[0.0, -1.2, 1.7, -2.07, -1.57, 0.0]]}
    cm = build_cell_model(cell_from_dict(doc, Path('.')))
    data = Measurements(q=q_all[train], eta=eta_all[train])
    t0 = time.perf_counter()
    start, _ = registered_start(cm, data)
    result = honest_precision(identify(cm.model, data, cm.cell.sigma, cm.q_work, p0=start))
    choice = choose_residual(cm, data, result)
    fit_s = time.perf_counter() - t0
    cov = physical_covariance(result, choice.model, cm.cell.sigma)
    outside = field_covariance(cm.model, data, result, choice.model, cm.cell.sigma)
    misfit = physical_misfit(cm.model, data, result)
    lines += ['## 3. UR10 Series A (real, laser tracker)', '',
              f'Geometric calibration on {UR10_TRAIN} poses of the first quarter of Series A '
              f'with shoulder_pan < {pan_median:.3f} rad (training rms {result.rms_m * 1e6:.0f} '
              f'µm, χ²/dof {result.chi2 / result.dof:.1f}); {choice.reason}; length scales '
              + ', '.join(f'{k} {v:.3g}' for k, v in choice.model.relevant_joints().items())
              + f'; fit and choice {fit_s:.0f} s.', '',
              '| held out | poses | physical rms | with learned residual | ratio | inside fitted '
              'region | 95 % coverage (measured) | χ²/dof (measured) | physical model\'s own '
              '95 % coverage | coverage range under the joint statement | worth (independent '
              'points) | p (joint statement) |',
              '|---|---|---|---|---|---|---|---|---|---|---|---|']
    for name, idx in (('same quarter and region, not trained on', same_time),
                      ('later, same region', later_same), ('other region (any time)', other)):
        q, eta = q_all[idx], eta_all[idx]
        model = choice.model if choice.chosen else None
        tcp = predict_tcp(cm.model, result.values, result.estimated,
                          cov if model is not None else result.covariance, model, q,
                          outside)
        physical = (tcp.position - tcp.correction.mean) if tcp.correction is not None \
            else tcp.position
        noise = (choice.model.noise_covariance_m2 if model is not None
                 else float(np.mean(np.broadcast_to(cm.cell.sigma, (3,)) ** 2)) *
                 result.covariance_scale * np.eye(3))
        cover = covered(eta - tcp.position, tcp.covariance + noise)
        chi2 = float(np.mean(mahalanobis(eta - tcp.position, tcp.covariance + noise)) / 3.0)
        inside = (f'{np.mean(tcp.correction.inside):.2f}' if tcp.correction is not None
                  else 'n/a (not chosen)')
        ratio = rms(eta - tcp.position) / rms(eta - physical)
        _, jac = cm.model.jacobian(result.values, q)
        own = physical_coverage(eta - physical, jac[:, :, cm.model.params.indices(
            list(result.estimated))], result, misfit, cm.cell.sigma)
        est = jac[:, :, cm.model.params.indices(list(result.estimated))]
        check = joint_check(eta - tcp.position, est, cov if model is not None
                            else result.covariance, q, model, outside, noise)
        lines.append(f'| {name} | {len(idx)} | {rms(eta - physical) * 1e6:.0f} µm | '
                     f'{rms(eta - tcp.position) * 1e6:.0f} µm | {ratio:.4f} | {inside} | '
                     f'{cover:.3f} | {chi2:.2f} | {own:.3f} | {check} |')
    lines.append('')
    print('\n'.join(lines[-7:]), flush=True)


def _bag(session: str, folder: Path) -> Path:
    out = folder / f'{session}.mcap'
    table = TIAGO / f'qualisys_{session}_static_postures.csv'
    if cli(['import-csv', str(table), '--mapping',
            str(ROOT / 'test' / 'data' / 'tiago_mocap_mapping.yaml'), '--out', str(out)]) != 0:
        raise SystemExit(f'import-csv failed for {table}')
    return out


def tiago(lines: list[str]) -> None:
    cell = ROOT / 'test' / 'data' / 'tiago_mocap_cell.yaml'
    with tempfile.TemporaryDirectory() as tmp:
        cm, data, _ = load_measurements(cell, _bag('2021-11-30', Path(tmp)))
        _, new, _ = load_measurements(cell, _bag('2021-11-26', Path(tmp)))
    cal = calibrate_cell(cm, data, 'geometric')
    cm = cal.cell or cm
    kept = data.subset(cal.robust.kept)
    choice = choose_residual(cm, kept, cal.result)
    rows = point_rows(cm.model, new)
    new = new.subset(rows)
    result = cal.result
    idx = cm.model.params.indices(list(result.estimated))
    pred, jac = cm.model.jacobian(result.values, new.q, None, new.reflector)
    model = choice.model if choice.chosen else None
    cov = physical_covariance(result, model, cm.cell.sigma)
    misfit = physical_misfit(cm.model, kept, result)
    outside = field_covariance(cm.model, kept, result, choice.model, cm.cell.sigma)
    tcp = corrected_tcp(pred, jac[:, :, idx], cov, new.q, model, outside)
    noise = (choice.model.noise_covariance_m2 if model is not None
             else float(np.mean(np.broadcast_to(cm.cell.sigma, (3,)) ** 2))
             * result.covariance_scale * np.eye(3))
    cover = covered(new.eta - tcp.position, tcp.covariance + noise)
    chi2 = float(np.mean(mahalanobis(new.eta - tcp.position, tcp.covariance + noise)) / 3.0)
    inside = f'{np.mean(tcp.correction.inside):.2f}' if model is not None else 'n/a (not chosen)'
    e_phys, e_learned = new.eta - pred, new.eta - tcp.position
    own = physical_coverage(e_phys, jac[:, :, idx], result, misfit, cm.cell.sigma)
    lines += ['## 4. TIAGo mocap (real, four markers per posture)', '',
              f'Geometric calibration on the 37-posture session 2021-11-30 ({len(kept)} marker '
              f'points kept); {choice.reason}.', '',
              '| held out | points | physical rms | with learned residual | ratio | inside '
              'fitted region | 95 % coverage (measured) | χ²/dof (measured) | physical model\'s '
              'own 95 % coverage | coverage range under the joint statement | worth '
              '(independent points) | p (joint statement) |',
              '|---|---|---|---|---|---|---|---|---|---|---|---|',
              f'| 2021-11-26 | {len(new)} | {rms(e_phys) * 1e3:.3f} mm | '
              f'{rms(e_learned) * 1e3:.3f} mm | {rms(e_learned) / rms(e_phys):.4f} | {inside} | '
              f'{cover:.3f} | {chi2:.2f} | {own:.3f} | '
              + joint_check(e_learned, jac[:, :, idx], cov, np.atleast_2d(new.q), model,
                            outside, noise) + ' |', '']
    print('\n'.join(lines[-6:]), flush=True)


def main() -> None:
    n_smooth = int(sys.argv[1]) if len(sys.argv) > 1 else 10
    n_clean = int(sys.argv[2]) if len(sys.argv) > 2 else 100
    lines = ['# Learned residual (Gaussian process of the physical model\'s residuals)', '',
             f'`.venv/bin/python bench/learned_residual.py {n_smooth} {n_clean}`; '
             'OMP_NUM_THREADS=1, 2-core machine.', '']
    simulated(n_smooth, n_clean, lines)
    ur10(lines)
    tiago(lines)
    OUT.write_text('\n'.join(lines) + '\n')
    print(f'written: {OUT}')


if __name__ == '__main__':
    main()
