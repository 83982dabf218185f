"""Real UR10: calibrate on one region of joint space, validate on the others and on Series D.

Series A (laser tracker, one set-up, 2020-07-14 to 07-18: four days, not the one night its
README says) is cut into ``REGIONS`` regions of joint space
(k-means in normalised joint space, ``core.estimation.folds.region_fold_ids``, seed 0). For each
region in turn, up to ``N_TRAIN`` of its poses (random, seed 0) calibrate:

* geometric: the full geometric model;
* diagnose path: ``diagnose`` (α = 0.01, general effects on), its best effect refitted;
  recommended only when it predicts held-out regions of the training poses better beyond
  the held-out noise and is worse beyond noise in no held-out fold, region blocks and joint
  range ends (``ModelComparison.holds_elsewhere``), else the geometric model;
* screen's best, unchecked: the refit with the screen's best effect, whatever its regions say
  (what the diagnose path recommended before);
* auto: ``calibrate_cell(model='auto')``.

Each is scored (rms of the measured minus the predicted probe origin) on every other region
of Series A and on Series D (months later, tracker and probe set up again: the placement,
base and probe offset, re-registered on D, ``validate --register base+reflector``).
Slow: not part of ``make test``. Writes bench/results/region_holdout_ur10.md.

    nice -n 19 .venv/bin/python bench/region_holdout_ur10.py [DATA_DIR [regions ...]]
"""
from __future__ import annotations

import sys
import time
from pathlib import Path

import numpy as np
import yaml
from general_effects_ur10 import CELL, MAPPING

from kpi_calib_ros.app.calibration_document import calibration_document
from kpi_calib_ros.app.cell_model import build_cell_model
from kpi_calib_ros.app.identify import calibrate_cell, identify_cell, with_effects
from kpi_calib_ros.app.validate import validate_calibration
from kpi_calib_ros.core.diagnosis.effect_selection import effect_start
from kpi_calib_ros.core.diagnosis.model_comparison import compare_models
from kpi_calib_ros.core.diagnosis.verdict import diagnose
from kpi_calib_ros.core.effects.registry import parse_effect_spec
from kpi_calib_ros.core.estimation.folds import pose_index, region_fold_ids
from kpi_calib_ros.core.measurement.data import Measurements
from kpi_calib_ros.io.cell import cell_from_dict
from kpi_calib_ros.io.csv_import import read_postures
from kpi_calib_ros.io.csv_mapping import mapping_from_dict

ROOT = Path(__file__).resolve().parents[1]
REGIONS = 4
N_TRAIN = 200


def series(path: Path) -> Measurements:
    """One series' joint readings and probe origins, without stamps (D's are not usable)."""
    doc = yaml.safe_load(MAPPING.read_text())
    for key in ('stamp_columns', 'stamp_format', 'stamp_timezone'):
        doc.pop(key, None)
    rows = list(read_postures(path, mapping_from_dict(doc)))
    return Measurements(q=np.array([r.q for r in rows]),
                        eta=np.array([r.points[0][1] for r in rows]),
                        reflector=np.zeros(len(rows), int))


def rms(cm, p: np.ndarray, data: Measurements) -> float:
    return float(np.sqrt(np.mean(np.sum((data.eta - cm.model.predict(p, data.q)) ** 2, 1))))


def on_d(cm, p: np.ndarray, d: Measurements, result) -> float:
    """Rms on Series D with the placement re-registered; NaN when validate cannot (its
    re-registration needs a positive definite placement covariance)."""
    doc = calibration_document(cm, result)
    try:
        return float(validate_calibration(cm, p, doc, d, 'base+reflector').rms_m)
    except np.linalg.LinAlgError:
        return float('nan')


