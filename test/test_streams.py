"""Streams and pairing: synthesised cell data pairs back to the commanded poses."""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from kpi_calib_ros.core.acquisition.outcomes import REJECTION_REASONS, PairedMeasurement, Rejection
from kpi_calib_ros.core.acquisition.pairing import Pairer, pair_measurements
from kpi_calib_ros.core.acquisition.streams import JointSample, PointSample, synthesize_streams

NAMES = ('joint_1', 'joint_2', 'joint_3', 'joint_4', 'joint_5', 'joint_6')
FRAME = 'tracker'
N_POSES = 8
NOISE = 1e-5
# A mimic joint the joint states may also carry: stage = 0.5 · joint_1 − 0.1.
DERIVED = {'stage': (np.r_[0.5, np.zeros(5)], -0.1)}


def within_limits(q):
    """The robot's check of a still pose: joint_1 within ±3 rad."""
    return f'joint_1 at {q[0]:.3g} rad is outside [-3, 3]' if abs(q[0]) > 3.0 else ''


def make_cell(seed: int = 7, noise: float = NOISE):
    rng = np.random.default_rng(seed)
    q = rng.uniform(-2.0, 2.0, (N_POSES, len(NAMES)))
    eta = rng.uniform(-1.5, 1.5, (N_POSES, 3))
    joints, points = synthesize_streams(q, NAMES, eta, FRAME, joint_noise_rad=noise, rng=rng)
    return q, eta, joints, points


def replace(sample, **changes):
    return dataclasses.replace(sample, **changes)


def test_synthesised_streams_look_like_a_real_cell():
    q, eta, joints, points = make_cell(noise=0.0)
    stamps = np.array([s.stamp_ns for s in joints])
    # 50 Hz throughout: while moving and while holding.
    assert np.all(np.diff(stamps) == 20_000_000)
    assert stamps[-1] - stamps[0] == N_POSES * 4_000_000_000
    # Starts at home and moves from there to the first pose.
    np.testing.assert_array_equal(joints[0].positions, np.zeros(len(NAMES)))
    positions = np.array([s.positions for s in joints])
    velocities = np.array([s.velocities for s in joints])
    # The published velocity is the derivative of the published position.
    np.testing.assert_allclose(np.gradient(positions, 0.02, axis=0), velocities, atol=5e-3)
    assert np.abs(velocities).max() > 0.5
    for k, point in enumerate(points):
        # One point per pose, in the middle of the hold, with the robot standing still there.
        assert point.stamp_ns == stamps[0] + k * 4_000_000_000 + 3_000_000_000
        np.testing.assert_array_equal(point.xyz, eta[k])
        hold = np.abs(stamps - point.stamp_ns) <= 1_000_000_000
        np.testing.assert_array_equal(positions[hold], np.tile(q[k], (hold.sum(), 1)))
        assert np.all(velocities[hold] == 0.0)


def test_pairs_back_to_exactly_the_configurations():
    q, eta, joints, points = make_cell(noise=0.0)
    result = pair_measurements(joints, points, NAMES, FRAME)
    assert result.rejections == {} and result.rejected == []
    np.testing.assert_allclose(result.q, q, rtol=0, atol=1e-12)
    np.testing.assert_array_equal(result.eta, eta)
    np.testing.assert_array_equal(result.stamps_ns, [p.stamp_ns for p in points])


def test_pairs_back_within_noise():
    q, eta, joints, points = make_cell()
    result = pair_measurements(joints, points, NAMES, FRAME)
    assert result.rejections == {}
    # q is the mean of the 21 samples within ±200 ms at 50 Hz: σ/√21 per joint.
    assert np.abs(result.q - q).max() < 5 * NOISE / np.sqrt(21)
    np.testing.assert_array_equal(result.eta, eta)


def test_input_order_does_not_matter():
    _, _, joints, points = make_cell()
    reference = pair_measurements(joints, points, NAMES, FRAME)
    rng = np.random.default_rng(3)
    shuffled = pair_measurements([joints[i] for i in rng.permutation(len(joints))],
                                 [points[i] for i in rng.permutation(len(points))], NAMES, FRAME)
    np.testing.assert_array_equal(shuffled.q, reference.q)
    np.testing.assert_array_equal(shuffled.eta, reference.eta)
    np.testing.assert_array_equal(shuffled.stamps_ns, reference.stamps_ns)


