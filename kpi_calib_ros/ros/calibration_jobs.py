"""The node's jobs on the accepted measurements: ``~/identify``, ``~/diagnose`` and
``~/validate``, and publishing a calibration.

``~/identify`` fits every accepted measurement (as ``kpi-calib identify``), writes the
results atomically and publishes them (:meth:`CalibrationJobs._publish_calibration`, which
a stopped sequential campaign also uses); a fit that is not valid, or a change beyond the
drift model, is not published and the last good calibration stays. ``~/diagnose`` and
``~/validate`` run ``kpi-calib diagnose`` and ``kpi-calib validate`` on the same
measurements. The computation is in :mod:`kpi_calib_ros.ros.job_work` (worker threads or a
child process); these coroutines run on the executor and update the node's
:class:`~kpi_calib_ros.ros.run_state.RunState` and publishers.
"""
from __future__ import annotations

import json
from typing import Any

import numpy as np
from std_msgs.msg import String

from kpi_calib_ros.app.validate import passed
from kpi_calib_ros.core.errors import DataError
from kpi_calib_ros.core.estimation.drift_state import DriftSwing
from kpi_calib_ros.core.estimation.precision import precision_statement
from kpi_calib_ros.io.fitted_stamps import write_fitted_stamps
from kpi_calib_ros.io.names import FITTED_STAMPS_FILE
from kpi_calib_ros.ros import job_work
from kpi_calib_ros.ros.answers import identify_answer, validate_answer
from kpi_calib_ros.ros.node_parts import NodeParts
from kpi_calib_ros.ros.stored_measurements import model_measurements, station_measurements


