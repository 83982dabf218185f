"""A restarted node serves its last valid calibration.

At start, data_dir/calibration.yaml (written by the last valid ``~/identify`` or stopped
sequential campaign) is read back once the robot model is known, before anything is
identified, and checked against the current cell and robot description
(:func:`~kpi_calib_ros.app.stored_calibration.read_stored_calibration`). A calibration
that fits is published again as ``~/identify`` published it: the latched
``~/calibration`` (the file's text), the calibrated robot description, ``~/tcp`` and the
markers' TCP; ``~/tcp_query`` answers with it and /diagnostics says where it came from.
A damaged or invalid file, or one of another cell or robot, is logged with the file and
the reason, and the node starts without a calibration, as it would without the file.
"""
from __future__ import annotations

import numpy as np
from std_msgs.msg import String

from kpi_calib_ros.app.stored_calibration import read_stored_calibration
from kpi_calib_ros.core.errors import DataError, KpiCalibError
from kpi_calib_ros.io.fitted_stamps import read_fitted_stamps
from kpi_calib_ros.io.names import CALIBRATION_FILE, FITTED_STAMPS_FILE, LEARNED_RESIDUAL_FILE
from kpi_calib_ros.io.result_set import complete_pending
from kpi_calib_ros.ros import conversions as cv
from kpi_calib_ros.ros.node_parts import NodeParts


class CalibrationRestore(NodeParts):
    """The restore job of :class:`~kpi_calib_ros.ros.node.CalibrationNode`, on the state,
    publishers and methods :class:`~kpi_calib_ros.ros.node_parts.NodeParts` declares."""

    def _find_calibration(self) -> None:
        """At start: a calibration.yaml in data_dir is restored once the robot model is
        known (``restore_pending``). A result set a killed job had committed but not
        moved into place is completed first (:mod:`kpi_calib_ros.io.result_set`)."""
        complete_pending(self.data_dir)
        self._run.restore_pending = (self.data_dir / CALIBRATION_FILE).is_file()

    async def _restore(self) -> tuple[bool, str]:
        """Read data_dir/calibration.yaml back for this cell and publish it as the
        calibration; DataError (logged by the job) names the file and why it is not used."""
        cm, path = self._model(), self.data_dir / CALIBRATION_FILE
        if self._run.result is not None:  # a job of this run published one first
            return True, f'{path} not restored: this run has published a newer calibration'
        try:
            stored = await self._offload(read_stored_calibration, cm, path)
        except KpiCalibError as exc:
            raise DataError(f'{exc}; the node starts without a calibration (call '
                            '~/identify)') from None
        # ~/validate tests on what was measured after it: the stamps the node wrote when it
        # published this calibration; without them, the restored measurements stamped up
        # to the calibration's last one.
        stamp = stored.identified_at_ns
        fitted = read_fitted_stamps(self.data_dir / FITTED_STAMPS_FILE, stored.text)
        if fitted is None and stamp is not None and len(self.store):
            # The stamps alone: no temperature reading needed (none may have arrived yet).
            stamps = np.asarray(self.store.measurements(
                cm.joint_names, cm.cell.tracker_frame, cm.cell.reflector_names or ('',)
            )[0].stamps_ns).ravel()
            fitted = {int(t) for t in stamps if t <= stamp}
        fitted = fitted or set()
        run = self._run
        run.restored, run.cell, run.identified_with = stored, stored.cell, stored.measurements
        section = stored.doc.get('learned_residual')
        if isinstance(section, dict):  # as ~/identify with identify_learned_residual said
            run.learned_residual = ('chosen' if section.get('file') and (
                self.data_dir / LEARNED_RESIDUAL_FILE).is_file() else 'not chosen')
        self._pub_calibration.publish(String(data=stored.text))
        self._calibration_text, self._identified_stamps = stored.text, fitted
        self._pub_urdf.publish(String(data=stored.urdf))
        publisher = self._tcp_publisher(len(stored.tcp))
        for msg in cv.tcp_pose_msgs(stored.tcp, stored.tcp_covariance,
                                    stored.cell.cell.tracker_frame, stamp or 0):
            publisher.publish(msg)
        self._publish_markers()
        self._publish_diagnostics(force=True)
        return True, stored.summary()


__all__ = ['CalibrationRestore']
