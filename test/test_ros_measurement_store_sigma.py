"""A point's stated σ in the node's measurement store, without ROS: paired with its point by
stamp and frame id whichever arrives first, kept across restarts (in the log, as a bag
keeps it), rejected when invalid and dropped when no point claims it, never silently."""
from __future__ import annotations

import numpy as np
import pytest
from test_ros_measurement_store import FRAME, NAMES, SECOND, feed, live_order, streams

from kpi_calib_ros.io import measurement_log
from kpi_calib_ros.io.bag_writing import StreamEncoders
from kpi_calib_ros.io.measurement_log import MeasurementLog
from kpi_calib_ros.ros.measurement_store import SIGMA_WAIT_S, MeasurementStore

TOPIC = '/tracker/point/sigma'


def stated(n: int, seed: int = 5) -> np.ndarray:
    """(n, 3) σ per point and axis (m), each point its own, 5-60 µm."""
    return np.random.default_rng(seed).uniform(5e-6, 60e-6, (n, 3))


def test_sigma_before_or_after_its_point_is_stored_with_it_and_survives_a_restart(tmp_path):
    """Even points: σ first; odd points: σ after the measurement was stored. Every row
    carries its own σ; a restarted campaign reloads them from the log, and the log read
    as a bag (kpi-calib identify) gives the same rows."""
    joints, points = streams(6)
    sigma = stated(6)
    store = MeasurementStore(tmp_path, sigma_topic=TOPIC)
    store.set_chain(NAMES, FRAME)
    for i, p in enumerate(points):
        if i % 2 == 0:
            assert store.receive_sigma(p.stamp_ns, p.frame_id, sigma[i]) == []
    feed(store, live_order(joints, points))
    assert len(store) == 6
    for i, p in enumerate(points):
        if i % 2:
            assert store.receive_sigma(p.stamp_ns, p.frame_id, sigma[i]) == []
    data, _ = store.measurements(NAMES, FRAME)
    np.testing.assert_array_equal(data.sigma, sigma)
    counts = store.counts()
    assert counts['stated_sigma'] == 6 and counts['pending_sigma'] == 0
    assert counts['received.sigma'] == 6 and counts['rejected'] == 0
    store.close()

    restarted = MeasurementStore(tmp_path, sigma_topic=TOPIC)
    restarted.set_chain(NAMES, FRAME)
    data, _ = restarted.measurements(NAMES, FRAME)
    np.testing.assert_array_equal(data.sigma, sigma)
    # A replay after the restart: its σ are duplicates, the first ones stay.
    again = restarted.receive_sigma(points[0].stamp_ns, points[0].frame_id, 2 * sigma[0])
    assert [r.reason for r in again] == ['duplicate_sigma'] and TOPIC in again[0].detail
    np.testing.assert_array_equal(restarted.measurements(NAMES, FRAME)[0].sigma, sigma)
    restarted.close()

    log = sorted(tmp_path.glob('measurements_*.mcap'))[0]
    contents = measurement_log.read_log_with_sigma(log)
    assert len(contents[0]) == 6 and len(contents[1]) == 6


def test_a_point_without_sigma_takes_the_cell_sigma(tmp_path):
    """σ for points 0 and 3 only: those rows carry it, the others NaN (the cell's σ)."""
    joints, points = streams(6)
    sigma = stated(6)
    store = MeasurementStore(tmp_path)
    store.set_chain(NAMES, FRAME)
    for i in (0, 3):
        store.receive_sigma(points[i].stamp_ns, points[i].frame_id, sigma[i])
    feed(store, live_order(joints, points))
    data, _ = store.measurements(NAMES, FRAME)
    np.testing.assert_array_equal(data.sigma[[0, 3]], sigma[[0, 3]])
    assert np.isnan(data.sigma[[1, 2, 4, 5]]).all()


@pytest.mark.parametrize('bad', [[0.0, 1e-5, 1e-5], [1e-5, -1e-5, 1e-5], [np.nan, 1e-5, 1e-5],
                                 [np.inf, 1e-5, 1e-5]])
def test_an_invalid_sigma_is_rejected_naming_the_topic(tmp_path, bad):
    joints, points = streams(2)
    store = MeasurementStore(tmp_path, sigma_topic=TOPIC)
    store.set_chain(NAMES, FRAME)
    rejected = store.receive_sigma(points[0].stamp_ns, points[0].frame_id, np.array(bad))
    assert [r.reason for r in rejected] == ['invalid_sigma']
    assert TOPIC in rejected[0].detail and f'stamp {points[0].stamp_ns} ns' in rejected[0].detail
    feed(store, live_order(joints, points))
    data, _ = store.measurements(NAMES, FRAME)
    assert len(data) == 2 and data.sigma is None   # the point stays, weighed by the cell
    assert store.counts()['rejected.invalid_sigma'] == 1


