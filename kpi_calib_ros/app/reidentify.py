"""Re-identification of a work cycle with the last calibration as prior (``identify
--prior``, the node's ``reidentify_with_prior``).

The previous calibration enters as a Gaussian prior on its identified parameters, widened
by the drift model for the time since it (:func:`cycle_prior`). Three rules make the
update a proper Kalman step:

* **the same gauge**: position data cannot separate every parameter, so the previous
  identification held some at chosen values (``dropped``) and its covariance describes
  the kept ones *given* those. The new cycle therefore frees only the previous
  identified set (plus the base and reflector placement when they are not in the prior)
  and holds the rest where the previous calibration had them. Freeing them again lets
  the data move directions the prior no longer constrains: on the default cell with 10
  random poses and no drift the TCP std grew from 16 µm (prior) to 49-62 µm.
* **the start is the prior mean** (every parameter at the previous calibration's value),
  not the nominal robot;
* **a change is not blended** (:mod:`kpi_calib_ros.core.campaigns.change_detection`): when the new
  points contradict the prior beyond the drift model, nothing is updated; the document
  goes to calibration.failed.yaml with the ``change_test`` and the moved parameters, and
  ``kpi-calib identify`` exits with :data:`EXIT_CHANGE`.
"""
from __future__ import annotations

import dataclasses
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from kpi_calib_ros.app.calibration_document import (
    CellCalibration,
    add_robust_sections,
    calibration_document,
    require_valid,
    robust_summary,
)
from kpi_calib_ros.app.cell_model import CellModel
from kpi_calib_ros.app.finish import finish_calibration
from kpi_calib_ros.app.identify import calibrate_cell, with_iteration_limit
from kpi_calib_ros.app.measurements import load_measurements
from kpi_calib_ros.app.placement import (
    places_the_points,
    registered_from,
    registered_start,
)
from kpi_calib_ros.app.validate import calibration_noise_scale
from kpi_calib_ros.core.acquisition.outcomes import PairingResult
from kpi_calib_ros.core.campaigns.change_detection import CHANGE_ALPHA, ChangeTest, change_test
from kpi_calib_ros.core.diagnosis.model_selection import level_free
from kpi_calib_ros.core.errors import DataError
from kpi_calib_ros.core.estimation.drift_state import (
    DriftState,
    DriftSwing,
    initial_state,
    state_predicted,
    state_updated,
)
from kpi_calib_ros.core.estimation.least_squares import CalibrationResult, identify
from kpi_calib_ros.core.estimation.prior import (
    DRIFT_ANGLE_PER_SQRT_HOUR,
    DRIFT_LENGTH_PER_SQRT_HOUR,
    PLACEMENT_PREFIXES,
    Prior,
    drift_covariance,
    mapped_drift,
)
from kpi_calib_ros.core.measurement.data import Measurements
from kpi_calib_ros.core.simulation import random_configurations
from kpi_calib_ros.io.calibration_file import (
    drift_state_from_dict,
    prior_from_calibration,
    read_calibration_document,
)
from kpi_calib_ros.io.results import writable_folder

# Exit code of `kpi-calib identify --prior` when the new cycle contradicts the prior.
EXIT_CHANGE = 3
DRIFT_MODELS = ('thermal', 'isotropic')
# Random measurable configurations over which the drift is mapped onto the identified set.
DRIFT_MAP_POSES = 200
# A drift time longer than this (h) is implausible for a work cycle's prior: a clock set
# wrong or a calibration of another era; widened all the same, with a warning.
PLAUSIBLE_DRIFT_HOURS = 24.0 * 366


