"""Pairing under faults: clocks that jump back, points ahead of their joint states,
reset, and hostile joint states (huge arrays, ever-changing names)."""
from __future__ import annotations

import numpy as np
import pytest

from kpi_calib_ros.core.acquisition.outcomes import PairedMeasurement, Rejection
from kpi_calib_ros.core.acquisition.pairing import (
    INDEX_CACHE_SIZE,
    NAMES_KEPT,
    Pairer,
    pair_measurements,
)
from kpi_calib_ros.core.acquisition.streams import JointSample, PointSample, synthesize_streams
from kpi_calib_ros.ros.measurement_store import MeasurementStore

NAMES = ('joint_1', 'joint_2', 'joint_3', 'joint_4', 'joint_5', 'joint_6')
FRAME = 'tracker'
N_POSES = 6
RECORDED = 1_600_000_000_000_000_000   # a recording made some time ago (ns)
WALL = 1_790_000_000_000_000_000       # "now" on the wall clock (ns)


def recording(seed: int, start_ns: int = RECORDED):
    rng = np.random.default_rng(seed)
    q = rng.uniform(-2.0, 2.0, (N_POSES, len(NAMES)))
    eta = rng.uniform(-1.5, 1.5, (N_POSES, 3))
    joints, points = synthesize_streams(q, NAMES, eta, FRAME, start_ns=start_ns,
                                        joint_noise_rad=1e-5, rng=rng)
    return q, joints, points


def live(pairer: Pairer, joints, points, latency_ns: int = 0) -> list:
    """Deliver both streams as a replay does: in stamp order, points ``latency_ns`` late
    (negative: early), polling on the joint-stamp clock."""
    arrivals = sorted([(s.stamp_ns, 0, s) for s in joints]
                      + [(p.stamp_ns + latency_ns, 1, p) for p in points], key=lambda a: a[:2])
    decided = []
    for now, kind, item in arrivals:
        pairer.add_point(item) if kind else pairer.add_joint_sample(item)
        decided += pairer.poll(now)
    return decided


def accepted(decisions) -> list[PairedMeasurement]:
    return [d for d in decisions if isinstance(d, PairedMeasurement)]


def still_sample(stamp_ns: int, names=NAMES) -> JointSample:
    return JointSample(stamp_ns, names, np.zeros(len(names)))


def test_one_wall_clock_joint_state_before_a_recording_costs_nothing():
    _, joints, points = recording(1)
    reference = pair_measurements(joints, points, NAMES, FRAME)
    pairer = Pairer(NAMES, FRAME)
    pairer.add_joint_sample(still_sample(WALL))
    assert pairer.poll(WALL) == []
    got = accepted(live(pairer, joints, points))
    assert len(got) == N_POSES == len(reference)
    np.testing.assert_array_equal([m.q for m in got], reference.q)
    assert pairer.clock_jumps == 1 and pairer.epoch == 1 and dict(pairer.rejections) == {}


def test_an_older_recording_after_a_newer_one_pairs_against_its_own_joint_states():
    q_new, joints_new, points_new = recording(2, RECORDED + 3_600_000_000_000)
    q_old, joints_old, points_old = recording(3, RECORDED)
    pairer = Pairer(NAMES, FRAME)
    first = accepted(live(pairer, joints_new, points_new))
    second = accepted(live(pairer, joints_old, points_old)) + accepted(pairer.flush())
    assert len(first) == len(second) == N_POSES and pairer.clock_jumps == 1
    # Each point took the configuration of its own recording (noise 1e-5 rad).
    np.testing.assert_allclose([m.q for m in first], q_new, atol=1e-4)
    np.testing.assert_allclose([m.q for m in second], q_old, atol=1e-4)


def test_a_looped_bag_pairs_again_in_each_loop():
    q, joints, points = recording(4)
    pairer = Pairer(NAMES, FRAME)
    loops = [accepted(live(pairer, joints, points)) for _ in range(3)]
    assert [len(loop) for loop in loops] == [N_POSES] * 3 and pairer.clock_jumps == 2
    for loop in loops:
        np.testing.assert_allclose([m.q for m in loop], q, atol=1e-4)


