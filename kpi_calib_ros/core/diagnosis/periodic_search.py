"""Frequencies of periodic joint errors found from the residuals: a Lomb–Scargle search.

A joint-angle error δq_j(q_j) moves measurement i by J_q,i[:, j] δq_j: along the direction
the point moves when joint j turns. Random poses sample q_j irregularly, so the periodogram
of the residual along that direction over cycles per revolution (Lomb–Scargle: a sinusoid
least-squares fit at each frequency, irregular samples) shows a periodic error at its
frequency. Here it is the generalised form: at each k the whitened residuals r are fitted
by the two columns W J_q[:, j]·sin(k q_j), W J_q[:, j]·cos(k q_j) with the geometric
parameters refitted (their span projected out, as the floating mean of Zechmeister &
Kürster 2009 is), and the power is the χ² reduction

    P_j(k) = rᵀ U (UᵀU)⁻¹ Uᵀ r,   U = (I − B Bᵀ) W J_q,j [sin k q_j, cos k q_j]

(B the orthonormal basis of the geometric Jacobian): the F-test numerator of the effect
``periodic_joint_error:<joint>:k=<k>`` at that k, exactly as the screen computes it.

Frequencies searched: k = 2 … K_j for each revolute joint (k = 1 is ``cyclic_joint_error``,
screened by name; k = 2 is ``cyclic_joint_error_h2``), K_j the pseudo-Nyquist frequency
of the poses along the joint, π N / Δ_j cycles per revolution (N poses over the span Δ_j
≤ 2π of its angles: two samples per period on average), at most :data:`MAX_SEARCHED`.
Frequencies within the search's resolution 2π/Δq (Δq the joint's measured range,
:func:`~kpi_calib_ros.core.effects.general.frequency_resolution`) of a periodic error the
model already has on that joint are not searched: over the measured range they are that
error's own peak, aliased, not a second gear stage. Each periodogram reports the resolution
and the frequencies it refused.
A peak must also stand out from every frequency outside its resolution window: the
runner-up there explains the residuals nearly as well when the poses are too few for the
error's frequency (it lies beyond the search, and the frequencies searched are its
aliases). The margin (P_peak − P_runner-up)/s², s² the residual variance the peak leaves
per degree of freedom, is the gap between the two largest powers; of frequencies that
explain alike (independent χ²₂ powers, exponential with mean 2) that gap is itself
exponential with mean 2 (memorylessness): P(margin > c) = e^(−c/2). A peak whose margin
is below c = 2 ln(1/α), α = :data:`AMBIGUITY_ALPHA` (9.2), is *ambiguous* and not a
candidate. Simulated, a k = 40 error of 0.25 mrad on 40 poses over 3.2 rad (searched to
k = 39): margins 0.4, 1.3 and 3.8 at k = 25 and 36, where a second frequency at the beat
(k = 4 after 36) made fresh poses 32 % worse than the geometric level; found within the
search: 1190–2280; k = 39 (within the resolution of the true 40): 16 and 32. The real
UR10 (Series A, 1200 and 2 × 300 poses): shoulder_pan and shoulder_lift at k = 17 and
wrist_1 at 34 stand out in every subset (12–215); wrist_3's peak (35, 43, 54) never does
(0.3–1.2), nor wrist_2's (13, 14, 17) twice of three (0.4, 5.5; 10.9).
The peak of each joint becomes a candidate whose ``searched`` is the number of k tried
there: the screen multiplies its p-value by it (Bonferroni over the search; the peak's
p-value is the smallest of the K_j − 1 tests), and then by the number of candidates, so
the family-wise level of the diagnosis stays the stated α.
"""
from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numpy as np
import scipy.stats

from kpi_calib_ros.core.effects.general import (
    frequency_resolution,
    periodic_cycles,
    periodic_joint_error,
)
from kpi_calib_ros.core.effects.registry import BoundEffect, available_effects, bind_effect
from kpi_calib_ros.core.estimation.least_squares import CalibrationResult
from kpi_calib_ros.core.estimation.residuals import LinearizedFit, linearized_fit
from kpi_calib_ros.core.measurement.data import Measurements
from kpi_calib_ros.core.measurement.tracker import MeasurementModel
from kpi_calib_ros.core.measurement.weighting import weighted_rows

MAX_SEARCHED = 64  # cycles per revolution searched at most
MIN_CYCLES = 2     # k = 1 is cyclic_joint_error, screened by name
AMBIGUITY_ALPHA = 0.01  # a peak's margin over the runner-up beyond a tie at this level


@dataclass(frozen=True)
class Periodogram:
    """The search along one joint.

    cycles : (K,) int, the frequencies tried (cycles per revolution); power : (K,) χ²
    reduction of a sinusoid at each (units of σ²); peak : the k of the largest;
    p_value : F-test p-value of the peak times K (Bonferroni over the search).
    """

    joint: str
    cycles: np.ndarray
    power: np.ndarray
    peak: int
    p_value: float
    # 2π/Δq (cycles per revolution) and the frequencies left out as within it of a periodic
    # error the model has on this joint (its k's).
    resolution: float = float('nan')
    refused: tuple[int, ...] = ()
    near: tuple[int, ...] = ()
    # The best frequency outside the peak's resolution window, the peak's margin over it in
    # units of the residual variance the peak leaves, and the margin noise can reach
    # (module docstring); 0 / NaN when no frequency lies outside the window.
    runner_up: int = 0
    margin: float = float('nan')
    margin_needed: float = float('nan')

    @property
    def ambiguous(self) -> bool:
        """Whether the runner-up outside the resolution window explains nearly as well."""
        return bool(np.isfinite(self.margin) and self.margin < self.margin_needed)


