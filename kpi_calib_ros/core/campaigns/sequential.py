"""Sequential campaign: each next pose chosen from what has been measured, stop at a target.

A fixed design fixes N in advance from a stated tracker σ and a model that may both be
wrong. Here the campaign starts with the smallest design that makes every
identifiable parameter and every working pose's TCP estimable (plus
``initial_margin`` poses), the first poses of a batch KPI design three times that size
ordered so that its prefixes are good designs
(:func:`~kpi_calib_ros.core.campaigns.plan_order.nested_order`), and after every
measurement

1. re-identifies (:func:`kpi_calib_ros.core.estimation.least_squares.identify`, warm start);
2. estimates σ from the residuals, σ̂² = σ_s² χ²/dof, and takes its upper confidence
   limit σ_u² = σ_s² χ² / χ²_dof(1 − confidence): with probability ``confidence`` the
   true σ is below σ_u (never below what the data say: σ_u ≥ σ̂). ``confidence`` is
   0.975 by default so that the target holds in ≥ 95 % of campaigns despite the test
   being repeated after every measurement (see
   :class:`~kpi_calib_ros.core.campaigns.settings.CampaignSettings`);
3. predicts the TCP covariance (eq. 19) with σ_u, and stops when the statistic — the
   largest per-axis TCP std over the working poses — is ≤ the target. The largest, not
   the mean: a tolerance holds at every working pose and on every axis, and the worst
   one decides whether the cell may run;
4. otherwise picks as next pose the feasible candidate (joint limits, incidence,
   capsules, beam: :mod:`design_constraints`) that lowers the KPI criterion (eq. 24a)
   most, by the rank-3 Woodbury update of :mod:`design_exchange` with the Jacobians at
   the current estimate.

*Outliers.* Every re-identification applies the batch identification's outlier rule
(:func:`kpi_calib_ros.core.estimation.robust.robust_identify`: Bonferroni threshold on the distance
in robust σ̂, one point per round): an excluded measurement is named in the status and
left out of the fit, the χ² and the pure error, and its pose is measured again next
(a replicate that agrees with the fit says the first reading was a fault, one that
agrees with the excluded reading says the model misses there). Only then does the
lack-of-fit test below judge the model: one wild point is not a missing effect.

*Model adequacy.* A χ² test against the stated σ cannot tell an understated σ from an
effect the model lacks. When it rejects, the campaign measures ``replicates`` already
measured poses again (the ones that help the KPI most); their scatter is pure error,
free of any model. The classical lack-of-fit F test then compares the rest of the
residual with it. The campaign stops with "model inadequate: call ~/diagnose" when the
systematic part of the residual (per axis, rms) exceeds the target at level
``inadequacy_alpha``: F = (MS_lof − target²) / MS_pe > F_crit. A model that misses the
measured points systematically by more than the target cannot be trusted to place the
TCP within it, and more measurements do not shrink a bias. The level is small because
the test is repeated after every measurement.

*What a pose gives.* A measurement is a pose, and a pose gives every row the cell
declares (:attr:`~kpi_calib_ros.core.measurement.tracker.MeasurementModel.pose_channels`):
each reflector's point and each tracked body's rotation. The plan, the estimability and
the stop statistic count all of them, as the identification does; the pure error is the
scatter of each reflector's point over the replicates of a pose; the outlier rule judges
rows, and a pose with an excluded row is measured again.
"""
from __future__ import annotations

import dataclasses
import time
from typing import Sequence

import numpy as np

from kpi_calib_ros.core.campaigns.plan_order import inverse, nested_order, plan_ahead
from kpi_calib_ros.core.campaigns.settings import (
    MAX_MEASUREMENTS,
    MODEL_INADEQUATE,
    TARGET_MET,
    CampaignSettings,
    CampaignStatus,
)
from kpi_calib_ros.core.campaigns.statistics import lack_of_fit, pure_error, sigma_upper_limit
from kpi_calib_ros.core.design.cell import DesignCell
from kpi_calib_ros.core.design.criteria import DesignProblem, scales
from kpi_calib_ros.core.design.exchange import exchange
from kpi_calib_ros.core.errors import ConfigError, DataError
from kpi_calib_ros.core.estimation.estimability import result_estimability
from kpi_calib_ros.core.estimation.least_squares import CalibrationResult, identify
from kpi_calib_ros.core.estimation.plausibility import moved_beyond
from kpi_calib_ros.core.estimation.prior import Prior
from kpi_calib_ros.core.estimation.robust import (
    ExcludedMeasurement,
    Fit,
    OutlierSettings,
    RobustResult,
    robust_identify,
)
from kpi_calib_ros.core.measurement.data import Measurements
from kpi_calib_ros.core.measurement.replicates import SAME_POSE_TOLERANCE, pose_groups

