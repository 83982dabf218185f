"""Plots of the reports: the diagnosis's residual plots, ``identify``'s and ``validate``'s.

matplotlib with the Agg backend, imported when a plot is drawn. :func:`write_plots` draws
what :func:`kpi_calib_ros.io.report.write_report` shows in report.md: the residuals
against each joint angle, each joint's gravity torque, time and tracker distance, the
residuals seen as joint errors, the measured points with magnified residual vectors in
3-D, the error before/after adding the effect and the periodogram of each joint's
periodic search. :func:`write_identification_plot` draws ``identify``'s residuals and the
TCP's 95 % region, :func:`write_validation_plots` ``validate``'s residuals of new points.
Residuals in µm.
"""
from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import scipy.stats

from kpi_calib_ros.core.diagnosis.cell_diagnosis import CellDiagnosis
from kpi_calib_ros.core.diagnosis.periodic_search import Periodogram

_UM = 1e6
IDENTIFICATION_PLOT_FILE = 'identification.png'
PERIODOGRAM_PLOT_FILE = 'periodogram.png'
_AXES = ('x', 'y', 'z')
_COLOURS = ('tab:red', 'tab:green', 'tab:blue')


def _pyplot():
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt
    return plt


def _grid(plt, n: int):
    cols = min(3, n)
    rows = int(np.ceil(n / cols))
    fig, axes = plt.subplots(rows, cols, figsize=(4.2 * cols, 3.0 * rows), squeeze=False,
                             sharey=True)
    for ax in axes.ravel()[n:]:
        ax.set_visible(False)
    return fig, axes.ravel()


def _scatter_components(ax, x: np.ndarray, residuals: np.ndarray, outliers: np.ndarray,
                        label: str = 'outlier |r|') -> None:
    for k in range(3):
        ax.plot(x, residuals[:, k] * _UM, '.', ms=4, color=_COLOURS[k], label=f'r_{_AXES[k]}')
    if outliers.any():
        ax.plot(x[outliers], np.linalg.norm(residuals[outliers], axis=1) * _UM, 'kx', ms=8,
                label=label)
    ax.axhline(0.0, color='0.6', lw=0.8)
    ax.grid(alpha=0.3)


def write_validation_plots(out_dir: str | Path, robot: Any, q: np.ndarray,
                           residuals: np.ndarray, marked: np.ndarray,
                           repeated: np.ndarray | None = None) -> Path:
    """``validation_residuals.png``: residuals (N, 3) m of new points against each joint
    value (N, n), the ``marked`` (N,) points (outside the training ranges) crossed, the
    ``repeated`` ones (training poses measured again) circled."""
    plt = _pyplot()
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    names = robot.joint_names
    revolute = [j.kind != 'prismatic' for j in robot.joints]
    fig, axes = _grid(plt, len(names))
    for j, ax in enumerate(axes[:len(names)]):
        x = np.degrees(q[:, j]) if revolute[j] else q[:, j] * 1e3
        _scatter_components(ax, x, residuals, marked, label='outside training range |r|')
        if repeated is not None and repeated.any():
            ax.plot(x[repeated], np.linalg.norm(residuals[repeated], axis=1) * _UM, 'o',
                    mfc='none', mec='0.3', ms=6, label='training pose again |r|')
        ax.set_xlabel(f'{names[j]} ({"deg" if revolute[j] else "mm"})')
    axes[0].set_ylabel('residual (µm)')
    axes[0].legend(fontsize=7)
    fig.suptitle('Validation residuals against each joint value')
    fig.tight_layout()
    path = out / 'validation_residuals.png'
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return path