def main(argv: list[str]) -> int:
    data_dir = Path(argv[0]) if argv else Path('/work/shared/data/ipa_ur10')
    which = [int(a) for a in argv[1:]] or list(range(REGIONS))
    base = build_cell_model(cell_from_dict(CELL, data_dir))
    a = series(data_dir / 'Series_A' / 'measurements_grid.csv')
    d = series(data_dir / 'Series_D' / 'measurements_iso_cubes.csv')
    poses, pose = pose_index(a.q)
    region = region_fold_ids(poses, REGIONS, seed=0)[pose]
    rows, notes = [], []
    out = ROOT / 'bench' / 'results' / 'region_holdout_ur10.md'
    for r in which:
        t0 = time.time()
        inside = np.flatnonzero(region == r)
        pick = np.random.default_rng(0).permutation(inside)[:N_TRAIN]
        train = a.subset(pick)
        geo = identify_cell(base, train)
        models = {'geometric': (base, geo)}
        diag = diagnose(base.model, train, geo)
        recommended, best_spec = 'geometric', None
        if diag.best is not None:
            best_spec = diag.best.spec
            effect = parse_effect_spec(best_spec, base.robot)
            richer = with_effects(base, (effect,))
            after = identify_cell(richer, train,
                                  p0=effect_start(geo.values, effect, diag.best.values))
            models['screen best, unchecked'] = (richer, after)
            cmp = compare_models((base.model, geo), (richer.model, after), train)
            assert cmp.gain is not None
            if cmp.holds_elsewhere:
                recommended = 'screen best, unchecked'
            notes.append(f'- region {r}: screen proposes `{best_spec}`; training regions '
                         f'{cmp.other_region_rms_before_m * 1e6:.1f} -> '
                         f'{cmp.other_region_rms_after_m * 1e6:.1f} µm, where measured '
                         f'{cmp.validation_rms_before_m * 1e6:.1f} -> '
                         f'{cmp.validation_rms_after_m * 1e6:.1f} µm, held-out gain z = '
                         f'{cmp.gain.z:.2f} (needed > {cmp.gain.threshold():.2f}), '
                         f'worse beyond noise in '
                         f'{cmp.worse_folds[0]} of {cmp.worse_folds[1]} held-out folds: '
                         f'{"recommended" if cmp.holds_elsewhere else "NOT recommended"}')
        models['diagnose path'] = models[recommended]
        auto = calibrate_cell(base, train, 'auto')
        models['auto'] = (auto.cell or base, auto.result)
        notes.append(f'- region {r}: auto {auto.choice.level} + {list(auto.choice.effects)}; '
                     f'{auto.choice.reason}')
        figures = {}
        for name, (cm, res) in models.items():
            figures[name] = [rms(cm, res.values, a.subset(np.flatnonzero(region == o)))
                             for o in range(REGIONS) if o != r] + [on_d(cm, res.values, d, res)]
        others = [o for o in range(REGIONS) if o != r]
        for name, values in figures.items():
            worse = sum(v > figures['geometric'][i] * 1.0 for i, v in enumerate(values))
            label = name + (f' (`{best_spec}`)' if name.startswith('screen') else '')
            if name == 'auto':
                label += f' ({", ".join(auto.choice.effects) or "no effect"})'
            rows.append(f'| {r} ({len(pick)} poses) | {label} | '
                        + ' | '.join(f'{v * 1e6:.1f}' for v in values)
                        + f' | {worse if name != "geometric" else ""} |')
        print('\n'.join(rows[-len(figures):]), f'({time.time() - t0:.0f} s)', flush=True)
        header = ['# Real UR10: calibrated on one region of joint space, validated on the '
                  'others and on Series D', '',
                  f'Series A cut into {REGIONS} k-means regions of normalised joint space '
                  f'(seed 0); up to {N_TRAIN} poses of one region calibrate; rms (µm) on '
                  'every other region of A and on Series D (placement re-registered). '
                  '"worse": on how many of these the model predicts worse than the geometric '
                  'one. Command: `nice -n 19 .venv/bin/python bench/region_holdout_ur10.py`', '',
                  '| trained on region | model | other regions of A (in order) and D | | | |'
                  ' worse than geometric |', '|---|---|---|---|---|---|---|']
        out.write_text('\n'.join(header + rows + ['', *notes]) + '\n')
        del others
    print(out.read_text())
    return 0


if __name__ == '__main__':
    sys.exit(main(sys.argv[1:]))
