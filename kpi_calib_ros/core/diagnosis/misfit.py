"""The four answers of a diagnosis.

Where the model fails, what is missing, the command that adds it, and the error before and after
on held-out poses.

:func:`answer_misfit` combines what the diagnosis found (it takes plain remedies, so the
diagnosis's result type can hold the answer):

* *where*: the inputs the residual analysis flags
  (:mod:`kpi_calib_ros.core.diagnosis.residual_analysis`), with their shares and the ranges where
  the misfit is largest -- model-free, so it answers even when no effect does;
* *what*: the most likely named effect of the library when one is significant
  (:func:`kpi_calib_ros.core.diagnosis.verdict.diagnose`; ``named``, built by
  :func:`kpi_calib_ros.app.diagnose.named_remedy`), unless one of the ``general``
  remedies offered (any :class:`Remedy`: the learned residual, a general effect, each with
  its own command and held-out figures) removes more than twice the fraction of the
  held-out mean square it removes; and when a smooth function of the flagged inputs
  removes more than twice the fraction that remedy removes, or there is none, "a smooth
  misfit depending on X and Y that none of our effects has" (only when that function
  predicts held-out poses better than the model without it), with what the smooth
  correction gains on held-out poses (a named effect that explains a sliver of the misfit
  is not the answer). Fractions, not differences: each remedy's 'before' comes from its
  own cross-validation;
* *command* and *before/after*: of the remedy chosen.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np

from kpi_calib_ros.core.diagnosis.residual_analysis import ResidualAnalysis

__all__ = ['MisfitAnswer', 'Remedy', 'answer_misfit']

NAMED, GENERAL, SMOOTH, NONE = 'named effect', 'general effect', 'smooth misfit', 'none'
POSES = 'poses'
# What a design whose measurements do not determine the TCP misses, and what adds it.
POSES_WHAT = ('poses that determine the TCP: these measurements leave it undetermined, so no '
              'residual can show what the calibration misses there')
POSES_COMMAND = 'kpi-calib design (poses that spread every joint), then measure them'


@dataclass(frozen=True)
class Remedy:
    """What is missing and what adding it gains.

    Attributes
    ----------
    kind : str
        ``'named effect'`` (of the library), ``'general effect'`` (a general or learned
        correction), ``'smooth misfit'`` (found by the residual analysis, no command adds
        it), ``'poses'`` (the measurements do not determine the TCP) or ``'none'``.
    what : str
        One sentence naming it.
    command : str
        The option or command that adds it ('' when none does).
    held_out_before_m, held_out_after_m : float
        Rms (m) of the error on held-out poses without and with it (NaN: not estimable).
    basis : str
        How the held-out figures were obtained.
    part : str
        A smooth misfit only: the command of the remedy at hand that explains part of it
        ('' when none does).
    """

    kind: str
    what: str
    command: str = ''
    held_out_before_m: float = float('nan')
    held_out_after_m: float = float('nan')
    basis: str = ''
    part: str = ''


@dataclass(frozen=True)
class MisfitAnswer:
    """Where the model fails and what is missing (see the module docstring).

    Attributes
    ----------
    where : str
        The inputs the misfit depends on and where it is largest, or why none is named.
    inputs : tuple of str
        The flagged inputs, strongest first.
    missing : Remedy
        What is missing, the command and the held-out error before/after.
    """

    where: str
    inputs: tuple[str, ...]
    missing: Remedy

    def lines(self) -> list[str]:
        """Return the four answers as short lines for a terminal or a report."""
        m = self.missing
        held = ''
        if np.isfinite(m.held_out_before_m):
            after = (f'{m.held_out_after_m * 1e6:.1f} µm' if np.isfinite(m.held_out_after_m)
                     else 'not estimable')
            held = f'{m.held_out_before_m * 1e6:.1f} µm -> {after}'
            if m.basis:
                held += f' ({m.basis})'
        command = m.command or ('none needed' if m.kind == NONE else
                                f'none answers it alone: {m.part} explains part of it (a first '
                                'step; diagnose again after it)' if m.part else
                                'none: no effect of the library has this shape')
        return [f'where the model fails: {self.where}',
                f'what is missing: {m.what}',
                f'the command that adds it: {command}',
                f'error on held-out poses before -> after: {held or "not estimable"}']


def answer_misfit(analysis: ResidualAnalysis | None, named: Remedy | None = None,
                  general: Sequence[Remedy] = (), chi2_adequate: bool = False,
                  model_adequate: bool = False, tcp_estimable: bool = True) -> MisfitAnswer:
    """Give the four answers from the residual analysis and the remedies at hand.

    Parameters
    ----------
    analysis : ResidualAnalysis or None
        The model-free analysis of the calibration's residuals (None: not run).
    named : Remedy, optional
        The significant named effect of the screen, with its held-out figures
        (:func:`kpi_calib_ros.app.diagnose.named_remedy`).
    general : sequence of Remedy
        Other remedies (general effects, learned corrections) with their held-out figures.
    chi2_adequate, model_adequate : bool
        The χ² test passes; the diagnosis calls the model adequate.
    tcp_estimable : bool
        The measurements determine the TCP at every working pose
        (:mod:`kpi_calib_ros.core.estimation.estimability`); when they do not, what is
        missing is poses, not an effect.
    """
    flagged = analysis.significant if analysis is not None else ()
    where = _where(analysis, chi2_adequate)
    offered = [g for g in general if np.isfinite(g.held_out_after_m)
               and g.held_out_after_m < g.held_out_before_m]
    smooth = None
    # Only a smooth function that predicts held-out poses better (its own figures): on the
    # real TIAGo the flagged inputs' combined function took the held-out error from 2749
    # to 7073 µm and was named what is missing all the same.
    if flagged and analysis is not None and analysis.combined_after_m < analysis.combined_before_m:
        pair = analysis.pair
        depends = (f'{pair.names[0]} and {pair.names[1]} jointly (not a sum of one-input '
                   f'functions, F test p = {pair.p_value:.2g})' if pair and pair.significant
                   else _names(flagged))
        smooth = Remedy(
            SMOOTH, f'a smooth misfit depending on {depends} that none of our effects has',
            '', analysis.combined_before_m, analysis.combined_after_m,
            f'geometry refitted with a smooth function of {_names(flagged)}, '
            f'{analysis.folds} pose folds')
    # Remedies are compared by the fraction of the held-out mean square each removes (each
    # states its own 'before': the screen's, the learned residual's and the analysis's
    # cross-validations differ). A physical named effect stays the answer unless another
    # remedy removes more than twice its fraction.
    chosen = named
    if offered:
        best_general = max(offered, key=_gain)
        if chosen is None or _gain(best_general) > 2 * _gain(chosen):
            chosen = best_general
    if not tcp_estimable:
        # No effect is the answer while the data leave the TCP free: each would be judged
        # on residuals that cannot show the error where the data do not reach.
        missing = Remedy(POSES, POSES_WHAT, POSES_COMMAND)
    elif chosen is not None:
        missing = chosen
        # A remedy that leaves most of what a smooth correction removes is only part of
        # the answer: the smooth misfit is what is missing, the remedy a partial step.
        if smooth is not None and _gain(smooth) > 2 * _gain(missing):
            partial = (f'{smooth.what}; the best remedy at hand, {missing.command}, lowers '
                       f'the held-out error only from {missing.held_out_before_m * 1e6:.1f} '
                       f'to {missing.held_out_after_m * 1e6:.1f} µm')
            missing = Remedy(SMOOTH, partial, '', smooth.held_out_before_m,
                             smooth.held_out_after_m, smooth.basis, missing.command)
    elif smooth is not None:
        missing = smooth
    elif model_adequate:
        missing = Remedy(NONE, 'nothing: the residuals are as small as the stated σ predicts')
    else:
        missing = Remedy(NONE, 'no named effect and no smooth function of one input '
                               'explains the misfit (look at outliers, the stated σ, or an '
                               'interaction of several inputs)')
    return MisfitAnswer(where, tuple(s.name for s in flagged), missing)


def _gain(remedy: Remedy) -> float:
    """Fraction of the held-out mean square a remedy removes, 1 − after²/before².

    0 when unknown.
    """
    gain = 1.0 - (remedy.held_out_after_m / remedy.held_out_before_m) ** 2
    return float(gain) if np.isfinite(gain) else 0.0


def _names(scores: Sequence) -> str:
    names = [s.name for s in scores[:3]]
    return names[0] if len(names) == 1 else ', '.join(names[:-1]) + ' and ' + names[-1]


def _where(analysis: ResidualAnalysis | None, chi2_adequate: bool) -> str:
    if analysis is None:
        return 'not analysed'
    flagged = analysis.significant
    if not flagged:
        if chi2_adequate:
            return 'nowhere: no input explains more of the residuals than noise would'
        return ('no single input explains the misfit beyond noise (Holm over '
                f'{len(analysis.scores)} inputs, α = {analysis.alpha:g})')
    parts = [f'{s.name} (explains {s.share:.0%} of the held-out residual sum of squares, '
             f'p = {s.p_value:.2g}; {s.region})' for s in flagged[:3]]
    more = f'; {len(flagged) - 3} more inputs flagged' if len(flagged) > 3 else ''
    return '; '.join(parts) + more
