"""Never worse than nominal, recording by recording: a joint calibration of several set-ups
that predicts held-out poses better over all rows and worse on one set-up is not valid, the
set-up named; a sound campaign keeps each set-up's figures, which pool to the overall one."""
from __future__ import annotations

import numpy as np

from kpi_calib_ros import api
from kpi_calib_ros.core.measurement import recordings as rec
from kpi_calib_ros.core.simulation import (
    random_configurations,
    simulate_measurements,
    true_parameters,
)

SIGMA = 2e-5
MOVE_B = np.array([-1.2, 1.5, 0.1, 0.02, -0.03, 0.6])  # set-up B: metres and 35° away


def _set_ups(cm, seed: int, poses_b: int, b_built_to_urdf: bool):
    """Set-up A: 40 poses of a robot with the simulator's geometric errors; set-up B:
    ``poses_b`` poses from another station, of the same robot or (``b_built_to_urdf``) of a
    robot built to its URDF (another unit of the type, or one re-mastered after a repair)."""
    rng = np.random.default_rng(seed)
    robot = true_parameters(cm.model.params, rng)
    b = robot.copy()
    if b_built_to_urdf:
        n_geo = len(cm.geometric)
        b[6:n_geo - 3] = cm.model.params.nominal[6:n_geo - 3]  # placement and probe kept
    b[:6] += MOVE_B
    parts = [simulate_measurements(cm.model, p, random_configurations(cm.model, p, n, rng),
                                   SIGMA, rng) for p, n in ((robot, 40), (b, poses_b))]
    return {'a': parts[0], 'b': parts[1]}


def test_a_set_up_the_calibration_harms_makes_it_not_valid_and_is_named(cm):
    """B measures a robot built to its URDF: the shared robot, fitted mostly to A, predicts
    B's held-out poses several times worse than the nominal robot with B's placement
    registered, though better over all rows. Not valid, B named with both figures and the
    fix; A not named."""
    cal = api.calibrate(cm, _set_ups(cm, 1, 20, True), model='geometric')
    assert cal.nominal is not None and cal.nominal.better  # the overall verdict holds
    assert not cal.valid
    named = [p for p in cal.problems if 'set-up' in p]
    assert len(named) == 1 and "recording 'b'" in named[0], cal.problems
    a, b = cal.nominal.recordings
    assert (a.name, b.name) == ('a', 'b')
    assert b.harmed and not a.harmed
    assert b.calibrated_in_region_m > 3 * b.nominal_in_region_m
    assert f'{b.calibrated_in_region_m * 1e6:.1f} µm' in named[0]
    assert f'{b.nominal_in_region_m * 1e6:.1f} µm' in named[0]
    assert 'register it separately' in named[0] and 'drop its bag' in named[0]


def test_a_sound_campaign_keeps_every_set_up_and_its_figures_pool_to_the_overall(cm):
    """One robot from two stations: valid, no set-up harmed, each set-up's held-out rms
    near the noise floor σ√3 and far below the nominal robot's; the rows' held-out residuals
    are the overall figure's, so the set-ups' figures pool (rms weighted by rows) to it."""
    cal = api.calibrate(cm, _set_ups(cm, 1, 20, False), model='geometric')
    assert cal.valid, cal.problems
    comparison = cal.nominal
    assert comparison is not None and not comparison.harmed
    assert [r.name for r in comparison.recordings] == ['a', 'b']
    assert [r.rows for r in comparison.recordings] == [40, 20]
    floor = SIGMA * np.sqrt(3)
    for r in comparison.recordings:
        assert 0.7 * floor < r.calibrated_in_region_m < 1.5 * floor
        assert r.nominal_in_region_m > 10 * r.calibrated_in_region_m
        assert 0 < r.noise_m < 0.2 * floor
        assert r.to_dict()['worse_than_nominal'] is False

    def pooled(key: str) -> float:
        rows = np.array([r.rows for r in comparison.recordings])
        values = np.array([getattr(r, key) for r in comparison.recordings])
        return float(np.sqrt(np.sum(rows * values ** 2) / rows.sum()))
    np.testing.assert_allclose(pooled('calibrated_in_region_m'),
                               comparison.calibrated.in_region_m, rtol=1e-10)
    np.testing.assert_allclose(pooled('nominal_in_region_m'),
                               comparison.nominal.in_region_m, rtol=1e-10)
    np.testing.assert_allclose(pooled('calibrated_other_region_m'),
                               comparison.calibrated.other_region_m, rtol=1e-10)


def test_one_recording_has_no_per_recording_verdict(cm):
    """One recording: the comparison is the one of a single bag, no recording figures."""
    data = _set_ups(cm, 2, 1, False)['a']
    cal = api.calibrate(cm, {'only': data}, model='geometric')
    assert cal.nominal is not None and cal.nominal.recordings == ()
    assert 'recordings' not in cal.nominal.to_dict()
    assert rec.placed_model(cm.model, [rec.Recording('only')]) is cm.model
