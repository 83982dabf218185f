"""Diagnosis report: diagnosis.json, report.md with plots, and before/after comparisons.

Writes what :func:`kpi_calib_ros.app.diagnose.diagnose_cell` computes (calibrate,
diagnose, add the suggested effect, compare) with :func:`write_report`: the documents
(diagnosis.json, report.md) and their terminal text are made here, the plots report.md
shows by :mod:`kpi_calib_ros.io.report_plots` (which also draws ``identify``'s and
``validate``'s). Units in files are SI; plots and text use µm for residuals.
"""
from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np

from kpi_calib_ros.core.diagnosis import Candidate, CellDiagnosis, ModelComparison
from kpi_calib_ros.core.diagnosis.out_of_sample import DOMAIN_TEXT, NOT_ESTIMABLE, OutOfSample
from kpi_calib_ros.core.diagnosis.periodic_search import Periodogram
from kpi_calib_ros.core.estimation.cross_validation import fold_kinds
from kpi_calib_ros.core.estimation.precision import ExpectedTcpError, precision_statement
from kpi_calib_ros.io.names import DIAGNOSIS_FILE, REPORT_FILE
from kpi_calib_ros.io.report_plots import write_plots
from kpi_calib_ros.io.residual_plots import (
    analysis_lines,
    analysis_text,
    analysis_to_dict,
    answer_to_dict,
    write_partial_residual_plot,
)
from kpi_calib_ros.io.results import write_atomic

_UM = 1e6


# ------------------------------------------------------------------ documents
# Why a figure of diagnosis.json is null (JSON has no NaN): what it would need.
UNDETERMINED_STD = ('not determined by these measurements (no direction of its own beside the '
              'geometry and the other parameters): no finite std')
NO_DOF = 'no degrees of freedom left: no test'


def finite(x: float) -> float | None:
    """``x`` as a JSON number, None when it is not finite (JSON has no NaN)."""
    return float(x) if np.isfinite(x) else None


def _with_reason(doc: dict[str, Any], key: str, x: float, reason: str) -> dict[str, Any]:
    """``doc[key]`` = :func:`finite` of ``x``; ``doc[key + '_reason']`` when it is None."""
    doc[key] = finite(x)
    if doc[key] is None:
        doc[f'{key}_reason'] = reason
    return doc


def _parameter_dict(name: str, value: float, std: float, unit: str) -> dict[str, Any]:
    return _with_reason({'name': name, 'value': float(value)}, 'std', std, UNDETERMINED_STD) | {
        'unit': unit}


def _candidate_dict(c: Candidate) -> dict[str, Any]:
    doc: dict[str, Any] = {'effect': c.effect, 'joint': c.joint, 'spec': c.spec,
                           'rms_after_m': float(c.rms_after_m)}
    _with_reason(doc, 'validation_rms_after_m', c.validation_rms_after_m, NOT_ESTIMABLE)
    return doc | {
            'p_value': finite(c.p_value), 'p_value_raw': finite(c.p_value_raw),
            'significant': bool(c.significant),
            'parameters': [_parameter_dict(n, v, s, u)
                           for n, v, s, u in zip(c.parameter_names, c.values, c.std, c.units)],
            'std_basis': precision_statement(float(c.covariance_scale)),
            'explanation': c.explanation, 'plausible': bool(c.plausible),
            'plausibility': c.plausibility, 'also_explained_by': list(c.also_explained_by),
            'note': c.note, 'frequencies_searched': int(c.searched)}


