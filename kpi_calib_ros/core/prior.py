"""Gaussian prior information on named parameters (maximum a posteriori identification).

A prior p ~ N(m, C) over some of the model's parameters enters
:func:`kpi_calib_ros.core.estimation.identify` as extra residual rows L (m − p) with
LᵀL = Λ = C⁻¹, so the Gauss–Newton minimises ½‖W(η − h)‖² + ½(p − m)ᵀ Λ (p − m) and the
KKT covariance of eq. (19) becomes C_p = (FᵀF + Λ)⁻¹. Parameters the prior does not name
are unconstrained.

Two sources:

* :func:`tolerance_prior` -- nominal tolerances: each robot parameter (joint placement
  and joint offset) has a std around its nominal value; base and reflector placements
  stay free (they are measured anew in every cell);
* :func:`prior_from_calibration` -- a previous calibration's values and
  ``parameter_covariance``, widened by :func:`drift_widened` for the time since it, and
  optionally moved along a drift state (:class:`DriftSwing`, :class:`DriftState`,
  :func:`state_predicted`, :func:`state_updated`): the deviation and rate of each
  parameter in a daily swing, carried from cycle to cycle so the prior follows a thermal
  trend instead of lagging it.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Callable, Sequence

import numpy as np
import scipy.linalg

from kpi_calib_ros.core.errors import DataError
from kpi_calib_ros.core.parameters import ParameterSet

# Thermal expansion of steel/aluminium-steel arm structures, per metre and kelvin.
THERMAL_EXPANSION_PER_K = 12e-6
# Assumed temperature change of a shop floor: a random walk of 1 K per √hour.
KELVIN_PER_SQRT_HOUR = 1.0
# Default drift rates (random walks, std per √hour): relative length change of a
# placement (thermal growth) and angle drift of joint offsets and placement rotations
# (encoder/reducer settling, 20 µrad ≈ 20 µm at 1 m).
DRIFT_LENGTH_PER_SQRT_HOUR = THERMAL_EXPANSION_PER_K * KELVIN_PER_SQRT_HOUR
DRIFT_ANGLE_PER_SQRT_HOUR = 2e-5
PLACEMENT_PREFIXES = ('base.', 'reflector.')


@dataclass(frozen=True)
class Prior:
    """Gaussian prior N(mean, covariance) on the parameters ``names`` (SI units).

    Attributes
    ----------
    names : tuple of str
        Parameter names (a subset of the model's, any order).
    mean : (k,) ndarray
    covariance : (k, k) ndarray
        Symmetric positive definite.
    """

    names: tuple[str, ...]
    mean: np.ndarray
    covariance: np.ndarray

    def __post_init__(self) -> None:
        k = len(self.names)
        mean = np.asarray(self.mean, float)
        cov = np.asarray(self.covariance, float)
        if len(set(self.names)) != k or mean.shape != (k,) or cov.shape != (k, k):
            raise DataError(f'prior: {k} unique names need a ({k},) mean and ({k}, {k}) '
                            f'covariance, got {mean.shape} and {cov.shape}')
        if not (np.all(np.isfinite(mean)) and np.all(np.isfinite(cov))):
            raise DataError('prior: mean and covariance must be finite')
        if not np.allclose(cov, cov.T, rtol=1e-9, atol=0.0):
            raise DataError('prior: covariance must be symmetric')
        try:
            np.linalg.cholesky(cov)
        except np.linalg.LinAlgError:
            raise DataError('prior: covariance must be positive definite (a parameter with '
                            'zero prior std is not a prior; fix it by leaving it out of '
                            'the free parameters)') from None
        object.__setattr__(self, 'mean', mean)
        object.__setattr__(self, 'covariance', 0.5 * (cov + cov.T))

    @property
    def std(self) -> np.ndarray:
        """Standard deviations (n,) of the prior, the parameters' units."""
        return np.sqrt(np.diag(self.covariance))

    def rows(self, params: ParameterSet) -> tuple[np.ndarray, np.ndarray]:
        """Square-root information rows over the model's full parameter vector.

        Returns
        -------
        L : (k, n_p) ndarray
            LᵀL = Λ = C⁻¹ in the columns of ``names``, zero elsewhere.
        lm : (k,) ndarray
            L m, so that the prior residual is ``lm − L @ p``.

        Raises
        ------
        DataError
            A prior name is not a parameter of the model.
        """
        unknown = [n for n in self.names if n not in params.names]
        if unknown:
            raise DataError(f'prior names unknown parameter(s) {unknown}; valid names are '
                            f'those of calibration.yaml parameters')
        # C = G Gᵀ (Cholesky), so Λ = G⁻ᵀ G⁻¹ and L = G⁻¹ (whitening rows).
        g = np.linalg.cholesky(self.covariance)
        l_small = scipy.linalg.solve_triangular(g, np.eye(len(self.names)), lower=True)
        full = np.zeros((len(self.names), len(params.names)))
        full[:, params.indices(list(self.names))] = l_small
        return full, l_small @ self.mean


def tolerance_prior(params: ParameterSet, translation: float, rotation: float,
                    offset: float, n_geometric: int | None = None) -> Prior:
    """Independent prior around the nominal values from manufacturing tolerances.

    Parameters
    ----------
    params : ParameterSet
        The model's parameters (geometric first).
    translation, rotation, offset : float
        Std of every joint placement translation (m), placement rotation (rad) and joint
        offset (rad, or m for a prismatic joint).
    n_geometric : int, optional
        Number of geometric parameters; effect parameters after them get no prior.
        Default: all.
    """
    for value, key in ((translation, 'translation'), (rotation, 'rotation'),
                       (offset, 'offset')):
        if not np.isfinite(value) or value <= 0:
            raise DataError(f'prior {key} std must be positive, got {value}')
    n_geo = len(params.names) if n_geometric is None else n_geometric
    names, std = [], []
    for name, unit in zip(params.names[:n_geo], params.units[:n_geo]):
        if name.startswith(PLACEMENT_PREFIXES):
            continue
        names.append(name)
        std.append(offset if name.endswith('.offset')
                   else translation if unit == 'm' else rotation)
    mean = np.array([params.nominal[params.index(n)] for n in names])
    return Prior(tuple(names), mean, np.diag(np.square(std)))


def drift_covariance(names: Sequence[str], lengths: dict[str, float],
                     length_rate: float = DRIFT_LENGTH_PER_SQRT_HOUR,
                     angle_rate: float = DRIFT_ANGLE_PER_SQRT_HOUR,
                     link_vectors: dict[tuple[str, str, str], np.ndarray] | None = None,
                     drifting: Callable[[str], bool] | None = None,
                     rotation_rate: float | None = None) -> np.ndarray:
    """Q (k, k): the covariance the parameters ``names`` gain per hour (random walks).

    A translation parameter named in ``lengths`` (the nominal length, m, of the link its
    placement belongs to) drifts by ``length_rate`` × length per √hour, independently
    per axis (isotropic); every other translation gets no drift; every joint offset
    (rad) drifts by ``angle_rate`` rad per √hour and every placement rotation (joint
    placements, base angles) by ``rotation_rate`` (default: ``angle_rate``); a prismatic
    offset (m) by ``length_rate`` × its length. ``drifting(name)`` false: no drift (e.g.
    effects).

    ``link_vectors`` (thermal model) maps the names of a translation triple (x, y, z) to
    its nominal vector t (m): thermal growth scales a link, δt = α ΔT t, so the triple
    drifts along t only, Q = length_rate² t tᵀ per hour (rank one; the temperature as a
    random walk of ``length_rate`` / α K per √hour). These triples override ``lengths``.
    """
    rotation_rate = angle_rate if rotation_rate is None else rotation_rate
    if length_rate < 0 or angle_rate < 0 or rotation_rate < 0:
        raise DataError('drift rates must be >= 0')
    names = list(names)
    q = np.diag([0.0 if drifting is not None and not drifting(n)
                 else (length_rate * lengths[n]) ** 2 if n in lengths
                 else 0.0 if _is_translation(n)
                 else angle_rate ** 2 if n.endswith('.offset') else rotation_rate ** 2
                 for n in names])
    for triple, vector in (link_vectors or {}).items():
        where = [(names.index(n), float(v)) for n, v in zip(triple, vector) if n in names]
        if not where:
            continue
        idx = np.array([i for i, _ in where])
        t = np.array([v for _, v in where])
        q[idx, idx] = 0.0  # the isotropic terms of these names, replaced
        q[np.ix_(idx, idx)] = length_rate ** 2 * np.outer(t, t)
    return q


def drift_widened(prior: Prior, hours: float, lengths: dict[str, float],
                  length_rate: float = DRIFT_LENGTH_PER_SQRT_HOUR,
                  angle_rate: float = DRIFT_ANGLE_PER_SQRT_HOUR,
                  link_vectors: dict[tuple[str, str, str], np.ndarray] | None = None
                  ) -> Prior:
    """``prior`` after ``hours`` of drift: C + Q·|hours| with Q of
    :func:`drift_covariance` on the prior's own parameters (see
    :func:`mapped_drift` when those are a reduced, identified set)."""
    if not np.isfinite(hours):
        raise DataError(f'drift time must be finite, got {hours} h')
    q = drift_covariance(prior.names, lengths, length_rate, angle_rate, link_vectors)
    return Prior(prior.names, prior.mean, prior.covariance + q * abs(hours))


def mapped_drift(q_full: np.ndarray, jacobian: np.ndarray,
                 kept: Sequence[int] | np.ndarray) -> np.ndarray:
    """The drift Q_full of every parameter mapped onto the identified ones ``kept``.

    Position data cannot separate all parameters: an identification keeps a maximal
    independent set and holds the rest, whose physical drift then shows up in the kept
    ones (the growth of a held link length appears as a change of the kept parameters
    that reproduce it). With J (m, n_p) the Jacobian of the measured points over many
    configurations, the kept parameters' change that reproduces a change δp of all is
    G δp, G = J_k⁺ J (least squares), so the kept set drifts by G Q_full Gᵀ.

    Returns
    -------
    (k, k) ndarray, k = len(kept)
    """
    kept = list(kept)
    g, *_ = np.linalg.lstsq(jacobian[:, kept], jacobian, rcond=None)
    q = g @ q_full @ g.T
    return 0.5 * (q + q.T)


def _is_translation(name: str) -> bool:
    return name.rsplit('.', 1)[-1] in ('x', 'y', 'z', 'tx', 'ty', 'tz')


def prior_from_calibration(doc: dict, keep_placement: bool = False) -> Prior:
    """Prior from a calibration document (the dict of calibration.yaml): the identified
    parameters' values and ``parameter_covariance``.

    The base and reflector placements are left out unless ``keep_placement``: a tracker
    or mocap frame moved between campaigns would otherwise pull the robot's parameters.

    Raises
    ------
    DataError
        The document lacks ``parameters`` or ``parameter_covariance``, or they disagree.
    """
    try:
        values = {p['name']: float(p['value']) for p in doc['parameters']}
        cov_doc = doc['parameter_covariance']
        names = list(cov_doc['names'])
        matrix = np.array(cov_doc['matrix'], dtype=float)
    except (KeyError, TypeError, ValueError) as exc:
        raise DataError(f'prior calibration lacks or mangles {exc}: give a calibration.yaml '
                        'written by `kpi-calib identify` (parameters, parameter_covariance)'
                        ) from None
    if matrix.shape != (len(names), len(names)) or any(n not in values for n in names):
        raise DataError('prior calibration: parameter_covariance names and matrix do not '
                        'fit the parameters; give an unedited calibration.yaml')
    # A covariance computed through a KKT solve is symmetric to round-off only (relative
    # to its correlation scale); a larger asymmetry is an edited or damaged file.
    scale = np.sqrt(np.outer(np.abs(np.diag(matrix)), np.abs(np.diag(matrix))))
    if not np.all(np.abs(matrix - matrix.T) <= 1e-6 * scale):
        raise DataError('prior calibration: parameter_covariance is not symmetric; give an '
                        'unedited calibration.yaml')
    matrix = 0.5 * (matrix + matrix.T)
    keep = [i for i, n in enumerate(names)
            if keep_placement or not n.startswith(PLACEMENT_PREFIXES)]
    if not keep:
        raise DataError('prior calibration identified no robot parameter to use as prior')
    kept = [names[i] for i in keep]
    return Prior(tuple(kept), np.array([values[n] for n in kept]),
                 matrix[np.ix_(keep, keep)])



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
        for value, key in ((self.temperature_k, 'temperature swing (K)'),
                           (self.offset_rad, 'offset swing (rad)')):
            if not (np.isfinite(value) and value >= 0):
                raise DataError(f'drift velocity: {key} must be finite and >= 0, got {value}')
        if not (np.isfinite(self.period_hours) and self.period_hours > 0):
            raise DataError('drift velocity: the period must be a positive number of hours, '
                            f'got {self.period_hours}')

    @classmethod
    def from_values(cls, values: Sequence[float]) -> DriftSwing:
        """The swing of ``[temperature_K, offset_rad(, period_h)]`` (period default
        `DAY_HOURS`), as the CLI's ``--drift-velocity`` and the node's ``drift_velocity`` give
        it.

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

    @staticmethod
    def from_dict(section: Any) -> 'DriftState':
        """The ``drift_state`` section of calibration.yaml; DataError names the field."""
        if not isinstance(section, dict):
            raise DataError('drift_state must be a mapping (names, values, covariance, '
                            'cross_covariance); give an unedited calibration.yaml')
        missing = [k for k in ('names', 'values', 'covariance', 'cross_covariance')
                   if k not in section]
        if missing:
            raise DataError(f'drift_state lacks {missing}; give an unedited calibration.yaml')
        names = section['names']
        if not isinstance(names, list) or not all(isinstance(n, str) for n in names) \
                or len(set(names)) != len(names):
            raise DataError('drift_state.names must be a list of unique parameter names')
        try:
            arrays = [np.array(section[k], dtype=float)
                      for k in ('values', 'covariance', 'cross_covariance')]
        except (TypeError, ValueError) as exc:
            raise DataError(f'drift_state: values, covariance and cross_covariance must be '
                            f'numbers ({exc})') from None
        return DriftState(tuple(names), *arrays)


def state_predicted(prior: Prior, state: DriftState, swing: DriftSwing, shape: np.ndarray,
                    hours: float) -> tuple[Prior, DriftState]:
    """The prior and drift state of the same ``names`` after ``hours``.

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
    """The drift state of a calibration that has none: z = 0 with the stationary
    covariance (the deviation and rate of the swing unknown), uncorrelated with p."""
    k = len(names)
    cov = np.kron(swing.stationary(), 0.5 * np.asarray(shape, float))
    return DriftState(tuple(names), np.zeros(2 * k), cov, np.zeros((k, 2 * k)))


def initial_state(names: Sequence[str], swing: DriftSwing, shape: np.ndarray,
                  stored: DriftState | None) -> DriftState:
    """The drift state of the prior parameters ``names`` before extrapolation: ``stored``
    (a previous calibration's ``drift_state``) for the names it has; for the others, and
    for all without one, the stationary state of the swing (:func:`stationary_state`),
    uncorrelated."""
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
    """The drift state after a cycle's identification (its Kalman update).

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