class CalibrationJobs(NodeParts):
    """The identify, diagnose and validate jobs of
    :class:`~kpi_calib_ros.ros.node.CalibrationNode`, on the state, publishers and methods
    :class:`~kpi_calib_ros.ros.node_parts.NodeParts` declares."""

    def _publish_calibration(self, cal: Any, measured: np.ndarray, marker_rows: np.ndarray,
                             identified_with: int, text: str, urdf: str, tcp: list,
                             stamps: np.ndarray | None) -> None:
        """Make ``cal`` (fitted to ``measured`` (m), of which ``marker_rows`` are points,
        from ``identified_with`` measurements stamped ``stamps``) the published
        calibration: ~/calibration, the calibrated URDF, ~/tcp and the markers."""
        self._run.robust, self._run.result = cal.robust, cal.result
        self._run.cell, self._run.restored = cal.cell, None
        self._run.learned_residual = ''  # data_dir/learned_residual.yaml was removed
        self._run.measured, self._run.marker_rows = measured, marker_rows
        self._run.identified_with = identified_with
        self._identifications += 1
        self._run.result_error = ''
        self._pub_calibration.publish(String(data=text))
        self._calibration_text = text
        self._identified_stamps = {int(t) for t in np.asarray(stamps).ravel()}
        try:  # for ~/validate after a restart (the calibration does not list them)
            write_fitted_stamps(self.data_dir / FITTED_STAMPS_FILE, text,
                                self._identified_stamps)
        except OSError as exc:
            self.get_logger().warning(f'{FITTED_STAMPS_FILE} not written ({exc}): after a '
                                      'restart, ~/validate takes the measurements stamped '
                                      "up to the calibration's last one as fitted")
        self._pub_urdf.publish(String(data=urdf))
        publisher = self._tcp_publisher(len(tcp))
        for msg in tcp:
            publisher.publish(msg)
        self._publish_markers()

    async def _identify(self) -> tuple[bool, str]:
        """Identify from every accepted measurement (as ``kpi-calib identify`` does);
        write the results atomically and publish them. Refused while a sequential campaign
        runs: its calibration is published when it stops, never one of part of it."""
        cm = self._model()
        if self._run.sequential_running():
            raise DataError('a sequential campaign is running: its calibration is published '
                            'on ~/calibration when it stops (~/campaign_status); call '
                            '~/reset to end it')
        try:
            # Pairing the measured inputs is part of the identification: a declared input
            # that never arrived left /diagnostics OK after the refusal.
            cm, data, pairing, stations = station_measurements(self.store, cm)
            out = await self._offload(
                job_work.identify_work, cm, data, pairing, self.data_dir,
                self.settings.reidentify_with_prior,
                DriftSwing(*self.settings.drift_velocity) if self.settings.drift_velocity
                else None,
                not self._run.campaign_inadequate(), self.settings.identify_learned_residual,
                stations, child=True)
        except Exception as exc:  # job boundary: also a full disk or a lost data_dir
            where = (f' (results not written to {self.data_dir})'
                     if isinstance(exc, OSError) else '')
            self._run.result_error = f'identification failed{where}: {exc}'
            self._publish_diagnostics(force=True)
            raise
        cal, change, prior, notes, learned = (out.calibration, out.change, out.prior,
                                              out.notes, out.learned)
        for note in notes:  # which prior, or why none; archived files skipped
            self.get_logger().warning(note)
        if change is not None:
            # Latched: the last re-identification's innovation test, consistent or not.
            self._pub_change_test.publish(String(data=json.dumps(
                {'prior': prior, 'measurements': len(data), **change.to_dict()}, allow_nan=False)))
        if cal is None:
            # A change beyond the drift model: not blended, never published as the
            # calibration; the last good one stays; /diagnostics says ERROR.
            assert change is not None
            self._run.result_error = change.summary()
            self.get_logger().error(f'identification from {len(data)} measurements with prior '
                                    f'{prior}: {change.summary()}')
            self._publish_diagnostics(force=True)
            return False, ('change detected, last good calibration kept: moved '
                           + (', '.join(m.name for m in change.moved) or 'no single parameter')
                           + '; measure a full campaign')
        result = cal.result
        if not cal.valid:
            # Never published as the calibration: the last good one stays on every topic
            # and in calibration.yaml; /diagnostics says ERROR with the reason.
            reason = ' | '.join(cal.problems)
            self._run.result_error = f'calibration not published: {reason}'
            self.get_logger().error(f'identification from {len(data)} measurements not '
                                    f'valid, last good calibration kept: {reason}')
            self._publish_diagnostics(force=True)
            return False, f'not published (last good calibration kept): {reason}'
        for e in cal.robust.excluded:
            self.get_logger().warning(e.text())
        for text in cal.robust.warnings:
            self.get_logger().warning(text)
        # Residual arrows: the fitted (kept) rows that are points; a tracked pose's
        # rotation row is no point to draw from.
        kept = np.asarray(cal.robust.kept, dtype=bool)
        points = (np.ones(len(data), dtype=bool) if data.reflector is None
                  else np.asarray(data.reflector) < cm.model.n_reflectors)
        self._publish_calibration(cal, data.eta[kept], points[kept], len(data), out.text,
                                  out.urdf, list(out.tcp), data.stamps_ns)
        # ~/tcp_query reads data_dir/learned_residual.yaml (written or removed with the set).
        self._run.learned_residual = learned[0]
        self._publish_diagnostics(force=True)
        if result.covariance_scale != 1.0:
            self.get_logger().warning('TCP and parameter std ' + precision_statement(
                result.covariance_scale, result.joint_sigma))
        if out.stations:
            self.get_logger().info(out.stations)
        rejected = {r: n for r, n in sorted(self.store.rejections.items()) if n}
        if rejected:  # a whole station's rows can be among them (stamps received before)
            notes = [*notes, 'rejected on arrival, not in this fit: ' + ', '.join(
                f'{n} {r}' for r, n in rejected.items()) + ' (counted on /diagnostics)']
        answer = identify_answer(len(data), cal, prior, notes, self.data_dir, learned[1])
        return True, answer + (f'\n{out.stations}' if out.stations else '')

    async def _diagnose(self) -> tuple[bool, str]:
        """Model diagnosis of the accepted measurements (as ``kpi-calib diagnose``): residual
        report, adequacy and the most likely missing effect; report files and ~/diagnosis."""
        cm, data, _, _ = station_measurements(self.store, self._model())
        doc, text, verdict, report = await self._offload(job_work.diagnose_work, cm, data,
                                                         self.data_dir, child=True)
        self._run.diagnosis = doc
        self._pub_diagnosis.publish(String(data=text))
        self._publish_diagnostics(force=True)
        # As ~/identify: a design that does not determine the TCP is no success.
        return doc.get('tcp_estimability', {}).get('tcp_estimable', True), \
            f'{verdict} Report: {report}'

    async def _validate(self) -> tuple[bool, str]:
        """Validate the last calibration on the measurements accepted since it was
        identified (as ``kpi-calib validate``): ~/validation, data_dir/validation/."""
        cm = self._model()
        if not self._calibration_text:
            raise DataError('no calibration to validate yet: call ~/identify first')
        data, pairing = model_measurements(self.store, cm)
        new = np.isin(np.asarray(data.stamps_ns),
                      np.fromiter(self._identified_stamps, dtype=np.int64), invert=True)
        if not new.any():
            raise DataError('no measurement accepted since the last identification; measure '
                            'new poses with auto_identify:=false, then call ~/validate')
        fresh = data.subset(new)
        stations, _ = self.store.stations(np.asarray(fresh.stamps_ns))
        if len(stations) > 1:
            raise DataError('the measurements since the last identification come from '
                            f"{len(stations)} stations ({', '.join(r.name for r in stations)}): "
                            'validate one station at a time (validate_register registers a '
                            'new one); call ~/identify to identify them together')
        doc, text = await self._offload(job_work.validate_work, cm, self._calibration_text, fresh,
                                        self.data_dir, self.settings.validate_register or None,
                                        stations[0].name if stations else '')
        self._pub_validation.publish(String(data=text))
        return passed(doc), validate_answer(doc)


__all__ = ['CalibrationJobs']
