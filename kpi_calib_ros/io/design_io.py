"""design.yaml (written and read back) and the design plots.

design.yaml holds ``joint_names`` and ``configurations`` (what ``kpi-calib
simulate --poses`` and a robot program read) plus the criterion, its value,
the predicted TCP standard deviation per working pose, constraint margins and
the independent verification. Two PNGs go next to it: the poses in the cell
(tracker, obstacles) and the 95 % TCP confidence ellipsoids of the heuristic
against the optimal design (Jost et al. 2017, Fig. 7).

This module writes what a design holds and builds none: it reads the fields of a
:class:`~kpi_calib_ros.core.design.optimum.DesignResult`, of its design problem and of the
obstacles through the shapes below (:class:`DesignRecord`, :class:`DrawnCell`,
:class:`CapsuleShape`, :class:`PlaneShape`), which those objects have.
"""
from __future__ import annotations

from pathlib import Path
from typing import Any, Mapping, Protocol, Sequence, runtime_checkable

import matplotlib

matplotlib.use('Agg')
import matplotlib.pyplot as plt  # noqa: E402  (backend first)
import numpy as np  # noqa: E402
import scipy.stats  # noqa: E402
import yaml  # noqa: E402

from kpi_calib_ros.core.errors import ConfigError  # noqa: E402
from kpi_calib_ros.core.model.robot import RobotModel  # noqa: E402
from kpi_calib_ros.io.results import write_atomic  # noqa: E402
from kpi_calib_ros.io.yaml_bounded import dump_yaml, read_yaml_file  # noqa: E402

CHI2_95_3D = float(scipy.stats.chi2.ppf(0.95, 3))


class Verification(Protocol):
    """The independent check of a design: ``ok`` and one line per violation."""

    @property
    def ok(self) -> bool: ...
    @property
    def violations(self) -> Sequence[str]: ...


class DesignRecord(Protocol):
    """The fields of a design that design.yaml, the plots and the summary show (SI units;
    see :class:`~kpi_calib_ros.core.design.optimum.DesignResult`)."""

    @property
    def configurations(self) -> np.ndarray: ...
    @property
    def joint_names(self) -> tuple[str, ...]: ...
    @property
    def criterion(self) -> str: ...
    @property
    def objective(self) -> float: ...
    @property
    def criteria(self) -> Mapping[str, float]: ...
    @property
    def exchange_objective(self) -> float: ...
    @property
    def tcp_covariance(self) -> np.ndarray: ...
    @property
    def tcp_std(self) -> np.ndarray: ...
    @property
    def working_pose_names(self) -> tuple[str, ...]: ...
    @property
    def parameter_names(self) -> tuple[str, ...]: ...
    @property
    def min_margin(self) -> np.ndarray: ...
    @property
    def incidence_deg(self) -> np.ndarray: ...
    @property
    def constraint_count(self) -> int: ...
    @property
    def verification(self) -> Verification: ...
    @property
    def flagged_pairs(self) -> Mapping[str, float]: ...
    @property
    def status(self) -> str: ...
    @property
    def candidates(self) -> int: ...
    @property
    def timings(self) -> Mapping[str, float]: ...


class DrawnCell(Protocol):
    """What the pose plot draws of a design problem (robot base frame, m)."""

    @property
    def robot(self) -> RobotModel: ...
    @property
    def tracker_in_base(self) -> np.ndarray: ...
    @property
    def q_work(self) -> np.ndarray: ...
    @property
    def working_pose_names(self) -> tuple[str, ...]: ...


@runtime_checkable
class CapsuleShape(Protocol):
    """An obstacle capsule: segment ``a``-``b`` swept by a ball of ``radius`` (m)."""

    @property
    def a(self) -> Sequence[float]: ...
    @property
    def b(self) -> Sequence[float]: ...
    @property
    def radius(self) -> float: ...


@runtime_checkable
class PlaneShape(Protocol):
    """An obstacle half-space bounded by the plane ``normal · x = offset`` (m)."""

    @property
    def normal(self) -> Sequence[float]: ...
    @property
    def offset(self) -> float: ...


class Obstacles(Protocol):
    """A scene's obstacles (capsules and half-spaces in the robot base frame)."""

    @property
    def obstacles(self) -> Sequence[Any]: ...


def design_to_dict(result: DesignRecord) -> dict[str, Any]:
    """YAML-ready description of a design (SI units: rad, m)."""
    unit = {'kpi': 'm^2', 'A': 'm^2', 'D': 'm^2', 'O1': '1', 'cond': '1', 'random': 'm^2'}
    return {
        'joint_names': list(result.joint_names),
        'configurations': [[float(v) for v in q] for q in result.configurations],
        'criterion': result.criterion,
        'objective': float(result.objective),
        'objective_unit': unit[result.criterion],
        'criteria': {k: float(v) for k, v in result.criteria.items()},
        'exchange_objective': float(result.exchange_objective),
        'working_poses': [
            {'name': name, 'tcp_std_m': [float(s) for s in std],
             'tcp_variance_mean_m2': float(np.trace(cov) / 3.0)}
            for name, std, cov in zip(result.working_pose_names, result.tcp_std,
                                      result.tcp_covariance)],
        'identified_parameters': list(result.parameter_names),
        'constraints': {
            'per_configuration': int(result.constraint_count),
            'min_margin_m': [float(m) for m in result.min_margin],
            'incidence_deg': [float(a) for a in result.incidence_deg],
        },
        'verification': {'ok': bool(result.verification.ok),
                         'violations': list(result.verification.violations)},
        'flagged_pairs': {k: float(v) for k, v in result.flagged_pairs.items()},
        'status': result.status,
        'candidates': int(result.candidates),
        'timings_s': {k: round(float(v), 3) for k, v in result.timings.items()},
    }