def test_small_disorder_between_drivers_is_merged_not_a_jump():
    q, joints, points = recording(5)
    # Every 7th joint state arrives 0.5 s late (a second driver on the topic, a slow link).
    delayed = sorted(joints, key=lambda s: s.stamp_ns + (500_000_000 if
                                                         (s.stamp_ns // 20_000_000) % 7 == 0
                                                         else 0))
    pairer = Pairer(NAMES, FRAME)
    got = accepted(live(pairer, delayed, points, latency_ns=2_000_000_000))
    assert pairer.clock_jumps == 0 and len(got) == N_POSES
    np.testing.assert_allclose([m.q for m in got], q, atol=1e-4)


@pytest.mark.parametrize('lead_ns', [30_000_000_000, 400_000_000])
def test_a_point_ahead_of_its_epoch_waits_for_the_jump(lead_ns):
    """After a wall-clock joint state, a recorded point overtakes its own joint states
    (by ``lead_ns`` of stream time): it waits and is paired once they arrive."""
    q, joints, points = recording(6)
    pairer = Pairer(NAMES, FRAME)
    pairer.add_joint_sample(still_sample(WALL))
    pairer.add_point(points[0])
    assert pairer.poll(WALL) == [] and pairer.pending == 1
    arrivals = [s for s in joints if s.stamp_ns < points[0].stamp_ns - lead_ns]
    pairer.add_joint_samples(arrivals)
    decided = live(pairer, [s for s in joints if s not in arrivals], points[1:])
    got = accepted(decided)
    assert len(got) == N_POSES and not [d for d in decided if isinstance(d, Rejection)]
    np.testing.assert_allclose(got[0].q, q[0], atol=1e-4)


def test_a_point_older_than_its_epoch_without_a_jump_is_rejected_after_the_timeout():
    _, joints, points = recording(7)
    pairer = Pairer(NAMES, FRAME, timeout_ns=500_000_000)
    pairer.add_joint_sample(still_sample(WALL))
    pairer.add_point(points[0])
    assert pairer.poll(WALL + 600_000_000) == [] and pairer.pending == 1
    [rejection] = pairer.poll(WALL + 700_000_000)
    assert rejection.reason == 'no_joint_state' and 'no backwards clock jump' in \
        rejection.detail and pairer.pending == 0


def test_points_of_the_old_epoch_are_decided_with_its_joint_states():
    """At the jump, a waiting point with joint states on both sides is accepted; one
    still waiting for the joint states after it is rejected, saying the clock jumped."""
    q, joints, points = recording(8)
    pairer = Pairer(NAMES, FRAME)
    cut = points[2].stamp_ns + 50_000_000      # the stream stops just after point 2
    decided = live(pairer, [s for s in joints if s.stamp_ns <= cut], points[:2])
    pairer.add_point(points[2])
    pairer.add_point(points[3])
    assert pairer.pending == 2
    pairer.add_joint_sample(still_sample(RECORDED - 10**12))   # a driver restarted
    decided += pairer.poll(RECORDED - 10**12)
    got = accepted(decided)
    assert [m.stamp_ns for m in got] == [p.stamp_ns for p in points[:3]]
    np.testing.assert_allclose(got[2].q, q[2], atol=1e-4)
    [rejection] = [d for d in decided if isinstance(d, Rejection)]
    assert rejection.stamp_ns == points[3].stamp_ns and rejection.reason == 'no_joint_state'
    assert 'jumped back' in rejection.detail and pairer.clock_jumps == 1


def test_reset_forgets_the_clock_and_the_counts():
    _, joints, points = recording(9)
    pairer = Pairer(NAMES, FRAME)
    pairer.add_joint_sample(still_sample(WALL))
    pairer.add_point(PointSample(WALL, 'world', [0.0, 0.0, 1.0]))
    pairer.reset()
    assert (pairer.latest_joint_ns, pairer.clock_jumps, pairer.pending) == (None, 0, 0)
    assert dict(pairer.rejections) == {} and pairer.poll(WALL) == []
    assert len(accepted(live(pairer, joints, points))) == N_POSES and pairer.clock_jumps == 0


def replay_into(store: MeasurementStore, joints, points, start_mono_ns: int, rate: float) -> list:
    """Feed a measurement store as the node does: arrival times on the monotonic clock, polled."""
    t0 = joints[0].stamp_ns
    arrivals = sorted([(s.stamp_ns, 0, s) for s in joints] + [(p.stamp_ns, 1, p) for p in points],
                      key=lambda a: a[:2])
    decided = []
    for stamp, _, item in arrivals:
        now = start_mono_ns + int((stamp - t0) / rate)
        decided += store.receive(item, now)
        decided += store.poll(now)
    return decided


@pytest.mark.parametrize('rate', [1.0, 20.0])
def test_campaign_survives_a_wall_clock_joint_state_and_its_reset(tmp_path, rate):
    """The node's path: a stray wall-clock joint state, then a replayed recording, is all
    accepted; after ~/reset an older recording is accepted too."""
    _, joints, points = recording(10, RECORDED + 7_200_000_000_000)
    store = MeasurementStore(tmp_path)
    store.set_chain(list(NAMES), FRAME)
    store.receive(still_sample(WALL), 0)
    decided = replay_into(store, joints, points, 1_000_000, rate)
    assert len(accepted(decided)) == N_POSES == len(store)
    assert store.counts()['rejected'] == 0 and store.counts()['clock_jumps'] == 1
    store.reset()
    assert store.counts()['clock_jumps'] == 0 and len(store) == 0
    _, joints, points = recording(11)
    decided = replay_into(store, joints, points, 10**12, rate)
    assert len(accepted(decided)) == N_POSES == len(store)
    # Reset forgot the wall-clock stamp: the older recording is no jump any more.
    assert store.counts()['rejected'] == 0 and store.counts()['clock_jumps'] == 0
    store.close()


# ------------------------------------------------------------------ hostile joint states
def test_joint_states_far_longer_than_the_chain_are_rejected_by_reason():
    pairer = Pairer(NAMES, FRAME)
    limit = 4 * len(NAMES) + 64
    ok = NAMES + tuple(f'extra_{i}' for i in range(limit - len(NAMES)))
    pairer.add_joint_sample(JointSample(1, ok, np.zeros(len(ok))))
    huge = NAMES + tuple(f'extra_{i}' for i in range(1_000_000))
    pairer.add_joint_sample(JointSample(2, huge, np.zeros(len(huge))))
    [rejection] = pairer.poll(2)
    assert rejection.reason == 'oversized_joint_state' and '1000006 joints' in rejection.detail
    assert dict(pairer.rejections) == {'oversized_joint_state': 1}
    assert pairer.buffered_joint_samples == 1 and pairer.index_cache_size == 1


def test_ever_changing_joint_names_keep_the_caches_bounded_and_still_pair():
    """2e4 joint states, each with a name never seen before (plus the chain): the index
    cache stays at its LRU size, foreign names are not kept, points still pair."""
    q, joints, points = recording(12)
    noisy = [JointSample(s.stamp_ns, (f'noise_{k}',) + s.names, np.r_[0.0, s.positions],
                         np.r_[0.0, s.velocities]) for k, s in enumerate(joints)]
    foreign = [JointSample(s.stamp_ns + 1, tuple(f'other_{k}_{i}' for i in range(40)),
                           np.zeros(40)) for k, s in enumerate(joints)]
    pairer = Pairer(NAMES, FRAME)
    for point in points:
        pairer.add_point(point)
    sizes = []
    for sample in sorted(noisy + foreign, key=lambda s: s.stamp_ns):
        pairer.add_joint_sample(sample)
        sizes.append(pairer.index_cache_size)
    assert len(noisy) + len(foreign) > 100 * INDEX_CACHE_SIZE
    assert max(sizes) == INDEX_CACHE_SIZE
    assert max(len(e.names) for e in pairer._entries) == NAMES_KEPT
    got = accepted(pairer.flush())
    assert len(got) == N_POSES and pairer.ignored_joint_samples == len(foreign)
    np.testing.assert_allclose([m.q for m in got], q, atol=1e-4)


def test_arguments_of_the_fault_handling_are_checked():
    with pytest.raises(ValueError, match='jump_ns'):
        Pairer(NAMES, FRAME, jump_ns=0)
    with pytest.raises(ValueError, match='max_names'):
        Pairer(NAMES, FRAME, max_names=3)


def test_a_pose_read_alike_every_time_is_paired_to_the_bit():
    """Each of six poses visited three times (three payloads), its joint states read alike:
    every point's pose is the reading itself, so the campaign has six poses, not more. A
    plain mean of the window's readings rounded some (24 poses of three payloads counted as
    28, their rows then in different cross-validation folds)."""
    rng = np.random.default_rng(3)
    q = rng.uniform(-2.0, 2.0, (N_POSES, len(NAMES)))
    visits = np.repeat(q, 3, axis=0)
    joints, points = synthesize_streams(visits, NAMES, rng.uniform(-1.5, 1.5, (len(visits), 3)),
                                        FRAME, start_ns=RECORDED)
    got = pair_measurements(joints, points, NAMES, FRAME).q
    assert np.array_equal(got, visits)
    assert len(np.unique(got, axis=0)) == N_POSES
