"""The node's sequential campaign (``campaign:=sequential``) as jobs.

``~/design`` starts the campaign and publishes its initial design; each accepted
measurement then makes a step due (:meth:`RunState.sequential_due
<kpi_calib_ros.ros.run_state.RunState.sequential_due>`), which adds what the campaign
has not seen, re-identifies and publishes the next poses and ``~/campaign_status``;
a campaign data_dir/campaign_state.yaml keeps is resumed after a restart. The
computation is in :mod:`kpi_calib_ros.ros.job_work` (worker threads); these coroutines
run on the executor and update the node's :class:`~kpi_calib_ros.ros.run_state.RunState`.
"""
from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np
import yaml
from std_msgs.msg import String

from kpi_calib_ros.app.cell_model import CellModel
from kpi_calib_ros.core.campaigns.settings import STATION_CHANGED
from kpi_calib_ros.core.errors import DataError, KpiCalibError
from kpi_calib_ros.core.measurement.data import Measurements
from kpi_calib_ros.io.campaign_io import CampaignState, read_campaign_state, write_campaign_state
from kpi_calib_ros.io.names import (
    CAMPAIGN_PRIOR_FILE,
    CAMPAIGN_STATE_FILE,
    MEASUREMENT_POSES_TOPIC,
)
from kpi_calib_ros.ros import conversions as cv
from kpi_calib_ros.ros import job_work
from kpi_calib_ros.ros.answers import campaign_progress
from kpi_calib_ros.ros.node_parts import NodeParts
from kpi_calib_ros.ros.stored_measurements import model_measurements, station_rows


