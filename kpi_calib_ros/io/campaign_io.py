"""Files of a sequential campaign: the plan, campaign.yaml, the TCP-std plot, the node's
campaign state (``campaign_state.yaml``: what a restarted node resumes from), and the
change-test plot of a work cycle (``identify --prior``)."""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Sequence

import matplotlib

matplotlib.use('Agg')
import matplotlib.pyplot as plt  # noqa: E402  (backend first)
import numpy as np  # noqa: E402

from kpi_calib_ros.core.campaigns.change_detection import ChangeTest  # noqa: E402
from kpi_calib_ros.core.campaigns.settings import CampaignSettings, SimulatedRun
from kpi_calib_ros.core.errors import ConfigError, DataError  # noqa: E402
from kpi_calib_ros.io.results import write_atomic  # noqa: E402
from kpi_calib_ros.io.yaml_bounded import dump_yaml, load_yaml_bounded

STATE_VERSION = 1
CHANGE_PLOT_FILE = 'change_test.png'


def write_plan(path: str | Path, joint_names: Sequence[str], q: np.ndarray,
               settings: CampaignSettings) -> Path:
    """Poses as a design.yaml (``joint_names``, ``configurations``: controller values,
    rad), readable by ``kpi-calib simulate --poses``."""
    doc = {'joint_names': list(joint_names),
           'configurations': [[float(v) for v in row] for row in np.atleast_2d(q)],
           'criterion': 'kpi', 'campaign': 'sequential',
           'target_tcp_std_m': float(settings.target_std)}
    return write_atomic(path, dump_yaml(doc))


def write_campaign(path: str | Path, run: SimulatedRun, working_pose_names: Sequence[str],
                   curve: dict[int, tuple[float, float]]) -> Path:
    """campaign.yaml: final status, predicted vs true TCP error, the history and the
    fixed designs it is compared with."""
    final = run.final
    error = run.tcp_estimated - run.tcp_true
    doc: dict[str, Any] = {
        'status': final.to_dict(working_pose_names),
        'initial_design': int(run.initial),
        'working_poses': [{'name': n, 'predicted_tcp_std_m': [float(x) for x in s],
                           'tcp_std_true_sigma_m': [float(x) for x in st],
                           'true_error_m': [float(x) for x in e]}
                          for n, s, st, e in zip(working_pose_names, final.tcp_std,
                                                 run.tcp_std_true, error)],
        'history': [{'measurements': int(s.measurements), 'statistic_m': float(s.statistic),
                     'sigma_upper_m': float(s.sigma_upper), 'p_value': float(s.p_value),
                     'step_seconds': float(s.step_seconds)} for s in run.history],
        'fixed_designs': [{'n': int(n), 'kpi_m2': v[0], 'max_tcp_std_m': v[1]}
                          for n, v in sorted(curve.items())],
    }
    return write_atomic(path, dump_yaml(doc))


def plot_campaign(path: str | Path, run: SimulatedRun,
                  curve: dict[int, tuple[float, float]], target_std: float) -> Path:
    """Largest per-axis TCP std against the number of measurements: the sequential
    campaign (conservative σ and stated σ) and fixed KPI designs of each size."""
    fig, ax = plt.subplots(figsize=(7, 4.5))
    n = [s.measurements for s in run.history]
    stat = [s.statistic for s in run.history]
    stated = [s.statistic * s.sigma_stated / s.sigma_upper for s in run.history]
    ax.plot(n, np.array(stat) * 1e6, 'o-', ms=3, label='sequential (upper-limit sigma)')
    ax.plot(n, np.array(stated) * 1e6, '-', alpha=0.6, label='sequential (stated sigma)')
    sizes = sorted(curve)
    ax.plot(sizes, [curve[k][1] * 1e6 for k in sizes], 's--', ms=3,
            label='fixed KPI designs (stated sigma)')
    ax.axhline(target_std * 1e6, color='k', lw=0.8, label='target')
    ax.set_xlabel('measurements')
    ax.set_ylabel('largest per-axis TCP std (um)')
    ax.set_yscale('log')
    ax.set_title(f'stopped after {run.final.measurements}: {run.final.stop_reason}')
    ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return Path(path)


@dataclass(frozen=True)
class CampaignState:
    """A node's sequential campaign as ``campaign_state.yaml`` keeps it.

    Attributes
    ----------
    settings : CampaignSettings
        Target and cap the campaign runs to.
    design_seed : int
        Seed of its initial design (with the cell it fixes the candidates and the plan).
    steps : tuple of tuple of int
        The stamps (ns) of the measurements each step added, in the order added; the
        campaign is rebuilt by adding them again step by step.
    status : dict
        The last ``~/campaign_status`` document ({} before the first step).
    station : str
        The tracker station it plans and identifies (its measurements only; '' : every
        measurement, a state written before stations).
    base_in_tracker : tuple of float
        The base pose [x, y, z, roll, pitch, yaw] (m, rad) it plans from, where a
        calibration of several stations placed the station; () : the cell file's.
    """

    settings: CampaignSettings
    design_seed: int
    steps: tuple[tuple[int, ...], ...] = ()
    status: dict = field(default_factory=dict)
    station: str = ''
    base_in_tracker: tuple[float, ...] = ()

    @property
    def stopped(self) -> bool:
        return self.status.get('stop_reason', 'running') != 'running'


