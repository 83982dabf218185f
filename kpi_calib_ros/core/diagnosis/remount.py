"""A probe remounted between recordings and not declared.

Several recordings of one robot (:mod:`kpi_calib_ros.core.measurement.recordings`) share
the reflector offsets unless a recording says its probe was remounted
(``--remounted <name>``, a manifest's ``reflector_remounted: true``). A remount left
undeclared moves one recording's points by the shift of the probe in the tip frame, which
turns with the tool: no placement of that recording's base absorbs it, the shared robot
bends to it, and every recording, the others too, is fitted millimetres off while the
identification converges and the comparison with the nominal robot (equally wrong about
the probe) can still favour it.

The test. At the calibration, the alternative in which every recording after the first
whose probe is shared has its own reflector offsets (3 per reflector) is linearised: the
columns ``A`` of the shared offsets restricted to that recording's rows are added to the
calibration's whitened Jacobian ``J``. With ``Q`` the projector off the columns of ``J``,
the residual ``Q r`` (χ² without the prior) and the fit of ``Q A`` to it, the shifts
explain ``Δ`` of it; the F statistic ``(Δ/k)/((|Qr|² − Δ)/(m − rank J − k))`` (k: the
rank of ``Q A``) does not rest on the stated σ, so a misfit the model lacks elsewhere
inflates both. The recordings disagree on the probe (:attr:`RemountTest.disagrees`) when the
F test rejects at :data:`ALPHA` AND the shifts explain at least :data:`FRACTION` of the
calibration's χ²: a significant shift that explains a sliver of the misfit is a model
that lacks something else (the shifts absorb a little of anything), not a probe.
Each recording's shift (the offsets it would have minus the shared ones, in the tip
frame) is reported with its std at the residual scatter after the shifts; the recordings
named are those whose own shift is significant (Wald χ²₃ at :data:`ALPHA`).

Measured. Simulated (``test/test_recordings.py``, the audit's campaign through
``kpi-calib identify``): three set-ups of 40 poses, σ 20 µm, the third's probe moved
[4, -3, 10] mm and not declared: χ²/dof 2.67e6/321, the shifts explain 98.8 % of it and
name that recording alone, its shift [3.97, -2.99, 9.85] mm; declared, the test of the
set-up still sharing the probe explains 1 % (p = 0.37). Real UR10 (../shared/data/ipa_ur10,
1200 poses of Series A, 316 of D): A split into two recordings of 600, 0.05 % (p = 0.30);
A and D (the probe remounted months later) undeclared, significant (p = 8e-15, x shifted
0.21 ± 0.03 mm) but 1.3 % of a χ² the model's misfit dominates: not named. Real TIAGo
(../shared/data/tiago_mocap, four markers): three sessions of one afternoon, 0.75 %
(p = 0.95); two days, markers 1-2 mm apart (p = 7e-13) and 7.2 % of χ²: not named.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.stats

from kpi_calib_ros.core.estimation.least_squares import CalibrationResult
from kpi_calib_ros.core.estimation.residuals import linearized_fit
from kpi_calib_ros.core.measurement.data import Measurements
from kpi_calib_ros.core.measurement.recordings import reflector_names, row_recording
from kpi_calib_ros.core.measurement.tracker import MeasurementModel
from kpi_calib_ros.core.measurement.weighting import weighted_rows
from kpi_calib_ros.core.model.parameters import reflector_prefixes

__all__ = ['ALPHA', 'FRACTION', 'RecordingShift', 'RemountTest', 'remount_test']

# Level of the F test and of each recording's Wald test.
ALPHA = 1e-3
# Share of the calibration's χ² the shifts must explain to call the probe moved.
FRACTION = 0.5


@dataclass(frozen=True)
class RecordingShift:
    """One recording's probe shift from the shared offsets (m, tip frame, per reflector)."""

    name: str
    shift_m: np.ndarray       # (n_reflectors, 3)
    std_m: np.ndarray         # (n_reflectors, 3)
    p_value: float            # Wald χ² of the shift being zero

    @property
    def significant(self) -> bool:
        """Whether the shift is beyond its noise at :data:`ALPHA`."""
        return bool(self.p_value < ALPHA)

    @property
    def size_m(self) -> float:
        """The largest reflector's shift length (m)."""
        return float(np.max(np.linalg.norm(self.shift_m, axis=1)))


