"""Result files: calibration.yaml and small helpers to write files atomically.

:func:`calibration_to_dict` writes the identification itself; the application layer
(:func:`kpi_calib_ros.app.calibration_document.add_robust_sections`) adds ``valid`` /
``invalid_reasons``, ``model`` (level, every level's ``predicted_rms_m`` and
``cv_rms_m``, reason), ``robust``
(``sigma_stated_m``, ``sigma_robust_m``, ``sigma_ratio``, ``loss``, ``loss_scale``,
``outlier_threshold_sigma``, ``excluded`` [{index, stamp_ns, distance_m, distance_sigma,
reason}], ``outliers``, ``used_indices``, ``warnings``) and ``tcp_estimable`` /
``tcp_estimability`` (per pose: ``estimable``, ``relative_residual``,
``not_determined``); a TCP entry that is not determined has ``std``, ``covariance`` and
``trace_m2`` null. An invalid document is written as calibration.failed.yaml.
"""
from __future__ import annotations

import os
import tempfile
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from kpi_calib_ros.core.acquisition.outcomes import PairingResult
from kpi_calib_ros.core.errors import ConfigError
from kpi_calib_ros.core.estimation.least_squares import CalibrationResult
from kpi_calib_ros.core.estimation.precision import precision_statement
from kpi_calib_ros.core.estimation.residuals import (
    SIGMA_OVERSTATED,
    is_adequate,
    noise_verdict,
    sigma_overstated_text,
)
from kpi_calib_ros.io.names import CALIBRATION_FILE, truth_path
from kpi_calib_ros.io.yaml_bounded import dump_yaml


def _umask() -> int:
    # Read, not set-and-restore: os.umask() would change it for every thread meanwhile.
    try:
        with open('/proc/self/status') as f:
            for line in f:
                if line.startswith('Umask:'):
                    return int(line.split()[1], 8)
    except OSError:
        pass
    return 0o022


