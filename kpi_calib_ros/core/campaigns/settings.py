"""Options of a sequential campaign, its status after each measurement and its stop reasons.

See :mod:`kpi_calib_ros.core.campaigns.sequential` for the campaign itself.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np

from kpi_calib_ros.core.errors import ConfigError

__all__ = ['TARGET_MET', 'MODEL_INADEQUATE', 'MAX_MEASUREMENTS', 'CampaignSettings',
           'CampaignStatus', 'SimulatedRun']

TARGET_MET = 'target met'
MODEL_INADEQUATE = 'model inadequate: call ~/diagnose'
MAX_MEASUREMENTS = 'max_measurements reached'
# The node's campaign stopped because the tracker station changed under it (its stations'
# measurements stay; ~/identify takes every station together).
STATION_CHANGED = 'station changed'


@dataclass(frozen=True)
class CampaignSettings:
    """Options of a sequential campaign.

    Attributes
    ----------
    target_std : float
        Target of the largest per-axis TCP std over the working poses (m).
    max_measurements : int
        Hard cap on the number of measurements.
    confidence : float
        One-sided confidence of the σ upper limit. The limit is checked after every
        measurement and the campaign stops at the first crossing, which favours runs
        whose σ̂ happens to be low: at 0.95 the target was met in 47 of 50 simulated
        campaigns (bench/results/sequential_campaign.md), so the default is 0.975 for
        "target met in ≥ 95 % of campaigns".
    initial_margin : int
        Poses added to the smallest estimable initial design (σ needs some dof).
    replicates : int
        Poses measured again for the pure-error estimate once χ² rejects.
    adequacy_alpha : float
        Level of the χ² test against the stated σ that triggers the replicates.
    inadequacy_alpha : float
        Level of the lack-of-fit test "bias > target" (repeated after every measurement).
    """

    target_std: float
    max_measurements: int = 200
    confidence: float = 0.975
    initial_margin: int = 2
    replicates: int = 5
    adequacy_alpha: float = 0.01
    inadequacy_alpha: float = 0.001

    def __post_init__(self) -> None:
        """Check target std, measurement cap, confidence, margin and replicates."""
        if not (np.isfinite(self.target_std) and self.target_std > 0):
            raise ConfigError('target_tcp_std', f'must be a positive length in m, got '
                              f'{self.target_std!r} (e.g. 1.0e-5 for 10 µm)')
        if self.max_measurements < 1:
            raise ConfigError('max_measurements', f'must be >= 1, got {self.max_measurements}')
        if not 0.5 <= self.confidence < 1.0:
            raise ConfigError('confidence', f'must be in [0.5, 1), got {self.confidence}')
        if self.initial_margin < 0 or self.replicates < 1:
            raise ConfigError('initial_margin', 'initial_margin must be >= 0 and replicates '
                              f'>= 1, got {self.initial_margin}, {self.replicates}')


@dataclass(frozen=True)
class CampaignStatus:
    """State of the campaign after the last measurement.

    Attributes
    ----------
    measurements : int
    tcp_std : (t, 3) ndarray
        Per-axis TCP std at each working pose from the conservative σ (m).
    statistic : float
        ``tcp_std.max()`` (m); inf before the TCP is estimable.
    target_std : float
    sigma_stated, sigma_hat, sigma_upper : float
        Stated σ, σ̂ from χ²/dof and its upper confidence limit (m, per axis).
    chi2, dof, p_value : float, int, float
        χ² against the stated σ.
    lack_of_fit : dict
        The F test once replicates exist (``pure_error_dof``, ``bias_rms_m``, ``p_value``).
    stop_reason : str
        '' while running; :data:`TARGET_MET`, :data:`MODEL_INADEQUATE` or
        :data:`MAX_MEASUREMENTS`.
    next_configurations : (m, n) ndarray
        The plan: next pose first (empty once stopped).
    next_candidates : (m,) ndarray of int
        Candidate index of each planned pose (-1: not a candidate).
    step_seconds : float
        Time of the last re-identification and next-pose choice.
    excluded : tuple of dict
        Measurements the outlier rule left out: ``measurement`` (0-based, campaign
        order), ``stamp_ns`` (None without stamps), ``distance_m``, ``reason``.
    confidence : float
        Confidence of ``sigma_upper``.
    """

    measurements: int
    tcp_std: np.ndarray
    statistic: float
    target_std: float
    sigma_stated: float
    sigma_hat: float
    sigma_upper: float
    chi2: float
    dof: int
    p_value: float
    lack_of_fit: dict
    stop_reason: str
    next_configurations: np.ndarray
    next_candidates: np.ndarray
    step_seconds: float
    excluded: tuple[dict, ...] = ()
    confidence: float = 0.975

    @property
    def stopped(self) -> bool:
        """Whether the campaign has a stop reason."""
        return bool(self.stop_reason)

    def to_dict(self, working_pose_names: Sequence[str]) -> dict:
        """YAML-ready form (``~/campaign_status``)."""
        return {
            'measurements': int(self.measurements), 'target_tcp_std_m': float(self.target_std),
            'statistic_m': float(self.statistic),
            'statistic': 'largest per-axis TCP std over the working poses, from the upper '
                         f'{100 * self.confidence:g} % confidence limit of sigma',
            'tcp_std_m': {n: [float(x) for x in row]
                          for n, row in zip(working_pose_names, self.tcp_std)},
            'sigma_m': {'stated': float(self.sigma_stated), 'estimated': float(self.sigma_hat),
                        'upper_limit': float(self.sigma_upper)},
            'chi2': float(self.chi2), 'dof': int(self.dof), 'p_value': float(self.p_value),
            'lack_of_fit': {k: float(v) for k, v in self.lack_of_fit.items()},
            'excluded': [dict(e) for e in self.excluded],
            'stop_reason': self.stop_reason or 'running',
            'next_poses': len(self.next_configurations),
            'step_seconds': float(self.step_seconds)}


@dataclass(frozen=True)
class SimulatedRun:
    """One simulated sequential campaign.

    Attributes
    ----------
    history : tuple of CampaignStatus
        Status after the initial design and after every further measurement.
    configurations : (N, n) ndarray
        Measured poses in order (URDF joint values, rad).
    candidates : (N,) ndarray
        Candidate index of each (-1: none).
    initial : int
        Size of the initial design.
    tcp_true, tcp_estimated : (t, 3) ndarray
        True and finally estimated KPI points (tracker frame, m).
    tcp_std_true : (t, 3) ndarray
        Per-axis TCP std of the final design with the TRUE σ (at the estimate), m.
    """

    history: tuple[CampaignStatus, ...]
    configurations: np.ndarray
    candidates: np.ndarray
    initial: int
    tcp_true: np.ndarray
    tcp_estimated: np.ndarray
    tcp_std_true: np.ndarray

    @property
    def final(self) -> CampaignStatus:
        """The last status of the campaign."""
        return self.history[-1]