def plot_change(path: str | Path, change: ChangeTest, top: int = 14) -> Path:
    """What moved since the last calibration: the likelihood ratio of each prior
    parameter's shift (the ``top`` largest) against the per-parameter threshold of the
    drift model, the moved ones red, each labelled with its shift ± std (mm or mrad)."""
    shifts = sorted(change.parameters, key=lambda m: -m.lr)[:top]
    moved = {m.name for m in change.moved}
    fig, ax = plt.subplots(figsize=(8, 0.28 * max(len(shifts), 4) + 1.4))
    names = [m.name for m in shifts][::-1]
    lr = np.maximum([m.lr for m in shifts][::-1], 1e-3)
    ax.barh(names, lr, color=['tab:red' if n in moved else 'tab:gray' for n in names])
    for y, m in enumerate(shifts[::-1]):
        ax.text(lr[y] * 1.1, y, f'{m.shift * 1e3:+.3g} ± {m.shift_std * 1e3:.2g}',
                va='center', fontsize=6)
    ax.axvline(change.lr_threshold, color='k', ls='--', lw=1,
               label=f'threshold (family-wise α = {change.alpha:g})')
    ax.set_xscale('log')
    ax.set_xlim(right=float(np.max(lr)) * 20 if len(lr) else 10)
    ax.set_xlabel('likelihood ratio of the shift since the prior (shift in mm or mrad)')
    ax.tick_params(axis='y', labelsize=7)
    verdict = ('consistent with the drift model' if change.consistent
               else 'CHANGE: not blended')
    ax.set_title(f'Work cycle against the last calibration: {verdict} '
                 f'(χ² {change.chi2:.1f} / {change.dof})', fontsize=9)
    ax.legend(fontsize=7, loc='lower right')
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return Path(path)


def write_campaign_state(path: str | Path, state: CampaignState) -> Path:
    """Write ``state`` atomically (a reader sees the old state or the new one)."""
    s = state.settings
    doc = {'version': STATE_VERSION, 'campaign': 'sequential',
           'settings': {'target_tcp_std_m': float(s.target_std),
                        'max_measurements': int(s.max_measurements),
                        'confidence': float(s.confidence), 'design_seed': int(state.design_seed)},
           'steps': [[int(t) for t in step] for step in state.steps],
           'status': state.status, 'station': state.station,
           'base_in_tracker': [float(v) for v in state.base_in_tracker]}
    return write_atomic(path, dump_yaml(doc))


def read_campaign_state(path: str | Path) -> CampaignState:
    """Read a campaign state; DataError names the file and the field, and the fix."""
    path = Path(path)
    fix = 'call ~/reset to archive it and start a new campaign'
    try:
        # Bounded like every document from outside: a damaged or hostile file in
        # data_dir is refused by name, never a hang or the node's memory.
        doc = load_yaml_bounded(path.read_text(), str(path), 'data_dir', fix)
    except (OSError, UnicodeDecodeError) as exc:
        raise DataError(f'{path}: not readable ({exc}); {fix}') from None
    except ConfigError as exc:
        raise DataError(str(exc)) from None
    if not isinstance(doc, dict) or doc.get('version') != STATE_VERSION:
        raise DataError(f'{path}: version must be {STATE_VERSION}; {fix}')
    try:
        raw = doc['settings']
        settings = CampaignSettings(target_std=float(raw['target_tcp_std_m']),
                                    max_measurements=int(raw['max_measurements']),
                                    confidence=float(raw['confidence']))
        seed = int(raw['design_seed'])
        steps = tuple(tuple(int(t) for t in step) for step in doc['steps'])
        status = doc['status']
        if not isinstance(status, dict):
            raise TypeError('status must be a mapping')
        station = doc.get('station') or ''
        if not isinstance(station, str):
            raise TypeError('station must be a name')
        base = tuple(float(v) for v in doc.get('base_in_tracker') or ())
        if base and (len(base) != 6 or not np.all(np.isfinite(base))):
            raise ValueError('base_in_tracker must be 6 finite numbers')
    except (KeyError, TypeError, ValueError) as exc:
        raise DataError(f'{path}: field {exc} missing or malformed; {fix}') from None
    return CampaignState(settings, seed, steps, status, station, base)