def write_design(path: str | Path, result: DesignRecord,
                 extra: dict[str, Any] | None = None) -> Path:
    """Write design.yaml atomically; ``extra`` adds top-level sections (e.g. ``geometry``)."""
    doc = design_to_dict(result)
    doc.update(extra or {})
    return write_atomic(path, dump_yaml(doc))


def read_design_poses(path: str | Path) -> tuple[list[str], np.ndarray]:
    """``(joint_names, configurations (N, n))`` of a design.yaml (rad, chain order)."""
    path = Path(path)
    if not path.is_file():
        raise ConfigError('poses', f'file {str(path)!r} does not exist')
    doc = read_yaml_file(path, 'poses', 'give a design.yaml written by kpi-calib design')
    try:
        names = [str(n) for n in doc['joint_names']]
        q = np.asarray(doc['configurations'], float)
    except (yaml.YAMLError, TypeError, KeyError, ValueError) as exc:
        raise ConfigError('poses', f'{path} is not a design.yaml with joint_names and '
                          f'configurations: {exc}') from exc
    if q.ndim != 2 or q.shape[1] != len(names) or not np.all(np.isfinite(q)):
        raise ConfigError('poses.configurations', f'must be finite rows of {len(names)} joint '
                          f'values (one per joint_names), got shape {q.shape}')
    return names, q


# --------------------------------------------------------------------------- plots
def _draw_capsule(ax, a: np.ndarray, b: np.ndarray, radius: float, color: str,
                  alpha: float) -> None:
    """Wireframe of a capsule: its cylinder surface (the caps are left out)."""
    axis = b - a
    length = np.linalg.norm(axis)
    z = axis / length if length > 1e-9 else np.array([0.0, 0.0, 1.0])
    x = np.cross(z, [1.0, 0.0, 0.0] if abs(z[0]) < 0.9 else [0.0, 1.0, 0.0])
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    phi, s = np.meshgrid(np.linspace(0, 2 * np.pi, 16), np.linspace(0, 1, 4))
    pts = (a[:, None, None] + axis[:, None, None] * s
           + radius * (x[:, None, None] * np.cos(phi) + y[:, None, None] * np.sin(phi)))
    ax.plot_wireframe(pts[0], pts[1], pts[2], color=color, alpha=alpha, linewidth=0.4)


