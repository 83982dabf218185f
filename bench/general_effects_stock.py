"""General effects and the residual analysis on stock arms: found, and the error after.

Every serial arm of example-robot-data (one URDF per arm; the test of
``test/test_urdf_export.py`` loads them all) in a tracker cell 2.5 m away, no working poses,
σ = 20 µm, 60 random poses (an active target: every incidence), random geometric errors,
seed 1. Three campaigns per arm through ``diagnose_cell`` (the path of ``kpi-calib
diagnose``: robust calibration, screen with the general effects, refit, residual analysis):

* ``periodic``: periodic_joint_error:<J>:k=10 on the revolute joint nearest the middle of
  the chain, a = b;
* ``bending``: link_bending of the joint whose bending signature has the largest part that
  neither the geometry nor any joint's compliance reproduces, c_u = c_v < 0;
* ``clean``: none.

Sizes: the part of the effect's signature the geometric parameters (and, for the bending,
the joint compliances) cannot reproduce is √150 σ over the 60 poses. A bending that needs a
compliance beyond the plausible 1e-4 rad/(N m) to get there (a light arm) is marked so.
Per campaign: the effect added, the inputs the residual analysis flags, and the rms error
of the calibrated point against the true one at 200 fresh poses (noise-free), before and
after the effect, beside the clean calibration's. Writes
bench/results/general_effects_stock.md (~3 min).

    .venv/bin/python bench/general_effects_stock.py [arm ...]
"""
from __future__ import annotations

import sys
import time
from pathlib import Path

import numpy as np

from kpi_calib_ros.app.cell_model import CellModel, build_cell_model
from kpi_calib_ros.app.diagnose import diagnose_cell
from kpi_calib_ros.core.diagnosis.effect_signature import augmented_model
from kpi_calib_ros.core.effects.registry import parse_effect_spec
from kpi_calib_ros.core.estimation.least_squares import identify
from kpi_calib_ros.core.estimation.residuals import linearized_fit, orthonormal_basis
from kpi_calib_ros.core.simulation import (
    random_configurations,
    simulate_measurements,
    true_parameters,
)
from kpi_calib_ros.io.arm_cell import arm_cell_document
from kpi_calib_ros.io.cell import cell_from_dict
from kpi_calib_ros.io.cell_settings import hidden_effects

SIGMA = 20e-6
N_POSES = 60
N_FRESH = 200
SEED = 1
TARGET_CHI2 = 150.0  # the effect's part no geometric parameter reproduces, σ²
PLAUSIBLE_BENDING = 1e-4  # rad/(N m)
# id: (URDF under example-robot-data/robots, base, tip, what it brings)
ARMS = {
    'ur5': ('ur_description/urdf/ur5_robot.urdf', 'world', 'wrist_3_link', 'transmissions'),
    'ur10': ('ur_description/urdf/ur10_robot.urdf', 'world', 'wrist_3_link', 'transmissions'),
    'panda': ('panda_description/urdf/panda.urdf', 'panda_link0', 'panda_leftfinger',
              '7R + prismatic finger, mimic'),
    'kinova': ('kinova_description/robots/kinova.urdf', 'base', 'j2s6s200_link_6',
               'continuous joints'),
    'anymal_kinova': ('anymal_b_simple_description/robots/anymal-kinova.urdf', 'base',
                      'j2s6s200_link_6', 'arm on a legged base'),
    'xarm7': ('xarm_description/urdf/xarm7.urdf', 'world', 'link7', '7R, joint1…'),
    'z1': ('z1_description/urdf/z1.urdf', 'world', 'gripperMover', '7R with gripper'),
    'so101': ('so_arm_description/urdf/so101.urdf', 'base_link', 'moving_jaw_so101_v1_link',
              '0.6 kg arm'),
    'baxter': ('baxter_description/urdf/baxter.urdf', 'base', 'l_gripper_l_finger',
               '7R + prismatic finger, mimic'),
    'pr2': ('pr2_description/urdf/pr2.urdf', 'base_footprint', 'l_gripper_l_finger_tip_link',
            'prismatic torso, continuous, mimic, 10 joints'),
    'tiago': ('tiago_description/robots/tiago_no_hand.urdf', 'base_footprint', 'arm_7_link',
              'prismatic torso, 8 joints'),
    'talos_left_arm': ('talos_data/robots/talos_left_arm.urdf', 'arm_left_1_link',
                       'gripper_left_motor_double_link', 'chain after a joint it lacks, mimic'),
    'centauro': ('centauro_description/urdf/centauro.urdf', 'pelvis', 'arm1_6',
                 'torso + 6R arm'),
    'allegro': ('allegro_hand_description/urdf/allegro_right_hand.urdf', 'palm_link',
                'link_3.0', 'finger, joint names with dots'),
}