@pytest.mark.parametrize('latency_ns', [-1_500_000_000, 0, 50_000_000, 900_000_000])
def test_live_arrival_matches_batch(latency_ns):
    """Points delivered before, with, or after the joint states around them (live node)."""
    _, _, joints, points = make_cell()
    reference = pair_measurements(joints, points, NAMES, FRAME)
    arrivals = [(s.stamp_ns, 0, s) for s in joints] + [
        (p.stamp_ns + latency_ns, 1, p) for p in points]
    pairer = Pairer(NAMES, FRAME)
    decided = []
    for now, kind, item in sorted(arrivals, key=lambda a: a[:2]):
        pairer.add_point(item) if kind else pairer.add_joint_sample(item)
        decided += pairer.poll(now)
    assert pairer.pending == 0
    accepted = [d for d in decided if isinstance(d, PairedMeasurement)]
    assert len(accepted) == N_POSES
    np.testing.assert_array_equal(np.array([m.q for m in accepted]), reference.q)
    np.testing.assert_array_equal([m.stamp_ns for m in accepted], reference.stamps_ns)


def test_joint_order_and_extra_joints_do_not_matter():
    q, _, joints, points = make_cell()
    reference = pair_measurements(joints, points, NAMES, FRAME)
    order = np.array([4, 0, 5, 2, 1, 3])
    shuffled = [JointSample(s.stamp_ns, ('gripper',) + tuple(NAMES[i] for i in order),
                            np.r_[0.02, s.positions[order]], np.r_[0.0, s.velocities[order]])
                for s in joints]
    # A gripper driver publishing only its own joint on the same topic is ignored, not an error.
    gripper_only = [JointSample(s.stamp_ns + 1, ('gripper',), [np.nan]) for s in joints[::5]]
    result = pair_measurements(shuffled + gripper_only, points, NAMES, FRAME)
    assert result.rejections == {}
    np.testing.assert_array_equal(result.q, reference.q)


def test_a_renamed_robot_is_reported_as_missing_joints():
    _, _, joints, points = make_cell()
    renamed = [JointSample(s.stamp_ns, tuple(f'a{i}' for i in range(6)), s.positions)
               for s in joints]
    result = pair_measurements(renamed, points, NAMES, FRAME)
    assert len(result) == 0 and result.rejections == {'missing_joints': N_POSES}
    assert "'a1'" in result.rejected[0].detail and "'joint_1'" in result.rejected[0].detail


