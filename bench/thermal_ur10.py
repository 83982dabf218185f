"""Real data: does a thermal effect help the UR10 of ../shared/data/ipa_ur10 predict later poses?

Series A carries the cell temperature with every pose (22.9-23.7 °C); its stamps run from
2020-07-14 16:39 to 2020-07-18 (4.2 days; the data README says overnight). Each pose gets
``delta_temperature`` (temperature − 20 °C) as a covariate, as ``kpi-calib import-csv`` + the
cell's ``temperature:`` section would give it. Calibration
on 400 random poses of the first 60 % of the poses by time, prediction of 1500 random
poses of the last 40 %: held-out rms (3-D distance) of the geometric model, of the geometric
model plus each thermal effect (fitted), and of ``auto`` (which screens the thermal effects
with the library's). The probe origin is used as a point (its orientation is not used);
base pose and probe offset are registered from the data. Writes
bench/results/thermal_ur10.md.

    .venv/bin/python bench/thermal_ur10.py
"""
from __future__ import annotations

import time
from pathlib import Path

import numpy as np
import yaml

from kpi_calib_ros.app.cell_model import build_cell_model
from kpi_calib_ros.app.identify import calibrate_cell, identify_cell, with_effects
from kpi_calib_ros.core.measurement.covariates import DELTA_TEMPERATURE
from kpi_calib_ros.core.measurement.data import Measurements
from kpi_calib_ros.io.cell import cell_from_dict
from kpi_calib_ros.io.csv_import import read_postures
from kpi_calib_ros.io.csv_mapping import mapping_from_dict

HERE = Path(__file__).resolve().parent
_BESIDE = HERE.parents[1] / 'shared' / 'data' / 'ipa_ur10'
DATA = _BESIDE if _BESIDE.is_dir() else Path('/work/shared/data/ipa_ur10')
MAPPING = HERE.parent / 'test' / 'data' / 'ipa_ur10_mapping.yaml'
EFFECTS = ('thermal_growth', 'thermal_link_growth:shoulder_lift_joint',
           'thermal_link_growth:elbow_joint', 'thermal_link_growth:wrist_1_joint',
           'thermal_zero_drift:shoulder_lift_joint', 'thermal_zero_drift:elbow_joint')


def series_a() -> Measurements:
    rows = list(read_postures(DATA / 'Series_A' / 'measurements_grid.csv',
                              mapping_from_dict(yaml.safe_load(MAPPING.read_text()))))
    rows.sort(key=lambda r: r.stamp_ns)
    celsius = np.array([r.temperatures['laser_tracker'] for r in rows], float)
    return Measurements(q=np.array([r.q for r in rows]),
                        eta=np.array([r.points[0][1] for r in rows]),
                        stamps_ns=np.array([r.stamp_ns for r in rows], np.int64),
                        covariates={'temperature.laser_tracker': celsius,
                                    DELTA_TEMPERATURE: celsius - 20.0})


def rms(cm, result, data) -> float:
    miss = data.eta - cm.model.predict(result.values, data.q, covariates=data.covariates)
    return float(np.sqrt(np.mean(np.sum(miss ** 2, axis=1))))


def main() -> str:
    doc = {'robot': {'urdf': 'package://example-robot-data/robots/ur_description/urdf/'
                             'ur10_robot.urdf', 'base_frame': 'base_link', 'tip_frame': 'tool0'},
           'tracker': {'frame_id': 'laser_tracker'}, 'reflectors': [{'name': 'probe'}],
           'noise': {'sigma': 2.0e-5}, 'identification': {'model': 'geometric'},
           'working_poses': [[0.0, -1.2, 1.7, -2.07, -1.57, 0.0]]}
    cm = build_cell_model(cell_from_dict(doc, DATA))
    data = series_a()
    hours = (data.stamps_ns - data.stamps_ns[0]) / 3.6e12
    temp = data.covariates['temperature.laser_tracker']
    split = int(0.6 * len(data))
    rng = np.random.default_rng(0)
    train = data.subset(np.sort(rng.choice(split, 400, replace=False)))
    later = data.subset(np.sort(split + rng.choice(len(data) - split, 1500, replace=False)))
    lines = ['# Thermal effects on the real UR10 (Series A, temperature recorded)', '',
             __doc__.split('\n\n')[1].replace('\n', ' '), '',
             f'{len(data)} poses over {hours[-1]:.1f} h; temperature {temp.min():.2f} to '
             f'{temp.max():.2f} °C (first 60 %: {temp[:split].min():.2f} to '
             f'{temp[:split].max():.2f}; last 40 %: {temp[split:].min():.2f} to '
             f'{temp[split:].max():.2f}); correlation of temperature with time '
             f'{np.corrcoef(hours, temp)[0, 1]:+.2f}.', '',
             '| model | fitted | training rms (mm) | later poses rms (mm) | s |',
             '|---|---|---|---|---|']
    t0 = time.perf_counter()
    base = identify_cell(cm, train)
    lines.append(f'| geometric | - | {base.rms_m * 1e3:.3f} | {rms(cm, base, later) * 1e3:.3f} | '
                 f'{time.perf_counter() - t0:.0f} |')
    print(lines[-1], flush=True)
    for spec in EFFECTS:
        t0 = time.perf_counter()
        warm = with_effects(cm, (spec,))
        result = identify_cell(warm, train, p0=np.concatenate([base.values, [0.0]]))
        name = warm.model.params.names[-1]
        fitted = f'{name} = {result.value(name):.3g} ± {result.std_of(name):.2g}'
        lines.append(f'| + {spec} | {fitted} | {result.rms_m * 1e3:.3f} | '
                     f'{rms(warm, result, later) * 1e3:.3f} | {time.perf_counter() - t0:.0f} |')
        print(lines[-1], flush=True)
    t0 = time.perf_counter()
    cal = calibrate_cell(cm, train, model='auto')
    chosen = cal.cell if cal.cell is not None else cm
    lines.append(f'| auto | level {cal.choice.level}, effects {list(cal.choice.effects) or "none"}'
                 f' | {cal.result.rms_m * 1e3:.3f} | {rms(chosen, cal.result, later) * 1e3:.3f} | '
                 f'{time.perf_counter() - t0:.0f} |')
    print(lines[-1], flush=True)
    lines += ['', f'auto: {cal.choice.reason}']
    text = '\n'.join(lines) + '\n'
    (HERE / 'results' / 'thermal_ur10.md').write_text(text)
    print(text)
    return text


if __name__ == '__main__':
    main()