def plot_design(cell: DrawnCell, scene: Obstacles | None, result: DesignRecord,
                path: str | Path) -> Path:
    """PNG of the design poses (link origins joined), tracker and obstacles, base frame."""
    fig = plt.figure(figsize=(8, 7))
    ax = fig.add_subplot(projection='3d')
    robot = cell.robot
    tracker = cell.tracker_in_base[:3, 3]
    tip_points = []
    for q in result.configurations:
        poses, tip = robot.pin_link_poses(q)
        chain = np.array([poses[k][:3, 3] for k in robot.link_names] + [tip[:3, 3]])
        ax.plot(*chain.T, color='tab:orange', alpha=0.35, linewidth=1.0)
        tip_points.append(tip[:3, 3])
    tips = np.array(tip_points)
    ax.scatter(*tips.T, color='tab:red', s=8, label=f'{len(tips)} reflector positions')
    for t in tips[:: max(1, len(tips) // 20)]:
        ax.plot(*np.c_[tracker, t], color='tab:green', alpha=0.15, linewidth=0.5)
    ax.scatter(*tracker, color='tab:green', marker='^', s=80, label='laser tracker')
    for q_work, name in zip(cell.q_work, cell.working_pose_names):
        tip = robot.pin_tip_pose(q_work)
        ax.scatter(*tip[:3, 3], color='black', marker='*', s=120, label=f'working pose {name}')
    lim = np.max(np.abs(np.r_[tips, tracker[None]])) * 1.1
    if scene is not None:
        for obs in scene.obstacles:
            if isinstance(obs, CapsuleShape):
                _draw_capsule(ax, np.array(obs.a), np.array(obs.b), obs.radius, 'tab:blue', 0.4)
            elif isinstance(obs, PlaneShape):
                _draw_plane(ax, obs, lim)
    ax.set(xlabel='x (m)', ylabel='y (m)', zlabel='z (m)', xlim=(-lim, lim), ylim=(-lim, lim),
           zlim=(-lim / 2, lim), title=f'{result.criterion} design, base frame')
    ax.legend(loc='upper left', fontsize=8)
    fig.tight_layout()
    path = Path(path)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def _draw_plane(ax, plane: PlaneShape, lim: float) -> None:
    n = np.array(plane.normal)
    u = np.cross(n, [0.0, 0.0, 1.0] if abs(n[2]) < 0.9 else [1.0, 0.0, 0.0])
    u /= np.linalg.norm(u)
    v = np.cross(n, u)
    s, t = np.meshgrid(np.linspace(-lim, lim, 2), np.linspace(-lim, lim, 2))
    pts = n[:, None, None] * plane.offset + u[:, None, None] * s + v[:, None, None] * t
    ax.plot_surface(pts[0], pts[1], pts[2], color='grey', alpha=0.12)


def plot_ellipsoids(results: Sequence[DesignRecord], labels: list[str], path: str | Path,
                    pose: int = 0) -> Path:
    """95 % confidence ellipsoids of the TCP at one working pose (µm), like Fig. 7.

    One 3-D panel and the three 2-D projections (x-y, x-z, y-z; each projection
    of the 3-D 95 % region), in the tracker frame centred on the TCP.
    """
    fig = plt.figure(figsize=(11, 9))
    ax3 = fig.add_subplot(2, 2, 1, projection='3d')
    axes2 = [fig.add_subplot(2, 2, k) for k in (2, 3, 4)]
    colors = ['tab:red', 'tab:blue', 'tab:green', 'tab:purple']
    scale = np.sqrt(CHI2_95_3D) * 1e6
    u, v = np.meshgrid(np.linspace(0, 2 * np.pi, 30), np.linspace(0, np.pi, 15))
    sphere = np.stack([np.cos(u) * np.sin(v), np.sin(u) * np.sin(v), np.cos(v)])
    circle = np.stack([np.cos(np.linspace(0, 2 * np.pi, 100)),
                       np.sin(np.linspace(0, 2 * np.pi, 100))])
    for res, label, color in zip(results, labels, colors):
        cov = res.tcp_covariance[pose]
        w, vec = np.linalg.eigh(cov)
        axes_m = vec * np.sqrt(np.maximum(w, 0.0)) * scale
        pts = np.tensordot(axes_m, sphere, axes=1)
        ax3.plot_wireframe(*pts, color=color, alpha=0.35, linewidth=0.5)
        mean_var = np.trace(cov) / 3.0
        for ax, (i, j) in zip(axes2, [(0, 1), (0, 2), (1, 2)]):
            sub = cov[np.ix_([i, j], [i, j])]
            w2, v2 = np.linalg.eigh(sub)
            ell = (v2 * np.sqrt(np.maximum(w2, 0.0)) * scale) @ circle
            ax.plot(*ell, color=color,
                    label=f'{label}: mean variance {mean_var * 1e12:.3g} µm²')
    names = 'xyz'
    for ax, (i, j) in zip(axes2, [(0, 1), (0, 2), (1, 2)]):
        ax.set(xlabel=f'{names[i]} (µm)', ylabel=f'{names[j]} (µm)', aspect='equal')
        ax.grid(alpha=0.3)
    axes2[0].legend(fontsize=8)
    ax3.set(xlabel='x (µm)', ylabel='y (µm)', zlabel='z (µm)',
            title=f'TCP 95 % confidence, working pose {results[0].working_pose_names[pose]}')
    fig.tight_layout()
    path = Path(path)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


# ------------------------------------------------------------------------- summary
def summary_text(result: DesignRecord, baseline: DesignRecord | None = None) -> str:
    """Readable summary for stdout."""
    lines = [f'criterion {result.criterion}: objective {result.objective:.4g} '
             f'(exchange {result.exchange_objective:.4g}), {len(result.configurations)} '
             f'configurations from {result.candidates} candidates, '
             f'{result.constraint_count} constraints per configuration']
    for name, std, cov in zip(result.working_pose_names, result.tcp_std, result.tcp_covariance):
        line = (f'  working pose {name}: TCP std {np.round(std * 1e6, 2).tolist()} µm, '
                f'mean variance {np.trace(cov) / 3 * 1e12:.4g} µm²')
        if baseline is not None:
            ref = np.trace(baseline.tcp_covariance[result.working_pose_names.index(name)]) / 3
            line += f' ({100 * (1 - np.trace(cov) / 3 / ref):.1f} % below heuristic)'
        lines.append(line)
    lines.append(f'  min capsule margin {np.min(result.min_margin) * 1e3:.1f} mm, max incidence '
                 f'{np.max(result.incidence_deg):.1f} deg')
    for label, rate in result.flagged_pairs.items():
        lines.append(f'  WARNING: pair {label} in collision in {100 * rate:.0f} % of measurable '
                     'poses: ignored; check the capsules')
    lines.append(f'  verification: {"ok" if result.verification.ok else "FAILED"}'
                 + ''.join(f'\n    {v}' for v in result.verification.violations[:20]))
    lines.append(f'  status: {result.status}')
    lines.append('  time: ' + ', '.join(f'{k} {v:.1f} s' for k, v in result.timings.items()))
    return '\n'.join(lines)