@dataclass(frozen=True)
class RemountTest:
    """Whether recordings that share the probe disagree on it (module docstring)."""

    chi2: float               # |Q r|², the calibration's χ² off its own columns (no prior)
    explained: float          # Δ: what the per-recording offsets take of it
    f_stat: float
    p_value: float
    shifts: tuple[RecordingShift, ...]

    @property
    def fraction(self) -> float:
        """Share of the χ² the shifts explain."""
        return self.explained / self.chi2 if self.chi2 > 0 else 0.0

    @property
    def disagrees(self) -> bool:
        """Whether the recordings disagree on the probe: F test and share of χ²."""
        return bool(self.p_value < ALPHA and self.fraction >= FRACTION
                    and any(s.significant for s in self.shifts))

    @property
    def moved(self) -> tuple[RecordingShift, ...]:
        """The recordings whose own shift is significant."""
        return tuple(s for s in self.shifts if s.significant)

    def text(self) -> str:
        """One line: who moved, by how much, how much of χ² it explains, and the fix."""
        who = ', '.join(f'{s.name!r} by {s.size_m * 1e3:.3g} mm '
                        f'({_vector_mm(s.shift_m)})' for s in self.moved)
        names = ' '.join(f'--remounted {s.name}' for s in self.moved)
        return (f'the recordings disagree on the probe: the reflector offsets of {who} '
                f'(tip frame) explain {100 * self.fraction:.4g} % of the calibration\'s χ² '
                f'(F = {self.f_stat:.3g}, p = {self.p_value:.2g}); a probe remounted '
                f'between recordings must be declared: pass {names} (a manifest: '
                'reflector_remounted: true; the node: station_reflector_remounted:=true '
                'before a station is measured, or kpi-calib identify on its logs with '
                '--remounted), or, when it was not remounted, the recordings measure a '
                'different tool or robot')

    def to_dict(self) -> dict:
        """YAML-ready figures (m)."""
        return {'disagrees': self.disagrees, 'chi2': float(self.chi2),
                'explained_fraction': float(self.fraction), 'f': float(self.f_stat),
                'p_value': float(self.p_value),
                'shifts': [{'recording': s.name, 'shift_m': s.shift_m.tolist(),
                            'std_m': s.std_m.tolist(), 'p_value': float(s.p_value),
                            'significant': s.significant} for s in self.shifts]}


def _vector_mm(shift: np.ndarray) -> str:
    return '; '.join('[' + ', '.join(f'{v * 1e3:.3g}' for v in row) + '] mm' for row in shift)


def remount_test(model: MeasurementModel, data: Measurements,
                 result: CalibrationResult) -> RemountTest | None:
    """Test whether the recordings of ``data`` that share the probe disagree on it.

    ``result`` is the calibration of ``model`` on ``data`` (every row kept by it). None with
    no recording after the first that shares the first's probe, or no degrees of freedom.
    """
    params = model.params
    shared = [r for r in model.recordings
              if not any(n in params.names for p in reflector_prefixes(params)
                         for n in reflector_names(r, p))]
    if not shared:
        return None
    prefixes = reflector_prefixes(params)
    cols = params.indices([f'{p}.{c}' for p in prefixes for c in 'xyz'])
    sys_ = linearized_fit(model, data, result)
    q = np.atleast_2d(data.q)
    _, jac = model.jacobian(sys_.p, q, sys_.tau, data.reflector, data.rotation,
                            data.covariates)
    a_all = weighted_rows(jac, sys_.w, cols)                  # (3N, 3R)
    index = np.repeat(row_recording(data, ('',) + tuple(model.recordings)), 3)
    blocks = []
    for name in shared:
        i = 1 + list(model.recordings).index(name)
        blocks.append(np.where((index == i)[:, None], a_all, 0.0))
    a = np.hstack(blocks)
    basis = sys_.basis
    qr_ = sys_.r - basis @ (basis.T @ sys_.r)
    qa = a - basis @ (basis.T @ a)
    chi2 = float(qr_ @ qr_)
    coef, _, rank, sv = np.linalg.lstsq(qa, qr_, rcond=None)
    fitted = qa @ coef
    explained = float(fitted @ fitted)
    dof = len(qr_) - basis.shape[1] - rank
    if rank == 0 or dof <= 0 or chi2 <= 0:
        return None
    rest = max(chi2 - explained, 0.0)
    scale = rest / dof                                       # residual variance, whitened
    f_stat = (explained / rank) / scale if scale > 0 else float('inf')
    p_value = float(scipy.stats.f.sf(f_stat, rank, dof))
    cov = np.linalg.pinv(qa.T @ qa, rcond=1e-10) * scale
    n_ref = len(prefixes)
    shifts = []
    for k, name in enumerate(shared):
        sl = slice(3 * n_ref * k, 3 * n_ref * (k + 1))
        delta, c = coef[sl], cov[sl, sl]
        wald = float(delta @ np.linalg.pinv(c, rcond=1e-10) @ delta)
        r = int(np.linalg.matrix_rank(c, tol=1e-12 * max(np.abs(c).max(), 1e-300)))
        p = float(scipy.stats.chi2.sf(wald, r)) if r else 1.0
        std = np.sqrt(np.clip(np.diag(c), 0, None))
        shifts.append(RecordingShift(name, delta.reshape(n_ref, 3), std.reshape(n_ref, 3), p))
    return RemountTest(chi2, explained, f_stat, p_value, tuple(shifts))
