"""One source per concept: weighted Jacobian rows, the reflector point, measurable poses."""
from __future__ import annotations

import numpy as np

from kpi_calib_ros.core.measurement.weighting import weighted_rows
from kpi_calib_ros.core.model.kinematics import reflector_point
from kpi_calib_ros.core.simulation import measurable_batch, sampling_bounds


def test_weighted_rows_are_w_times_j_in_measurement_order():
    rng = np.random.default_rng(0)
    jac = rng.normal(size=(5, 3, 7))
    w = np.array([1.0, 10.0, 100.0])
    rows = weighted_rows(jac, w)
    expected = np.vstack([np.diag(w) @ j for j in jac])
    np.testing.assert_array_equal(rows, expected)
    idx = np.array([6, 0, 3])
    np.testing.assert_array_equal(weighted_rows(jac, w, idx), expected[:, idx])


def test_model_point_is_pinocchio_tip_with_the_reflector_offset(cm):
    """The CasADi measurement model at nominal parameters and the independent Pinocchio
    forward kinematics place the reflector at the same point (tracker frame)."""
    rng = np.random.default_rng(1)
    lo, hi = sampling_bounds(cm.model)
    q = rng.uniform(lo, hi, size=(20, cm.robot.n_joints))
    predicted = cm.model.predict(cm.model.params.nominal, q)
    base_in_tracker = np.linalg.inv(cm.tracker_in_base)
    for qi, point in zip(q, predicted):
        tip = base_in_tracker @ cm.robot.pin_tip_pose(qi)
        np.testing.assert_allclose(reflector_point(tip, cm.cell.reflector_offset), point,
                                   atol=1e-12)


def test_measurable_batch_keeps_exactly_the_visible_draws(cm):
    p, cos_limit = cm.model.params.nominal, np.cos(cm.cell.max_incidence)
    kept = measurable_batch(cm.model, p, np.random.default_rng(2), 2000, cos_limit)
    lo, hi = sampling_bounds(cm.model)
    drawn = np.random.default_rng(2).uniform(lo, hi, size=(2000, len(lo)))
    visible = cm.model.incidence_cos(p, drawn) >= cos_limit
    assert 0 < len(kept) < 2000
    np.testing.assert_array_equal(kept, drawn[visible])