@dataclass(frozen=True)
class CyclePrior:
    """A previous calibration prepared as the prior of a new cycle.

    Attributes
    ----------
    prior : Prior
        Its identified parameters (placement only if ``keep_placement``), widened.
    values : dict of str to float
        Every parameter value of the previous calibration (the start and the held gauge).
    allowed : tuple of str
        Parameters the new cycle may free.
    keep_placement : bool
        The base and reflector placement are in the prior (tracker and reflector nest
        not moved since), else they are identified anew without prior.
    hours : float
        Drift time from the calibration's ``identified_at_ns`` to the first new point.
    description : str
        One line on how the prior was made.
    noise_scale, noise_dof : float, int or None
        χ²/dof of the previous calibration and its dof when its model was not adequate
        (its covariance was scaled by it, ``precision.covariance_scale``): the new points
        are then weighted by the noise it showed, σ·√noise_scale, not the stated σ, so
        prior and data keep their balance and the same unmodelled effects are no change.
        1.0 and None when the model was adequate.
    warnings : tuple of str
        A negative or implausible drift time: which clocks disagree (``identified_at_ns``
        of the calibration against the stamps of the new measurements).
    state : DriftState or None
        With a drift state (``swing``): the deviations and rates of the prior's parameters
        and their covariance with them, extrapolated with ``prior`` to the new cycle (the
        prior's mean is already moved along them); None without.
    swing : DriftSwing or None
        The daily swing the drift state is modelled on (``--drift-velocity``).
    """

    prior: Prior
    values: dict[str, float]
    allowed: tuple[str, ...]
    keep_placement: bool
    hours: float
    description: str
    noise_scale: float = 1.0
    noise_dof: int | None = None
    state: DriftState | None = None
    swing: DriftSwing | None = None
    warnings: tuple[str, ...] = ()


def read_prior_calibration(path: str | Path, key: str = '--prior') -> dict[str, Any]:
    """A previous calibration to start a cycle from: checked field by field
    (:func:`~kpi_calib_ros.io.calibration_file.read_calibration_document`) and valid
    (:func:`~kpi_calib_ros.app.calibration_document.require_valid`: its values are no
    knowledge to weigh new measurements with when its identification failed).

    Raises
    ------
    ConfigError
        Naming ``key`` and the file: unreadable, or ``valid: false`` with its reasons.
    """
    doc = read_calibration_document(path, key)
    require_valid(doc, key, path, 'prior (or identify without --prior)')
    return doc


def link_vectors(cm: CellModel) -> dict[tuple[str, str, str], np.ndarray]:
    """Nominal translation triples of the model: every joint placement (the URDF joint
    origin), the base in the tracker frame and each reflector offset (m)."""
    params = cm.model.params
    out: dict[tuple[str, str, str], np.ndarray] = {}
    for joint in cm.robot.joints:
        stem = f'{joint.name}.placement.t'
        out[(stem + 'x', stem + 'y', stem + 'z')] = np.array(joint.placement[:3, 3], float)
    prefixes = ['base'] + [n[:-2] for n in params.names
                           if n.startswith('reflector') and n.endswith('.x')]
    for prefix in prefixes:
        names = (f'{prefix}.x', f'{prefix}.y', f'{prefix}.z')
        if all(n in params.names for n in names):
            out[names] = np.array([params.nominal[params.index(n)] for n in names])
    return out


