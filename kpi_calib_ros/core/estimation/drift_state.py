"""Drift state of a daily swing: each parameter's deviation and rate, carried between cycles.

The deviation and rate of each parameter are carried from cycle to cycle so the prior of a
re-identification follows a thermal trend instead of lagging it.

:class:`DriftSwing` is the physics (a lightly damped stochastic oscillator per
parameter), :class:`DriftState` the state z = (d, ḋ) with its covariance and its
cross-covariance with the parameters; :func:`state_predicted` moves a prior
(:class:`~kpi_calib_ros.core.estimation.prior.Prior`) and its state over a drift time,
:func:`state_updated` is the Kalman update after a cycle's identification.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np
import scipy.linalg

from kpi_calib_ros.core.errors import DataError
from kpi_calib_ros.core.estimation.prior import THERMAL_EXPANSION_PER_K, Prior

__all__ = [
    'DAY_HOURS', 'TEMPERATURE_SWING_K', 'OFFSET_SWING_RAD', 'DriftSwing', 'DriftState',
    'state_predicted', 'stationary_state', 'initial_state', 'state_updated',
]

# Drift state of a daily swing (a stochastic harmonic oscillator per parameter).
DAY_HOURS = 24.0

# Default amplitude (±) of a shop floor's daily temperature cycle and of the joint offsets'
# daily drift that goes with it (encoder and reducer warm-up), the drift state's defaults.
TEMPERATURE_SWING_K = 5.0
OFFSET_SWING_RAD = 5e-5


@dataclass(frozen=True)
class DriftSwing:
    """A daily drift, the physics of the drift state (``--drift-velocity``).

    Every link's temperature swings by up to ±``temperature_k`` K and every joint offset
    by up to ±``offset_rad`` with the period ``period_hours`` (ω = 2π / period): a link
    of length l grows by up to α T l, α = :data:`THERMAL_EXPANSION_PER_K`, along its
    vector. Each parameter's deviation d from its mean follows a lightly damped
    stochastic oscillator, d̈ + 2ζω ḋ + ω² d = white noise, with ζ = 1/2π (the swing keeps
    its phase for about one period) and the noise that makes the stationary std of d
    the swing's RMS (α T l / √2, B / √2) and of ḋ ω times it. The state carried from
    cycle to cycle is z = (d, ḋ): the parameters' deviation and drift rate.

    Unlike a random walk, an extrapolation follows the trend (the rate), and unlike an
    integrated random walk, the uncertainty of what the data do not see stays bounded by
    the swing.
    """

    temperature_k: float = TEMPERATURE_SWING_K
    offset_rad: float = OFFSET_SWING_RAD
    period_hours: float = DAY_HOURS

    def __post_init__(self) -> None:
        """Check that the swings are finite and >= 0 and the period is positive."""
        for value, key in ((self.temperature_k, 'temperature swing (K)'),
                           (self.offset_rad, 'offset swing (rad)')):
            if not (np.isfinite(value) and value >= 0):
                raise DataError(f'drift velocity: {key} must be finite and >= 0, got {value}')
        if not (np.isfinite(self.period_hours) and self.period_hours > 0):
            raise DataError('drift velocity: the period must be a positive number of hours, '
                            f'got {self.period_hours}')

    @classmethod
    def from_values(cls, values: Sequence[float]) -> DriftSwing:
        """Return the swing of ``[temperature_K, offset_rad(, period_h)]``.

        The period defaults to `DAY_HOURS`; the values as the CLI's ``--drift-velocity`` and the
        node's ``drift_velocity`` give them.

        Raises
        ------
        DataError
            Not two or three numbers, or a value out of range (see the class).
        """
        values = tuple(float(v) for v in values)
        if len(values) not in (2, 3):
            raise DataError('drift velocity: give temperature_K, offset_rad and optionally '
                            f'period_h (2 or 3 numbers), got {len(values)}')
        return cls(*values)

    def values(self) -> tuple[float, float, float]:
        """(temperature_k, offset_rad, period_hours)."""
        return (self.temperature_k, self.offset_rad, self.period_hours)

    @property
    def omega(self) -> float:
        """Angular frequency of the swing, rad per hour."""
        return 2 * np.pi / self.period_hours

    @property
    def damping(self) -> float:
        """ζ of the oscillator: its amplitude decays by e in one period."""
        return 1 / (2 * np.pi)

    @property
    def length_amplitude(self) -> float:
        """Relative length swing α T."""
        return THERMAL_EXPANSION_PER_K * self.temperature_k

    def transition(self, hours: float) -> np.ndarray:
        """Φ (2, 2): (d, ḋ) after ``hours``, ḋ per hour."""
        w = self.omega
        a = np.array([[0.0, 1.0], [-w ** 2, -2 * self.damping * w]])
        return scipy.linalg.expm(a * hours)

    def stationary(self) -> np.ndarray:
        """(2, 2) stationary covariance of (d, ḋ) for a unit shape: diag(1, ω²)."""
        return np.diag([1.0, self.omega ** 2])

    def to_dict(self) -> dict:
        """YAML-ready form (K, rad, h)."""
        return {'temperature_k': float(self.temperature_k), 'offset_rad': float(self.offset_rad),
                'period_hours': float(self.period_hours)}


@dataclass(frozen=True)
class DriftState:
    """The drift state z = (d, ḋ) of named parameters with its uncertainty.

    Attributes
    ----------
    names : tuple of str
        k parameters.
    state : (2k,) ndarray
        Their deviations d from the mean of the swing (m, rad), then their rates ḋ (per
        hour).
    covariance : (2k, 2k) ndarray
        Covariance of the state.
    cross : (k, 2k) ndarray
        cov(parameter i, state j), the parameters of the same ``names``.
    """

    names: tuple[str, ...]
    state: np.ndarray
    covariance: np.ndarray
    cross: np.ndarray

    def __post_init__(self) -> None:
        """Check shapes, finiteness and symmetry; store the arrays, the covariance symmetrised."""
        k = len(self.names)
        shapes = {'values': (2 * k,), 'covariance': (2 * k, 2 * k),
                  'cross_covariance': (k, 2 * k)}
        for value, key in ((self.state, 'values'), (self.covariance, 'covariance'),
                           (self.cross, 'cross_covariance')):
            arr = np.asarray(value, float)
            if arr.shape != shapes[key]:
                raise DataError(f'drift_state.{key}: {k} names need shape {shapes[key]}, got '
                                f'{arr.shape}; give an unedited calibration.yaml')
            if not np.all(np.isfinite(arr)):
                raise DataError(f'drift_state.{key} must be finite')
            object.__setattr__(self, {'values': 'state', 'cross_covariance': 'cross'}.get(
                key, key), arr)
        cov = self.covariance
        scale = np.sqrt(np.outer(np.abs(np.diag(cov)), np.abs(np.diag(cov))))
        if not np.all(np.abs(cov - cov.T) <= 1e-6 * scale + 1e-300):
            raise DataError('drift_state.covariance must be symmetric; give an unedited '
                            'calibration.yaml')
        object.__setattr__(self, 'covariance', 0.5 * (cov + cov.T))

    @property
    def rates(self) -> np.ndarray:
        """ḋ (k,), per hour."""
        return self.state[len(self.names):]

    def to_dict(self) -> dict:
        """YAML-ready form: names, state, covariance and cross-covariance (SI units)."""
        return {'names': list(self.names), 'values': [float(x) for x in self.state],
                'covariance': [[float(x) for x in row] for row in self.covariance],
                'cross_covariance': [[float(x) for x in row] for row in self.cross]}


def state_predicted(prior: Prior, state: DriftState, swing: DriftSwing, shape: np.ndarray,
                    hours: float) -> tuple[Prior, DriftState]:
    """Return the prior and drift state of the same ``names`` after ``hours``.

    ``shape`` (k, k): the covariance of the parameters' swing amplitude (twice the
    stationary covariance of d). With Φ the oscillator's transition
    (:meth:`DriftSwing.transition`) and Q = (P∞ − Φ P∞ Φᵀ) ⊗ shape/2 its exact discrete
    noise (P∞ = :meth:`DriftSwing.stationary`), z' = Φ z + w and p' = p + (d' − d) =
    p + B z + w_d with B = (Φ₁₁ − 1, Φ₁₂): m + B z; C_pp + B C_zp + C_pz Bᵀ + B C_zz Bᵀ +
    Q_dd; (C_pz + B C_zz) Φᵀ + Q_d·; Φ C_zz Φᵀ + Q.
    """
    if tuple(prior.names) != tuple(state.names):
        raise DataError('drift state and prior must name the same parameters in one order')
    if not np.isfinite(hours):
        raise DataError(f'drift time must be finite, got {hours} h')
    k = len(prior.names)
    phi2 = swing.transition(float(hours))
    p_inf = swing.stationary()
    eye = np.eye(k)
    phi = np.kron(phi2, eye)
    q = np.kron(p_inf - phi2 @ p_inf @ phi2.T, 0.5 * np.asarray(shape, float))
    b = np.kron(np.array([[phi2[0, 0] - 1.0, phi2[0, 1]]]), eye)
    czz, cpz = state.covariance, state.cross
    cpp = prior.covariance + b @ cpz.T + cpz @ b.T + b @ czz @ b.T + q[:k, :k]
    cross = (cpz + b @ czz) @ phi.T + q[:k, :]
    czz = phi @ czz @ phi.T + q
    return (Prior(prior.names, prior.mean + b @ state.state, 0.5 * (cpp + cpp.T)),
            DriftState(state.names, phi @ state.state, 0.5 * (czz + czz.T), cross))


def stationary_state(names: Sequence[str], swing: DriftSwing, shape: np.ndarray
                     ) -> DriftState:
    """Return the drift state of a calibration that has none.

    z = 0 with the stationary covariance (the deviation and rate of the swing unknown),
    uncorrelated with p.
    """
    k = len(names)
    cov = np.kron(swing.stationary(), 0.5 * np.asarray(shape, float))
    return DriftState(tuple(names), np.zeros(2 * k), cov, np.zeros((k, 2 * k)))


def initial_state(names: Sequence[str], swing: DriftSwing, shape: np.ndarray,
                  stored: DriftState | None) -> DriftState:
    """Return the drift state of the prior parameters ``names`` before extrapolation.

    ``stored`` (a previous calibration's ``drift_state``) for the names it has; for the others,
    and for all without one, the stationary state of the swing (:func:`stationary_state`),
    uncorrelated.
    """
    k = len(names)
    fresh = stationary_state(names, swing, shape)
    if stored is None:
        return fresh
    have = [i for i, n in enumerate(names) if n in stored.names]
    new = [i for i in range(k) if i not in have]
    znew = new + [k + i for i in new]
    zhave = have + [k + i for i in have]
    at = [stored.names.index(names[i]) for i in have]
    kk = len(stored.names)
    zat = at + [kk + i for i in at]
    state, cov, cross = np.zeros(2 * k), np.zeros((2 * k, 2 * k)), np.zeros((k, 2 * k))
    cov[np.ix_(znew, znew)] = fresh.covariance[np.ix_(znew, znew)]
    state[zhave] = stored.state[zat]
    cov[np.ix_(zhave, zhave)] = stored.covariance[np.ix_(zat, zat)]
    cross[np.ix_(have, zhave)] = stored.cross[np.ix_(at, zat)]
    return DriftState(tuple(names), state, cov, cross)


def state_updated(prior: Prior, state: DriftState, names: Sequence[str],
                  mean: np.ndarray, covariance: np.ndarray) -> DriftState:
    """Return the drift state after a cycle's identification (its Kalman update).

    The data see the parameters only, so given the predicted joint Gaussian of the
    parameters p ~ N(m, C_pp) (``prior``) and the state z (``state``, cov(p, z) = C_pz)
    and the posterior N(p̂, P) of p (``mean``, ``covariance`` over ``names``):
    K = C_zp C_pp⁻¹, ẑ = z + K (p̂ − m), C_zz − K (C_pp − P) Kᵀ and cov(p̂, ẑ) = P Kᵀ.
    Prior names the identification held are left out (marginalised).
    """
    names = list(names)
    k = len(prior.names)
    keep = [i for i, n in enumerate(prior.names) if n in names]
    if not keep:
        raise DataError('the identification estimated none of the prior parameters: the '
                        'drift state cannot be updated')
    zkeep = keep + [k + i for i in keep]
    post = [names.index(prior.names[i]) for i in keep]
    cpp = prior.covariance[np.ix_(keep, keep)]
    cpz = state.cross[np.ix_(keep, zkeep)]
    gain = np.linalg.solve(cpp, cpz).T          # C_zp C_pp⁻¹ (C_pp symmetric)
    p_post = np.asarray(covariance, float)[np.ix_(post, post)]
    innovation = np.asarray(mean, float)[post] - prior.mean[keep]
    czz = state.covariance[np.ix_(zkeep, zkeep)] - gain @ (cpp - p_post) @ gain.T
    return DriftState(tuple(prior.names[i] for i in keep),
                      state.state[zkeep] + gain @ innovation, 0.5 * (czz + czz.T),
                      p_post @ gain.T)