__all__ = ['MAX_HORIZON', 'INITIAL_STARTS', 'NESTED_FACTOR', 'REPLICATE_EVERY',
           'SequentialCampaign']

# Look-ahead of the plan (poses): the next-pose step must stay below 1 s on two cores.
MAX_HORIZON = 30
# Random starts of the exchange algorithm for the initial design (its quality is the
# start of every prefix).
INITIAL_STARTS = 3
# Size of the batch design the initial design and the first planned poses are nested in,
# in multiples of the initial design's size.
NESTED_FACTOR = 3
# While replicates are due, one replicate after every REPLICATE_EVERY - 1 new poses.
REPLICATE_EVERY = 3


class SequentialCampaign:
    """The loop of the module text over a fixed set of feasible candidates.

    Parameters
    ----------
    cell : DesignCell
    problem : DesignProblem
        Identifiable parameters and KPI Jacobians at the nominal parameters
        (``DesignContext.problem``).
    candidates : (c, n) ndarray
        Feasible configurations (``DesignContext.candidates.configurations``).
    settings : CampaignSettings
    free : list of str, optional
        Parameters the identification may free (the model level); all by default.
    rng : numpy.random.Generator
        For the exchange algorithm of the initial design.
    prior : Prior, optional
        What is known before the campaign (e.g. the calibration of the stations measured
        before, its placements marginalised): in every fit, in the initial design's size
        and the plan (``problem`` built with it, ``problem.prior_information``), and the
        start of the fits at ``start`` (its values).
    """

    def __init__(self, cell: DesignCell, problem: DesignProblem, candidates: np.ndarray,
                 settings: CampaignSettings, rng: np.random.Generator,
                 free: list[str] | None = None, prior: Prior | None = None,
                 start: np.ndarray | None = None) -> None:
        sigma = np.asarray(cell.sigma, float)
        if not np.allclose(sigma, sigma[0]):
            raise ConfigError('noise.sigma', 'the sequential campaign estimates one σ for '
                              f'all axes; give a scalar σ (got {sigma.tolist()})')
        self.cell, self.problem, self.settings = cell, problem, settings
        self.candidates = np.asarray(candidates, float)
        self.free = free
        self.sigma = float(sigma[0])
        self.rng = rng
        self.q = np.zeros((0, cell.robot.n_joints))     # one row per measured pose
        self.rows = Measurements(q=self.q, eta=np.zeros((0, 3)),  # every row measured
                                 reflector=np.zeros(0, int), stamps_ns=np.zeros(0, np.int64))
        self._row_pose = np.zeros(0, int)  # the pose (index in q) of every row
        self.used: list[int] = []   # candidate index of every measurement (-1: other pose)
        self.result: CalibrationResult | None = None
        self.robust: RobustResult | None = None
        self.status: CampaignStatus | None = None
        self._suspects: list[int] = []  # excluded measurements, to be measured again
        self.prior = prior
        self._start = (cell.model.params.nominal if start is None
                       else np.asarray(start, float)).copy()
        self._p = self._start.copy()
        self._replicating = False
        self._statistic = float('inf')
        self._last_plan: list[int] = []

    @property
    def start(self) -> np.ndarray:
        """Return where the first fit starts and the initial design is linearised.

        The prior's values, or the nominal parameters.
        """
        return self._start.copy()

    # ------------------------------------------------------------------ initial design
    def initial_design(self) -> np.ndarray:
        """Candidate indices of the initial design, n0 + ``initial_margin`` poses.

        n0 is the smallest size whose KPI exchange design has a nonsingular information and
        makes every working pose's TCP estimable.

        The poses are not the exchange design of that size: they are the first ones of
        the :func:`nested_order` of the best of ``INITIAL_STARTS`` KPI exchange designs
        of ``NESTED_FACTOR`` times that size, and the rest of that order is the start of
        the plan. A design optimal for its own small size is a poor subset of larger
        designs, and no choice of the later poses repairs it until the campaign has
        about three times as many poses (bench/results/sequential_campaign.md).
        """
        rows = self.problem.rows(self.cell.model, self.candidates)
        loss = self.problem.loss('kpi')
        base = self.problem.prior_information
        first = 1 if base is not None else int(np.ceil(self.problem.k / 3))
        for n in range(first, len(self.candidates)):
            try:
                res = exchange(rows, n, loss, self.rng, base=base)
            except ValueError:
                continue
            if np.isfinite(res.loss) and self._estimable(self.candidates[res.selected]):
                break
        else:
            raise ConfigError('design.candidates', 'no candidate subset makes the TCP '
                              'estimable; check the working poses and the joint ranges')
        cap = min(len(self.candidates), self.settings.max_measurements)
        size = n + self.settings.initial_margin
        self._check_cap(size, n)
        big = min(NESTED_FACTOR * size, cap)
        best = res if big == n else None
        for _ in range(INITIAL_STARTS if best is None else 0):
            trial = exchange(rows, big, loss, self.rng, base=base)
            if best is None or trial.loss < best.loss:
                best = trial
        assert best is not None
        order = nested_order(rows, np.asarray(best.selected, int), loss, n, base)
        while size < len(order) and not self._estimable(self.candidates[order[:size]]):
            size += 1
        self._check_cap(size, n)
        self._last_plan = [int(i) for i in order[size:]]
        return order[:size]

    def _check_cap(self, size: int, smallest: int) -> None:
        """Raise a ConfigError when the campaign may not measure even its initial design.

        The error names the cap and the initial design's size.
        """
        s = self.settings
        if size > s.max_measurements or size > len(self.candidates):
            limit = ('max_measurements', s.max_measurements) if size > s.max_measurements \
                else ('design.candidates', len(self.candidates))
            raise ConfigError(limit[0], f'{limit[1]} is below the initial design of {size} '
                              f'poses (the smallest KPI design that determines every '
                              f'identifiable parameter and the TCP has {smallest}, + '
                              f'initial_margin {s.initial_margin}); give at least {size}')

    def match_candidates(self, q: np.ndarray,
                         tolerance: float = SAME_POSE_TOLERANCE) -> np.ndarray:
        """Candidate index (N,) of each measured pose ``q`` (N, n).

        The candidate within ``tolerance`` (rad, m) on every joint, -1 if none (a robot that
        stopped off the planned pose).
        """
        out = np.full(len(q), -1)
        for i, row in enumerate(np.atleast_2d(q)):
            dist = np.max(np.abs(self.candidates - row), axis=1)
            j = int(np.argmin(dist))
            if dist[j] <= tolerance:
                out[i] = j
        return out

    @property
    def eta(self) -> np.ndarray:
        """Every measured row (m, tracker frame; zero on rotation rows), :attr:`rows`."""
        return self.rows.eta

    @property
    def stamps(self) -> np.ndarray:
        """Stamp of every measured row (ns; -1: none), :attr:`rows`."""
        return np.asarray(self.rows.stamps_ns, np.int64)

    def _estimable(self, q: np.ndarray) -> bool:
        model = self.cell.model
        rows = model.pose_measurements(self._p, q)  # every row of each pose
        return result_estimability(model, rows.q, self.cell.sigma, self._p,
                                   self.cell.q_work, self.cell.working_pose_names,
                                   free=self.free, reflector=rows.reflector,
                                   rotation=rows.rotation, prior=self.prior,
                                   tau_work=self.cell.tau_work).all_estimable

    # ---------------------------------------------------------------------- the loop
    def add(self, q: np.ndarray, eta: np.ndarray,
            candidate: int | Sequence[int] | np.ndarray = -1,
            reflector: np.ndarray | None = None,
            rotation: np.ndarray | None = None,
            stamps_ns: Sequence[int] | np.ndarray | None = None) -> CampaignStatus:
        """Add measurements (rows q (m, n), eta (m, 3) tracker frame, m) and update the plan.

        As :class:`~kpi_calib_ros.core.measurement.data.Measurements`: ``reflector`` (m,) the
        row channel of each row (None: reflector 0 throughout) and ``rotation`` (m, 3, 3)
        the measured rotations of rotation rows. A pose is the consecutive rows with the
        same ``q`` and no channel twice (each reflector's point, each tracked body's
        rotation). ``candidate`` gives the candidate index of each pose (-1: found by
        :meth:`match_candidates`); a measured candidate is not proposed again except as
        a replicate. ``stamps_ns`` (m,) name the rows the outlier rule excludes.

        Raises
        ------
        DataError
            Too few measurements for the identifiable parameters (measure the whole
            initial design first).
        """
        start = time.perf_counter()
        q, eta = np.atleast_2d(np.asarray(q, float)), np.atleast_2d(np.asarray(eta, float))
        if q.shape[1] != self.cell.robot.n_joints or eta.shape != (len(q), 3):
            raise ValueError(f'q {q.shape} and eta {eta.shape} do not fit '
                             f'{self.cell.robot.n_joints} joints')
        stamps = (np.full(len(q), -1, np.int64) if stamps_ns is None
                  else np.asarray(stamps_ns, np.int64).reshape(len(q)))
        model = self.cell.model
        channel = (np.zeros(len(q), int) if reflector is None
                   else np.asarray(reflector, int).reshape(len(q)))
        bad = sorted(set(channel.tolist()) - set(model.pose_channels))
        if bad or (rotation is None and np.any(channel >= model.n_reflectors)):
            raise ValueError(f'reflector: row channels must be among {model.pose_channels} '
                             f'(rotation rows with their rotation=), got {bad or "no rotation"}')
        rows = Measurements(q=q, eta=eta, reflector=channel, stamps_ns=stamps,
                            rotation=None if rotation is None else np.asarray(rotation, float))
        starts = _pose_starts(q, channel)
        poses = q[starts]
        first = len(self.q)
        self._row_pose = np.concatenate([
            self._row_pose, first + np.searchsorted(starts, np.arange(len(q)), side='right') - 1])
        self.q = np.vstack([self.q, poses])
        self.rows = _concatenate(self.rows, rows)
        index = np.broadcast_to(np.asarray(candidate, int), (len(poses),))
        index = np.where(index >= 0, index, self.match_candidates(poses))
        self.used.extend(int(i) for i in index)
        robust = self._robust_fit()
        res = robust.result
        kept = np.asarray(robust.kept, bool)
        self.robust, self.result, self._p = robust, res, res.values.copy()
        s = self.settings
        self._suspects = [e.index for e in robust.excluded]
        if res.p_value < s.adequacy_alpha and self._pure_error(kept, np.ones(3))[1] == 0:
            # χ² rejects before any replicate: the first one is the pose whose point
            # stands out most (studentized), so a fault is found before a misfit is judged.
            self._suspects.append(self._most_suspect(kept))
        sigma_hat = self.sigma * np.sqrt(res.chi2 / res.dof) if res.dof > 0 else float('inf')
        sigma_up = sigma_upper_limit(res.chi2, res.dof, self.sigma, s.confidence)
        scale = (sigma_up / self.sigma) ** 2
        tcp_std = np.sqrt(np.diagonal(res.tcp_covariance, axis1=1, axis2=2) * scale)
        statistic = float(np.max(tcp_std)) if np.all(np.isfinite(tcp_std)) else float('inf')
        if res.p_value < s.adequacy_alpha:
            self._replicating = True
        elif robust.excluded:
            # The rejection was the excluded faults': the rest fits as a clean campaign's
            # does, which takes no replicates (and runs no lack-of-fit test on few).
            self._replicating = False
        ss_pe, dof_pe = self._pure_error(kept, np.full(3, 1.0 / self.sigma))
        lof = lack_of_fit(res.chi2, res.dof, ss_pe, dof_pe, s.target_std / self.sigma,
                          s.inadequacy_alpha)
        if lof:
            lof['bias_rms_m'] = lof.pop('bias_rms_sigma') * self.sigma
            lof['sigma_pure_error_m'] = lof.pop('sigma_pure_error_sigma') * self.sigma
        reason = ''
        if res.converged and statistic <= s.target_std:
            reason = TARGET_MET
        elif lof.get('rejects', 0.0) > 0:
            reason = MODEL_INADEQUATE
        elif len(self.q) >= s.max_measurements:
            reason = MAX_MEASUREMENTS
        self._statistic = statistic
        plan, plan_index = ((np.zeros((0, self.cell.robot.n_joints)), np.zeros(0, int))
                            if reason else self._plan(dof_pe))
        excluded = tuple(
            {'measurement': int(e.index),
             'stamp_ns': int(self.stamps[e.index]) if self.stamps[e.index] >= 0 else None,
             'distance_m': float(e.distance_m), 'reason': e.reason}
            for e in robust.excluded)
        self.status = CampaignStatus(
            measurements=len(self.q), tcp_std=tcp_std, statistic=statistic,
            target_std=s.target_std, sigma_stated=self.sigma, sigma_hat=float(sigma_hat),
            sigma_upper=sigma_up, chi2=res.chi2, dof=res.dof, p_value=res.p_value,
            lack_of_fit=lof, stop_reason=reason, next_configurations=plan,
            next_candidates=plan_index,
            step_seconds=time.perf_counter() - start, excluded=excluded,
            confidence=s.confidence)
        return self.status

    def _robust_fit(self) -> RobustResult:
        """Identify with the batch outlier rule (warm start).

        More outliers than the rule may exclude is no longer a few faults: every point is kept,
        and the lack-of-fit test judges the model.
        """
        cell = self.cell
        # The warm start, unless a point since excluded threw it beyond the tolerances of
        # a robot (a 50 mm fault moved a wrist placement 0.93 m and a joint zero 7.6 rad,
        # never to come back, and every later plan and the final calibration rested on it):
        # then from where the campaign started.
        warm = self._p if not moved_beyond(cell.model, self._p, self._start) \
            else self._start

        def fit(data: Measurements, p0: np.ndarray | None = None,
                point_weights: np.ndarray | None = None) -> CalibrationResult:
            return identify(cell.model, data, cell.sigma, cell.q_work,
                            list(cell.working_pose_names),
                            p0=warm if p0 is None else p0, free=self.free,
                            identifiability_method=cell.identification_method,
                            priority=list(cell.identification_priority) or None,
                            point_weights=point_weights, prior=self.prior)
        data = self.rows
        try:
            robust = robust_identify(cell.model, data, cell.sigma, fit)
        except DataError:
            return robust_identify(cell.model, data, cell.sigma, fit,
                                   outliers=OutlierSettings(exclude=False))
        if robust.result.p_value >= self.settings.adequacy_alpha:
            return robust
        return self._replicate_fault(data, robust, fit)

    def _replicate_fault(self, data: Measurements, robust: RobustResult,
                         fit: Fit) -> RobustResult:
        """Judge a pose measured more than once whose readings disagree.

        The reading whose removal lets the fit pass the χ² test is a fault (the replicate agrees
        with the model, the first reading does not); a misfit fails with either removed, so
        nothing is excluded and the lack-of-fit test judges the model.
        """
        kept = np.asarray(robust.kept, bool)
        labels = self._replicate_labels()
        best: tuple[float, int, RobustResult] | None = None
        for g in np.unique(labels[kept]):
            members = np.flatnonzero((labels == g) & kept)
            if len(members) < 2:
                continue
            for i in members:
                keep = kept.copy()
                keep[i] = False
                trial = robust_identify(self.cell.model, data.subset(keep), self.cell.sigma,
                                        fit, outliers=OutlierSettings(exclude=False))
                if best is None or trial.result.chi2 < best[0]:
                    best = (trial.result.chi2, int(i), trial)
        if best is None or best[2].result.p_value < self.settings.adequacy_alpha:
            return robust
        _, fault, trial = best
        index = np.flatnonzero(kept & (np.arange(len(kept)) != fault))
        new_kept = np.zeros(len(kept), bool)
        new_kept[index] = np.asarray(trial.kept, bool)
        one = self.rows.subset(np.arange(fault, fault + 1))
        predicted = self.cell.model.predict(trial.result.values, one.q, None, one.reflector,
                                            one.rotation)[0]
        distance = float(np.linalg.norm(self.eta[fault] - predicted))
        stamp = int(self.stamps[fault]) if self.stamps[fault] >= 0 else None
        fault_entry = ExcludedMeasurement(
            fault, stamp, distance, distance / self.sigma,
            'fault: its pose measured again agrees with the model, this reading does not '
            f'(without it chi2 p = {trial.result.p_value:.3g})')
        return dataclasses.replace(trial, kept=new_kept,
                                   excluded=tuple(robust.excluded) + (fault_entry,))

    def _most_suspect(self, kept: np.ndarray) -> int:
        """Return the kept measurement with the largest studentized distance to the fit.

        The distance is r_iᵀ(I − H_ii)⁻¹r_i with H the hat matrix of the weighted Jacobian: a
        point the fit is drawn towards (high leverage) counts its residual accordingly.
        """
        model, res = self.cell.model, self.result
        assert res is not None
        idx = model.params.indices(list(res.estimated))
        rows = self.rows.subset(kept)
        q = rows.q
        pred, jac = model.jacobian(self._p, rows.q, None, rows.reflector, rows.rotation)
        r = rows.eta - pred
        j = jac[:, :, idx]
        flat = j.reshape(-1, len(idx))
        inv = np.linalg.pinv(flat.T @ flat)
        score = np.full(len(q), -np.inf)
        for i in range(len(q)):
            h = j[i] @ inv @ j[i].T
            try:
                score[i] = float(r[i] @ np.linalg.solve(np.eye(3) - h, r[i]))
            except np.linalg.LinAlgError:
                continue
        return int(np.flatnonzero(kept)[int(np.argmax(score))])

    def _plan(self, dof_pe: int) -> tuple[np.ndarray, np.ndarray]:
        """Return the plan, next pose first, and the candidate index of each (-1: not a candidate).

        First the pose of a measurement the outlier rule excluded, measured once only (a
        replicate tells a fault from a misfit); while χ² has rejected and the pure-error dof are
        short, a replicate of the measured pose that helps the KPI most, every third pose; then
        the candidates :func:`plan_ahead` chooses in :meth:`_estimate_problem`.
        """
        model = self.cell.model
        problem = self._estimate_problem()
        loss = problem.loss('kpi')
        info = problem.information(problem.rows(model, self._kept_q()))
        rows = problem.rows(model, self.candidates)
        exclude = np.array(sorted({u for u in self.used if u >= 0}), int)
        planned = plan_ahead(rows, info, self._horizon(), loss, exclude,
                             start_plan=self._last_plan)
        self._last_plan = [int(i) for i in planned]
        q_plan, index = self.candidates[planned], planned
        labels = pose_groups(self.q)
        counts = np.bincount(labels, minlength=len(labels))[labels]
        # Excluded rows -> their poses, measured once so far.
        suspects = [p for p in dict.fromkeys(int(self._row_pose[i]) for i in self._suspects)
                    if counts[p] == 1]
        if suspects:
            pick = suspects[0]
            q_plan = np.vstack([self.q[pick], q_plan])
            index = np.concatenate([[self.used[pick]], index])
        # A replicate after every two new poses: a block of them right after the χ²
        # rejection spends several poses in a row on little KPI and is the worst prefix.
        elif (self._replicating and dof_pe < 3 * self.settings.replicates
                and np.all(counts[-REPLICATE_EVERY + 1:] == 1)):
            once = np.flatnonzero(counts == 1)
            if len(once):
                gain = loss.delta(inverse(info), problem.rows(model, self.q[once]), +1.0)
                pick = int(once[int(np.argmin(gain))])
                q_plan = np.vstack([self.q[pick], q_plan])
                index = np.concatenate([[self.used[pick]], index])
        return q_plan, np.asarray(index, int)

    def _kept_q(self) -> np.ndarray:
        """Joint values of the poses whose every row the last fit kept.

        A pose with an excluded row is measured again, and its information counted then.
        """
        if self.robust is None:
            return self.q
        lost = np.unique(self._row_pose[~np.asarray(self.robust.kept, bool)])
        return np.delete(self.q, lost, axis=0)

    def _pure_error(self, kept: np.ndarray, weight: np.ndarray) -> tuple[float, int]:
        """:func:`pure_error` of the kept point rows, per reflector."""
        channel = np.asarray(self.rows.reflector)
        points = kept & (channel < self.cell.model.n_reflectors)
        return pure_error(self.rows.q[points], self.rows.eta[points], weight, channel[points])

    def _replicate_labels(self) -> np.ndarray:
        """(rows,) one label per reflector (or rotation channel) and pose measured again.

        The rows of one reflector (or rotation channel) at one pose measured again share a
        label: they are replicates of each other, not of the other reflectors.
        """
        channel = np.asarray(self.rows.reflector)
        return pose_groups(self.rows.q) * (int(np.max(channel, initial=0)) + 1) + channel

    def _estimate_problem(self) -> DesignProblem:
        """Return the KPI design problem at the current estimate.

        Its parameters are those the identification estimated there. The design problem of the
        batch design has the parameters identifiable at the nominal geometry; a real robot's (J2
        and J3 not exactly parallel) makes more of them identifiable, the calibration estimates
        them, and their variance is part of the statistic the campaign stops on (the batch KPI
        designs calibrate to an 8-9 % larger TCP std than the design problem says,
        bench/results/sequential_campaign.md).
        """
        model = self.cell.model
        assert self.result is not None
        idx = model.params.indices(list(self.result.estimated))
        weight = self.problem.weight
        _, jac = model.pose_jacobian(self._p, self._kept_q())  # every row of each pose
        column_scale, physical_scale = scales(jac[:, :, idx],
                                              np.tile(weight, model.rows_per_pose))
        kpi = model.jacobian(self._p, self.cell.q_work, self.cell.tau_work)[1][:, :, idx]
        prior_info = None
        if self.prior is not None:  # in the scaled columns, as build_problem has it
            scaled = self.prior.rows(model.params)[0][:, idx] * column_scale
            prior_info = scaled.T @ scaled
        return DesignProblem(tuple(self.result.estimated), idx, self._p.copy(), weight,
                             column_scale, physical_scale, kpi, self.problem.kpi_weights,
                             prior_info)

    def _horizon(self) -> int:
        """Poses still needed, from the std falling as 1/√N (at least 1)."""
        status_stat = self._statistic
        n = len(self.q)
        left = self.settings.max_measurements - n
        if not np.isfinite(status_stat):
            return max(1, min(left, n))
        need = n * (status_stat / self.settings.target_std) ** 2 - n
        return int(np.clip(np.ceil(need), 1, max(1, min(left, MAX_HORIZON))))