def comparison_to_dict(cmp: ModelComparison) -> dict[str, Any]:
    """YAML/JSON-ready before/after numbers (SI units)."""
    doc: dict[str, Any] = {'effects': list(cmp.effects),
                           'rms_before_m': float(cmp.rms_before_m),
                           'rms_after_m': float(cmp.rms_after_m)}
    _with_reason(doc, 'validation_rms_before_m', cmp.validation_rms_before_m, NOT_ESTIMABLE)
    _with_reason(doc, 'validation_rms_after_m', cmp.validation_rms_after_m, NOT_ESTIMABLE)
    _with_reason(doc, 'chi2_p_value_before', cmp.p_value_before, NO_DOF)
    _with_reason(doc, 'chi2_p_value_after', cmp.p_value_after, NO_DOF)
    return doc | {
            'effect_parameters': [
                {k: (finite(v) if isinstance(v, float) else v) for k, v in p.items()}
                for p in cmp.effect_parameters],
            'tcp_std_m': [{'name': n, 'before': [float(x) for x in b],
                           'after': [float(x) for x in a]}
                          for n, b, a in zip(cmp.working_pose_names, cmp.tcp_std_before_m,
                                             cmp.tcp_std_after_m)],
            'warnings': list(cmp.warnings), 'std_basis': cmp.std_basis,
            'other_region_rms_before_m': _finite(cmp.other_region_rms_before_m),
            'other_region_rms_after_m': _finite(cmp.other_region_rms_after_m),
            'region_blocks': int(cmp.region_blocks),
            'held_out_fold_rms_before_m': [_finite(v) for v in cmp.held_out_folds_before_m],
            'held_out_fold_rms_after_m': [_finite(v) for v in cmp.held_out_folds_after_m],
            'held_out_folds_worse': cmp.worse_folds[0],
            'other_recording_rms_before_m': _finite(cmp.other_recording_rms_before_m),
            'other_recording_rms_after_m': _finite(cmp.other_recording_rms_after_m),
            'recordings_held_out': int(cmp.recordings_held_out),
            'held_out_gain': None if cmp.gain is None else cmp.gain.to_dict(),
            'holds_elsewhere': cmp.holds_elsewhere,
            'extrapolated': list(cmp.extrapolated), 'implausible': list(cmp.implausible),
            'readmitted': list(cmp.readmitted),
            'recommended': cmp.holds_elsewhere}


def _finite(value: float) -> float | None:
    return float(value) if np.isfinite(value) else None


def region_verdict(cmp: ModelComparison) -> str:
    """Whether the richer model is recommended: only when it predicts held-out regions of
    joint space better beyond noise (as ``auto`` asks)."""
    gain = ('' if cmp.gain is None or not np.isfinite(cmp.gain.z) else
            f'gain z = {cmp.gain.z:.2f} in held-out noise units (needed > '
            f'{cmp.gain.threshold():.2f}), ')
    figures = (gain + f'{_validation(cmp.other_region_rms_before_m, "", " µm")} -> '
               f'{_validation(cmp.other_region_rms_after_m, "", " µm")} over held-out regions '
               f'of joint space ({cmp.region_blocks} regions), '
               f'{_validation(cmp.validation_rms_before_m, "", " µm")} -> '
               f'{_validation(cmp.validation_rms_after_m, "", " µm")} where measured'
               + (f', {_validation(cmp.other_recording_rms_before_m, "", " µm")} -> '
                  f'{_validation(cmp.other_recording_rms_after_m, "", " µm")} over recordings '
                  'held out whole (each one\'s placement registered)'
                  if cmp.recordings_held_out else '')
               + f'; worse beyond the noise in {cmp.worse_folds[0]} of {cmp.worse_folds[1]} '
               f'held-out folds {fold_kinds(cmp.recordings_held_out)}')
    if cmp.warnings:
        return (f'NOT recommended: a fit did not converge, so its cross-validated figures '
                f'judge a last iterate, not a minimum ({figures}); raise '
                'identification.max_iterations / --max-iterations and compare again')
    if cmp.extrapolated:
        return (f'NOT recommended: {"; ".join(cmp.extrapolated)} ({figures})')
    if cmp.implausible:
        return (f'NOT recommended: refitted with {", ".join(cmp.effects)} the calibration is not '
                f'plausible, identify would not publish it: {"; ".join(cmp.implausible)} '
                f'({figures})')
    if cmp.holds_elsewhere:
        return (f'recommended: {", ".join(cmp.effects)} predicts held-out regions of the '
                f'measured poses better ({figures}); checked within the measured joint ranges '
                'only')
    return (f'NOT recommended: {", ".join(cmp.effects)} does not predict held-out regions of '
            f'joint space better beyond noise, or is worse beyond noise in a held-out fold '
            f'({figures}); keep the model without it')


