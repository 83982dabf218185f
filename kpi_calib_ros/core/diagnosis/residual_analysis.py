"""Where a calibration's model fails, without a model of the failure.

For every *input* of a measurement (each joint angle, each joint's gravity torque, the
distance to the tracker, time, the reflector, any recorded covariate such as a
temperature): how much of the residual the geometric model leaves can a smooth function of
that input alone explain on held-out poses, and is that more than noise would give?

The model of one input ``x`` with direction fields ``g_k`` (m per unit of ``f_k``) is

    r_i ≈ Σ_k g_k(i) f_k(x_i) + (geometric parameters refitted) + noise,

``f_k`` a cubic regression spline (or harmonics of a revolute joint's turn). The inputs
and their fields come from :mod:`kpi_calib_ros.core.diagnosis.residual_inputs`. The fields say how
the input moves the point: for joint ``j`` (its angle or its gravity torque) the column
∂p/∂q_j of the position Jacobian, so ``f`` is an error of the joint angle (rad) -- its
component along the direction the point moves, divided by the lever, is what the
partial-residual plot shows; for the distance the line of sight (``f`` a range error, m);
for inputs with no direction of their own (time, a temperature, any covariate) the three
tracker axes and the point's offset from the centroid of the points, so ``f`` is a drift
(m) per axis and a scale (strain): a thermal growth of the links is a scale of the arm
about its base, i.e. a scale about the centroid plus a translation. Reflector index: a
constant per reflector (categorical) per axis.

Choices, and why:

* **Whitened residuals.** Everything runs on the fit's weighted rows
  (:func:`~kpi_calib_ros.core.estimation.residuals.linearized_fit`: each row's stated σ,
  joint-reading noise), so a noisy row counts as little as in the fit.
* **The geometry refitted.** A constant joint error is an offset, a linear one a scale the
  geometric parameters already absorb; the spline columns are projected off the span of the
  identified parameters' Jacobian, so an input is credited only with the part of the misfit
  no geometric parameter can reproduce.
* **Regression splines, not penalised smoothers.** An unpenalised spline basis of a fixed
  size makes the projected fit an ordinary linear least-squares problem: under the null
  (residuals independent of the input) its F statistic is *exactly* F-distributed with the
  rank of the projected columns, whatever the stated σ (the F test estimates the scale
  from the residuals themselves, so a misstated σ does not flag every input). The basis
  size is chosen from a small grid (``BASIS_SIZES``) by cross-validation; the p-value is
  the smallest of the grid times its length (Bonferroni), so picking the best size keeps
  the level. A penalised GAM or a Gaussian process with one length scale per input would
  give smoother curves but only approximate tests (effective degrees of freedom) and cost
  an optimisation per input; scipy's B-spline design matrix is enough and fast (a few
  seconds for a thousand rows). A joint angle is periodic: for a revolute joint the grid
  also holds Fourier bases (harmonics 1..H of the turn, and single frequencies of 2 to 48
  cycles per turn of which only the strongest is cross-validated, a periodogram peak),
  the natural smoother of a gear's errors at 3 or 40 cycles per turn, which a spline of a
  few dozen pieces cannot follow.
* **Family of inputs.** Holm's step-down over the inputs: on data the model explains, the
  probability that any input is flagged stays below ``alpha``. An input is flagged when
  its test rejects *and* its cross-validated share is positive: a fit the F test finds but
  that predicts held-out poses worse (a few rows at the end of a short lever) does not
  say where the model fails.
* **Cross-validated share.** Folds over poses (rows measured at one pose stay together,
  :func:`~kpi_calib_ros.core.estimation.folds.identifiable_folds`); the held-out residuals of
  the refit are exact for a linear model (the PRESS identity). ``share`` is
  1 − CV-SSE(geometry + spline)/CV-SSE(geometry): the fraction of the held-out residual
  sum of squares the input explains; ``share_systematic`` divides the same reduction by the
  held-out sum of squares beyond the noise the stated σ predicts (its exact expectation
  under the model, Σ_F tr((I − H_FF)⁻¹)).
* **Two inputs jointly.** When two joint angles are flagged, a tensor product (harmonics
  1-2 of each joint's turn: the low orders on the torus of two angles; a cubic spline of
  5 for a prismatic joint) of the top two along the first one's direction is tested
  (F) against the sum of their smooths: "a smooth misfit depending on joints X and Y"
  that no sum of one-input functions is.
* **Ranking.** Significant inputs first, then by the evidence (the p-value before Holm,
  then ``share``): a shape that needs many functions for few poses keeps a small
  cross-validated share while its F test is unmistakable; between two inputs that explain
  the same (a joint angle and its gravity torque) the one that needs fewer functions wins.
* **Fields from the predicted points.** A field built from the measured point would hold
  the residual itself (a cubic in the distance times the line of sight contains η, and
  the geometry spans h(p̂)): every residual would be "explained".
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Mapping, Sequence

import numpy as np
import scipy.interpolate
import scipy.stats

from kpi_calib_ros.core.diagnosis.residual_bases import (
    basis_columns,
    basis_text,
    candidate_bases,
    fourier_basis,
    spline_basis,
)
from kpi_calib_ros.core.diagnosis.residual_curves import (
    curve_region,
    fitted_curve,
    implied_values,
)
from kpi_calib_ros.core.diagnosis.residual_inputs import ResidualInput, residual_inputs
from kpi_calib_ros.core.estimation.folds import fold_rows, held_out_blocks, identifiable_folds
from kpi_calib_ros.core.estimation.least_squares import CalibrationResult
from kpi_calib_ros.core.estimation.residuals import (
    ADEQUACY_ALPHA,
    LinearizedFit,
    linearized_fit,
    orthonormal_basis,
)
from kpi_calib_ros.core.measurement.data import Measurements
from kpi_calib_ros.core.measurement.replicates import as_first_of_pose
from kpi_calib_ros.core.measurement.tracker import MeasurementModel
from kpi_calib_ros.core.measurement.weighting import unweighted, weighted_rows

__all__ = ['BASIS_SIZES', 'HARMONICS', 'InputScore', 'PairScore', 'ResidualAnalysis',
           'ResidualInput', 'analyse_calibration', 'analyse_residuals', 'residual_inputs']

BASIS_SIZES = (4, 8, 16, 32, 64)   # spline functions per field tried; Bonferroni over them
HARMONICS = (2, 4, 8, 16, 32, 48)  # highest harmonic of the Fourier bases of a periodic input
DEFAULT_FOLDS = 10                 # pose folds of the cross-validated share
MIN_POSES_PER_COLUMN = 3           # a basis with more columns than poses / 3 is not tried
RANK_TOLERANCE = 1e-6              # singular value of the unit-column projected design


@dataclass(frozen=True)
class InputScore:
    """How much of the misfit one input explains (see the module docstring).

    Attributes
    ----------
    name, kind, unit, field_names, field_units, categorical
        As the :class:`ResidualInput`.
    basis : str
        The basis chosen by cross-validation ('cubic spline, 16 functions', 'harmonics
        1-32 of the turn', 'one constant per value'; '' when the geometry absorbs every
        column).
    dof : int
        Rank of the spline columns the geometry cannot reproduce.
    share : float
        1 − CV-SSE(with the input)/CV-SSE(geometry alone), held-out poses (can be < 0).
    share_systematic : float
        The same reduction over the held-out sum of squares beyond the noise the stated σ
        predicts; NaN when there is none beyond it.
    held_out_rms_before_m, held_out_rms_after_m : float
        Rms (m) of the held-out residual of the geometric refit alone and with the spline.
    explained_rms_m : float
        Rms (m) of the point displacement the input's fit explains (all data).
    f_statistic, p_value_raw, p_value : float
        F test of the spline columns (at the size with the smallest p), ``p_value_raw``
        Bonferroni over the sizes tried, ``p_value`` Holm-adjusted over the inputs.
    significant : bool
        ``p_value`` < alpha and ``share`` > 0 (NaN share: the test alone).
    x : (N,) ndarray
        The input's values.
    implied : (N, d) ndarray
        Each row's residual along each field, divided by the field's squared norm: the
        function value the residual implies (``field_units``); NaN where the field is 0.
    weight : (N, d) ndarray
        Whitened squared norm of each field (1/unit²): how much each implied value counts.
    curve_x : (G,) ndarray
        Input values of the plotted fit.
    curve : (G, d) ndarray
        Weighted spline fit of ``implied`` against ``x``, at ``curve_x``.
    region : str
        Where the fitted function is largest ('' when not significant).
    """

    name: str
    kind: str
    unit: str
    field_names: tuple[str, ...]
    field_units: tuple[str, ...]
    categorical: bool
    basis: str
    dof: int
    share: float
    share_systematic: float
    held_out_rms_before_m: float
    held_out_rms_after_m: float
    explained_rms_m: float
    f_statistic: float
    p_value_raw: float
    p_value: float
    significant: bool
    x: np.ndarray = field(repr=False)
    implied: np.ndarray = field(repr=False)
    weight: np.ndarray = field(repr=False)
    curve_x: np.ndarray = field(repr=False)
    curve: np.ndarray = field(repr=False)
    region: str = ''


@dataclass(frozen=True)
class PairScore:
    """Whether the misfit depends on two inputs jointly, beyond the sum of their smooths.

    The top two flagged joint angles: a tensor product of both (harmonics 1-2 of a
    revolute joint's turn, a cubic spline of 5 functions for a prismatic one) along the
    first one's direction, tested (F) against the additive model of
    their own smooths.

    Attributes
    ----------
    names : tuple of str
        The two inputs.
    dof : int
        Rank of the interaction columns beyond the additive model and the geometry.
    f_statistic, p_value : float
        F test of the interaction columns.
    significant : bool
        ``p_value`` < alpha and the pair predicts held-out poses better than the sum.
    held_out_rms_additive_m, held_out_rms_after_m : float
        Held-out rms (m) of the additive model of the two and of it with the interaction.
    """

    names: tuple[str, str]
    dof: int
    f_statistic: float
    p_value: float
    significant: bool
    held_out_rms_additive_m: float
    held_out_rms_after_m: float


@dataclass(frozen=True)
class ResidualAnalysis:
    """Inputs ranked by the misfit they explain, and all significant ones together.

    Attributes
    ----------
    scores : tuple of InputScore
        Significant first, then by ``p_value_raw`` and ``share``.
    alpha : float
        Family-wise level (Holm over the inputs).
    folds : int
        Pose folds of the cross-validation (0: none possible with this design).
    chi2, dof : float, int
        Whitened residual sum of squares of the fit and its degrees of freedom.
    combined : tuple of str
        The significant inputs, fitted together (an additive model).
    combined_before_m, combined_after_m : float
        Held-out rms (m) of the geometric refit alone and with the combined splines (and
        the interaction when ``pair`` is significant).
    pair : PairScore or None
        The interaction of the top two flagged joint angles (None: fewer, or too few
        poses for its 25 columns).
    """

    scores: tuple[InputScore, ...]
    alpha: float
    folds: int
    chi2: float
    dof: int
    combined: tuple[str, ...] = ()
    combined_before_m: float = float('nan')
    combined_after_m: float = float('nan')
    pair: PairScore | None = None

    @property
    def significant(self) -> tuple[InputScore, ...]:
        """The inputs flagged at the family-wise level, best first."""
        return tuple(s for s in self.scores if s.significant)


# ---------------------------------------------------------------- analysis
def _design(inp: ResidualInput, basis: np.ndarray, w: np.ndarray) -> np.ndarray:
    """Whitened columns (3N, d·M): field k times basis function m, row by row."""
    cols = []
    for k in range(inp.fields.shape[2]):
        g = weighted_rows(inp.fields[:, :, k:k + 1], w)[:, 0]   # (3N,)
        cols.append(np.repeat(basis, 3, axis=0) * g[:, None])
    return np.hstack(cols)


def _unique_basis(design: np.ndarray, geometry: np.ndarray) -> np.ndarray:
    """Orthonormal basis of the part of ``design``'s span the geometry cannot reproduce."""
    norms = np.linalg.norm(design, axis=0)
    keep = norms > 0
    if not keep.any():
        return np.zeros((design.shape[0], 0))
    d = design[:, keep] / norms[keep]
    d = d - geometry @ (geometry.T @ d)
    u, s, _ = np.linalg.svd(d, full_matrices=False)
    return u[:, s > RANK_TOLERANCE]


class _Press:
    """Held-out residuals of a linear refit, folds over poses (PRESS identity)."""

    def __init__(self, geometry: np.ndarray, pose_folds: np.ndarray | None) -> None:
        self.geometry = geometry
        self.folds: list[np.ndarray] = ([] if pose_folds is None
                                        else [rows for _, rows in fold_rows(pose_folds)])

    def held_out(self, u: np.ndarray, r: np.ndarray) -> tuple[np.ndarray, float] | None:
        """Held-out residuals (3N,) of r ≈ [geometry, u]·δ and their expected sum of squares.

        The expected sum of squares under pure unit noise; None when a fold leaves a column
        undetermined.
        """
        basis = np.hstack([self.geometry, u])
        e = r - basis @ (basis.T @ r)
        held = np.empty_like(r)
        noise = 0.0
        for test, m in zip(self.folds, held_out_blocks(basis, self.folds)):
            if m.smallest < 1e-10:
                return None
            held[test] = m.solve(e[test])
            noise += m.trace_inverse()
        return held, noise


def _rms_m(held: np.ndarray, w: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.sum(unweighted(held, w) ** 2, axis=1))))