def write_atomic(path: str | Path, text: str) -> Path:
    """Write ``text`` so readers see the old file or the new one, never a partial one."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f'.{path.name}.')
    try:
        # mkstemp creates 0600; results are for the cell (HMI, other users): 0644 less umask.
        os.fchmod(fd, 0o644 & ~_umask())
        with os.fdopen(fd, 'w') as f:
            f.write(text)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return path


def writable_folder(path: str | Path, key: str = 'out') -> Path:
    """Create folder ``path`` if needed and prove a file can be written in it (read-only
    file system, permissions, a file in the way), so a command fails before its
    computation, not after; a file-system root (``/``) is refused. ConfigError names
    ``key``."""
    path = Path(path)
    resolved = path.resolve()
    if resolved.parent == resolved:
        # Results are a folder of files (calibration.yaml, plots, validation/...) that a
        # later run replaces: never spread over a file system's root.
        raise ConfigError(key, f'{str(path)!r} is the root of a file system: the results '
                          '(calibration.yaml, plots, ...) would be written and replaced '
                          'there; give a folder of their own, e.g. ./calibration_out')
    try:
        path.mkdir(parents=True, exist_ok=True)
        with tempfile.TemporaryFile(dir=path, prefix='.write_test.'):
            pass
    except OSError as exc:
        raise ConfigError(key, f'cannot write results to {str(path)!r}: '
                          f'{exc.strerror or exc}; give a writable folder') from None
    return path


def writable_file(path: str | Path, key: str = 'out', example: str = 'out') -> Path:
    """Check that file ``path`` can be written, before a command computes it: a folder
    (``/``, an existing directory) is refused, so is a folder that cannot be written
    (read-only, permissions; the nearest existing one when the folder is still to be
    made), and a file in the way. ConfigError names ``key`` and
    suggests ``example`` (a file name) in the folder given."""
    path = Path(path)
    if str(path).endswith(('/', os.sep)) or path.is_dir():
        inside = Path(example) if path.resolve() == path.resolve().parent else path / example
        raise ConfigError(key, f'{str(path)!r} is a folder: give the file to write, e.g. '
                          f'{str(inside)!r}')
    # Nothing is created here: the nearest existing folder must take a new file.
    parent = path.parent
    while not parent.exists() and parent != parent.parent:
        parent = parent.parent
    try:
        if not parent.is_dir():
            raise NotADirectoryError(0, f'{parent} is a file, not a folder')
        with tempfile.TemporaryFile(dir=parent, prefix='.write_test.'):
            pass
    except OSError as exc:
        raise ConfigError(key, f'cannot write {str(path)!r}: {exc.strerror or exc}; give a '
                          'file in a writable folder') from None
    return path


def _point_sigma_summary(result: CalibrationResult) -> dict[str, Any] | None:
    if result.point_sigma is None:
        return None
    rows = np.asarray(result.point_sigma)
    own = np.any(rows != np.asarray(result.sigma), axis=1)
    return {'rows': int(own.sum()),
            'mean': [float(v) for v in rows[own].mean(axis=0)] if own.any() else None,
            'max': [float(v) for v in rows[own].max(axis=0)] if own.any() else None}


def calibration_to_dict(result: CalibrationResult,
                        pairing: PairingResult | None = None) -> dict[str, Any]:
    """YAML-ready description of a calibration (SI units, stable parameter names)."""
    std = dict(zip(result.estimated, result.std))
    parameters = []
    for name, value, unit in zip(result.names, result.values, result.units):
        entry = {'name': name, 'value': float(value), 'unit': unit,
                 'estimated': name in std}
        if name in std:
            entry['std'] = float(std[name])
        parameters.append(entry)
    tcp = []
    for name, point, cov in zip(result.working_pose_names, result.tcp, result.tcp_covariance):
        tcp.append({'name': name, 'position': [float(x) for x in point],
                    'covariance': [[float(x) for x in row] for row in cov],
                    'std': [float(x) for x in np.sqrt(np.diag(cov))],
                    'trace_m2': float(np.trace(cov))})
    verdict, lower_p = noise_verdict(float(result.chi2), int(result.dof))
    doc: dict[str, Any] = {
        'status': {'converged': bool(result.converged), 'code': int(result.status),
                   'message': result.message, 'iterations': int(result.iterations)},
        'measurements': int(len(result.residuals)),
        'rms_m': float(result.rms_m),
        'max_residual_m': float(np.max(np.linalg.norm(result.residuals, axis=1))),
        'noise_sigma_m': [float(s) for s in result.sigma],
        # The tracker's own σ per point (m) where the data stated it, weighing those rows in
        # place of noise_sigma_m: how many rows, their mean and largest σ per axis; null: none.
        'noise_point_sigma_m': _point_sigma_summary(result),
        # noise.joint_sigma the fit carried (rad, chain order); null: exact joint readings.
        'noise_joint_sigma_rad': (None if result.joint_sigma is None
                                  else [float(s) for s in result.joint_sigma]),
        # `adequate`: the upper tail (the model); `noise_verdict`: the lower tail (the
        # stated σ; core.estimation.residuals.noise_verdict), each at the adequacy level.
        'model_adequacy': {'chi2': float(result.chi2), 'dof': int(result.dof),
                           'p_value': float(result.p_value),
                           'adequate': is_adequate(result.p_value),
                           'noise_verdict': verdict, 'lower_tail_p': lower_p},
        # Which σ the std and covariances below rest on (core.estimation.precision).
        'precision': {'covariance_scale': float(result.covariance_scale),
                      'basis': precision_statement(float(result.covariance_scale),
                                                   result.joint_sigma)},
        'parameters': parameters,
        # Not identifiable: held fixed (at the prior, or where an earlier selection round
        # left it); their value is a choice of gauge, not a measurement.
        'dropped_parameters': [{'name': d.name, 'reason': d.reason} for d in result.dropped],
        'tcp': tcp,
        'residuals_m': [[float(x) for x in r] for r in result.residuals],
    }
    # The full C_p of the identified parameters (m, rad): `kpi-calib validate` predicts
    # the error of new points from it.
    doc['parameter_covariance'] = {'names': list(result.estimated),
                                   'matrix': [[float(x) for x in row]
                                              for row in result.covariance]}
    if pairing is not None:
        doc['pairing'] = {'accepted': int(len(pairing)),
                          'rejected': {k: int(v) for k, v in sorted(pairing.rejections.items())}}
        if len(pairing):
            # When the robot was as calibrated: a later campaign widens this calibration,
            # used as its prior, by the drift since then (core.estimation.prior.drift_widened).
            # Stamps that number a table's rows are no date: then none is stated.
            if pairing.stamps_are_times:
                doc['identified_at_ns'] = int(np.max(pairing.stamps_ns))
            # The joint ranges the calibration has seen: validation marks poses beyond them.
            doc['training_joint_ranges'] = {
                name: [float(lo), float(hi)] for name, lo, hi in zip(
                    pairing.joint_names, pairing.q.min(axis=0), pairing.q.max(axis=0))}
            # The poses themselves, once each: validation tells a pose measured again
            # (repeatability) from a new one (generalisation).
            doc['training_configurations'] = {
                'joints': list(pairing.joint_names),
                'q': [[float(x) for x in row] for row in np.unique(pairing.q, axis=0)]}
    return doc


def write_calibration(out_dir: str | Path, doc: dict[str, Any]) -> Path:
    return write_atomic(Path(out_dir) / CALIBRATION_FILE, dump_yaml(doc))


def write_truth(bag_path: str | Path, truth: dict[str, Any]) -> Path:
    """Write the simulated truth of a bag to ``<bag>.truth.yaml``."""
    return write_atomic(truth_path(bag_path), dump_yaml(truth))


def read_truth(bag_path: str | Path) -> dict[str, Any]:
    """The simulated truth written next to a simulated bag (``<bag>.truth.yaml``)."""
    return yaml.safe_load(truth_path(bag_path).read_text())


def summary_text(doc: dict[str, Any]) -> str:
    """Readable summary of a calibration document for a terminal."""
    lines = [f"measurements: {doc['measurements']}"]
    if 'pairing' in doc:
        rej = doc['pairing']['rejected']
        lines.append(f"rejected: {sum(rej.values())} {rej if rej else ''}".rstrip())
    est = [p for p in doc['parameters'] if p['estimated']]
    lines += [f"status: {doc['status']['message']}",
              f"identified parameters: {len(est)} (dropped {len(doc['dropped_parameters'])})",
              f"rms residual: {doc['rms_m'] * 1e6:.1f} µm  "
              f"(max {doc['max_residual_m'] * 1e6:.1f} µm)",
              f"model adequacy: chi2/dof = {doc['model_adequacy']['chi2']:.1f}/"
              f"{doc['model_adequacy']['dof']}, p = {doc['model_adequacy']['p_value']:.3g}"]
    lines += [f'WARNING: {w}' for w in doc.get('warnings', [])]
    adequacy = doc['model_adequacy']
    if adequacy.get('noise_verdict') == SIGMA_OVERSTATED:
        lines.append('WARNING: ' + sigma_overstated_text(adequacy['chi2'], adequacy['dof'],
                                                         adequacy['lower_tail_p']))
    precision = doc.get('precision', {})
    if precision.get('covariance_scale', 1.0) != 1.0:
        lines.append(f"WARNING: std {precision['basis']}")
    if not doc['tcp']:
        lines.append('TCP: none reported (the cell gives no working_poses; add them to '
                     'estimate the KPI points and their covariance)')
    for t in doc['tcp']:
        if t.get('std') is None:
            lines.append(f"TCP {t['name']}: NOT DETERMINED by the measurements (not estimable)")
            continue
        s = ', '.join(f'{x * 1e6:.1f}' for x in t['std'])
        lines.append(f"TCP {t['name']}: std [{s}] µm, "
                     f"sqrt(trace) {np.sqrt(t['trace_m2']) * 1e6:.1f} µm")
    return '\n'.join(lines)