def diagnosis_to_dict(cd: CellDiagnosis) -> dict[str, Any]:
    """The diagnosis.json document: verdict, rms, ranked candidates (best first)."""
    diag, rep = cd.diagnosis, cd.diagnosis.residuals
    doc: dict[str, Any] = {
        'model_adequate': bool(diag.model_adequate),
        'converged': bool(cd.result.converged), 'status': cd.result.message,
        'rms_m': float(diag.rms_m),
        **_with_reason({}, 'validation_rms_m', diag.validation_rms_m, NOT_ESTIMABLE),
        'noise_floor_m': float(np.sqrt(np.sum(cd.result.sigma ** 2))),
        'candidates': [_candidate_dict(c) for c in diag.candidates],
        'verdict': diag.verdict, 'set_up': list(cd.set_up),
        'alpha': diag.alpha, 'folds': diag.folds,
        'residuals': {'measurements': int(len(rep.norms)), 'max_m': float(rep.max_m),
                      'percentiles_m': {str(k): float(v) for k, v in rep.percentiles_m.items()},
                      'chi2': float(rep.chi2), 'dof': int(rep.dof),
                      **_with_reason({}, 'p_value', rep.p_value, NO_DOF),
                      'adequate': bool(rep.adequate),
                      'outliers': cd.given_index(rep.outlier),
                      'excluded': list(cd.excluded),
                      'sigma_stated_m': float(rep.sigma_stated_m),
                      **_with_reason({}, 'sigma_robust_m', rep.sigma_robust_m, NO_DOF),
                      'sigma_warning': rep.sigma_warning,
                      'high_leverage': cd.given_index(rep.high_leverage)},
        'not_distinguishable': [{'effect': c.effect, 'joint': c.joint, 'spec': c.spec,
                                 'reason': c.explanation} for c in diag.not_distinguishable],
        'periodic_search': [periodogram_dict(g) for g in diag.periodograms],
    }
    if cd.out_of_sample is not None:
        doc['out_of_sample'] = cd.out_of_sample.to_dict()
    if cd.expected is not None:
        doc['expected_tcp_error'] = cd.expected.to_dict()
    if cd.estimability is not None:
        doc['tcp_estimability'] = cd.estimability.to_dict()
    if cd.comparison is not None:
        doc['added_effect'] = comparison_to_dict(cd.comparison)
        if cd.after_out_of_sample is not None:
            doc['added_effect']['out_of_sample'] = cd.after_out_of_sample.to_dict()
    if cd.residual_analysis is not None:
        doc['residual_inputs'] = analysis_to_dict(cd.residual_analysis)
    if cd.answer is not None:
        doc['misfit'] = answer_to_dict(cd.answer)
    return doc




def _validation(rms_m: float, width: str = '', unit: str = '') -> str:
    """A cross-validated rms in µm, or why there is none: NaN when no folds keep
    every identified parameter determined (core.estimation.folds.identifiable_folds)."""
    if not np.isfinite(rms_m):
        return NOT_ESTIMABLE
    return f'{rms_m * _UM:{width}.1f}{unit}'


def _fold_name(folds: int) -> str:
    return 'leave one pose out' if folds == 0 else f'{folds}-fold'


