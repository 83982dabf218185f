"""Registration of the base in the tracker frame and the reflector on the tip (Horn + LSQ + GN)."""
import numpy as np
import pinocchio as pin
import pytest

from kpi_calib_ros.core.errors import DataError
from kpi_calib_ros.core.estimation.least_squares import identify
from kpi_calib_ros.core.estimation.registration import horn, register
from kpi_calib_ros.core.simulation import (
    random_configurations,
    simulate_measurements,
    true_parameters,
)

SIGMA = 10e-6  # tracker noise per axis (m)



@pytest.fixture(scope='module')
def campaign(cm):
    rng = np.random.default_rng(5)
    q = random_configurations(cm.model, cm.geometric.nominal, 40, rng)
    tips = np.array([cm.robot.pin_tip_pose(row) for row in q])
    return q, tips


def _with_placement(cm, base, offset):
    p = cm.model.params.nominal.copy()
    for k, c in enumerate('xyz'):
        p[cm.model.params.index(f'base.{c}')] = base[k]
        p[cm.model.params.index(f'reflector.{c}')] = offset[k]
    for k, c in enumerate(('roll', 'pitch', 'yaw')):
        p[cm.model.params.index(f'base.{c}')] = base[3 + k]
    return p


def _rotation_error(rpy_a, rpy_b):
    ra, rb = (pin.rpy.rpyToMatrix(*v) for v in (rpy_a, rpy_b))
    return float(np.linalg.norm(pin.log3(ra.T @ rb)))


def test_horn_recovers_an_exact_rigid_motion():
    rng = np.random.default_rng(0)
    x = rng.normal(size=(10, 3))
    rot = pin.exp3(np.array([0.3, -2.0, 1.0]))
    t = np.array([1.0, -2.0, 0.5])
    r_est, t_est = horn(x, x @ rot.T + t)
    assert np.allclose(r_est, rot, atol=1e-12) and np.allclose(t_est, t, atol=1e-12)


@pytest.mark.parametrize('yaw', [np.pi / 2, np.pi, -2.5])
def test_base_and_offset_recovered_to_noise_level_from_nothing(cm, campaign, yaw):
    q, tips = campaign
    nominal = np.asarray(cm.cell.base_in_tracker, float)
    base = nominal + np.array([0.8, -0.6, 0.3, 0.05, -0.04, 0.0])
    base[5] = yaw  # the truth is anywhere: the closed form needs no start
    offset = np.array([0.012, -0.03, 0.085])
    rng = np.random.default_rng(9)
    eta = cm.model.predict(_with_placement(cm, base, offset), q) + rng.normal(
        scale=SIGMA, size=(len(q), 3))
    reg = register(eta, tips)
    # Noise level: σ/√N on a 1 m arm, a few σ to spare.
    assert np.linalg.norm(reg.base_in_tracker[:3] - base[:3]) < 2e-5
    assert _rotation_error(reg.base_in_tracker[3:], base[3:]) < 2e-5
    assert np.linalg.norm(reg.reflector_offset - offset) < 2e-5
    # The residual is the noise: 3-D rms ≈ σ√3 (9 of 120 degrees of freedom fitted).
    assert reg.rms_m == pytest.approx(SIGMA * np.sqrt(3 * (1 - 9 / 120)), rel=0.25)


def test_kinematic_errors_leave_a_small_registered_miss(cm, campaign):
    q, tips = campaign
    rng = np.random.default_rng(2)
    p_true = true_parameters(cm.model.params, rng)
    eta = cm.model.predict(p_true, q)
    reg = register(eta, tips)
    base_true = p_true[[cm.model.params.index(f'base.{c}') for c in
                        ('x', 'y', 'z', 'roll', 'pitch', 'yaw')]]
    # Joint-level errors of a few 0.1 mm / mrad: base found to the mm, rms well below 20 mm.
    assert np.linalg.norm(reg.base_in_tracker[:3] - base_true[:3]) < 0.01
    assert 1e-5 < reg.rms_m < 5e-3