def cycle_prior(cm: CellModel, doc: dict[str, Any], data: Measurements | None,
                length_rate: float = DRIFT_LENGTH_PER_SQRT_HOUR,
                angle_rate: float = DRIFT_ANGLE_PER_SQRT_HOUR,
                keep_placement: bool = False, drift_model: str = 'thermal',
                hours: float | None = None, rotation_rate: float | None = None,
                placement_rate: float | None = None,
                swing: DriftSwing | None = None) -> CyclePrior:
    """The previous calibration ``doc`` (calibration.yaml) as the prior of ``data``.

    Drift (:func:`kpi_calib_ros.core.estimation.prior.drift_widened`) over the time from its
    ``identified_at_ns`` to the first measurement of ``data`` (or over ``hours``, e.g.
    for a design before the data exist): ``thermal`` grows each
    translation along its nominal vector (rank one, the physics of thermal expansion),
    ``isotropic`` each axis independently by ``length_rate`` × the vector's length;
    joint offsets by ``angle_rate`` and placement rotations by ``rotation_rate``
    (default ``angle_rate``) either way. The base position in the tracker frame and the
    reflector offsets grow by ``placement_rate`` (relative, per √hour; default
    ``length_rate``: the floor between tracker and robot expands like the arm).

    ``swing`` (:class:`~kpi_calib_ros.core.estimation.drift_state.DriftSwing`) adds a drift state:
    the deviations and rates of the prior's parameters (``drift_state`` of ``doc``; the
    swing's stationary state when it has none, backwards compatible) extrapolate the prior
    over the drift time (:func:`~kpi_calib_ros.core.estimation.drift_state.state_predicted`), on top
    of the random walks. The swing of link translations (along each link's vector for
    ``thermal``) and joint offsets is modelled, mapped onto the identified parameters as
    the random walk is; placement rotations, the base and the reflectors get none.

    Raises
    ------
    DataError
        The calibration lacks its covariance or names parameters this cell lacks.
    """
    if drift_model not in DRIFT_MODELS:
        raise DataError(f'drift model must be one of {DRIFT_MODELS}, got {drift_model!r}')
    prior = prior_from_calibration(doc, keep_placement=keep_placement)
    params = cm.model.params
    unknown = [n for n in prior.names if n not in params.names]
    if unknown:
        missing = [e for e in doc.get('effects') or ()
                   if e not in {x.name for x in cm.model.effects}]
        raise DataError(f'the prior calibration has parameters {unknown} this cell model '
                        'lacks; use a calibration of the same robot and effects'
                        + (f' (its effects {missing}, which --model auto may have added, '
                           f'belong in the cell: effects: {missing})' if missing else ''))
    values = {p['name']: float(p['value']) for p in doc['parameters']
              if p['name'] in params.names}
    vectors = link_vectors(cm)
    lengths = {n: float(np.linalg.norm(v)) for triple, v in vectors.items() for n in triple}
    for joint in cm.robot.joints:
        if joint.kind == 'prismatic':
            lengths[f'{joint.name}.offset'] = float(max(abs(joint.lower), abs(joint.upper)))
    rotation = angle_rate if rotation_rate is None else rotation_rate
    placement = length_rate if placement_rate is None else placement_rate
    if placement < 0:
        raise DataError(f'placement drift rate must be >= 0, got {placement}')
    stamp = doc.get('identified_at_ns')
    if (hours is None and stamp is not None and data is not None
            and data.stamps_ns is not None and len(data.stamps_ns)):
        hours = (int(np.min(data.stamps_ns)) - int(stamp)) / 3.6e12
    warnings = drift_time_warnings(hours, stamp) if hours is not None and stamp is not None \
        and data is not None else []
    if hours is None:
        hours = 0.0
        how = ('prior calibration NOT widened for drift: '
               + ('it has no identified_at_ns stamp' if stamp is None
                  else 'the measurements carry no stamps'))
    else:
        how = (f'prior calibration widened for {abs(hours):.3g} h of {drift_model} drift '
               f'(lengths {length_rate:.3g}/√h relative, offsets {angle_rate:.3g} rad/√h, '
               f'placement rotations {rotation:.3g} rad/√h, base and reflector position '
               f'{placement:.3g}/√h relative)')
    how += ('; base and reflector placement in the prior (not moved)' if keep_placement
            else '; base and reflector placement identified anew')
    old_identified = set(doc['parameter_covariance']['names'])
    allowed = tuple(n for n in params.names
                    if n in old_identified or n not in values
                    or (not keep_placement and n.startswith(PLACEMENT_PREFIXES)))
    # The drift of every parameter, mapped onto the identified ones (the held ones' drift
    # shows in them; core.estimation.prior.mapped_drift), on the configurations the robot reaches.
    geometric = set(cm.geometric.names)
    thermal = drift_model == 'thermal'
    placed = {n for triple in vectors for n in triple if n.startswith(PLACEMENT_PREFIXES)}

    def robot_drift(length: float, angle: float, rotation: float | None) -> np.ndarray:
        # Every geometric parameter but the placement of the base and the reflectors.
        return drift_covariance(params.names, {n: v for n, v in lengths.items()
                                               if n not in placed},
                                length, angle,
                                link_vectors={t: v for t, v in vectors.items()
                                              if t[0] not in placed} if thermal else None,
                                drifting=lambda n: n in geometric and n not in placed,
                                rotation_rate=rotation)
    q_full = robot_drift(length_rate, angle_rate, rotation_rate)
    q_full += drift_covariance(params.names, {n: lengths[n] for n in placed}, placement,
                               0.0, link_vectors={t: v for t, v in vectors.items()
                                                  if t[0] in placed} if thermal else None,
                               drifting=lambda n: n in placed, rotation_rate=0.0)
    start = params.with_values(values)
    configurations = random_configurations(cm.model, start, DRIFT_MAP_POSES,
                                           np.random.default_rng(0))
    _, jac = cm.model.pose_jacobian(start, configurations)
    kept = params.indices(list(allowed))
    where = [list(allowed).index(n) for n in prior.names]

    def on_prior(q: np.ndarray) -> np.ndarray:
        # Mapped onto the identified parameters (core.estimation.prior.mapped_drift), the prior's.
        return mapped_drift(q, jac.reshape(-1, len(params.names)), kept)[np.ix_(where, where)]
    q_prior = on_prior(q_full)
    widened = Prior(prior.names, prior.mean, prior.covariance + q_prior * abs(hours))
    state = None
    if swing is not None:
        # The swing amplitude's covariance over every parameter (along each link's vector
        # for thermal), mapped onto the prior's parameters like the random walk.
        shape = on_prior(robot_drift(swing.length_amplitude, swing.offset_rad, 0.0))
        state = initial_state(prior.names, swing, shape,
                              drift_state_from_dict(doc['drift_state'])
                              if 'drift_state' in doc else None)
        widened, state = state_predicted(widened, state, swing, shape, hours)
        values = {**values, **dict(zip(prior.names, map(float, widened.mean)))}
        stored = 'drift_state' in doc
        how += (f'; drift state (daily swing ±{swing.temperature_k:g} K, offsets '
                f'±{swing.offset_rad:.3g} rad, period {swing.period_hours:g} h): '
                + ('its drift_state' if stored else 'no drift_state in it: stationary')
                + f' extrapolated over {hours:.3g} h')
    covariance_scale = calibration_noise_scale(doc)
    fitted = fitted_sigma_ratio(cm, doc)
    noise_scale = covariance_scale * fitted ** 2
    noise_dof = None
    if covariance_scale != 1.0:
        noise_dof = int((doc.get('model_adequacy') or {}).get('dof', 0)) or None
        how += (f'; its model was not adequate (chi2/dof {covariance_scale:.3g}): new points '
                f'are weighted by the noise it showed, {np.sqrt(noise_scale):.3g} x the '
                'stated sigma, and the change test accounts for that estimate'
                + (f' ({noise_dof} dof)' if noise_dof else ''))
    elif fitted != 1.0:
        how += (f'; it was fitted at {fitted:.3g} x the stated sigma (the noise its own prior '
                'showed, noise_sigma_m): new points are weighted by it')
    return CyclePrior(widened, values, allowed, keep_placement, hours, how, noise_scale,
                      noise_dof, state, swing, tuple(warnings))