def bad_input_cases():
    """Each case: (name, mutate(joints, points) -> (joints, points), reason, poses lost)."""
    def nan_point(j, p):
        p[1] = replace(p[1], xyz=[np.nan, 0.0, 0.0])
        return j, p

    def wrong_frame(j, p):
        p[2] = replace(p[2], frame_id='world')
        return j, p

    def during_motion(j, p):
        # Half-way through the move to pose 4: the robot is at full speed.
        return j, p + [PointSample(p[4].stamp_ns - 2_000_000_000, FRAME, [0.1, 0.2, 0.3])]

    def no_joint_state(j, p):
        return j, p + [PointSample(p[-1].stamp_ns + 60_000_000_000, FRAME, [0.1, 0.2, 0.3])]

    def missing_joint(j, p):
        stamp = p[3].stamp_ns
        for i, s in enumerate(j):
            if abs(s.stamp_ns - stamp) <= 200_000_000 and i % 2:
                j[i] = JointSample(s.stamp_ns, s.names[:2] + s.names[3:],
                                   np.delete(s.positions, 2), np.delete(s.velocities, 2))
        return j, p

    def nan_joint_state(j, p):
        i = next(i for i, s in enumerate(j) if s.stamp_ns == p[5].stamp_ns)
        j[i] = replace(j[i], positions=np.r_[j[i].positions[:5], np.nan])
        return j, p

    def duplicate(j, p):
        return j, p + [p[6]]

    def unknown_reflector(j, p):
        # A second point at pose 0's stamp, from a reflector the cell does not have.
        return j, p + [replace(p[0], frame_id=f'{FRAME}#spare')]

    def invalid_orientation(j, p):
        # A tracked pose whose quaternion is not a unit one, beside pose 0.
        return j, p + [replace(p[0], orientation=[0.0, 0.0, 0.0, 2.0])]

    def oversized(j, p):
        s = j[7]
        extra = tuple(f'x{i}' for i in range(100))
        return j + [JointSample(s.stamp_ns + 1, s.names + extra, np.zeros(106))], p

    def mimic_mismatch(j, p):
        # Around pose 7 the joint states also carry the mimic joint, 10 mm off its relation.
        for i, s in enumerate(j):
            if abs(s.stamp_ns - p[7].stamp_ns) <= 200_000_000:
                value = 0.5 * s.positions[0] - 0.1 + 0.01
                j[i] = JointSample(s.stamp_ns, s.names + ('stage',), np.r_[s.positions, value],
                                   np.r_[s.velocities, 0.0])
        return j, p

    def beyond_limits(j, p):
        # Around pose 4 joint_1 reads 5 rad more: a wrong zero, beyond its limits.
        for i, s in enumerate(j):
            if abs(s.stamp_ns - p[4].stamp_ns) <= 200_000_000:
                j[i] = replace(s, positions=np.r_[s.positions[0] + 5.0, s.positions[1:]])
        return j, p

    return [('nan_point', nan_point, 'non_finite_point', 1),
            ('wrong_frame', wrong_frame, 'wrong_frame', 1),
            ('during_motion', during_motion, 'robot_moving', 0),
            ('no_joint_state', no_joint_state, 'no_joint_state', 0),
            ('missing_joint', missing_joint, 'missing_joints', 1),
            ('nan_joint_state', nan_joint_state, 'non_finite_joint_state', 0),
            ('duplicate', duplicate, 'duplicate_stamp', 0),
            ('oversized', oversized, 'oversized_joint_state', 0),
            ('unknown_reflector', unknown_reflector, 'unknown_reflector', 0),
            ('invalid_orientation', invalid_orientation, 'invalid_orientation', 0),
            ('mimic_mismatch', mimic_mismatch, 'mimic_mismatch', 1),
            ('beyond_limits', beyond_limits, 'outside_joint_limits', 1)]


@pytest.mark.parametrize('name, mutate, reason, lost', bad_input_cases(),
                         ids=[c[0] for c in bad_input_cases()])
def test_each_bad_input_is_rejected_with_its_reason(name, mutate, reason, lost):
    q, _, joints, points = make_cell()
    joints, points = mutate(list(joints), list(points))
    result = pair_measurements(joints, points, NAMES, FRAME, derived=DERIVED,
                               joint_check=within_limits)
    assert result.rejections == {reason: 1}
    assert [r.reason for r in result.rejected] == [reason] and result.rejected[0].detail
    assert len(result) == N_POSES - lost
    # Nothing vanishes: every point is accepted or rejected exactly once.
    point_rejections = sum(r.reason not in ('non_finite_joint_state', 'oversized_joint_state')
                           for r in result.rejected)
    assert len(result) + point_rejections == len(points)
    kept = np.isin([p.stamp_ns for p in make_cell()[3]], result.stamps_ns)
    assert np.abs(result.q - q[kept]).max() < 5 * NOISE / np.sqrt(20)


def test_all_bad_inputs_together_are_all_counted():
    _, _, joints, points = make_cell()
    joints, points = list(joints), list(points)
    for _, mutate, _, _ in bad_input_cases():
        joints, points = mutate(joints, points)
    result = pair_measurements(joints, points, NAMES, FRAME, derived=DERIVED,
                               joint_check=within_limits)
    assert result.rejections == {reason: 1 for reason in REJECTION_REASONS}
    assert len(result) == N_POSES - 5


def test_velocity_alone_reveals_motion():
    """A driver that repeats stale positions while moving is caught by its velocities."""
    stamps = np.arange(0, 1_000_000_001, 20_000_000)
    joints = [JointSample(t, NAMES, np.zeros(6), np.r_[0.0, 0.01, 0, 0, 0, 0]) for t in stamps]
    result = pair_measurements(joints, [PointSample(500_000_000, FRAME, [1.0, 0, 0])], NAMES,
                               FRAME)
    assert result.rejections == {'robot_moving': 1}
    assert "'joint_2'" in result.rejected[0].detail