def comparison_text(cmp: ModelComparison) -> str:
    """Readable before/after summary for a terminal."""
    lines = [f"with {', '.join(cmp.effects)}:",
             f'  rms             {cmp.rms_before_m * _UM:7.1f} -> {cmp.rms_after_m * _UM:7.1f} µm',
             f'  validation rms  {_validation(cmp.validation_rms_before_m, "7", " µm")} -> '
             f'{_validation(cmp.validation_rms_after_m, "7", " µm")} (held-out poses)',
             f'  other regions   {_validation(cmp.other_region_rms_before_m, "7", " µm")} -> '
             f'{_validation(cmp.other_region_rms_after_m, "7", " µm")} (held-out regions of '
             f'joint space, {cmp.region_blocks} regions)',
             f'  {region_verdict(cmp)}',
             f'  χ² p-value      {cmp.p_value_before:9.3g} -> {cmp.p_value_after:9.3g}']
    if cmp.readmitted:
        lines.append(f'  measurements {list(cmp.readmitted)}, outliers of the model without '
                     f'{", ".join(cmp.effects)}, are within the threshold with it: both fits '
                     'and this comparison include them')
    if cmp.std_basis and cmp.effect_parameters:
        lines.append(f'  std {cmp.std_basis}')
    for p in cmp.effect_parameters:
        if 'std' in p:
            lines.append(f"  {p['name']} = {p['value']:.4g} ± {p['std']:.2g} {p['unit']}")
        else:
            lines.append(f"  {p['name']}: not estimated ({p['dropped']})")
    for name, b, a in zip(cmp.working_pose_names, cmp.tcp_std_before_m, cmp.tcp_std_after_m):
        lines.append(f'  TCP {name} std [{", ".join(f"{x * _UM:.1f}" for x in b)}] -> '
                     f'[{", ".join(f"{x * _UM:.1f}" for x in a)}] µm')
    lines += [f'  WARNING: {w}' for w in cmp.warnings]
    return '\n'.join(lines)


def periodogram_dict(gram: Periodogram) -> dict[str, Any]:
    """One joint's frequency search (core.diagnosis.periodic_search) for diagnosis.json: the range
    of cycles per revolution searched, the peak, its χ² reduction and p-value (× the
    number searched)."""
    return {'joint': gram.joint,
            'cycles_searched': [int(gram.cycles[0]), int(gram.cycles[-1])],
            'peak_cycles_per_revolution': int(gram.peak),
            'peak_delta_chi2': float(np.max(gram.power)), 'p_value': finite(gram.p_value),
            'resolution_cycles_per_revolution': finite(gram.resolution),
            'refused_as_aliased': [int(k) for k in gram.refused],
            'periodic_errors_in_model': [int(k) for k in gram.near],
            'runner_up_cycles_per_revolution': int(gram.runner_up) or None,
            'margin': finite(gram.margin), 'margin_needed': finite(gram.margin_needed),
            'ambiguous': gram.ambiguous}


def periodic_search_line(grams: tuple[Periodogram, ...]) -> str:
    """One line: the peak of each joint's periodogram and its p-value."""
    return ('periodic joint errors, peak of each periodogram (cycles/rev, p × frequencies '
            'searched; resolution 2π/Δq): '
            + ', '.join(f'{g.joint} {g.peak} (p = {g.p_value:.2g}; ±{g.resolution:.3g}'
                        + (f'; {len(g.refused)} frequencies within it of k = '
                           f'{", ".join(map(str, g.near))} refused as aliased' if g.refused
                           else '')
                        + (f'; ambiguous: k = {g.runner_up} explains nearly as well, margin '
                           f'{g.margin:.3g} < {g.margin_needed:.3g}, not a candidate'
                           if g.ambiguous else '') + ')' for g in grams))