def fitted_sigma_ratio(cm: CellModel, doc: dict[str, Any]) -> float:
    """The noise σ the calibration ``doc`` was fitted at (``noise_sigma_m``) over the cell's
    stated σ (mean over the axes); 1 when it states none.

    A calibration identified with a prior whose model was not adequate was fitted at the
    noise that prior showed (:func:`with_noise_scale`) and is adequate at it
    (``covariance_scale`` 1): the next cycle weighs its points by that σ too, or prior and
    data lose their balance and the change test rejects the same robot (a 3× noise: χ² 830
    for 111 dof, p 2e-110).
    """
    written = doc.get('noise_sigma_m')
    if written is None:
        return 1.0
    try:
        fitted = float(np.mean(np.asarray(written, float)))
    except (TypeError, ValueError):
        return 1.0
    stated = float(np.mean(np.asarray(cm.cell.sigma, float)))
    if not np.isfinite(fitted) or fitted <= 0.0 or stated <= 0.0:
        return 1.0
    ratio = fitted / stated
    return 1.0 if abs(ratio - 1.0) < 1e-9 else ratio


def drift_time_warnings(hours: float, stamp_ns: int) -> list[str]:
    """Warnings for a drift time ``hours`` from a calibration's ``identified_at_ns``
    (``stamp_ns``) to the first new measurement that no clock in agreement gives:
    negative (the calibration dated after the data) or beyond
    :data:`PLAUSIBLE_DRIFT_HOURS`. The prior is widened by |hours| either way (the
    larger uncertainty), never narrowed."""
    clocks = (f'the clock that stamped the prior calibration\'s measurements '
              f'(identified_at_ns {int(stamp_ns)}) and the clock that stamped the new '
              'measurements (header.stamp of the joint states and points) disagree')
    if hours < 0:
        return [f'the prior calibration is dated {-hours:.3g} h AFTER the first new '
                f'measurement: {clocks}, or the prior is not from an earlier cycle; widened '
                f'for {-hours:.3g} h all the same; check both clocks (NTP, use_sim_time) and '
                'the --prior file']
    if hours > PLAUSIBLE_DRIFT_HOURS:
        return [f'the prior calibration is {hours:.6g} h ({hours / 24 / 365.25:.3g} years) '
                f'older than the new measurements, more than the '
                f'{PLAUSIBLE_DRIFT_HOURS:g} h a work cycle\'s prior plausibly is: {clocks}, '
                'or the prior is from another era; widened that far all the same (little '
                'is left of it); check both clocks and the --prior file']
    return []