def _pose_starts(q: np.ndarray, channel: np.ndarray) -> np.ndarray:
    """First row (indices) of each pose among rows ``q`` (m, n) with row channels ``channel`` (m,).

    A pose ends where ``q`` changes or a channel comes again.
    """
    starts: list[int] = []
    seen: set[int] = set()
    for i in range(len(q)):
        if i == 0 or not np.array_equal(q[i], q[i - 1]) or int(channel[i]) in seen:
            starts.append(i)
            seen = set()
        seen.add(int(channel[i]))
    return np.array(starts, int)


def _concatenate(a: Measurements, b: Measurements) -> Measurements:
    """Return the rows of ``a`` then those of ``b``.

    Rotations are identity where one has none, stamps -1 and stated σ NaN (the cell's) where one
    has none.
    """
    def rotations(m: Measurements) -> np.ndarray:
        return (np.broadcast_to(np.eye(3), (len(m), 3, 3)) if m.rotation is None
                else np.asarray(m.rotation))
    rotation = (None if a.rotation is None and b.rotation is None
                else np.concatenate([rotations(a), rotations(b)]))

    def sigmas(m: Measurements) -> np.ndarray:
        return np.full((len(m), 3), np.nan) if m.sigma is None else np.asarray(m.sigma)
    sigma = (None if a.sigma is None and b.sigma is None
             else np.concatenate([sigmas(a), sigmas(b)]))
    return Measurements(q=np.vstack([a.q, b.q]), eta=np.vstack([a.eta, b.eta]),
                        reflector=np.concatenate([np.zeros(len(a), int) if a.reflector is None
                                                  else a.reflector,
                                                  np.zeros(len(b), int) if b.reflector is None
                                                  else b.reflector]),
                        rotation=rotation, sigma=sigma,
                        stamps_ns=np.concatenate([_stamps(a), _stamps(b)]))


def _stamps(m: Measurements) -> np.ndarray:
    return (np.full(len(m), -1, np.int64) if m.stamps_ns is None
            else np.asarray(m.stamps_ns, np.int64).reshape(len(m)))

