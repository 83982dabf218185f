"""Files of a sequential campaign: the plan, campaign.yaml and the TCP-std plot."""
from __future__ import annotations

from pathlib import Path
from typing import Any, Sequence

import matplotlib

matplotlib.use('Agg')
import matplotlib.pyplot as plt  # noqa: E402  (backend first)
import numpy as np  # noqa: E402
import yaml  # noqa: E402

from kpi_calib_ros.core.sequential import CampaignSettings, SimulatedRun  # noqa: E402
from kpi_calib_ros.io.results import write_atomic  # noqa: E402


def write_plan(path: str | Path, joint_names: Sequence[str], q: np.ndarray,
               settings: CampaignSettings) -> Path:
    """Poses as a design.yaml (``joint_names``, ``configurations``: controller values,
    rad), readable by ``kpi-calib simulate --poses``."""
    doc = {'joint_names': list(joint_names),
           'configurations': [[float(v) for v in row] for row in np.atleast_2d(q)],
           'criterion': 'kpi', 'campaign': 'sequential',
           'target_tcp_std_m': float(settings.target_std)}
    return write_atomic(path, yaml.safe_dump(doc, sort_keys=False))


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
    return write_atomic(path, yaml.safe_dump(doc, sort_keys=False))


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
