"""Sequential campaign for a cell: the ``kpi-calib campaign`` command and its simulation.

Builds the feasible candidates and the KPI design problem of the cell (the batch
design's :func:`~kpi_calib_ros.core.design.optimum.design_context`, so every constraint of
the batch design holds), runs :class:`~kpi_calib_ros.core.campaigns.sequential.SequentialCampaign`
against a simulated true robot (the cell's ``simulation.hidden_effects`` included),
and compares it with fixed KPI designs of every size.
"""
from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Sequence

import numpy as np

from kpi_calib_ros.app.calibration_document import (
    CellCalibration,
    add_robust_sections,
    calibration_document,
    plausibility_gate,
)
from kpi_calib_ros.app.cell_model import CellModel, build_cell_model
from kpi_calib_ros.app.simulate import truth_cell_model
from kpi_calib_ros.core.acquisition.outcomes import PairingResult
from kpi_calib_ros.core.campaigns.sequential import SequentialCampaign
from kpi_calib_ros.core.campaigns.settings import (
    TARGET_MET,
    CampaignSettings,
    CampaignStatus,
    SimulatedRun,
)
from kpi_calib_ros.core.design.cell import DesignCell
from kpi_calib_ros.core.design.exchange import exchange
from kpi_calib_ros.core.design.optimum import DesignContext, design_context
from kpi_calib_ros.core.diagnosis.model_selection import ModelChoice, level_free
from kpi_calib_ros.core.errors import ConfigError, DataError
from kpi_calib_ros.core.estimation.estimability import result_estimability
from kpi_calib_ros.core.estimation.prior import Prior
from kpi_calib_ros.core.measurement.payload import payload_range
from kpi_calib_ros.core.measurement.weighting import row_torques
from kpi_calib_ros.core.simulation import simulate_pose_measurements, true_parameters
from kpi_calib_ros.io.campaign_io import plot_campaign, write_campaign, write_plan
from kpi_calib_ros.io.cell import load_cell

# Candidates of a campaign: fewer than a batch design's, so that re-evaluating every
# candidate's Jacobian at the current estimate fits the 1 s next-pose budget.
CAMPAIGN_CANDIDATES = 2000


def campaign_free(cm: CellModel) -> list[str]:
    """Free parameters of the cell's model level (``auto``: the full geometric model)."""
    level = cm.cell.identification.model
    return level_free(cm.model.params, 'geometric' if level == 'auto' else level,
                      len(cm.geometric))


def campaign_context(cm: CellModel, seed: int,
                     candidates: int = CAMPAIGN_CANDIDATES, prior: Prior | None = None,
                     p: np.ndarray | None = None, free: Sequence[str] | None = None
                     ) -> tuple[DesignCell, DesignContext]:
    """The cell's design problem and ``candidates`` feasible configurations; with ``prior``
    linearised at ``p`` over the parameters ``free`` (as a design with a prior)."""
    cell = cm.design_cell()
    settings = dataclasses.replace(cm.design_settings, candidates=candidates)
    return cell, design_context(cell, np.random.default_rng(seed), settings, prior=prior,
                                p=p, free=None if free is None else list(free))


def new_campaign(cm: CellModel, cell: DesignCell, ctx: DesignContext,
                 settings: CampaignSettings, seed: int, prior: Prior | None = None,
                 start: np.ndarray | None = None,
                 free: Sequence[str] | None = None) -> SequentialCampaign:
    """A sequential campaign on the cell; every pose is measured with every row the cell
    declares (each reflector's point, each tracked body's rotation). ``prior``, ``start``
    and ``free``: what is known before it (:class:`SequentialCampaign`), its values and the
    parameters its fits free (default: the cell's model level)."""
    return SequentialCampaign(cell, ctx.problem, ctx.candidates.configurations, settings,
                              np.random.default_rng(seed),
                              free=campaign_free(cm) if free is None else list(free),
                              prior=prior, start=start)


