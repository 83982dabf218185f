"""A servo-soft arm: joint compliance identified with the torque at the deflected configuration.

Simulated KR15-class default cell, tracker σ = 20 µm per axis; truth ``joint_compliance`` of
joint_2 (c = -3e-5 rad/(N m)) and joint_3 (-4e-5), 20× softer than its gearboxes: about 22 mrad
of sag. The truth is solved independently of the model's linearisation: δ = c τ(q + δ) by
fixed point on Pinocchio's gravity torques (to 1e-14 rad), the torques there given to the
model as measured ones. Per seed, the same 60 random poses measured with 0 and 10 kg
(``payload.mass`` per row), 60 fresh poses with 5 kg. ``calibrate_cell`` of the geometric
level with both compliances: as the tool does it (the torque at the deflected
configuration, :mod:`kpi_calib_ros.core.measurement.deflection`), and with the torque at the
encoder's reading (the rows' gravity torques given as measured ones: no deflection feedback,
as before). The fresh poses are predicted the same way each. Writes
bench/results/servo_soft_compliance.md.

    .venv/bin/python bench/servo_soft_compliance.py [n_seeds]
"""
from __future__ import annotations

import sys
import time
from pathlib import Path

import numpy as np

from kpi_calib_ros.app.cell_model import build_cell_model
from kpi_calib_ros.app.identify import calibrate_cell, with_effects
from kpi_calib_ros.core.effects.registry import parse_effect_spec
from kpi_calib_ros.core.measurement.data import Measurements
from kpi_calib_ros.core.measurement.payload import row_payloads
from kpi_calib_ros.core.simulation import (
    held_deflection,
    random_configurations,
    true_parameters,
)
from kpi_calib_ros.io.cell import DEFAULT_CELL, cell_from_dict, read_cell_document

SIGMA = 20e-6
FLOOR = np.sqrt(3) * SIGMA
STIFF = {'joint_2': -3e-5, 'joint_3': -4e-5}
POSES = 60


def held(cm, c, q, cov):
    """The exact fixed point δ = c τ(q + δ) and the torques there."""
    return held_deflection(cm.robot, c, q, row_payloads(cov, len(q), cm.robot.payload))


def seed_run(cm0, cm, c, seed):
    rng = np.random.default_rng(seed)
    p_true = np.concatenate([true_parameters(cm0.model.params, rng), list(STIFF.values())])

    def measure(q, mass):
        cov = {'payload.mass': np.full(len(q), mass)}
        d, tau = held(cm, c, q, cov)
        eta = cm.model.predict(p_true, q, tau=tau, covariates=cov)
        return Measurements(q=q, eta=eta + rng.normal(0, SIGMA, eta.shape), covariates=cov), d
    q = random_configurations(cm.model, cm.model.params.nominal, POSES, rng)
    (a, da), (b, db) = measure(q, 0.0), measure(q, 10.0)
    data = Measurements(q=np.vstack([a.q, b.q]), eta=np.vstack([a.eta, b.eta]),
                        covariates={'payload.mass': np.concatenate(
                            [a.covariates['payload.mass'], b.covariates['payload.mass']])})
    fresh, _ = measure(random_configurations(cm.model, cm.model.params.nominal, POSES, rng), 5.0)
    out = {'sag_mrad': 1e3 * float(max(np.abs(da).max(), np.abs(db).max()))}
    at_reading = np.atleast_2d(cm.robot.gravity_torques(
        data.q, row_payloads(data.covariates, len(data), cm.robot.payload)))
    fresh_reading = np.atleast_2d(cm.robot.gravity_torques(
        fresh.q, row_payloads(fresh.covariates, len(fresh), cm.robot.payload)))
    for how, rows, tau_fresh in (('deflected', data, None),
                                 ('reading', Measurements(q=data.q, eta=data.eta,
                                                          covariates=data.covariates,
                                                          tau=at_reading), fresh_reading)):
        cal = calibrate_cell(cm, rows, model='geometric')
        z = [(cal.result.value(f'joint_compliance.{j}.c') - v)
             / cal.result.std_of(f'joint_compliance.{j}.c') for j, v in STIFF.items()]
        miss = fresh.eta - cm.model.predict(cal.result.values, fresh.q, tau=tau_fresh,
                                            covariates=fresh.covariates)
        out[how] = {'z': z, 'rms_m': cal.result.rms_m,
                    'fresh': float(np.sqrt(np.mean(np.sum(miss ** 2, axis=1)))) / FLOOR}
    return out


def main(argv: list[str]) -> int:
    seeds = int(argv[0]) if argv else 20
    doc = read_cell_document(DEFAULT_CELL)
    cm0 = build_cell_model(cell_from_dict(doc, DEFAULT_CELL.parent))
    cm = with_effects(cm0, tuple(parse_effect_spec(f'joint_compliance:{j}', cm0.robot)
                                 for j in STIFF))
    c = np.zeros(cm.robot.n_joints)
    c[[cm.robot.joint_names.index(j) for j in STIFF]] = list(STIFF.values())
    t0 = time.perf_counter()
    runs = []
    for seed in range(6000, 6000 + seeds):
        r = seed_run(cm0, cm, c, seed)
        runs.append(r)
        print(f"seed {seed}: sag {r['sag_mrad']:.1f} mrad; deflected z "
              f"{np.round(r['deflected']['z'], 2).tolist()} fresh {r['deflected']['fresh']:.2f}; "
              f"reading z {np.round(r['reading']['z'], 2).tolist()} fresh "
              f"{r['reading']['fresh']:.2f}", flush=True)
    seconds = (time.perf_counter() - t0) / seeds

    def row(how: str, label: str) -> str:
        within = sum(bool(np.all(np.abs(r[how]['z']) < 3)) for r in runs)
        fresh = np.array([r[how]['fresh'] for r in runs])
        worst = np.array([np.max(np.abs(r[how]['z'])) for r in runs])
        rms = np.array([r[how]['rms_m'] for r in runs]) * 1e6
        return (f'| {label} | {within}/{seeds} | {np.median(worst):.2f}, {worst.max():.2f} | '
                f'{np.median(rms):.1f} | {np.median(fresh):.2f}, {fresh.max():.2f} | '
                f'{int(np.sum(fresh > 1.2))} |')
    sag = np.array([r['sag_mrad'] for r in runs])
    lines = ['# A servo-soft arm: compliance at the deflected configuration', '',
             __doc__.split('\n\n')[1].replace('\n', ' '), '',
             f'{seeds} seeds (6000..{5999 + seeds}); sag {sag.min():.1f}–{sag.max():.1f} mrad; '
             f'noise floor √3 σ = {FLOOR * 1e6:.1f} µm. Command: '
             f'`.venv/bin/python bench/servo_soft_compliance.py {seeds}`; '
             f'{seconds:.1f} s per seed.',
             '', '| torque taken | compliances within 3σ | worst \\|error\\|/σ (median, max) | '
             'training rms µm (median) | fresh 5 kg rms / floor (median, max) | seeds above 1.2 |',
             '|---|---|---|---|---|---|',
             row('deflected', 'at the deflected configuration (the tool)'),
             row('reading', "at the encoder's reading (no feedback)")]
    out = Path(__file__).resolve().parent / 'results' / 'servo_soft_compliance.md'
    out.write_text('\n'.join(lines) + '\n')
    print(f'written {out}')
    return 0


if __name__ == '__main__':
    sys.exit(main(sys.argv[1:]))
