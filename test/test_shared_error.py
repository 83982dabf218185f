"""Points that share their errors (core.diagnosis.shared_error): the joint statement's
blocks are each point's statement, the test reduces to χ² without shared terms, and its
p-values are uniform over recordings drawn from a statement whose points share an error,
where χ² as if the points were independent is not."""
from __future__ import annotations

import numpy as np
import pytest
import scipy.stats

from kpi_calib_ros.core.diagnosis.corrected_tcp import corrected_tcp
from kpi_calib_ros.core.diagnosis.learned_residual import LearnedResidual
from kpi_calib_ros.core.diagnosis.shared_error import (
    joint_test_points,
    shared_error_test,
    statement_covariance,
)


def _spd(rng: np.random.Generator, k: int, scale: float) -> np.ndarray:
    a = rng.normal(size=(k, k))
    return scale * (a @ a.T / k + 0.1 * np.eye(k))


def test_joint_statement_blocks_are_each_points_statement():
    """Its diagonal blocks are corrected_tcp's covariance plus the noise, inside, between
    and outside the fitted region."""
    rng = np.random.default_rng(0)
    q_train = rng.uniform(-1, 1, (40, 3))
    y = 1e-4 * np.sin(2 * q_train[:, :1]) * np.array([1.0, 0.5, -0.3]) \
        + rng.normal(scale=2e-5, size=(40, 3))
    shape = np.diag([0.5, 1.0, 1.5])
    model = LearnedResidual(q=q_train, residual_m=y, joint_names=('a', 'b', 'c'),
                            amplitude_m2=1e-8, length_scales=np.array([0.5, 0.8, 2.0]),
                            noise_m2=4e-10, output_shape=shape, noise_shape=np.eye(3))
    q = np.vstack([q_train[:5] + 0.01, rng.uniform(1, 4, (15, 3))])
    jac = rng.normal(size=(len(q), 3, 4)) * 0.5
    c_in, c_out = _spd(rng, 4, 1e-10), _spd(rng, 4, 1e-8)
    noise = model.noise_covariance_m2
    tcp = corrected_tcp(np.zeros((len(q), 3)), jac, c_in, q, model, c_out)
    joint = statement_covariance(jac, c_in, q, model, c_out, noise)
    idx = np.arange(len(q))
    blocks = joint.reshape(len(q), 3, len(q), 3)[idx, :, idx, :]
    np.testing.assert_allclose(blocks, tcp.covariance + noise, rtol=1e-9,
                               atol=1e-9 * float(np.max(tcp.covariance)))
    assert np.min(np.linalg.eigvalsh(joint)) > 0
    # Far poses share the outside parameters' error: strongly correlated with each other.
    far = joint.reshape(len(q), 3, len(q), 3)[10, 0, 11, 0]
    assert abs(far) > 0.1 * np.sqrt(blocks[10, 0, 0] * blocks[11, 0, 0])


def test_without_shared_terms_it_is_the_chi2_test():
    """A block-diagonal statement: p is χ²(3M)'s, and the recording is worth M points."""
    rng = np.random.default_rng(1)
    m = 30
    blocks = [_spd(rng, 3, 1e-9) for _ in range(m)]
    joint = np.zeros((3 * m, 3 * m))
    for i, b in enumerate(blocks):
        joint[3 * i:3 * i + 3, 3 * i:3 * i + 3] = b
    e = np.array([rng.multivariate_normal(np.zeros(3), b) for b in blocks]) * 1.2
    out = shared_error_test(e, joint)
    chi2 = sum(float(x @ np.linalg.solve(b, x)) for x, b in zip(e, blocks))
    assert out.chi2 == pytest.approx(chi2, rel=1e-10)
    assert out.effective_points == pytest.approx(m, rel=1e-10)
    assert out.p_value == pytest.approx(scipy.stats.chi2.sf(chi2, 3 * m), rel=1e-8)


@pytest.mark.slow
def test_p_values_are_uniform_when_the_points_share_an_error():
    """100 points share the error of 4 parameters (10× the noise): over 300 recordings drawn
    from that statement the test's p-values are uniform and the share of points inside
    their 95 % ellipsoid falls inside the stated range in about 95 % of them; χ² as if the
    points were independent rejects far more than its level. A recording whose points all
    moved by 3 σ of the shared error is rejected."""
    rng = np.random.default_rng(2)
    m, k = 100, 4
    jac = rng.normal(size=(m, 3, k))
    flat = jac.reshape(3 * m, k)
    joint = flat @ (100.0 * np.eye(k)) @ flat.T + np.eye(3 * m)
    root = np.linalg.cholesky(joint)
    p, p_independent, in_range = [], [], []
    for _ in range(300):
        e = (root @ rng.normal(size=3 * m)).reshape(m, 3)
        out = shared_error_test(e, joint, draws=400, seed=int(rng.integers(1 << 30)))
        p.append(out.p_value)
        p_independent.append(scipy.stats.chi2.sf(out.chi2, out.dof))
        in_range.append(out.share_range[0] <= out.share <= out.share_range[1])
    assert out.effective_points < 0.3 * m
    assert scipy.stats.kstest(p, 'uniform').pvalue > 0.01
    assert 0.005 <= np.mean(np.array(p) < 0.05) <= 0.1
    assert np.mean(np.array(p_independent) < 0.05) > 0.2
    assert 0.9 <= np.mean(in_range) <= 0.99
    shifted = (root @ rng.normal(size=3 * m)).reshape(m, 3) \
        + (jac @ (30.0 * np.ones(k)))
    assert shared_error_test(shifted, joint).p_value < 1e-3


def test_large_recordings_are_tested_on_a_seeded_subset():
    assert np.array_equal(joint_test_points(5, 10), np.arange(5))
    sub = joint_test_points(1000, 100, seed=3)
    assert len(sub) == 100 and np.all(np.diff(sub) > 0)
    assert np.array_equal(sub, joint_test_points(1000, 100, seed=3))