def diagnosis_text(cd: CellDiagnosis, top: int = 5) -> str:
    """Readable diagnosis summary for a terminal."""
    diag, rep = cd.diagnosis, cd.diagnosis.residuals
    pct = ', '.join(f'p{k} {v * _UM:.1f}' for k, v in rep.percentiles_m.items())
    lines = [*([f'WARNING: the calibration did not converge ({cd.result.message}); the '
               'diagnosis judges its last iterate, not a minimum (identification.'
               'max_iterations raises the limit)'] if not cd.result.converged else []),
             *[f'WARNING: {line}; the recordings before the robot: the effects below are '
               'screened on a fit this bends' for line in cd.set_up],
             diag.verdict,
             f'rms {diag.rms_m * _UM:.1f} µm, validation rms '
             f'{_validation(diag.validation_rms_m, "", " µm")} '
             f'(noise floor σ√3 {np.sqrt(np.sum(cd.result.sigma ** 2)) * _UM:.1f} µm); '
             f'|r| {pct}, max {rep.max_m * _UM:.1f} µm',
             f'noise σ: stated {rep.sigma_stated_m * _UM:.3g} µm, robust estimate '
             f'from the residuals {rep.sigma_robust_m * _UM:.3g} µm',
             *([f'WARNING: {rep.sigma_warning}'] if rep.sigma_warning else []),
             *([cd.out_of_sample.text()] if cd.out_of_sample is not None else []),
             *([f'diagnosed the {len(cd.data)} measurements identify keeps; excluded as '
                f'outliers: {list(cd.excluded)}'] if cd.excluded else []),
             *(expected_tcp_lines(cd.expected) if cd.expected is not None else []),
             f'outliers: {cd.given_index(rep.outlier)}, high leverage: '
             f'{cd.given_index(rep.high_leverage)}',
             f'candidates (best first, {len(diag.candidates)} distinguishable, '
             f'{len(diag.not_distinguishable)} not):']
    for i, c in enumerate(diag.candidates[:top], 1):
        mark = '*' if c.significant else ' '
        lines.append(f' {mark}{i}. {c.spec:40s} validation rms '
                     f'{_validation(c.validation_rms_after_m, "6", " µm")}  p = {c.p_value:.2g}')
    if diag.periodograms:
        lines.append(periodic_search_line(diag.periodograms))
    if diag.best is not None:
        lines.append(f'why: {diag.best.explanation}')
    for c in diag.not_distinguishable:
        if c.spec == 'tracker_scale' or c.unique_fraction > 0:
            lines.append(f'{c.spec}: {c.explanation}')
    if cd.comparison is not None:
        lines.append(comparison_text(cd.comparison))
    if cd.residual_analysis is not None:
        lines += analysis_text(cd.residual_analysis, cd.answer)
    return '\n'.join(lines)


def write_diagnosis_json(out_dir: str | Path, doc: dict[str, Any]) -> Path:
    # allow_nan=False: a figure that is not a number is null with its reason, never NaN.
    return write_atomic(Path(out_dir) / DIAGNOSIS_FILE,
                        json.dumps(doc, indent=2, allow_nan=False) + '\n')


def expected_tcp_lines(expected: ExpectedTcpError) -> list[str]:
    """Terminal lines: the expected TCP error of every working pose beside its parameter
    part, and what the expected error rests on."""
    return [f'TCP {n}: expected error {e * _UM:.1f} µm (with the misfit), parameter part '
            f'tcp_std {s * _UM:.1f} µm (sqrt(trace))'
            for n, s, e in zip(expected.working_pose_names, expected.tcp_std_m,
                               expected.expected_tcp_error_m)] + [
        f'expected TCP error: {expected.basis}']


def out_of_sample_table(oos: OutOfSample) -> list[str]:
    """report.md section: the predicted error of new measurements per domain."""
    lines = ['', '## Predicted out-of-sample error', '',
             f'Error of a new measurement at fresh poses, {oos.method}; '
             f'σ̂ = {np.mean(oos.sigma_hat_m) * _UM:.3g} µm per axis (χ²/dof = '
             f'{oos.scale:.3g}, dof {oos.dof}). An effect the model lacks biases it low.', '',
             '| fresh poses | rms (µm) | 95 % interval (µm) | parameters alone (µm) |',
             '|---|---|---|---|']
    for d in oos.domains.values():
        if d.estimable:
            lines.append(f'| {DOMAIN_TEXT[d.domain]} | {d.rms_m * _UM:.1f} | '
                         f'{d.interval_m[0] * _UM:.1f}-{d.interval_m[1] * _UM:.1f} | '
                         f'{d.parameter_rms_m * _UM:.1f} |')
        else:
            lines.append(f'| {DOMAIN_TEXT[d.domain]} | {NOT_ESTIMABLE} (not determined: '
                         f'{", ".join(d.not_determined)}) | | |')
    if oos.caveat:
        lines += ['', f'**Warning:** {oos.caveat}.']
    return lines