def stock_cell(arm: str) -> CellModel:
    path, base, tip, _ = ARMS[arm]
    doc = arm_cell_document(f'package://example-robot-data/robots/{path}', base, tip, SIGMA)
    return build_cell_model(cell_from_dict(doc, Path('.')))


def campaign(cm: CellModel, hidden: dict):
    effects, overrides = hidden_effects(hidden, cm.robot)
    truth = augmented_model(cm.model, effects)
    rng = np.random.default_rng(SEED)
    p_true = true_parameters(truth.params, rng, overrides=overrides)
    q = random_configurations(cm.model, cm.model.params.nominal, N_POSES, rng,
                              max_incidence=np.pi)
    return simulate_measurements(truth, p_true, q, SIGMA, rng), p_true, truth, rng


def _displacement(cm: CellModel, spec: str, values: np.ndarray, q: np.ndarray):
    effect = parse_effect_spec(spec, cm.robot)
    richer = augmented_model(cm.model, (effect,))
    p = np.concatenate([cm.model.params.nominal, values])
    return (richer.predict(p, q) - cm.model.predict(cm.model.params.nominal, q)) / SIGMA, effect


def _unique(basis: np.ndarray, d: np.ndarray) -> float:
    v = d.ravel()
    return float(np.linalg.norm(v - basis @ (basis.T @ v)))


def sized_effects(cm: CellModel) -> tuple[tuple[str, dict], tuple[str, dict]]:
    """The periodic error and the bending of this arm, sized to :data:`TARGET_CHI2`."""
    data, *_ = campaign(cm, {})
    q = np.atleast_2d(data.q)
    fit = linearized_fit(cm.model, data, identify(cm.model, data, SIGMA, cm.q_work,
                                                  max_iterations=25))
    robot = cm.robot
    revolute = [i for i, j in enumerate(robot.joints) if j.kind != 'prismatic']
    mid = min(revolute, key=lambda i: abs(i - (robot.n_joints - 1) / 2))
    spec = f'periodic_joint_error:{robot.joint_names[mid]}:k=10'
    d, _ = _displacement(cm, spec, np.array([1e-4, 1e-4]), q)
    a = 1e-4 * np.sqrt(TARGET_CHI2) / _unique(fit.basis, d)
    periodic = (spec, {'a': a, 'b': a})
    # The bending's part that neither the geometry nor a joint compliance reproduces.
    tau = robot.gravity_torques(q)
    nominal = cm.model.params.nominal
    columns = [fit.basis]
    for j in range(robot.n_joints):
        dq = np.zeros_like(q)
        dq[:, j] = 1e-6 * tau[:, j]
        columns.append(((cm.model.predict(nominal, q + dq) - cm.model.predict(nominal, q))
                        / SIGMA).reshape(-1, 1))
    basis = orthonormal_basis(np.hstack(columns))
    best = None
    for name in robot.joint_names:
        try:
            d, effect = _displacement(cm, f'link_bending:{name}', np.array([-1e-6, -1e-6]), q)
        except ValueError:
            continue  # nothing with mass beyond it
        u = _unique(basis, d)
        if best is None or u > best[0]:
            best = (u, effect)
    assert best is not None
    c = -1e-6 * np.sqrt(TARGET_CHI2) / best[0]
    keys = [n.rsplit('.', 1)[1] for n in best[1].parameter_names]
    return periodic, (best[1].name, {k: c for k in keys})


