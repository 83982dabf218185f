"""Where the model fails: the ranked inputs, the four answers and partial-residual plots.

Writes what :mod:`kpi_calib_ros.core.diagnosis.residual_analysis` and
:mod:`kpi_calib_ros.core.diagnosis.misfit` compute: a ranked table (report.md and diagnosis.json)
and ``partial_residuals.png`` -- for each of the top inputs, every row's residual along the
direction the input moves the point, divided by the lever (the joint error it implies, a range
error, a drift or a scale), against the input, with the smooth fit; and ``learned_residual.png``,
the learned residual's field and its uncertainty along its most relevant joints. Units: µrad,
µm and ppm (10⁻⁶) in plots and text, SI in the JSON document.
"""
from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from kpi_calib_ros.core.diagnosis.misfit import MisfitAnswer
from kpi_calib_ros.core.diagnosis.residual_analysis import InputScore, ResidualAnalysis

if TYPE_CHECKING:  # scikit-learn is imported only where a residual is learned
    from kpi_calib_ros.core.diagnosis.learned_residual import LearnedResidual

PLOT_FILE = 'partial_residuals.png'
TOP = 6  # inputs plotted
_MICRO = {'rad': 'µrad', 'm': 'µm', '': 'ppm'}
_COLOURS = ('tab:red', 'tab:green', 'tab:blue', 'tab:purple')


def _finite(x: float) -> float | None:
    return float(x) if np.isfinite(x) else None


def analysis_to_dict(analysis: ResidualAnalysis) -> dict[str, Any]:
    """JSON-ready ranked inputs (SI units; NaN as null)."""
    return {'alpha': analysis.alpha, 'folds': analysis.folds,
            'chi2': float(analysis.chi2), 'dof': int(analysis.dof),
            'combined': list(analysis.combined),
            'combined_held_out_rms_before_m': _finite(analysis.combined_before_m),
            'combined_held_out_rms_after_m': _finite(analysis.combined_after_m),
            'pair': None if analysis.pair is None else {
                'names': list(analysis.pair.names), 'dof': analysis.pair.dof,
                'f_statistic': _finite(analysis.pair.f_statistic),
                'p_value': float(analysis.pair.p_value),
                'significant': bool(analysis.pair.significant),
                'held_out_rms_additive_m': _finite(analysis.pair.held_out_rms_additive_m),
                'held_out_rms_after_m': _finite(analysis.pair.held_out_rms_after_m)},
            'inputs': [{'name': s.name, 'kind': s.kind, 'unit': s.unit, 'basis': s.basis,
                        'dof': s.dof, 'share': _finite(s.share),
                        'share_systematic': _finite(s.share_systematic),
                        'held_out_rms_before_m': _finite(s.held_out_rms_before_m),
                        'held_out_rms_after_m': _finite(s.held_out_rms_after_m),
                        'explained_rms_m': _finite(s.explained_rms_m),
                        'f_statistic': _finite(s.f_statistic),
                        'p_value_raw': float(s.p_value_raw), 'p_value': float(s.p_value),
                        'significant': bool(s.significant), 'region': s.region}
                       for s in analysis.scores]}


def answer_to_dict(answer: MisfitAnswer) -> dict[str, Any]:
    """JSON-ready four answers (SI units)."""
    m = answer.missing
    return {'where': answer.where, 'inputs': list(answer.inputs), 'kind': m.kind,
            'what': m.what, 'command': m.command,
            'held_out_rms_before_m': _finite(m.held_out_before_m),
            'held_out_rms_after_m': _finite(m.held_out_after_m), 'basis': m.basis}


def _share(x: float) -> str:
    return f'{x:.2f}' if np.isfinite(x) else '–'