def cycle_start(cm: CellModel, data: Measurements, cp: CyclePrior) -> np.ndarray:
    """Start of the new cycle: every parameter at the previous calibration's value; the
    placement registered from the points when it is not in the prior and misses them by
    more than :data:`~kpi_calib_ros.app.placement.REGISTER_ABOVE_M` (a moved tracker)."""
    params = cm.model.params
    start = params.with_values(cp.values)
    if cp.keep_placement:
        return start
    if places_the_points(cm, data, start):
        return start
    if not cm.model.recordings:
        # The previous calibration's probe is held as a stated offset would be.
        return registered_from(cm, data, start)
    registered = registered_start(cm, data)[0]
    for i, name in enumerate(params.names):
        if name.startswith(PLACEMENT_PREFIXES):
            start[i] = registered[i]
    return start


@dataclass(frozen=True)
class Reidentification:
    """A cycle's outcome: the change test on the MAP fit of all points, and the
    calibration (None when a change was detected: nothing is blended)."""

    change: ChangeTest
    fit: CalibrationResult
    calibration: CellCalibration | None
    state: DriftState | None = None


def reidentify(cm: CellModel, data: Measurements, cp: CyclePrior, model: str | None = None,
               alpha: float = CHANGE_ALPHA) -> Reidentification:
    """Test the new cycle against the prior, then (when consistent) identify it with the
    prior as :func:`~kpi_calib_ros.app.identify.calibrate_cell` does (outliers, loss,
    estimability), in the previous calibration's gauge and from its values."""
    if len(data) == 0:
        raise DataError('no accepted measurement to identify from')
    cm = with_noise_scale(cm, cp.noise_scale)
    if data.sigma is not None and cp.noise_scale != 1.0:  # rows' own σ, as validate scales them
        data = dataclasses.replace(data, sigma=np.asarray(data.sigma, float)
                                   * np.sqrt(cp.noise_scale))
    start = cycle_start(cm, data, cp)
    level = model or cm.cell.identification.model
    free = [n for n in level_free(cm.model.params, 'geometric' if level == 'auto' else level,
                                  len(cm.geometric)) if n in set(cp.allowed)]
    fit = identify(cm.model, data, cm.cell.sigma, cm.q_work, list(cm.working_pose_names),
                   p0=start, free=free, identifiability_method=cm.cell.identification_method,
                   priority=list(cm.cell.identification_priority) or None, prior=cp.prior,
                   max_iterations=cm.cell.identification.max_iterations, tau_work=cm.tau_work)
    change = change_test(cm.model, data, cm.cell.sigma, fit, cp.prior, alpha,
                         sigma_dof=cp.noise_dof)
    if not change.consistent and cp.noise_scale != 1.0:
        what = ('the parameters named as moved' if change.moved else
                'a broad inconsistency with no single parameter moved')
        change = dataclasses.replace(change, caveat=(
            'The previous calibration\'s model was not adequate (chi2/dof '
            f'{cp.noise_scale:.3g}): {what} may be its unmodelled effects seen from other '
            'poses (a systematic misfit shifts the parameters with the poses it is fitted '
            'on), not a physical change; run kpi-calib diagnose on both recordings'))
    if not change.consistent:
        return Reidentification(change, fit, None)
    cal = calibrate_cell(without_exclusion(cm), data, model, cp.prior, start=start,
                         allowed=cp.allowed)
    state = None
    if cp.state is not None:
        res = cal.result
        state = state_updated(cp.prior, cp.state, res.estimated,
                              res.values[cm.model.params.indices(list(res.estimated))],
                              res.covariance)
    return Reidentification(change, fit, cal, state)