def searched_cycles(q_j: np.ndarray, max_cycles: int = MAX_SEARCHED) -> np.ndarray:
    """Frequencies (cycles per revolution) the poses' angles ``q_j`` (N,) support.

    ``MIN_CYCLES`` … min(``max_cycles``, ⌊π N / Δ⌋), Δ the span of the angles (≤ 2π).
    """
    q_j = np.asarray(q_j, float)
    span = min(float(np.ptp(q_j)) if len(q_j) else 0.0, 2.0 * math.pi)
    if span <= 0.0:
        return np.zeros(0, int)
    top = min(max_cycles, int(math.pi * len(np.unique(q_j)) / span))
    return np.arange(MIN_CYCLES, top + 1)


def periodograms(model: MeasurementModel, data: Measurements, result: CalibrationResult,
                 max_cycles: int = MAX_SEARCHED, fit: LinearizedFit | None = None
                 ) -> tuple[Periodogram, ...]:
    """Return the periodogram of every revolute joint of ``model`` at the fit ``result``.

    Parameters
    ----------
    model, data, result
        The calibration searched (its residuals, weights and geometric Jacobian).
    max_cycles : int
        Highest frequency searched, cycles per revolution.
    fit : LinearizedFit, optional
        ``linearized_fit(model, data, result)`` when the caller has it.

    Returns
    -------
    tuple of Periodogram
        One per revolute joint with at least one frequency to try, chain order.
    """
    sys_ = fit or linearized_fit(model, data, result)
    q = np.atleast_2d(data.q)
    lever = model.joint_jacobian(sys_.p, q, sys_.tau, sys_.reflector, sys_.rotation,
                                 sys_.covariates)
    r = sys_.r - sys_.basis @ (sys_.basis.T @ sys_.r)
    chi2 = float(r @ r)
    dof = len(r) - sys_.basis.shape[1] - 2
    out = []
    for j, joint in enumerate(model.robot.joints):
        if joint.kind == 'prismatic':
            continue
        cycles = searched_cycles(q[:, j], max_cycles)
        resolution = frequency_resolution(q[:, j])
        have = [k0 for e in model.effects if isinstance(e, BoundEffect)
                and e.joint == joint.name for k0 in (periodic_cycles(e),) if k0 is not None]
        aliased = np.array([any(abs(k - k0) < resolution for k0 in have) for k in cycles],
                           bool)
        refused = tuple(int(k) for k in cycles[aliased])
        cycles = cycles[~aliased]
        if not len(cycles) or dof <= 0:
            continue
        column = lever[:, :, j]
        power = np.zeros(len(cycles))
        for i, k in enumerate(cycles):
            waves = np.stack([np.sin(k * q[:, j]), np.cos(k * q[:, j])], axis=1)
            cols = weighted_rows(column[:, :, None] * waves[:, None, :], sys_.w)
            unique = cols - sys_.basis @ (sys_.basis.T @ cols)
            proj = unique.T @ r
            power[i] = float(proj @ np.linalg.lstsq(unique.T @ unique, proj, rcond=None)[0])
        best = int(np.argmax(power))
        left = max((chi2 - power[best]) / dof, 1e-300)
        f_stat = (power[best] / 2) / left
        p_raw = float(scipy.stats.f.sf(f_stat, 2, dof))
        outside = np.abs(cycles - cycles[best]) >= resolution
        runner_up, margin, needed = 0, float('nan'), float('nan')
        if outside.any():
            second = int(np.argmax(np.where(outside, power, -np.inf)))
            runner_up = int(cycles[second])
            margin = float((power[best] - power[second]) / left)
            needed = 2.0 * math.log(1.0 / AMBIGUITY_ALPHA)
        out.append(Periodogram(joint.name, cycles, power, int(cycles[best]),
                               min(1.0, p_raw * len(cycles)), resolution, refused,
                               tuple(have), runner_up, margin, needed))
    return tuple(out)


def periodic_candidates(model: MeasurementModel, found: tuple[Periodogram, ...]
                        ) -> list[BoundEffect]:
    """Return the peak of each periodogram as a candidate effect.

    ``searched`` = the number of frequencies tried (k = 2 is the named
    ``cyclic_joint_error_h2``); effects already in ``model`` and ambiguous peaks
    (:attr:`Periodogram.ambiguous`) left out.
    """
    have = {e.name for e in model.effects}
    out: list[BoundEffect] = []
    for gram in found:
        if gram.ambiguous:
            continue
        if gram.peak == 2:
            effect: BoundEffect = bind_effect(available_effects()['cyclic_joint_error_h2'],
                                              model.robot, gram.joint)
        else:
            effect = periodic_joint_error(model.robot, gram.joint, gram.peak)
        if effect.name not in have:
            out.append(dataclasses.replace(effect, searched=len(gram.cycles)))
    return out


__all__ = ['AMBIGUITY_ALPHA', 'MAX_SEARCHED', 'Periodogram', 'periodic_candidates', 'periodograms',
           'searched_cycles']