def test_wrong_units_or_joint_order_are_refused_with_the_distances(cm, campaign):
    q, tips = campaign
    eta = cm.model.predict(cm.model.params.nominal, q)
    with pytest.raises(DataError,
                       match=r'misses .* m rms .*units: the measured points spread 9\d\d times'):
        register(eta * 1000.0, tips)
    shuffled = np.array([cm.robot.pin_tip_pose(row[::-1]) for row in q])
    with pytest.raises(DataError, match='wrong order'):
        register(eta, shuffled)


def test_degenerate_postures_are_refused(cm):
    # Joint 1 only: the tip sweeps a circle, fine; joint 2 at one value and the tip
    # moving along a line is what breaks the rotation.
    tips = np.repeat(np.eye(4)[None], 6, axis=0)
    tips[:, 0, 3] = np.linspace(0.0, 1.0, 6)
    with pytest.raises(DataError, match='collinear'):
        register(tips[:, :3, 3] + [1.0, 2.0, 0.0], tips)
    tips[:, 1, 3] = [0.0, 0.3, -0.2, 0.5, 0.1, 0.4]
    with pytest.raises(DataError, match='orientations hardly vary'):
        register(tips[:, :3, 3] + [1.0, 2.0, 0.0], tips)
    with pytest.raises(ValueError, match='at least 4'):
        register(np.zeros((3, 3)), tips[:3])


def test_identification_from_the_registered_start_equals_the_one_from_the_true_placement(
        cm, campaign):
    """A base off by 1 m and 180° yaw and an unknown reflector: register, then identify."""
    q, tips = campaign
    rng = np.random.default_rng(21)
    params = cm.model.params
    p_true = true_parameters(params, rng)
    base_idx = [params.index(f'base.{c}') for c in ('x', 'y', 'z', 'roll', 'pitch', 'yaw')]
    refl_idx = [params.index(f'reflector.{c}') for c in 'xyz']
    p_true[base_idx] += [1.0, -0.4, 0.2, 0.0, 0.0, np.pi]
    p_true[refl_idx] = [0.02, -0.01, 0.09]
    data = simulate_measurements(cm.model, p_true, q, SIGMA, rng)

    perfect = params.nominal.copy()
    perfect[base_idx], perfect[refl_idx] = p_true[base_idx], p_true[refl_idx]
    reg = register(data.eta, tips)
    registered = params.nominal.copy()
    registered[base_idx], registered[refl_idx] = reg.base_in_tracker, reg.reflector_offset
    with pytest.raises(DataError, match='from the nominal'):  # the cell's nominal is 1 m off
        identify(cm.model, data, SIGMA, cm.q_work)
    from_truth = identify(cm.model, data, SIGMA, cm.q_work, p0=perfect)
    from_registration = identify(cm.model, data, SIGMA, cm.q_work, p0=registered)
    assert from_truth.converged and from_registration.converged
    # The QR may pick another (equivalent) identifiable subset at another start, so
    # compare what any gauge shares: the same model of the robot, i.e. the same
    # predicted points everywhere, KPI points and residuals (1e-9 relative to 1 m).
    assert len(from_registration.estimated) == len(from_truth.estimated)
    elsewhere = random_configurations(cm.model, p_true, 50, np.random.default_rng(8))
    for configurations in (q, elsewhere, cm.q_work):
        assert np.max(np.abs(cm.model.predict(from_registration.values, configurations)
                             - cm.model.predict(from_truth.values, configurations))) < 1e-9
    assert np.max(np.abs(from_registration.tcp - from_truth.tcp)) < 1e-9
    assert from_registration.rms_m == pytest.approx(from_truth.rms_m, rel=1e-9)


def test_a_few_gross_points_are_trimmed_and_do_not_move_the_registration(cm, campaign):
    """A 10 m point and a 0.3 m point among 40 drag a plain closed form by decimetres; the
    trimmed registration leaves them out, names them, and equals the registration of the
    clean points to noise level."""
    q, tips = campaign
    base = np.asarray(cm.cell.base_in_tracker, float) + np.array([0.5, 0.2, -0.1, 0, 0, 1.5])
    offset = np.array([0.0, 0.02, 0.05])
    rng = np.random.default_rng(11)
    eta = cm.model.predict(_with_placement(cm, base, offset), q) + rng.normal(
        scale=SIGMA, size=(len(q), 3))
    clean = register(eta, tips)
    bad = eta.copy()
    bad[7] += [10.0, 0.0, 0.0]
    bad[21] += [0.0, -0.3, 0.0]
    reg = register(bad, tips)
    assert reg.trimmed == (7, 21)
    assert np.allclose(reg.base_in_tracker[:3], clean.base_in_tracker[:3], atol=5 * SIGMA)
    assert _rotation_error(reg.base_in_tracker[3:], clean.base_in_tracker[3:]) < 1e-4
    assert np.allclose(reg.reflector_offset, clean.reflector_offset, atol=5 * SIGMA)
    assert reg.residuals_m[7] > 9.0 and reg.rms_m < 5 * SIGMA