class SequentialCampaignJobs(NodeParts):
    """The sequential campaign's jobs of :class:`~kpi_calib_ros.ros.node.CalibrationNode`,
    on the state, publishers and methods :class:`~kpi_calib_ros.ros.node_parts.NodeParts`
    declares."""

    def _find_campaign_state(self) -> None:
        """At start: a sequential campaign data_dir/campaign_state.yaml keeps is resumed
        (_resume) once the robot model is known, before anything is identified."""
        state_path = self.data_dir / CAMPAIGN_STATE_FILE
        if state_path.is_file():
            try:
                self._run.sequential_state = read_campaign_state(state_path)
            except DataError as exc:
                self._run.result_error = f'sequential campaign not resumed: {exc}'
                self.get_logger().error(self._run.result_error)
            else:
                stopped = self._run.sequential_state.status.get('stop_reason')
                if stopped == STATION_CHANGED:  # stopped by the node: nothing to resume
                    self._run.sequential_stopped = STATION_CHANGED
                    self.get_logger().info(f'sequential campaign found in {state_path} '
                                           f'stopped: {STATION_CHANGED}')
                    return
                self._run.resume_pending = True
                self.get_logger().info(
                    f'sequential campaign found in {state_path} '
                    f'({len(self._run.sequential_state.steps)} step(s), '
                    f"{self._run.sequential_state.status.get('stop_reason', 'running')}): "
                    'resuming it once the robot model is known')

    def _stop_for_station(self, before: tuple[str, bool], now: tuple[str, bool]) -> None:
        """The station changed under a running sequential campaign (the tracker moved, or
        the probe was remounted): the campaign plans and identifies from one placement, so it
        stops here, its plan withdrawn (an empty ~/measurement_poses) and ``stop_reason``
        :data:`STATION_CHANGED` in ~/campaign_status and campaign_state.yaml (a restart does
        not resume it). Its measurements stay: ``~/identify`` takes every station together,
        and a campaign at the new station, started with ``~/design`` once a calibration
        holds it, plans with that calibration as prior. The station change was refused
        before, and a campaign that lost the line of sight could go on only after
        ``~/reset`` archived its measurements."""
        state = self._run.sequential_state
        self._run.sequential_stopped = STATION_CHANGED
        advice = (f'measure a few poses at station {now[0]!r}, call ~/identify (every '
                  'station together), then ~/design with campaign:=sequential plans there '
                  'with that calibration as prior')
        if state is not None:
            doc = {**state.status, 'stop_reason': STATION_CHANGED,
                   'station_changed': {'from': before[0], 'to': now[0],
                                       'probe_remounted': now[1]},
                   'next': advice}
            state = dataclasses.replace(state, status=doc)
            self._run.sequential_state = state
            try:
                write_campaign_state(self.data_dir / CAMPAIGN_STATE_FILE, state)
            except OSError as exc:
                self.get_logger().error(f'campaign state not written: {exc}')
            self._pub_campaign_status.publish(String(data=yaml.safe_dump(doc, sort_keys=False)))
        try:
            names = self._model().joint_names
        except DataError:  # no robot model yet: no plan was published either
            names = []
        if names:
            self._pub_poses.publish(cv.joint_trajectory_msg(
                names, np.zeros((0, len(names)), dtype=float)))
        self.get_logger().warning(f'sequential campaign stopped: {STATION_CHANGED} from '
                                  f'{before[0]!r} to {now[0]!r}; {advice}')
        self._publish_diagnostics(force=True)

    async def _design_sequential(self, cm: CellModel) -> tuple[bool, str]:
        """Start a sequential campaign at the current station: publish its initial design
        on ~/measurement_poses. Measurements accepted before it from that station are part
        of the campaign (the first step adds them all); another station's are not. At a
        station the published calibration of several stations holds, it plans from where
        that calibration places the station (the cell file places the first one)."""
        settings, seed = job_work.campaign_settings(self.settings), self.settings.design_seed
        station, held, _ = self._design_station()
        placed, base, cp = cm, (), None
        if held:
            placed, base, cp = await self._offload(job_work.station_campaign, cm,
                                                   self._calibration_text, station)
        campaign, initial, points, path = await self._offload(
            job_work.sequential_start_work, placed, settings, seed, self.data_dir, station,
            base, cp, self._calibration_text if held else '')
        self._run.sequential, self._run.sequential_status = campaign, None
        self._run.sequential_cm = placed
        self._run.sequential_stopped = ''
        self._run.sequential_state = CampaignState(settings, seed, station=station,
                                                   base_in_tracker=tuple(base))
        self._run.sequential_stamps, self._run.sequential_initial = set(), len(initial)
        self._run.resume_pending, self._run.resumed = False, False
        self._pub_poses.publish(cv.joint_trajectory_msg(cm.joint_names, initial))
        self._design_points = points
        self._publish_markers()
        self._pub_campaign_status.publish(String(data=yaml.safe_dump({
            'measurements': len(self.store), 'initial_design': len(initial),
            'target_tcp_std_m': settings.target_std,
            'stop_reason': 'running'}, sort_keys=False)))
        return True, (f'sequential campaign: initial design of {len(initial)} poses '
                      f'published on {self.resolve_topic_name(MEASUREMENT_POSES_TOPIC)}, '
                      f'written to {path}; target TCP std {settings.target_std:g} m, '
                      f'at most {settings.max_measurements} measurements; station '
                      f'{station!r}'
                      + (' placed where the published calibration of several stations '
                         'places it, that calibration its prior' if held else ''))

    async def _resume(self) -> tuple[bool, str]:
        """Rebuild the campaign data_dir/campaign_state.yaml keeps, from the restored
        measurements (the same steps, so the same status and plan), and publish its
        plan and status again, saying it was resumed."""
        state = self._run.sequential_state
        assert state is not None
        cm, cp = self._model(), None
        prior = self.data_dir / CAMPAIGN_PRIOR_FILE
        if state.base_in_tracker and prior.is_file():  # started with a calibration as prior
            cm, _, cp = await self._offload(job_work.station_campaign, cm, prior.read_text(),
                                            state.station)
        elif state.base_in_tracker:
            cm = await self._offload(job_work.at_placement, cm, state.base_in_tracker)
        self._run.resume_pending = False
        data = station_rows(self.store, *model_measurements(self.store, cm),
                            state.station)[0] if len(self.store) else Measurements(
            q=np.zeros((0, len(cm.joint_names))), eta=np.zeros((0, 3)),
            stamps_ns=np.zeros(0, np.int64))
        try:
            campaign, initial, out = await self._offload(job_work.sequential_resume_work, cm,
                                                         state, data, self.data_dir, cp)
        except KpiCalibError as exc:
            self._run.result_error = f'sequential campaign not resumed: {exc}'
            self._publish_diagnostics(force=True)
            raise
        self._run.sequential, self._run.sequential_initial = campaign, len(initial)
        self._run.sequential_cm = cm
        self._run.sequential_stamps = {t for step in state.steps for t in step}
        self._run.resumed = True
        if out is None:  # no step yet: the initial design is still the plan
            self._pub_poses.publish(cv.joint_trajectory_msg(cm.joint_names, initial))
            self._pub_campaign_status.publish(String(data=yaml.safe_dump({
                'measurements': len(self.store), 'initial_design': len(initial),
                'target_tcp_std_m': state.settings.target_std, 'stop_reason': 'running',
                'resumed': True}, sort_keys=False)))
            message = f'initial design of {len(initial)} poses published again'
        else:
            self._run.sequential_state, self._run.sequential_status = out.state, out.status
            if len(out.plan):
                self._pub_poses.publish(cv.joint_trajectory_msg(cm.joint_names, out.plan))
            self._pub_campaign_status.publish(String(data=out.text))
            message = campaign_progress(out.status, len(out.plan))
        self._publish_diagnostics(force=True)
        return True, f'sequential campaign resumed from {self.data_dir}: {message}'

    async def _sequential_step(self) -> tuple[bool, str]:
        """Add the accepted measurements the campaign has not seen, re-identify and
        publish the updated plan (next pose first) and ~/campaign_status; once the
        campaign stopped (target met or cap), publish its calibration."""
        campaign, state = self._run.sequential, self._run.sequential_state
        if campaign is None or state is None:
            raise DataError('no sequential campaign: call ~/design with campaign:=sequential')
        cm = self._run.sequential_cm or self._model()
        # The campaign's station's measurements only: another station's points are in
        # another tracker frame (~/identify takes every station together).
        data, pairing = station_rows(self.store, *model_measurements(self.store, cm),
                                     state.station)
        stamps = np.asarray(data.stamps_ns, dtype=np.int64)
        new = np.array([int(t) not in self._run.sequential_stamps for t in stamps], dtype=bool)
        fresh = data.subset(new)
        out = await self._offload(job_work.sequential_step_work, campaign, cm, fresh, state,
                                  self.data_dir, pairing,
                                  {'resumed': True} if self._run.resumed else None)
        if self._run.sequential_stopped and self._run.sequential_state is not None:
            # The station changed while this step ran: the stop stands, in the file too.
            write_campaign_state(self.data_dir / CAMPAIGN_STATE_FILE,
                                 self._run.sequential_state)
            return False, f'sequential campaign stopped: {self._run.sequential_stopped}'
        status, plan = out.status, out.plan
        self._run.sequential_stamps.update(int(t) for t in stamps[new])
        self._run.sequential_status, self._run.sequential_state = status, out.state
        for e in status.excluded:
            self.get_logger().warning(f"measurement {e['measurement']} (stamp "
                                      f"{e['stamp_ns']} ns) excluded: "
                                      f"{e['distance_m'] * 1e6:.1f} µm from the fit; "
                                      f"{e['reason']}")
        if len(plan):
            self._pub_poses.publish(cv.joint_trajectory_msg(cm.joint_names, plan))
        self._pub_campaign_status.publish(String(data=out.text))
        if out.calibration is not None and out.result is not None:
            text, urdf, tcp = out.calibration
            self._publish_campaign_calibration(out.result, text, urdf, tcp, stamps)
        elif out.refused:
            # Never published as the calibration: /diagnostics says ERROR with the reason,
            # as ~/identify's refusal does.
            self._run.result_error = f'calibration not published: {out.refused}'
            self.get_logger().error(f'sequential campaign stopped ({status.stop_reason}) '
                                    'but its calibration is not valid, last good '
                                    f'calibration kept: {out.refused}')
        self._publish_diagnostics(force=True)
        if status.stopped:
            self.get_logger().info(f'sequential campaign stopped after {status.measurements} '
                                   f'measurements: {status.stop_reason}')
        return True, (campaign_progress(status, len(plan)) + f', {status.step_seconds:.2f} s'
                      + (f', {len(status.excluded)} excluded' if status.excluded else ''))

    def _publish_campaign_calibration(self, cal: Any, text: str, urdf: str, tcp: list,
                                      stamps: np.ndarray) -> None:
        """Publish a stopped campaign's calibration as ~/identify publishes one."""
        campaign = self._run.sequential
        assert campaign is not None
        kept = np.asarray(cal.robust.kept, dtype=bool)
        self._publish_calibration(cal, campaign.eta[kept], np.ones(int(kept.sum()), bool),
                                  len(campaign.q), text, urdf, tcp, stamps)


__all__ = ['SequentialCampaignJobs']