def test_a_sigma_no_point_claims_is_dropped_after_a_bounded_wait(tmp_path):
    """A σ whose stamp no point has: kept while it may still come (SIGMA_WAIT_S on the
    arrival clock and until the pairing clock passes its point's decision), then dropped
    and counted, naming the topic; it never reaches a measurement."""
    joints, points = streams(3)
    store = MeasurementStore(tmp_path, sigma_topic=TOPIC)
    store.set_chain(NAMES, FRAME)
    order = live_order(joints, points)
    t0 = 10 * SECOND
    stray = points[1].stamp_ns + 7  # no point has this stamp
    assert store.receive_sigma(stray, FRAME, np.full(3, 1e-5), now_ns=t0) == []
    for k, sample in enumerate(order):  # the whole stream arrives at once
        store.receive(sample, now_ns=t0 + k)
    assert store.counts()['pending_sigma'] == 1
    assert store.poll(t0 + int(SIGMA_WAIT_S * SECOND) - SECOND) == []
    dropped = store.poll(t0 + int(SIGMA_WAIT_S * SECOND) + 1)
    assert [d.reason for d in dropped] == ['unmatched_sigma']
    assert TOPIC in dropped[0].detail and str(stray) in dropped[0].detail
    counts = store.counts()
    assert counts['pending_sigma'] == 0 and counts['rejected.unmatched_sigma'] == 1
    assert len(store) == 3 and store.measurements(NAMES, FRAME)[0].sigma is None
    # Not a pairing rejection: the pairing result counts none.
    assert store.measurements(NAMES, FRAME)[1].rejections == {}


def test_a_sigma_waits_for_its_point_while_the_robot_model_is_unknown(tmp_path):
    """Before the chain is known nothing is paired, so nothing is dropped: σ given long
    before the model still meets its point."""
    joints, points = streams(2)
    sigma = stated(2)
    store = MeasurementStore(tmp_path)
    for i, p in enumerate(points):
        store.receive_sigma(p.stamp_ns, p.frame_id, sigma[i], now_ns=0)
    feed(store, live_order(joints, points))
    assert store.poll(100 * SECOND) == []
    store.set_chain(NAMES, FRAME)
    np.testing.assert_array_equal(store.measurements(NAMES, FRAME)[0].sigma, sigma)


def test_a_log_written_before_sigma_was_stored_still_loads(tmp_path, monkeypatch):
    """A log without the σ channel (as the node wrote it before): restored, no row
    states a σ, and kpi-calib identify reads it as before."""
    monkeypatch.setattr(measurement_log, 'StreamEncoders',
                        lambda joint, point, pose, *channels, sigma_topic=None, **others:
                        StreamEncoders(joint, point, pose, *channels, **others))
    joints, points = streams(4)
    old = MeasurementStore(tmp_path)
    old.set_chain(NAMES, FRAME)
    feed(old, live_order(joints, points))
    old.close()
    monkeypatch.undo()
    pairs, sigma = MeasurementLog.load(tmp_path)
    assert len(pairs) == 4 and sigma == {}
    restored = MeasurementStore(tmp_path)
    restored.set_chain(NAMES, FRAME)
    assert restored.restored == 4 and restored.measurements(NAMES, FRAME)[0].sigma is None
    # The σ of an old measurement given now is stored in the new log and kept.
    p = points[2]
    assert restored.receive_sigma(p.stamp_ns, p.frame_id, np.full(3, 3e-5)) == []
    restored.close()
    again = MeasurementStore(tmp_path)
    rows = again.measurements(NAMES, FRAME)[0].sigma
    np.testing.assert_array_equal(rows[2], np.full(3, 3e-5))
    assert np.isnan(rows[[0, 1, 3]]).all()
    again.close()


def test_sigma_given_before_the_first_joint_state_waits_for_its_point(tmp_path):
    """The tracker's σ arrive, then nothing for longer than SIGMA_WAIT_S (no joint state,
    no point: no pairing clock, nothing decided), then the stream: every row keeps its σ."""
    joints, points = streams(3)
    sigma = stated(3)
    store = MeasurementStore(tmp_path, sigma_topic=TOPIC)
    store.set_chain(NAMES, FRAME)
    t0 = 10 * SECOND
    for i, p in enumerate(points):
        assert store.receive_sigma(p.stamp_ns, p.frame_id, sigma[i], now_ns=t0) == []
    assert store.poll(t0 + 3 * int(SIGMA_WAIT_S * SECOND)) == []
    later = t0 + 3 * int(SIGMA_WAIT_S * SECOND)
    for k, sample in enumerate(live_order(joints, points)):
        store.receive(sample, now_ns=later + k)
    assert len(store) == 3
    np.testing.assert_array_equal(store.measurements(NAMES, FRAME)[0].sigma, sigma)
    counts = store.counts()
    assert counts['rejected.unmatched_sigma'] == 0 and counts['stated_sigma'] == 3
