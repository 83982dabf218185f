"""Names of the files and topics the package writes and reads, in one place.

Result files are written by the CLI and the node alike; the topic names are
those ``ros2 bag record`` captures and the node subscribes and publishes (``~/``
names resolve under the node's name).
"""
from __future__ import annotations

from pathlib import Path

# ---------------------------------------------------------------- result files
CALIBRATION_FILE = 'calibration.yaml'
# A failed, non-converged or KPI-not-estimable identification: written here, never over
# the last good calibration.yaml.
FAILED_CALIBRATION_FILE = 'calibration.failed.yaml'
CALIBRATED_URDF_FILE = 'robot_description_calibrated.urdf'
# The learned residual (Gaussian process over joint space) beside calibration.yaml: the
# calibrated URDF cannot carry it.
LEARNED_RESIDUAL_FILE = 'learned_residual.yaml'
DESIGN_FILE = 'design.yaml'
CAMPAIGN_PLAN_FILE = 'campaign_plan.yaml'   # initial design of a sequential campaign
CAMPAIGN_STATE_FILE = 'campaign_state.yaml'  # a node's sequential campaign, to resume it
# The calibration a sequential campaign at a later station took as prior, to resume it.
CAMPAIGN_PRIOR_FILE = 'campaign_prior.yaml'
# The stamps of the measurements the node's published calibration was fitted to.
FITTED_STAMPS_FILE = 'fitted_stamps.json'
DIAGNOSIS_DIR = 'diagnosis'
DIAGNOSIS_FILE = 'diagnosis.json'
REPORT_FILE = 'report.md'
VALIDATION_DIR = 'validation'
VALIDATION_FILE = 'validation.json'
# What a campaign reset archives: every result derived from the measurements.
# Every valid calibration of the node, kept by its identified_at_ns (not moved by reset).
CALIBRATIONS_DIR = 'calibrations'
RESULT_FILES = (CALIBRATION_FILE, FAILED_CALIBRATION_FILE, CALIBRATED_URDF_FILE, DIAGNOSIS_DIR,
                VALIDATION_DIR, CAMPAIGN_STATE_FILE, CAMPAIGN_PRIOR_FILE, LEARNED_RESIDUAL_FILE,
                FITTED_STAMPS_FILE)

# ---------------------------------------------------------------------- topics
DEFAULT_JOINT_TOPIC = '/joint_states'
DEFAULT_POINT_TOPIC = '/laser_tracker/point'
DEFAULT_POSE_TOPIC = '/laser_tracker/pose'   # tracked 6-DoF bodies (PoseStamped)
DEFAULT_TEMPERATURE_TOPIC = '/cell/temperature'   # sensor_msgs/Temperature of imported tables
# Measured inputs as named values (sensor_msgs/JointState: name = covariate, position = value,
# SI): what import-csv writes from a table's covariates and the node logs of its input topics.
DEFAULT_INPUTS_TOPIC = '/kpi_calib/inputs'
# The tracker's stated σ of a point, per axis (m), as geometry_msgs/Vector3Stamped on
# '<point topic>/sigma', with the point's stamp and frame id (paired by both); it covers the
# points of the point topic and the positions of tracked poses.
POINT_SIGMA_SUFFIX = '/sigma'


def point_sigma_topic(point_topic: str) -> str:
    """The companion topic of ``point_topic`` carrying each point's stated σ (m)."""
    return point_topic.rstrip('/') + POINT_SIGMA_SUFFIX
ROBOT_DESCRIPTION_TOPIC = '/robot_description'
DIAGNOSTICS_TOPIC = '/diagnostics'
MEASUREMENT_POSES_TOPIC = '~/measurement_poses'
CALIBRATION_TOPIC = '~/calibration'
CALIBRATED_URDF_TOPIC = '~/robot_description_calibrated'
MARKERS_TOPIC = '~/markers'
DIAGNOSIS_TOPIC = '~/diagnosis'
TCP_TOPIC = '~/tcp'
VALIDATION_TOPIC = '~/validation'
CAMPAIGN_STATUS_TOPIC = '~/campaign_status'
CHANGE_TEST_TOPIC = '~/change_test'
# Joint positions in (sensor_msgs/JointState, joints by name), the TCP with the learned
# residual and its covariance out (PoseWithCovarianceStamped, the query's stamp).
TCP_QUERY_TOPIC = '~/tcp_query'
TCP_CORRECTED_TOPIC = '~/tcp_corrected'


def truth_path(bag_path: str | Path) -> Path:
    """``<bag>.truth.yaml``: the simulated truth written next to a simulated bag."""
    bag_path = Path(bag_path)
    return bag_path.with_name(bag_path.stem + '.truth.yaml')