def analysis_lines(analysis: ResidualAnalysis, answer: MisfitAnswer | None) -> list[str]:
    """report.md section: the four answers and the ranked inputs."""
    lines = ['', '## Where the model fails', '']
    if answer is not None:
        lines += [f'- {line}' for line in answer.lines()] + ['']
    lines += [f'Every input scored model-free: a smooth function of it (cubic spline or '
              'harmonics of a joint\'s turn, chosen by cross-validation) along the direction '
              'the input moves the point, with the geometric parameters refitted. Share: '
              'fraction of the held-out residual sum of squares it explains '
              f'({analysis.folds} pose folds); beyond noise: of the part above what the '
              'stated σ predicts. p: exact F test, Bonferroni over the bases, Holm over '
              f'the {len(analysis.scores)} inputs (flagged below α = {analysis.alpha:g}).', '',
              '| # | input | flagged | p | share | beyond noise | held-out rms after (µm) | '
              'basis | where largest |', '|---|---|---|---|---|---|---|---|---|']
    for i, s in enumerate(analysis.scores, 1):
        after = (f'{s.held_out_rms_after_m * 1e6:.1f}' if np.isfinite(s.held_out_rms_after_m)
                 else '–')
        lines.append(f'| {i} | {s.name} | {"yes" if s.significant else "no"} | '
                     f'{s.p_value:.2g} | {_share(s.share)} | {_share(s.share_systematic)} | '
                     f'{after} | {s.basis} | {s.region} |')
    pair = analysis.pair
    if pair is not None:
        lines += ['', f'Interaction of {pair.names[0]} and {pair.names[1]} (tensor product '
                  f'along {pair.names[0]}\'s direction, beyond the sum of their '
                  f'smooths): F test p = {pair.p_value:.2g} ({pair.dof} columns), held-out '
                  f'rms {pair.held_out_rms_additive_m * 1e6:.1f} -> '
                  f'{pair.held_out_rms_after_m * 1e6:.1f} µm; '
                  f'{"flagged" if pair.significant else "not flagged"}.']
    if analysis.scores and np.isfinite(analysis.scores[0].held_out_rms_before_m):
        lines += ['', f'Held-out rms of the geometric model: '
                  f'{analysis.scores[0].held_out_rms_before_m * 1e6:.1f} µm.']
    return lines


def analysis_text(analysis: ResidualAnalysis, answer: MisfitAnswer | None,
                  top: int = 5) -> list[str]:
    """Terminal lines: the four answers and the top inputs."""
    lines = list(answer.lines()) if answer is not None else []
    lines.append(f'inputs (model-free, best first, {len(analysis.significant)} of '
                 f'{len(analysis.scores)} flagged):')
    for i, s in enumerate(analysis.scores[:top], 1):
        mark = '*' if s.significant else ' '
        lines.append(f' {mark}{i}. {s.name:40s} share {_share(s.share):>5s}  '
                     f'p = {s.p_value:.2g}  ({s.basis})')
    return lines


def _axis(score: InputScore) -> tuple[np.ndarray, np.ndarray, str]:
    """Plotted input values (degrees for joint angles) and their label."""
    if score.kind == 'joint' and score.unit == 'rad':
        return np.degrees(score.x), np.degrees(score.curve_x), f'{score.name} (deg)'
    if score.kind == 'joint':
        return score.x * 1e3, score.curve_x * 1e3, f'{score.name} (mm)'
    unit = f' ({score.unit})' if score.unit else ''
    return score.x, score.curve_x, f'{score.name}{unit}'