def write_identification_plot(out_dir: str | Path, residuals: np.ndarray,
                              sigma: np.ndarray, tcp_covariance: np.ndarray,
                              working_pose_names: tuple[str, ...] | list[str],
                              points: np.ndarray | None = None) -> Path:
    """``identification.png``: the residual (N, 3) m of every measurement the calibration
    used against its index, with ±3 of the stated σ (3,) m, and the 95 % region of the TCP
    at each working pose from its covariance (T, 3, 3) m² (eq. 19), projected on x-y, x-z
    and y-z (µm, tracker frame, centred on the TCP). ``points`` (N,) bool: the rows that
    are points (the others, rotations of a tracked body in rad, are left out)."""
    plt = _pyplot()
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    res = np.atleast_2d(np.asarray(residuals, float))
    if points is not None:
        res = res[np.asarray(points, bool)]
    sig = np.broadcast_to(np.asarray(sigma, float).reshape(-1)[:3], (3,)) * _UM
    fig, axes = plt.subplots(1, 4, figsize=(13.5, 3.3),
                             gridspec_kw={'width_ratios': [1.6, 1, 1, 1]})
    index = np.arange(len(res))
    for k in range(3):
        axes[0].plot(index, res[:, k] * _UM, '.', ms=4, color=_COLOURS[k], label=f'r_{_AXES[k]}')
    axes[0].axhline(3 * float(np.max(sig)), color='k', ls='--', lw=0.8, label='±3σ stated')
    axes[0].axhline(-3 * float(np.max(sig)), color='k', ls='--', lw=0.8)
    axes[0].axhline(0.0, color='0.6', lw=0.8)
    axes[0].set(xlabel='measurement', ylabel='residual (µm)',
                title=f'Residuals: rms |r| {np.sqrt(np.mean(np.sum(res ** 2, 1))) * _UM:.1f} µm')
    axes[0].legend(fontsize=7, ncol=2)
    axes[0].grid(alpha=0.3)
    scale = float(np.sqrt(scipy.stats.chi2.ppf(0.95, 3))) * _UM
    circle = np.stack([np.cos(np.linspace(0, 2 * np.pi, 100)),
                       np.sin(np.linspace(0, 2 * np.pi, 100))])
    cov_all = np.asarray(tcp_covariance, float).reshape(-1, 3, 3)
    for ax, (i, j) in zip(axes[1:], [(0, 1), (0, 2), (1, 2)]):
        for t, (cov, name) in enumerate(zip(cov_all, working_pose_names)):
            w, v = np.linalg.eigh(cov[np.ix_([i, j], [i, j])])
            ax.plot(*((v * np.sqrt(np.maximum(w, 0.0)) * scale) @ circle),
                    color=f'C{t % 10}', label=name)
        ax.set(xlabel=f'TCP {_AXES[i]} (µm)', ylabel=f'TCP {_AXES[j]} (µm)', aspect='equal')
        ax.grid(alpha=0.3)
    axes[1].set_title('TCP 95 % region (eq. 19)', fontsize=9)
    if len(cov_all):
        axes[1].legend(fontsize=7)
    else:
        axes[1].text(0.5, 0.5, 'no working poses: no TCP', ha='center', va='center',
                     transform=axes[1].transAxes)
    fig.tight_layout()
    path = out / IDENTIFICATION_PLOT_FILE
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return path


def _periodogram_plot(plt, grams: tuple[Periodogram, ...]):
    """The χ² reduction of a sinusoid at each frequency searched, one line per joint."""
    fig, ax = plt.subplots(figsize=(8, 3.4))
    for k, g in enumerate(grams):
        ax.plot(g.cycles, np.maximum(g.power, 1e-3), '.-', ms=4, lw=0.8, color=f'C{k % 10}',
                label=f'{g.joint}: peak {g.peak} (p = {g.p_value:.2g})')
        ax.plot([g.peak], [max(float(np.max(g.power)), 1e-3)], 'o', mfc='none',
                color=f'C{k % 10}')
    ax.set_yscale('log')
    ax.set_xlabel('cycles per revolution')
    ax.set_ylabel('χ² reduction (σ²)')
    ax.set_title('Periodic joint errors: the frequency search of each joint (p × frequencies '
                 'searched)', fontsize=9)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7, ncol=2)
    return fig


