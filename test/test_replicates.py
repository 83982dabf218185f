"""The same pose measured again (core/measurement/replicates.py): one tolerance in joint space,
checked
against the re-reads of a real robot, and the grouping of replicates."""
import csv

import numpy as np

from kpi_calib_ros.core.measurement.replicates import SAME_POSE_TOLERANCE, pose_groups, same_pose

from real_data import TIAGO_DATA

TIAGO = TIAGO_DATA
JOINTS = ['torso_lift_joint'] + [f'arm_{i}_joint' for i in range(1, 8)]


def _postures(session):
    with open(TIAGO / f'qualisys_{session}_static_postures.csv', newline='') as f:
        return np.array([[float(row[j]) for j in JOINTS] for row in csv.DictReader(f)])


def test_pose_groups_join_rows_within_the_tolerance_in_order_of_appearance():
    q = np.array([[0.5, 1.0], [0.0, 0.0], [0.5 + 2e-4, 1.0 - 3e-4], [0.0, 1e-5], [0.0, 0.1]])
    assert pose_groups(q).tolist() == [0, 1, 0, 1, 2]
    assert pose_groups(q, tolerance=1e-6).tolist() == [0, 1, 2, 3, 4]
    # A chain: each row within the tolerance of the next, the ends farther apart.
    chain = np.array([[0.0], [0.9e-3], [1.8e-3], [0.5]])
    assert pose_groups(chain).tolist() == [0, 0, 0, 1]
    assert pose_groups(np.zeros((0, 3))).shape == (0,)


def test_same_pose_is_every_joint_within_the_tolerance_of_one_other_row():
    others = np.array([[0.0, 0.0], [1.0, 1.0]])
    q = np.array([[0.9e-3, -0.9e-3], [1.1e-3, 0.0], [1.0, 1.0 + 0.5e-3], [0.5, 0.5]])
    assert same_pose(q, others).tolist() == [True, False, True, False]
    assert not same_pose(q, np.zeros((0, 2))).any()


def test_the_tolerance_separates_the_re_reads_of_a_real_robot_from_other_postures():
    """TIAGo, 2021-11: the postures of three sessions against the training session. A
    repeated posture reads back within the tolerance, every other one is far beyond it,
    and the tolerance of 1e-4 rad the sequential campaign used to group replicates with
    would miss most repeats."""
    train = _postures('2021-11-30')
    for session, repeats in (('2021-11-26', 37), ('2021-11-30-1403', 37),
                             ('2021-11-30-1504', 35)):
        q = _postures(session)
        nearest = np.array([np.min(np.max(np.abs(train - row), axis=1)) for row in q])
        again = same_pose(q, train)
        assert again.sum() == repeats
        assert np.max(nearest[again]) < 0.5 * SAME_POSE_TOLERANCE
        assert np.min(nearest[~again]) > 50 * SAME_POSE_TOLERANCE
        assert same_pose(q, train, tolerance=1e-4).sum() < 0.5 * repeats