def with_noise_scale(cm: CellModel, scale: float) -> CellModel:
    """``cm`` with its stated noise (``noise.sigma``, ``noise.sigma_rotation``) multiplied by
    √scale; ``cm`` itself for scale 1."""
    if scale == 1.0:
        return cm
    if not (scale > 0 and np.isfinite(scale)):
        raise DataError(f'prior calibration: precision.covariance_scale must be a positive '
                        f'number, got {scale!r}')
    factor = float(np.sqrt(scale))
    cell = dataclasses.replace(
        cm.cell, sigma=np.asarray(cm.cell.sigma, float) * factor,
        sigma_rotation=(None if cm.cell.sigma_rotation is None
                        else float(cm.cell.sigma_rotation) * factor))
    return dataclasses.replace(cm, cell=cell)


def without_exclusion(cm: CellModel) -> CellModel:
    """``cm`` with outliers reported but not excluded (``identification.outliers.exclude``
    false), for a cycle the change test has accepted.

    With a few poses and a prior, σ̂ (1.4826 · MAD of 30 residual components) is no
    scale to exclude by: on the work-cycle bench (10 poses, stated σ 20 µm) it fell to
    4.8 µm and consistent points were excluded one after another until the 20 % limit
    stopped the identification. The change test has already accepted every point
    against the stated σ and the prior; a point it does not accept shows as a change.
    """
    ident = cm.cell.identification
    outliers = dataclasses.replace(ident.outliers, exclude=False)
    cell = dataclasses.replace(cm.cell, identification=dataclasses.replace(
        ident, outliers=outliers))
    return dataclasses.replace(cm, cell=cell)