def _reregistered(cm, q, eta, names):
    from kpi_calib_ros.core.estimation.registration import reregister
    from kpi_calib_ros.core.measurement.data import Measurements
    index = cm.model.params.indices(names)
    return reregister(cm.model, cm.model.params.nominal.copy(), Measurements(q=q, eta=eta),
                      index, np.full(3, SIGMA), np.zeros(0, int), np.zeros((0, 0)))


def test_a_re_registered_placement_states_the_std_monte_carlo_finds(cm, campaign):
    """The std a re-registration states for the offsets of a remounted probe is the spread
    of the re-fitted offsets over 200 noise draws on the same poses (within 15 %)."""
    q = campaign[0][:12]
    names = ['reflector.x', 'reflector.y', 'reflector.z']
    truth = cm.model.predict(cm.model.params.nominal, q)
    rng = np.random.default_rng(21)
    fits = [_reregistered(cm, q, truth + rng.normal(scale=SIGMA, size=truth.shape), names)
            for _ in range(200)]
    index = cm.model.params.indices(names)
    spread = np.std([f.p[index] for f in fits], axis=0, ddof=1)
    assert np.allclose(fits[0].std, spread, rtol=0.15), (fits[0].std, spread)


def test_poses_that_never_turn_the_tool_cannot_place_base_and_probe_and_the_gate_says_so(
        cm, campaign):
    """Poses moving joint 1 alone: base and probe trade (undetermined, std inf) and
    registration_violations names both and the fixes; the probe alone (the tracker where
    it was) is determined by the same poses and passes."""
    from kpi_calib_ros.core.estimation.plausibility import registration_violations
    q = np.repeat(campaign[0][:1], 15, axis=0)
    q[:, 0] = np.linspace(-1.0, 1.0, len(q))
    eta = cm.model.predict(cm.model.params.nominal, q) + np.random.default_rng(3).normal(
        scale=SIGMA, size=(len(q), 3))
    both = [f'base.{c}' for c in ('x', 'y', 'z', 'roll', 'pitch', 'yaw')] + \
        ['reflector.x', 'reflector.y', 'reflector.z']
    fit = _reregistered(cm, q, eta, both)
    assert fit.dof < len(both) and not np.isfinite(fit.std).all()
    violations = registration_violations(cm.model, both, fit.std, q=q)
    text = ' '.join(v.text() for v in violations)
    assert len(violations) == 2 and 'cannot place the base' in text \
        and 'cannot place the probe' in text and '--register reflector' in text, text
    probe = _reregistered(cm, q, eta, both[6:])
    assert np.all(probe.std < 1e-4) and not registration_violations(cm.model, both[6:],
                                                                      probe.std, q=q)


def test_a_probe_moved_beyond_its_tolerance_names_both_causes(cm):
    """A marker remounted 36 mm away (re-fitted alone, determined) was said to be "the
    tracker set up elsewhere"; the tracker never moved. Both causes are named, and both
    fixes; within the tolerance nothing is said."""
    from kpi_calib_ros.core.estimation.plausibility import registration_violations
    names = ['reflector.x', 'reflector.y', 'reflector.z']
    far = registration_violations(cm.model, names, [1e-5] * 3, shift={'reflector': 0.0364})
    assert len(far) == 1
    text = far[0].text()
    assert 'tracker was set up elsewhere' in text and 'remounted this far' in text
    assert '--register base+reflector' in text
    assert 'identification.tolerances.reflector_offset' in text
    assert not registration_violations(cm.model, names, [1e-5] * 3, shift={'reflector': 0.01})