def test_points_wait_for_joint_states_then_time_out():
    _, _, joints, points = make_cell()
    pairer = Pairer(NAMES, FRAME, timeout_ns=500_000_000)
    pairer.add_point(points[0])
    before = [s for s in joints if s.stamp_ns <= points[0].stamp_ns]
    pairer.add_joint_samples(before)
    # The joint states after the stamp have not arrived yet: undecided, not rejected.
    assert pairer.poll(points[0].stamp_ns + 200_000_000) == [] and pairer.pending == 1
    # The driver went silent: after window + timeout the point is decided, with a reason.
    decided = pairer.poll(points[0].stamp_ns + 700_000_000)
    assert len(decided) == 1 and isinstance(decided[0], Rejection)
    assert decided[0].reason == 'no_joint_state' and pairer.pending == 0
    assert dict(pairer.rejections) == {'no_joint_state': 1}


def test_late_point_beyond_the_buffer_is_rejected_not_lost():
    _, _, joints, points = make_cell()
    pairer = Pairer(NAMES, FRAME, buffer_ns=5_000_000_000)
    pairer.add_joint_samples(joints)
    pairer.add_point(points[0])  # 29 s late; its joint states have been pruned
    decided = pairer.poll(joints[-1].stamp_ns)
    assert [d.reason for d in decided] == ['no_joint_state']
    assert 'buffer' in decided[0].detail


def test_memory_stays_bounded():
    pairer = Pairer(NAMES, FRAME, buffer_ns=2_000_000_000)
    for t in range(0, 600_000_000_000, 20_000_000):  # ten minutes at 50 Hz
        pairer.add_joint_sample(JointSample(t, NAMES, np.zeros(6), np.zeros(6)))
        if t % 4_000_000_000 == 0:
            pairer.add_point(PointSample(t - 1_000_000_000, FRAME, [1.0, 2.0, 3.0]))
    assert pairer.buffered_joint_samples <= 101
    assert len(pairer.poll(600_000_000_000)) == 150


def test_paired_measurement_converts_back_to_samples():
    q, eta, joints, points = make_cell(noise=0.0)
    pairer = Pairer(NAMES, FRAME)
    pairer.add_point(points[2])
    pairer.add_joint_samples(joints)
    [measurement] = pairer.poll(joints[-1].stamp_ns)
    joint, point = measurement.joint_sample(), measurement.point_sample()
    assert joint.stamp_ns == point.stamp_ns == points[2].stamp_ns
    assert joint.names == NAMES and joint.velocities is None
    np.testing.assert_allclose(joint.positions, q[2], atol=1e-12)
    np.testing.assert_array_equal(point.xyz, eta[2])


def test_arguments_are_checked_by_name():
    with pytest.raises(ValueError, match='joint_names'):
        Pairer([], FRAME)
    with pytest.raises(ValueError, match='joint_names'):
        Pairer(['a', 'a'], FRAME)
    with pytest.raises(ValueError, match='buffer_ns'):
        Pairer(NAMES, FRAME, window_ns=10, buffer_ns=20)
    with pytest.raises(ValueError, match='configurations'):
        synthesize_streams(np.zeros((3, 5)), NAMES, np.zeros((3, 3)), FRAME)
    with pytest.raises(ValueError, match='points'):
        synthesize_streams(np.zeros((3, 6)), NAMES, np.zeros((2, 3)), FRAME)
    with pytest.raises(ValueError, match='positions'):
        JointSample(0, ('a', 'b'), [1.0])
    with pytest.raises(ValueError, match='xyz'):
        PointSample(0, FRAME, [1.0, 2.0])


def test_samples_are_immutable():
    sample = JointSample(0, ['a'], [1.0], [0.0])
    with pytest.raises(ValueError):
        sample.positions[0] = 2.0
    with pytest.raises(dataclasses.FrozenInstanceError):
        sample.stamp_ns = 1
