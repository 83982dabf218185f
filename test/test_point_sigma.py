"""The tracker's own per-point uncertainty (``Measurements.sigma``), which grows with the
distance (a laser tracker: 15 µm + 6 µm/m), weighs every row in place of the cell's single
noise.sigma: χ², the TCP precision and the statistics in units of σ follow it."""
from __future__ import annotations

import numpy as np
import pytest
import scipy.stats

from kpi_calib_ros.core.errors import DataError
from kpi_calib_ros.core.estimation import identify
from kpi_calib_ros.core.measurement import Measurements, noise_weights, row_sigma
from kpi_calib_ros.core.simulation import random_configurations, true_parameters
from kpi_calib_ros.io.cell import DEFAULT_CELL, build_cell_model, load_cell

# An AT960's maximum permissible error, per axis: 15 µm + 6 µm/m of distance.
SIGMA_0_M, SIGMA_PER_M = 15e-6, 6e-6
POSES = 30


@pytest.fixture(scope='module')
def cell():
    return load_cell(DEFAULT_CELL)


@pytest.fixture(scope='module')
def cm(cell):
    return build_cell_model(cell)


def tracker_sigma(points: np.ndarray) -> np.ndarray:
    """(N, 3) σ per axis of points (N, 3) in the tracker frame (the tracker at the origin)."""
    distance = np.linalg.norm(points, axis=1)
    return np.repeat((SIGMA_0_M + SIGMA_PER_M * distance)[:, None], 3, axis=1)


def campaign(cm, seed: int, poses: int = POSES):
    rng = np.random.default_rng(seed)
    p_true = true_parameters(cm.model.params, rng)
    q = random_configurations(cm.model, p_true, poses, rng)
    return p_true, q, rng


def measure(cm, p_true, q, rng) -> Measurements:
    """Points with noise N(0, σ_i²) growing with the distance, each σ_i recorded."""
    clean = cm.model.predict(p_true, q)
    sigma = tracker_sigma(clean)
    return Measurements(q=q, eta=clean + rng.normal(size=clean.shape) * sigma, sigma=sigma)


def test_chi2_p_values_are_uniform_with_the_point_sigma(cm, cell):
    """50 campaigns, noise 15 µm + 6 µm/m (22-35 µm here): weighed by each point's σ the
    χ² p-values are uniform (KS); weighed by the cell's single 20 µm, χ² rejects most."""
    own, single = [], []
    for seed in range(50):
        p_true, q, rng = campaign(cm, seed)
        data = measure(cm, p_true, q, rng)
        own.append(identify(cm.model, data, cell.sigma, cm.q_work).p_value)
        plain = Measurements(q=data.q, eta=data.eta)
        single.append(identify(cm.model, plain, cell.sigma, cm.q_work).p_value)
    assert scipy.stats.kstest(own, 'uniform').pvalue > 0.01, np.round(own, 3)
    assert np.mean(np.array(single) < 0.01) > 0.8, np.round(single, 3)


def test_tcp_std_matches_monte_carlo_with_the_point_sigma(cm, cell):
    """One robot and design, 100 draws of distance-dependent noise: the TCP std from the
    points' σ (sqrt(trace) at the working pose) equals the Monte Carlo spread within 20 %;
    from the cell's single 20 µm it is more than 20 % short."""
    p_true, q, _ = campaign(cm, 11)
    rng = np.random.default_rng(12)
    tcp, own, single = [], [], []
    for _ in range(100):
        data = measure(cm, p_true, q, rng)
        result = identify(cm.model, data, cell.sigma, cm.q_work)
        tcp.append(result.tcp)
        own.append(np.trace(result.tcp_covariance, axis1=1, axis2=2))
        plain = identify(cm.model, Measurements(q=data.q, eta=data.eta), cell.sigma, cm.q_work)
        single.append(np.trace(plain.tcp_covariance, axis1=1, axis2=2))
    monte_carlo = np.sqrt(np.sum(np.var(np.array(tcp), axis=0, ddof=1), axis=1))
    np.testing.assert_allclose(np.sqrt(np.mean(own, axis=0)) / monte_carlo, 1.0, atol=0.2)
    assert np.all(np.sqrt(np.mean(single, axis=0)) / monte_carlo < 0.8)


def test_a_point_without_sigma_takes_the_cell_sigma(cm, cell):
    """Rows whose σ is NaN are weighed by the cell's σ: the fit equals the one with the cell's
    σ written into those rows, and the σ carried per row says so."""
    p_true, q, rng = campaign(cm, 3)
    data = measure(cm, p_true, q, rng)
    partial = data.sigma.copy()
    partial[::2] = np.nan
    filled = data.sigma.copy()
    filled[::2] = cell.sigma
    a = identify(cm.model, Measurements(q=data.q, eta=data.eta, sigma=partial), cell.sigma,
                 cm.q_work)
    b = identify(cm.model, Measurements(q=data.q, eta=data.eta, sigma=filled), cell.sigma,
                 cm.q_work)
    np.testing.assert_allclose(a.point_sigma, filled)
    np.testing.assert_allclose(a.values, b.values, rtol=0, atol=1e-12)
    assert a.chi2 == pytest.approx(b.chi2, rel=1e-9)
    np.testing.assert_allclose(row_sigma(cell.sigma, partial, len(q)), filled)
    np.testing.assert_allclose(noise_weights(cm.model, a.values, Measurements(
        q=data.q, eta=data.eta, sigma=partial), cell.sigma), 1.0 / filled)


@pytest.mark.parametrize('bad', [0.0, -1e-6, np.inf])
def test_a_bad_point_sigma_is_a_data_error(cm, cell, bad):
    p_true, q, rng = campaign(cm, 4, 10)
    data = measure(cm, p_true, q, rng)
    sigma = data.sigma.copy()
    sigma[2, 1] = bad
    with pytest.raises(DataError, match='per-row sigma'):
        identify(cm.model, Measurements(q=data.q, eta=data.eta, sigma=sigma), cell.sigma,
                 cm.q_work)