def campaign_calibration(cm: CellModel, campaign: SequentialCampaign,
                         pairing: PairingResult | None = None) -> tuple[CellCalibration, dict]:
    """The calibration a stopped campaign publishes: its own last fit (outliers excluded
    by the batch rule), with every std and covariance at the σ the campaign stopped on —
    the upper confidence limit σ_u, i.e. scaled by (σ_u/σ)² — so the TCP std it states
    are the campaign's ``tcp_std`` and its largest is the stop statistic. The document's
    ``campaign`` section says which σ and whether the target was met.

    Raises
    ------
    DataError
        Before the campaign's first step.
    """
    status, robust = campaign.status, campaign.robust
    if status is None or robust is None:
        raise DataError('the campaign has no measurement yet: nothing to calibrate')
    scale = (status.sigma_upper / status.sigma_stated) ** 2
    base = robust.result
    result = dataclasses.replace(base, std=base.std * np.sqrt(scale),
                                 covariance=base.covariance * scale,
                                 tcp_covariance=base.tcp_covariance * scale,
                                 covariance_scale=scale)
    # The rows the last fit kept (each reflector's point, each body's rotation: a pose
    # gives several rows), judged as identify judges its rows.
    rows = campaign.rows.subset(np.asarray(robust.kept, bool))
    free = tuple(campaign.free or cm.model.params.names)
    est = result_estimability(cm.model, rows.q, cm.cell.sigma, result.values,
                              cm.q_work, cm.working_pose_names, list(free),
                              reflector=rows.reflector, rotation=rows.rotation,
                              covariates=rows.covariates, tau=rows.tau,
                              tau_work=cm.tau_work)
    level = cm.cell.identification.model
    choice = ModelChoice(level='geometric' if level == 'auto' else level, requested=level,
                         predicted_rms_m={}, cv_rms_m={}, folds=0,
                         reason='the sequential campaign\'s model (no model selection)')
    # The campaign fits from the cell's placement (it plans from it): the reference.
    implausible = plausibility_gate(cm, result, cm.model.params.nominal,
                                    np.atleast_2d(rows.q), row_torques(cm.model, rows),
                                    rows.reflector, free, rows.covariates)
    cal = CellCalibration(result, dataclasses.replace(robust, result=result), choice, est, free,
                          cell=cm, implausible=implausible,
                          payload_range_kg=payload_range(rows.covariates, len(rows),
                                                         cm.robot.payload.mass))
    doc = add_robust_sections(calibration_document(cm, result, pairing), cal)
    if 'identified_at_ns' not in doc and len(campaign.stamps) and campaign.stamps.min() >= 0:
        doc['identified_at_ns'] = int(campaign.stamps.max())  # when the robot was measured
    basis = (f'scaled to the upper {100 * status.confidence:g} % confidence limit of sigma '
             f'({status.sigma_upper * 1e6:.3g} um, stated {status.sigma_stated * 1e6:.3g} um): '
             'the sigma the sequential campaign stopped on')
    doc['precision']['basis'] = basis
    # The covariance is scaled for confidence, not for noise: new points scatter by the noise
    # the fit showed (its own scale, 1 for an adequate model), which validate and --prior read.
    doc['precision']['noise_scale'] = float(base.covariance_scale)
    doc['campaign'] = {'statistic_m': float(status.statistic),
                       'statistic': 'largest per-axis TCP std over the working poses',
                       'sigma': basis, 'sigma_upper_m': float(status.sigma_upper),
                       'target_tcp_std_m': float(status.target_std),
                       'target_met': status.stop_reason == TARGET_MET,
                       'stop_reason': status.stop_reason or 'running',
                       'measurements': int(status.measurements)}
    return cal, doc


def simulate_sequential(campaign: SequentialCampaign, truth: CellModel, p_true: np.ndarray,
                        sigma_true: float, rng: np.random.Generator) -> SimulatedRun:
    """Run ``campaign`` to its stop against the true robot ``truth`` / ``p_true`` with
    tracker noise ``sigma_true`` (m per axis; a tracked body's orientation with the
    cell's ``noise.sigma_rotation``)."""
    initial = campaign.initial_design()
    q = campaign.candidates[initial]
    sigma_rotation = float(truth.cell.sigma_rotation or 0.0)

    def add(qq: np.ndarray, candidates: np.ndarray) -> CampaignStatus:
        rows = simulate_pose_measurements(truth.model, p_true, qq, sigma_true, sigma_rotation,
                                          rng)
        return campaign.add(rows.q, rows.eta, candidates, rows.reflector, rows.rotation)

    history = [add(q, initial)]
    while not history[-1].stopped:
        history.append(add(history[-1].next_configurations[:1],
                           history[-1].next_candidates[:1]))
    res = campaign.result
    assert res is not None
    tcp_true = truth.model.predict(p_true, truth.q_work, truth.tau_work)
    scale = (sigma_true / campaign.sigma) ** 2
    std_true = np.sqrt(np.diagonal(res.tcp_covariance, axis1=1, axis2=2) * scale)
    return SimulatedRun(tuple(history), campaign.q.copy(), np.array(campaign.used),
                        len(initial), tcp_true, res.tcp.copy(), std_true)