def write_report(out_dir: str | Path, cd: CellDiagnosis) -> Path:
    """diagnosis.json, the plots and report.md into ``out_dir``; returns report.md."""
    out = Path(out_dir)
    doc = diagnosis_to_dict(cd)
    write_diagnosis_json(out, doc)
    plots = write_plots(out, cd)
    if cd.residual_analysis is not None:
        plots.insert(0, write_partial_residual_plot(out, cd.residual_analysis))
    diag, rep = cd.diagnosis, cd.diagnosis.residuals
    lines = ['# Model diagnosis', '', *[f'**WARNING**: {line}' for line in cd.set_up],
             *([''] if cd.set_up else []), f'**{diag.verdict}**', '',
             '## Residuals of the calibrated model', '',
             '| quantity | value |', '|---|---|',
             f'| measurements | {len(rep.norms)} |',
             f'| rms | {rep.rms_m * _UM:.1f} µm |',
             f'| validation rms ({_fold_name(diag.folds)}, held-out poses) | '
             f'{_validation(diag.validation_rms_m, "", " µm")} |',
             f'| noise floor σ√3 | {doc["noise_floor_m"] * _UM:.1f} µm |',
             f'| noise σ stated / robust from residuals | '
             f'{doc["residuals"]["sigma_stated_m"] * _UM:.3g} / '
             f'{rep.sigma_robust_m * _UM:.3g} µm |',
             f'| max | {rep.max_m * _UM:.1f} µm |']
    lines += [f'| {k}th percentile of \\|r\\| | {v * _UM:.1f} µm |'
              for k, v in rep.percentiles_m.items()]
    lines += [f'| χ² / dof | {rep.chi2:.1f} / {rep.dof} (p = {rep.p_value:.3g}) |',
              f'| outliers (Bonferroni, α = {rep.alpha:g}) | '
              f'{cd.given_index(rep.outlier)} |',
              f'| high leverage (> 3× mean) | {cd.given_index(rep.high_leverage)} |',
              f'| excluded by identify (not diagnosed) | {list(cd.excluded)} |']
    if cd.residual_analysis is not None:
        lines += analysis_lines(cd.residual_analysis, cd.answer)
    if cd.out_of_sample is not None:
        lines += out_of_sample_table(cd.out_of_sample)
    if cd.expected is not None:
        lines += ['', '## Expected TCP error at the working poses', '',
                  cd.expected.basis + '.', '',
                  '| working pose | tcp_std_m: parameter part (µm) | expected_tcp_error_m: '
                  'with the misfit (µm) |', '|---|---|---|']
        lines += [f'| {n} | {s * _UM:.1f} | {e * _UM:.1f} |' for n, s, e in zip(
            cd.expected.working_pose_names, cd.expected.tcp_std_m,
            cd.expected.expected_tcp_error_m)]
    lines += ['', '## Candidate effects, best first', '',
              f'F-test of each augmented fit against the geometric one, Bonferroni over '
              f'{len(diag.candidates)} candidates, family-wise α = {diag.alpha:g}. Parameter '
              '± std as identify reports them: from the stated σ when the augmented fit '
              'passes the χ² test, else scaled by its χ²/dof.', '',
              '| # | effect | significant | p | rms after (µm) | validation rms after (µm) | '
              'parameters |', '|---|---|---|---|---|---|---|']
    for i, c in enumerate(diag.candidates, 1):
        params = '; '.join(f'{n.rsplit(".", 1)[1]} = {v:.3g} '
                           + (f'± {s:.2g} {u}' if np.isfinite(s) else f'{u} (grid)')
                           for n, v, s, u in zip(c.parameter_names, c.values, c.std, c.units))
        lines.append(f'| {i} | {c.spec} | {"yes" if c.significant else "no"} | {c.p_value:.2g} '
                     f'| {c.rms_after_m * _UM:.1f} | {_validation(c.validation_rms_after_m)} '
                     f'| {params} |')
    if diag.best is not None:
        lines += ['', f'Why {diag.best.spec}: {diag.best.explanation}']
    if diag.periodograms:
        lines += ['', '## Periodic joint errors: frequency search', '',
                  'Lomb–Scargle periodogram of the residual along each joint\'s direction over '
                  'cycles per revolution (geometry refitted at each frequency); the peak is '
                  'screened as `periodic_joint_error:<joint>:k=<peak>`, its p-value multiplied '
                  'by the number of frequencies searched.', '',
                  'Frequencies within the resolution 2π/Δq (Δq the joint\'s measured range) of a '
                  'periodic error the model has on the joint are refused: over that range they '
                  'are its peak aliased.', '',
                  'A peak is a candidate only when it stands out from the best frequency '
                  'outside its resolution window (the runner-up): its margin, the difference '
                  'of their Δχ² over the residual variance the peak leaves, above what two '
                  'frequencies that explain alike reach (α = 0.01); else it is '
                  'ambiguous, as when the poses are too few for the error\'s frequency.', '',
                  '| joint | cycles/rev searched | resolution 2π/Δq | refused as aliased | peak '
                  '| Δχ² at the peak | p | runner-up | margin (needed) |',
                  '|---|---|---|---|---|---|---|---|---|']
        lines += [f'| {g.joint} | {g.cycles[0]}–{g.cycles[-1]} | {g.resolution:.3g} | '
                  f'{", ".join(map(str, g.refused)) or "none"} | {g.peak} | '
                  f'{np.max(g.power):.1f} | {g.p_value:.2g} | {g.runner_up or "none"} | '
                  f'{g.margin:.3g} ({g.margin_needed:.3g}){" ambiguous" if g.ambiguous else ""}'
                  ' |' for g in diag.periodograms]
    lines += ['', '## Not distinguishable with this data', '']
    lines += [f'- **{c.spec}**: {c.explanation}' for c in diag.not_distinguishable] or ['- none']
    if cd.comparison is not None:
        cmp = cd.comparison
        lines += ['', f'## Before/after adding {", ".join(cmp.effects)}', '',
                  '| | geometric | with effect |', '|---|---|---|',
                  f'| rms (µm) | {cmp.rms_before_m * _UM:.1f} | {cmp.rms_after_m * _UM:.1f} |',
                  f'| validation rms (µm) | {_validation(cmp.validation_rms_before_m)} | '
                  f'{_validation(cmp.validation_rms_after_m)} |',
                  f'| validation rms, held-out regions of joint space (µm) | '
                  f'{_validation(cmp.other_region_rms_before_m)} | '
                  f'{_validation(cmp.other_region_rms_after_m)} |',
                  f'| χ² p-value | {cmp.p_value_before:.3g} | {cmp.p_value_after:.3g} |']
        for name, b, a in zip(cmp.working_pose_names, cmp.tcp_std_before_m,
                              cmp.tcp_std_after_m):
            lines.append(f'| TCP {name} std (µm) | {", ".join(f"{x * _UM:.1f}" for x in b)} | '
                         f'{", ".join(f"{x * _UM:.1f}" for x in a)} |')
        lines += ['', region_verdict(cmp) + '.', '', 'Effect parameters:', '']
        lines += [f"- {p['name']} = {p['value']:.4g} ± {p['std']:.2g} {p['unit']}"
                  if 'std' in p else f"- {p['name']}: not estimated ({p['dropped']})"
                  for p in cmp.effect_parameters]
    lines += ['', '## Plots', '']
    lines += [f'![{p.stem}]({p.name})' for p in plots]
    return write_atomic(out / REPORT_FILE, '\n'.join(lines) + '\n')