def write_partial_residual_plot(out_dir: str | Path, analysis: ResidualAnalysis,
                                top: int = TOP) -> Path:
    """``partial_residuals.png``: the ``top`` inputs of ``analysis`` (flagged first), each
    row's implied value along each of the input's directions against the input, points
    shaded by their weight, and the smooth fit."""
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt
    scores = analysis.scores[:top]
    cols = min(3, max(len(scores), 1))
    rows = int(np.ceil(max(len(scores), 1) / cols))
    fig, axes = plt.subplots(rows, cols, figsize=(4.6 * cols, 3.4 * rows), squeeze=False)
    for ax in axes.ravel()[len(scores):]:
        ax.set_visible(False)
    for ax, s in zip(axes.ravel(), scores):
        x, grid, label = _axis(s)
        for k, (name, unit) in enumerate(zip(s.field_names, s.field_units)):
            ok = s.weight[:, k] > 0
            if not ok.any():
                continue
            y = s.implied[ok, k] * 1e6
            # Points with a short lever imply large, noisy values: show the well-levered.
            keep = s.weight[ok, k] >= np.quantile(s.weight[ok, k], 0.1)
            colour = _COLOURS[k % len(_COLOURS)]
            ax.plot(x[ok][keep], y[keep], '.', ms=3, alpha=0.5, color=colour,
                    label=f'{name} ({_MICRO.get(unit, unit)})')
            if np.isfinite(s.curve[:, k]).any():
                style = 'o-' if s.categorical else '-'
                ax.plot(grid, s.curve[:, k] * 1e6, style, color=colour, lw=1.8)
            lo, hi = np.percentile(y[keep], [1, 99])
            pad = 0.2 * (hi - lo) + 1e-9
            ax.set_ylim(min(ax.get_ylim()[0], lo - pad) if k else lo - pad,
                        max(ax.get_ylim()[1], hi + pad) if k else hi + pad)
        ax.axhline(0.0, color='0.6', lw=0.8)
        ax.set_xlabel(label, fontsize=8)
        flag = 'flagged' if s.significant else 'not flagged'
        ax.set_title(f'{s.name}: share {_share(s.share)}, p = {s.p_value:.2g} ({flag})',
                     fontsize=8)
        ax.tick_params(labelsize=7)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=6)
    fig.suptitle('Partial residuals: each residual along the direction the input moves the '
                 'point, over the lever, with the smooth fit', fontsize=9)
    fig.tight_layout()
    path = Path(out_dir) / PLOT_FILE
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return path


LEARNED_PLOT_FILE = 'learned_residual.png'


def write_learned_residual_plot(out_dir: str | Path, residual: LearnedResidual, chosen: bool,
                                top: int = 2) -> Path:
    """``learned_residual.png``: the learned residual δ(q) along each of its ``top`` most
    relevant joints (shortest length scale), the other joints at the training poses'
    median: its mean per axis (µm), ± 2 std of the field itself shaded, the training
    residuals as dots and the training values of the joint as ticks."""
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt
    names = list(residual.joint_names)
    order = [names.index(n) for n in residual.relevant_joints()][:top]
    centre = np.median(residual.q, axis=0)
    fig, axes = plt.subplots(1, len(order), figsize=(5.2 * len(order), 3.5), squeeze=False)
    for ax, j in zip(axes[0], order):
        lo, hi = float(np.min(residual.q[:, j])), float(np.max(residual.q[:, j]))
        pad = 0.1 * (hi - lo) + 1e-6
        sweep = np.linspace(lo - pad, hi + pad, 150)
        q = np.repeat(centre[None], len(sweep), axis=0)
        q[:, j] = sweep
        pred = residual.predict(q)
        std = np.sqrt(np.maximum(np.diagonal(pred.covariance, axis1=1, axis2=2), 0.0))
        for k, axis in enumerate('xyz'):
            colour = _COLOURS[k]
            ax.plot(residual.q[:, j], residual.residual_m[:, k] * 1e6, '.', ms=3, alpha=0.35,
                    color=colour)
            ax.plot(sweep, pred.mean[:, k] * 1e6, '-', lw=1.6, color=colour, label=f'δ_{axis}')
            ax.fill_between(sweep, (pred.mean[:, k] - 2 * std[:, k]) * 1e6,
                            (pred.mean[:, k] + 2 * std[:, k]) * 1e6, color=colour, alpha=0.15)
        ax.plot(residual.q[:, j], np.full(len(residual.q), ax.get_ylim()[0]), '|', color='k',
                ms=8, label='training poses')
        ax.axhline(0.0, color='0.6', lw=0.8)
        ax.set_xlabel(f'{names[j]} (rad, m if prismatic); length scale '
                      f'{residual.length_scales[j]:.3g}', fontsize=8)
        ax.set_ylabel('residual (µm)', fontsize=8)
        ax.tick_params(labelsize=7)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=6, ncol=2)
    fig.suptitle(f'Learned residual ({"chosen" if chosen else "not chosen"}): the field ± 2 '
                 'std along its most relevant joints, the others at the median pose',
                 fontsize=9)
    fig.tight_layout()
    path = Path(out_dir) / LEARNED_PLOT_FILE
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return path