def fixed_curve(cell: DesignCell, ctx: DesignContext, sizes: list[int],
                seed: int) -> dict[int, tuple[float, float]]:
    """Batch KPI designs (exchange over the same candidates) of every size in ``sizes``:
    size -> (KPI criterion m², largest per-axis TCP std m), at the stated σ."""
    rows, problem = ctx.rows, ctx.problem
    loss = problem.loss('kpi')
    out = {}
    for n in sizes:
        res = exchange(rows, n, loss, np.random.default_rng(seed))
        tcp = problem.tcp_covariance(rows[res.selected])
        out[n] = (float(res.loss), float(np.sqrt(np.diagonal(tcp, axis1=1, axis2=2)).max()))
    return out


def run_campaign(cell_path: str | Path, target_std: float, out: str | Path,
                 simulate: bool = False, seed: int = 0, max_measurements: int = 200,
                 allow_code_effects: bool = False) -> int:
    """``kpi-calib campaign``: with ``simulate`` the whole loop against a simulated true
    robot (campaign.yaml, campaign_poses.yaml, campaign_tcp_std.png); without it the
    initial plan (initial_design.yaml) for a manual cell.

    Returns 0 when the target was met (or the plan written), 1 when the campaign
    stopped for another reason.
    """
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    cell_doc = load_cell(cell_path, allow_code_effects=allow_code_effects)
    cm = build_cell_model(cell_doc)
    settings = CampaignSettings(target_std=target_std, max_measurements=max_measurements)
    cell, ctx = campaign_context(cm, seed)
    campaign = new_campaign(cm, cell, ctx, settings, seed)
    if not simulate:
        initial = campaign.initial_design()
        q = cm.joint_coupling.to_controller(ctx.candidates.configurations[initial])
        path = write_plan(out / 'initial_design.yaml', cm.joint_names, q, settings)
        print(f'initial design: {len(q)} poses (smallest KPI design that determines every '
              f'identifiable parameter and the TCP, + {settings.initial_margin}); measure them, '
              'then add each next pose the node or this loop proposes')
        for i, row in enumerate(q):
            print(f'  {i + 1:3d}: ' + ' '.join(f'{v:+.4f}' for v in row))
        print(f'written: {path}')
        return 0
    truth, overrides = truth_cell_model(cell_doc)
    rng = np.random.default_rng(seed)
    p_true = true_parameters(truth.model.params, rng, overrides=overrides)
    run = simulate_sequential(campaign, truth, p_true, float(cm.cell.sigma[0]), rng)
    if len(run.configurations) > len(ctx.candidates.configurations):
        raise ConfigError('max_measurements', 'more measurements than candidates')
    sizes = sorted(set(range(run.initial, len(run.configurations) + 1,
                             max(1, (len(run.configurations) - run.initial) // 15))))
    curve = fixed_curve(cell, ctx, sizes, seed)
    final = run.final
    error = run.tcp_estimated - run.tcp_true
    written = write_campaign(out / 'campaign.yaml', run, cm.working_pose_names, curve)
    poses = write_plan(out / 'campaign_poses.yaml', cm.joint_names,
                       cm.joint_coupling.to_controller(run.configurations), settings)
    png = plot_campaign(out / 'campaign_tcp_std.png', run, curve, target_std)
    print(f'sequential campaign: {final.measurements} poses ({run.initial} initial), '
          f'stopped: {final.stop_reason}')
    print(f'  sigma: stated {final.sigma_stated * 1e6:.2f} um, estimated '
          f'{final.sigma_hat * 1e6:.2f} um, upper {100 * settings.confidence:.1f} % limit '
          f'{final.sigma_upper * 1e6:.2f} um')
    for name, std, err, std_true in zip(cm.working_pose_names, final.tcp_std, error,
                                        run.tcp_std_true):
        print(f'  {name}: predicted TCP std {np.round(std * 1e6, 2).tolist()} um '
              f'(target {target_std * 1e6:.2f} um), true error '
              f'{np.round(err * 1e6, 2).tolist()} um, std with the true sigma '
              f'{np.round(std_true * 1e6, 2).tolist()} um')
    times = [s.step_seconds for s in run.history[1:]]
    if times:
        print(f'  next-pose step: median {1e3 * float(np.median(times)):.0f} ms, max '
              f'{1e3 * max(times):.0f} ms')
    print(f'written: {written}, {poses}, {png}')
    return 0 if final.stop_reason == 'target met' else 1