def write_plots(out_dir: str | Path, cd: CellDiagnosis) -> list[Path]:
    """PNG plots of the residuals of ``cd`` into ``out_dir``; returns their paths."""
    plt = _pyplot()
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    rep = cd.diagnosis.residuals
    res, outl = rep.residuals, rep.outlier
    robot = cd.model.robot
    q = np.atleast_2d(cd.data.q)
    names = robot.joint_names
    revolute = [j.kind != 'prismatic' for j in robot.joints]
    paths = []

    def save(fig, name: str) -> None:
        fig.tight_layout()
        path = out / name
        fig.savefig(path, dpi=90)
        plt.close(fig)
        paths.append(path)

    fig, axes = _grid(plt, len(names))
    for j, ax in enumerate(axes[:len(names)]):
        _scatter_components(ax, np.degrees(q[:, j]) if revolute[j] else q[:, j] * 1e3, res, outl)
        ax.set_xlabel(f'{names[j]} ({"deg" if revolute[j] else "mm"})')
    axes[0].set_ylabel('residual (µm)')
    axes[0].legend(fontsize=7)
    fig.suptitle('Residuals against each joint value')
    save(fig, 'residuals_vs_joints.png')

    tau = robot.gravity_torques(q)
    unloaded = np.ptp(tau, axis=0) < 1e-6
    tau[:, unloaded] = 0.0  # numerical noise of ~1e-15 N m would set the axis scale
    fig, axes = _grid(plt, len(names))
    for j, ax in enumerate(axes[:len(names)]):
        _scatter_components(ax, tau[:, j], res, outl)
        ax.set_xlabel(f'gravity torque {names[j]} ({"N m" if revolute[j] else "N"})')
        if unloaded[j]:
            ax.set_title('no gravity torque on this joint', fontsize=8)
    axes[0].set_ylabel('residual (µm)')
    axes[0].legend(fontsize=7)
    fig.suptitle('Residuals against gravity torque (payload included)')
    save(fig, 'residuals_vs_torque.png')

    # The residual seen as an error of one joint: its component along the direction
    # the point moves when that joint turns, divided by the lever. A compliance is a
    # line against torque, backlash a step at zero torque, a cyclic error a sine.
    lever = cd.model.joint_jacobian(cd.result.values, q, None, cd.data.reflector,
                                    cd.data.rotation, cd.data.covariates)
    lever2 = np.sum(lever ** 2, axis=1)
    implied = np.einsum('nij,ni->nj', lever, res) / np.maximum(lever2, 1e-12)
    seen = lever2 > 0.05 * lever2.max(axis=0)
    fig, axes = plt.subplots(2, len(names), figsize=(2.6 * len(names), 5.2), squeeze=False)
    for j in range(len(names)):
        scale = 1e6  # µrad for revolute, µm for prismatic joints
        x = np.degrees(q[:, j]) if revolute[j] else q[:, j] * 1e3
        for row, xx, label in ((0, x, f'{names[j]} ({"deg" if revolute[j] else "mm"})'),
                               (1, tau[:, j], f'τ {names[j]} ({"N m" if revolute[j] else "N"})')):
            ax = axes[row, j]
            ax.plot(xx[seen[:, j]], implied[seen[:, j], j] * scale, '.', ms=4, color='tab:purple')
            ax.axhline(0.0, color='0.6', lw=0.8)
            ax.set_xlabel(label, fontsize=8)
            ax.tick_params(labelsize=7)
            ax.grid(alpha=0.3)
        axes[0, j].set_title(f'{names[j]} error', fontsize=8)
    axes[0, 0].set_ylabel('implied joint error (µrad or µm)', fontsize=8)
    axes[1, 0].set_ylabel('implied joint error (µrad or µm)', fontsize=8)
    fig.suptitle('Residuals seen as joint errors, against joint value (top) and gravity '
                 'torque (bottom)', fontsize=10)
    save(fig, 'joint_errors.png')

    fig, axes = plt.subplots(1, 2, figsize=(11, 3.4), sharey=True)
    stamps = cd.data.stamps_ns
    if stamps is not None and len(stamps) == len(res):
        t = (np.asarray(stamps, float) - float(np.min(stamps))) * 1e-9
        axes[0].set_xlabel('time since first measurement (s)')
    else:
        t = np.arange(len(res), dtype=float)
        axes[0].set_xlabel('measurement index (no time stamps)')
    _scatter_components(axes[0], t, res, outl)
    axes[0].plot(t, rep.norms * _UM, '-', color='0.5', lw=0.6, label='|r|')
    axes[0].set_ylabel('residual (µm)')
    axes[0].legend(fontsize=7)
    distance = np.linalg.norm(np.atleast_2d(cd.data.eta), axis=1)
    _scatter_components(axes[1], distance, res, outl)
    axes[1].set_xlabel('tracker distance (m)')
    fig.suptitle('Residuals against time (drift, warm-up) and tracker distance (scale)')
    save(fig, 'residuals_vs_time_distance.png')

    fig = plt.figure(figsize=(6.5, 5.5))
    ax = fig.add_subplot(projection='3d')
    eta = np.atleast_2d(cd.data.eta)
    pred = eta - res
    span = float(np.max(np.ptp(eta, axis=0)))
    gain = 0.1 * span / max(float(rep.max_m), 1e-12)
    ax.scatter(*eta.T, s=8, c='tab:blue', label='measured')
    ax.scatter(*pred.T, s=4, c='tab:orange', label='predicted')
    ax.quiver(*pred.T, *(res * gain).T, color='k', lw=0.8, arrow_length_ratio=0.2)
    ax.set_xlabel('x (m)')
    ax.set_ylabel('y (m)')
    ax.set_zlabel('z (m)')
    ax.legend(fontsize=7)
    ax.set_title(f'Measured vs predicted, tracker frame\n(residual arrows magnified {gain:.0f}×)',
                 fontsize=9)
    save(fig, 'measured_vs_predicted_3d.png')

    fig, axes = plt.subplots(1, 2, figsize=(11, 3.6))
    floor = float(np.sqrt(np.sum(cd.result.sigma ** 2))) * _UM
    top = cd.diagnosis.candidates[:8]
    labels = ['geometric'] + [c.spec for c in top]
    values = [cd.diagnosis.validation_rms_m * _UM] + [c.validation_rms_after_m * _UM for c in top]
    colours = ['0.5'] + ['tab:red' if c.significant else 'tab:gray' for c in top]
    axes[0].barh(labels[::-1], values[::-1], color=colours[::-1])
    axes[0].axvline(floor, color='k', ls='--', lw=1, label='noise floor σ√3')
    axes[0].set_xlabel('validation rms (µm), held-out poses')
    axes[0].legend(fontsize=7)
    axes[0].set_title('Candidates (red: significant)', fontsize=9)
    axes[0].tick_params(axis='y', labelsize=7)
    bins = np.linspace(0, max(rep.max_m, cd.after.rms_m * 3 if cd.after else 0) * _UM, 30)
    axes[1].hist(rep.norms * _UM, bins=bins, alpha=0.6, label='geometric model')
    if cd.after is not None and cd.added is not None:  # set together
        after = np.linalg.norm(cd.after.residuals, axis=1)
        axes[1].hist(after * _UM, bins=bins, alpha=0.6, label=f'+ {cd.added.name}')
        axes[1].set_title(f'|r| before/after: rms {cd.result.rms_m * _UM:.1f} -> '
                          f'{cd.after.rms_m * _UM:.1f} µm', fontsize=9)
    axes[1].set_xlabel('|residual| (µm)')
    axes[1].legend(fontsize=7)
    save(fig, 'before_after.png')
    if cd.diagnosis.periodograms:
        save(_periodogram_plot(plt, cd.diagnosis.periodograms), PERIODOGRAM_PLOT_FILE)
    return paths