def analyse_residuals(fit: LinearizedFit, residuals: np.ndarray,
                      inputs: Sequence[ResidualInput], q: np.ndarray,
                      folds: int = DEFAULT_FOLDS, alpha: float = ADEQUACY_ALPHA,
                      seed: int = 0, sizes: Sequence[int] = BASIS_SIZES,
                      harmonics: Sequence[int] = HARMONICS) -> ResidualAnalysis:
    """Score every input against the misfit of one calibration.

    Parameters
    ----------
    fit : LinearizedFit
        The calibration linearized at p̂ (whitened residuals, Jacobian, weights).
    residuals : (N, 3) ndarray
        η − h(p̂, q), m (for the implied values of the plots).
    inputs : sequence of ResidualInput
        What the misfit may depend on (:func:`~kpi_calib_ros.core.diagnosis.residual_inputs.
        residual_inputs` builds the standard ones;
        any other covariate is one more :class:`ResidualInput`).
    q : (N, n) ndarray
        Joint values, rad: rows of one pose (equal values, or within a reading's tolerance
        of each other, :func:`~kpi_calib_ros.core.measurement.replicates.pose_groups`) are
        one fold.
    folds : int
        Pose folds of the cross-validated share (0: leave one pose out).
    alpha : float
        Family-wise level over the inputs (Holm).
    sizes : sequence of int
        Spline functions per field tried.
    harmonics : sequence of int
        Highest harmonics of the Fourier bases tried on periodic inputs.

    Returns
    -------
    ResidualAnalysis
    """
    r = np.asarray(fit.r, float)
    geometry = fit.basis
    n_rows = len(r)
    dof0 = n_rows - geometry.shape[1]
    chi2 = float(r @ r)
    # A posture measured again (within a reading's tolerance: another session of the same
    # program) is one pose, held out with its repeats: in other folds they leaked its
    # residual into the fit (three real TIAGo sessions of 62 postures, 184 "poses": a
    # share of 0.71 for arm_6_joint, negative with the repeats held out together).
    q = as_first_of_pose(q)
    n_poses = len(np.unique(q, axis=0))
    pose_folds = identifiable_folds(fit.jac, q, folds, seed)
    press = _Press(geometry, pose_folds)
    base = press.held_out(np.zeros((n_rows, 0)), r) if pose_folds is not None else None
    base_sse = float(base[0] @ base[0]) if base else float('nan')
    base_noise = base[1] if base else float('nan')
    base_rms = _rms_m(base[0], fit.w) if base else float('nan')

    raw: list[float] = []
    chosen: list[dict[str, Any] | None] = []
    for inp in inputs:
        active = np.any(inp.fields != 0, axis=(1, 2))
        support = np.asarray(inp.values, float)[active]
        cap = max(1, n_poses // (MIN_POSES_PER_COLUMN * inp.fields.shape[2]))
        tests = []
        # A category (a recording, a reflector) is judged on how it differs from the others:
        # what its fields do alike on every row (a scale common to all recordings) is not
        # its own. On three real TIAGo sessions each later recording was flagged for a
        # 367 ppm scale that was one scale shared by all (alone, 1.2-1.4σ).
        against = geometry if not inp.categorical else np.hstack([geometry, _unique_basis(
            _design(inp, np.ones((len(inp.values), 1)), fit.w), geometry)])
        for size in candidate_bases(inp, support, cap, sizes, harmonics):
            u = _unique_basis(_design(inp, basis_columns(np.asarray(inp.values, float), size,
                                                  support), fit.w), against)
            if u.shape[1] == 0 or dof0 - u.shape[1] <= 0:
                continue
            coef = u.T @ r
            delta = float(coef @ coef)
            dof = dof0 - u.shape[1]
            f_stat = (delta / u.shape[1]) / max(chi2 - delta, 1e-300) * dof
            tests.append({'size': size, 'u': u, 'coef': coef, 'f': f_stat,
                          'p': float(scipy.stats.f.sf(f_stat, u.shape[1], dof))})
        if not tests:
            chosen.append(None)
            raw.append(1.0)
            continue
        # Cross-validate every basis but the single harmonics, of which only the one with
        # the strongest F test (a periodogram peak); the p-value is Bonferroni over all.
        single = [t for t in tests if t['size'][0] == 'harmonic']
        scored = [t for t in tests if t['size'][0] != 'harmonic'] + \
            ([min(single, key=lambda t: t['p'])] if single else [])
        for t in scored:
            held = press.held_out(t['u'], r) if pose_folds is not None else None
            t['cv'] = float(held[0] @ held[0]) if held else float('nan')
            t['rms'] = _rms_m(held[0], fit.w) if held else float('nan')
        finite = [t for t in scored if np.isfinite(t['cv'])]
        best = min(finite, key=lambda t: t['cv']) if finite else min(scored,
                                                                      key=lambda t: t['p'])
        chosen.append(best)
        raw.append(min(1.0, min(t['p'] for t in tests) * len(tests)))
    adjusted = _holm(np.array(raw))

    scores = []
    excess = base_sse - base_noise
    largest_m = float(np.max(np.linalg.norm(np.asarray(residuals, float), axis=1),
                             initial=0.0))
    for inp, pick, p_raw, p_adj in zip(inputs, chosen, raw, adjusted):
        best = pick or {}
        implied, weight = implied_values(inp, np.asarray(residuals, float), fit.w)
        active = np.any(inp.fields != 0, axis=(1, 2))
        support = np.asarray(inp.values, float)[active]
        size = best['size'] if best else ('spline', 0)
        grid, curve, determined = fitted_curve(inp, implied, weight, size, support) if best else \
            (np.unique(support)[:1], np.full((1, inp.fields.shape[2]), np.nan),
             np.full((1, inp.fields.shape[2]), np.nan))
        share = 1.0 - best['cv'] / base_sse if best else float('nan')
        # Flagged: the test rejects and the smooth predicts held-out poses better than the
        # geometry alone (a fit that only chases a few rows is not where the model fails).
        significant = bool(best and p_adj < alpha and not share <= 0)
        scores.append(InputScore(
            name=inp.name, kind=inp.kind, unit=inp.unit, field_names=inp.field_names,
            field_units=inp.field_units, categorical=inp.categorical,
            basis=basis_text(size) if best else '',
            dof=int(best['u'].shape[1]) if best else 0, share=float(share),
            share_systematic=float((base_sse - best['cv']) / excess)
            if best and excess > 0 else float('nan'),
            held_out_rms_before_m=base_rms,
            held_out_rms_after_m=best['rms'] if best else float('nan'),
            explained_rms_m=_rms_m(best['u'] @ best['coef'], fit.w) if best else 0.0,
            f_statistic=best['f'] if best else float('nan'), p_value_raw=float(p_raw),
            p_value=float(p_adj), significant=significant,
            x=np.asarray(inp.values, float), implied=implied, weight=weight,
            curve_x=grid, curve=curve,
            region=curve_region(inp, grid, determined, largest_m) if significant else ''))
    order = sorted(range(len(scores)), key=lambda i: (
        not scores[i].significant, scores[i].p_value_raw,
        -np.nan_to_num(scores[i].share, nan=-np.inf)))
    ranked = tuple(scores[i] for i in order)

    combined = tuple(i for i in order if scores[i].significant)
    # Two joint angles: a torque is itself a function of the angles, and an angle with its
    # own joint's torque leaves most of their plane empty (wild held-out predictions).
    top2 = [i for i in combined if inputs[i].kind == 'joint'][:2]
    pair, extra = None, np.zeros((n_rows, 0))
    if len(top2) == 2:
        pair, extra = _pair(inputs[top2[0]], inputs[top2[1]],
                            [(chosen[i] or {})['u'] for i in top2], r, geometry, fit.w,
                            press, n_poses, alpha)
    after = float('nan')
    if combined and pose_folds is not None:
        u = orthonormal_basis(np.hstack([(chosen[i] or {})['u'] for i in combined]
                                        + ([extra] if pair and pair.significant else [])))
        held = press.held_out(u, r)
        after = _rms_m(held[0], fit.w) if held else float('nan')
    return ResidualAnalysis(
        scores=ranked, alpha=alpha, folds=0 if pose_folds is None else folds, chi2=chi2,
        dof=dof0, combined=tuple(scores[i].name for i in combined),
        combined_before_m=base_rms, combined_after_m=after, pair=pair)


PAIR_FUNCTIONS = 5  # functions per input of the tensor product: a cubic spline of 5, or
PAIR_HARMONICS = 2  # harmonics 1-2 of the turn for a joint angle (5 functions too)


def _pair(a: ResidualInput, b: ResidualInput, additive: list[np.ndarray], r: np.ndarray,
          geometry: np.ndarray, w: np.ndarray, press: _Press, n_poses: int,
          alpha: float) -> tuple[PairScore | None, np.ndarray]:
    """Interaction of ``a`` and ``b`` along ``a``'s direction beyond their additive fit.

    Also its columns (projected off the geometry and the additive fit).
    """
    if PAIR_FUNCTIONS ** 2 > n_poses // MIN_POSES_PER_COLUMN:
        return None, np.zeros((len(r), 0))

    def basis(inp: ResidualInput) -> np.ndarray:
        x = np.asarray(inp.values, float)
        return fourier_basis(x, PAIR_HARMONICS) if inp.periodic else \
            spline_basis(x, PAIR_FUNCTIONS)
    ba, bb = basis(a), basis(b)
    tensor = (ba[:, :, None] * bb[:, None, :]).reshape(len(ba), -1)
    add = orthonormal_basis(np.hstack(additive))
    known = np.hstack([geometry, add])
    u = _unique_basis(_design(a, tensor, w), known)
    dof = len(r) - known.shape[1] - u.shape[1]
    if u.shape[1] == 0 or dof <= 0:
        return None, u
    e = r - add @ (add.T @ r)
    delta = float(np.sum((u.T @ e) ** 2))
    f_stat = (delta / u.shape[1]) / max(float(e @ e) - delta, 1e-300) * dof
    p = float(scipy.stats.f.sf(f_stat, u.shape[1], dof))
    held_add = press.held_out(add, r) if press.folds else None
    held_pair = press.held_out(np.hstack([add, u]), r) if press.folds else None
    before = _rms_m(held_add[0], w) if held_add else float('nan')
    after = _rms_m(held_pair[0], w) if held_pair else float('nan')
    better = not after >= before  # NaN (no folds): the test alone
    return PairScore((a.name, b.name), int(u.shape[1]), float(f_stat), p,
                     bool(p < alpha and better), before, after), u


def _holm(p: np.ndarray) -> np.ndarray:
    """Holm's step-down adjusted p-values (family-wise error control)."""
    m = len(p)
    if m == 0:
        return p
    order = np.argsort(p)
    adj = np.empty(m)
    running = 0.0
    for rank, i in enumerate(order):
        running = max(running, min(1.0, (m - rank) * p[i]))
        adj[i] = running
    return adj


def analyse_calibration(model: MeasurementModel, data: Measurements,
                        result: CalibrationResult,
                        covariates: Mapping[str, tuple[np.ndarray, str]] | None = None,
                        folds: int = DEFAULT_FOLDS, alpha: float = ADEQUACY_ALPHA,
                        seed: int = 0) -> ResidualAnalysis:
    """:func:`analyse_residuals` of ``result`` over the standard inputs of ``data`` and more.

    The standard inputs are
    :func:`~kpi_calib_ros.core.diagnosis.residual_inputs.residual_inputs`; the extra
    ``covariates`` map name -> (values, unit).
    """
    fit = linearized_fit(model, data, result)
    residuals = np.atleast_2d(data.eta) - model.predict(
        result.values, np.atleast_2d(data.q), fit.tau, data.reflector, data.rotation,
        fit.covariates)
    inputs = residual_inputs(model, data, result, covariates, fit.tau)
    return analyse_residuals(fit, residuals, inputs, data.q, folds, alpha, seed)