def fresh_error_m(model, values, truth, p_true, q) -> float:
    error = truth.predict(p_true, q) - model.predict(values, q)
    return float(np.sqrt(np.mean(np.sum(error ** 2, axis=1))))


def run(arm: str) -> list[dict]:
    cm = stock_cell(arm)
    periodic, bending = sized_effects(cm)
    rows = []
    for case, hidden in (('periodic', dict([periodic])), ('bending', dict([bending])),
                         ('clean', {})):
        t0 = time.perf_counter()
        data, p_true, truth, rng = campaign(cm, hidden)
        q = random_configurations(cm.model, cm.model.params.nominal, N_FRESH, rng,
                                  max_incidence=np.pi)
        cd = diagnose_cell(cm, data)
        added = cd.added.name if cd.added is not None else None
        before = fresh_error_m(cm.model, cd.result.values, truth, p_true, q)
        after = (fresh_error_m(cd.after_model, cd.after.values, truth, p_true, q)
                 if cd.after is not None else float('nan'))
        scores = cd.residual_analysis.scores
        spec = next(iter(hidden), None)
        size = max((abs(v) for v in hidden.get(spec, {}).values()), default=0.0)
        rows.append({'arm': arm, 'case': case, 'hidden': spec, 'size': size,
                     'implausible': case == 'bending' and size > PLAUSIBLE_BENDING,
                     'added': added, 'found': added == spec, 'before': before, 'after': after,
                     'flagged': [s.name for s in scores if s.significant],
                     'excluded': len(cd.excluded), 'seconds': time.perf_counter() - t0})
        r = rows[-1]
        print(f"{arm} {case}: hidden {spec} ({size:.2g}) added {added}; fresh "
              f"{before * 1e6:.1f} -> {after * 1e6:.1f} µm; flagged {r['flagged']} "
              f"({r['seconds']:.0f} s)", flush=True)
    return rows


def main(argv: list[str]) -> int:
    t0 = time.perf_counter()
    arms = argv or list(ARMS)
    rows = [r for arm in arms for r in run(arm)]
    clean = {r['arm']: r['before'] for r in rows if r['case'] == 'clean'}
    text = ['# General effects on stock arms (example-robot-data)', '',
            f'σ = 20 µm, {N_POSES} random poses (every incidence), seed {SEED}, no working '
            'poses; `diagnose_cell` (leave-one-out, family-wise α = 0.01). Hidden effects '
            f'sized so that √{TARGET_CHI2:.0f} σ of their signature is beyond the geometry '
            '(for the bending also beyond every joint compliance). Error: rms of the '
            f'calibrated point against the true one at {N_FRESH} fresh poses (noise-free), '
            'before → after the effect added; clean: the clean calibration\'s. Inputs: those '
            'the residual analysis flags (Holm, α = 0.01). Command: '
            f'`.venv/bin/python bench/general_effects_stock.py` '
            f'({time.perf_counter() - t0:.0f} s)', '',
            '| arm | what it brings | case | hidden | added | found | error before → after '
            '(µm) | clean (µm) | inputs flagged |', '|---|---|---|---|---|---|---|---|---|']
    for r in rows:
        hidden = '–' if r['hidden'] is None else f"`{r['hidden']}` ({r['size']:.2g})"
        if r['implausible']:
            hidden += ' implausible size'
        found = ('yes' if r['found'] else 'no') if r['hidden'] else \
            ('nothing added' if r['added'] is None else 'false alarm')
        after = '–' if np.isnan(r['after']) else f"{r['after'] * 1e6:.1f}"
        text.append(f"| {r['arm']} | {ARMS[r['arm']][3]} | {r['case']} | {hidden} | "
                    f"{'–' if r['added'] is None else '`' + r['added'] + '`'} | {found} | "
                    f"{r['before'] * 1e6:.1f} → {after} | {clean[r['arm']] * 1e6:.1f} | "
                    f"{', '.join(r['flagged'][:3]) or '–'} |")
    path = Path(__file__).resolve().parent / 'results' / 'general_effects_stock.md'
    path.write_text('\n'.join(text) + '\n')
    print('\n'.join(text))
    print(f'written {path}')
    return 0


if __name__ == '__main__':
    sys.exit(main(sys.argv[1:]))