def reidentification_document(cm: CellModel, out: Reidentification, cp: CyclePrior,
                              source: str, pairing: PairingResult | None = None
                              ) -> dict[str, Any]:
    """calibration.yaml (or, after a detected change, calibration.failed.yaml) of a
    cycle: the calibration document with ``prior`` and ``change_test``."""
    if out.calibration is not None:
        doc = add_robust_sections(calibration_document(cm, out.calibration.result, pairing),
                                  out.calibration)
    else:
        doc = calibration_document(cm, out.fit, pairing)
        doc['valid'] = False
        doc['invalid_reasons'] = [out.change.summary()]
    doc['prior'] = {'source': source, 'description': cp.description,
                    'hours': float(cp.hours), 'keep_placement': cp.keep_placement,
                    'warnings': list(cp.warnings)}
    doc['change_test'] = out.change.to_dict()
    if out.state is not None and cp.swing is not None:
        # The drift state for the next cycle (core.estimation.drift_state.DriftState; rates
        # per hour).
        doc['drift_state'] = {'swing': cp.swing.to_dict(), **out.state.to_dict()}
    return doc


def run_reidentify(cell_path: str | Path, bag_path: str | Path, out_dir: str | Path,
                   prior_path: str | Path, effects: str = '', model: str | None = None,
                   drift: tuple[float, ...] = (DRIFT_LENGTH_PER_SQRT_HOUR,
                                               DRIFT_ANGLE_PER_SQRT_HOUR),
                   keep_placement: bool = False, drift_model: str = 'thermal',
                   swing: DriftSwing | None = None, max_iterations: int | None = None,
                   **options: Any) -> int:
    """``kpi-calib identify --prior OLD/calibration.yaml``.

    ``swing`` (``--drift-velocity``): the daily swing of the drift state
    (:class:`~kpi_calib_ros.core.estimation.drift_state.DriftSwing`).

    Returns 0 for a valid calibration, 1 when it did not converge or the TCP is not
    estimable, :data:`EXIT_CHANGE` (3) when the new points contradict the prior beyond
    its drift model: then calibration.failed.yaml holds the ``change_test`` and an
    existing calibration.yaml is left as it was. A valid calibration is written as one set
    of files (:func:`kpi_calib_ros.app.finish.finish_calibration`), which removes an older
    learned_residual.yaml as plain identify does.
    """
    writable_folder(out_dir, '--out')
    old = read_prior_calibration(prior_path)
    cm, data, pairing = load_measurements(cell_path, bag_path, effects, **options)
    if max_iterations is not None:
        cm = with_iteration_limit(cm, max_iterations)
    cp = cycle_prior(cm, old, data, drift[0], drift[1], keep_placement=keep_placement,
                     drift_model=drift_model,
                     rotation_rate=drift[2] if len(drift) > 2 else None,
                     placement_rate=drift[3] if len(drift) > 3 else None,
                     swing=swing)
    for warning in cp.warnings:
        print(f'WARNING: {warning}', file=sys.stderr)
    out = reidentify(cm, data, cp, model)
    doc = reidentification_document(cm, out, cp, str(prior_path), pairing)
    done = finish_calibration(cm, out.calibration.result if out.calibration else out.fit,
                              doc, out_dir)
    path, urdf_path = done.path, done.urdf_path
    from kpi_calib_ros.io.campaign_io import CHANGE_PLOT_FILE, plot_change  # matplotlib
    plot_change(Path(out_dir) / CHANGE_PLOT_FILE, out.change)
    print(cp.description)
    print(out.change.summary())
    if out.calibration is None:
        print(f'written: {path} (calibration.yaml left as it was)')
        print('CHANGE DETECTED: ' + ', '.join(m.name for m in out.change.moved),
              file=sys.stderr)
        return EXIT_CHANGE
    from kpi_calib_ros.io.results import summary_text
    print(summary_text(doc))
    print(robust_summary(doc))
    print(f'written: {path}')
    if urdf_path is not None:
        print(f'calibrated robot description (URDF): {urdf_path}')
    return 0 if out.calibration.valid else 1
