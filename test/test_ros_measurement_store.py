"""The node's measurement store without ROS: live pairing equals batch pairing, nothing lost or
counted twice across restarts, the pairing clock follows the joint stream."""
from __future__ import annotations

import numpy as np
import pytest

from kpi_calib_ros.core.acquisition.outcomes import PairedMeasurement, Rejection
from kpi_calib_ros.core.acquisition.pairing import pair_measurements
from kpi_calib_ros.core.acquisition.streams import synthesize_streams
from kpi_calib_ros.core.errors import DataError
from kpi_calib_ros.io.measurement_log import MeasurementLog
from kpi_calib_ros.ros.measurement_store import MeasurementStore

NAMES = ['joint_1', 'joint_2', 'joint_3']
FRAME = 'laser_tracker'
SECOND = 1_000_000_000


def streams(n: int = 6, seed: int = 3):
    rng = np.random.default_rng(seed)
    return synthesize_streams(rng.uniform(-1, 1, (n, 3)), NAMES, rng.uniform(-2, 2, (n, 3)),
                              FRAME, joint_noise_rad=2e-5, rng=rng)


def live_order(joints, points):
    """Arrival order of a live cell: by stamp, a point just after the joint state before it."""
    return [s for _, _, s in sorted([(j.stamp_ns, 0, j) for j in joints]
                                    + [(p.stamp_ns, 1, p) for p in points],
                                    key=lambda item: item[:2])]


def feed(store: MeasurementStore, samples) -> list:
    decisions = []
    for sample in samples:
        decisions += store.receive(sample)
    return decisions


def test_live_campaign_equals_batch_pairing(tmp_path):
    joints, points = streams()
    store = MeasurementStore(tmp_path)
    store.set_chain(NAMES, FRAME)
    decisions = feed(store, live_order(joints, points))
    assert all(isinstance(d, PairedMeasurement) for d in decisions) and len(decisions) == 6
    data, pairing = store.measurements(NAMES, FRAME)
    batch = pair_measurements(joints, points, NAMES, FRAME)
    np.testing.assert_array_equal(data.q, batch.q)
    np.testing.assert_array_equal(data.eta, batch.eta)
    np.testing.assert_array_equal(data.stamps_ns, batch.stamps_ns)
    assert store.counts()['accepted'] == 6 and store.counts()['rejected'] == 0


def test_restart_restores_everything_and_counts_nothing_twice(tmp_path):
    joints, points = streams()
    order = live_order(joints, points)
    first = MeasurementStore(tmp_path)
    first.set_chain(NAMES, FRAME)
    feed(first, order[:len(order) // 2])
    accepted = len(first)
    assert 0 < accepted < 6
    # Killed: no close(). The next process on the same folder restores what was accepted.
    second = MeasurementStore(tmp_path)
    assert second.restored == len(second) == accepted
    second.set_chain(NAMES, FRAME)
    decisions = feed(second, order)  # the whole recording again
    duplicates = [d for d in decisions if isinstance(d, Rejection)]
    assert [d.reason for d in duplicates] == ['duplicate_stamp'] * accepted
    assert len(second) == 6
    data, _ = second.measurements(NAMES, FRAME)
    batch = pair_measurements(joints, points, NAMES, FRAME)
    np.testing.assert_array_equal(data.q, batch.q)
    np.testing.assert_array_equal(data.stamps_ns, batch.stamps_ns)
    second.close()
    assert len(MeasurementStore(tmp_path)) == 6


def test_samples_before_the_robot_model_are_paired_once_it_is_known(tmp_path):
    joints, points = streams(3)
    store = MeasurementStore(tmp_path)
    assert feed(store, live_order(joints, points)) == []
    decisions = store.set_chain(NAMES, FRAME)
    assert sum(isinstance(d, PairedMeasurement) for d in decisions) == 3


def test_oversized_joint_states_are_rejected_before_the_robot_model_too(tmp_path):
    """The early buffer (samples held until the chain is known) takes no absurd message:
    each is rejected and counted by reason; the campaign still pairs the rest."""
    from kpi_calib_ros.core.acquisition.streams import JointSample
    from kpi_calib_ros.ros.measurement_store import EARLY_MAX_NAMES
    joints, points = streams(3)
    store = MeasurementStore(tmp_path)
    names = tuple(f'fake_{i}' for i in range(EARLY_MAX_NAMES + 1))
    huge = [JointSample(joints[0].stamp_ns + k, names, np.zeros(len(names)))
            for k in range(50)]
    decisions = feed(store, huge + live_order(joints, points))
    assert [d.reason for d in decisions] == ['oversized_joint_state'] * 50
    assert store.counts()['rejected.oversized_joint_state'] == 50
    assert len(store._early) == len(joints) + len(points)  # nothing of the 50 held
    paired = store.set_chain(NAMES, FRAME)
    assert sum(isinstance(d, PairedMeasurement) for d in paired) == 3


def test_pairing_clock_follows_the_joint_stream(tmp_path):
    joints, points = streams(2)
    order = live_order(joints, points)
    k = order.index(points[0])
    # A backlog: the joint states after the first point arrive over a minute of wall
    # time; while they keep coming, the points wait for them instead of timing out.
    backlog = MeasurementStore(tmp_path / 'backlog')
    backlog.set_chain(NAMES, FRAME)
    wall, decisions = 0, []
    for i, sample in enumerate(order):
        wall += 1_000_000 if i <= k else 60 * SECOND // (len(order) - k)
        decisions += backlog.receive(sample, now_ns=wall) + backlog.poll(now_ns=wall)
    assert [type(d) for d in decisions] == [PairedMeasurement, PairedMeasurement]
    # When the joint stream stops, a point is decided after the pairer's timeout
    # (window 0.2 s + timeout 1 s), not before.
    stopped = MeasurementStore(tmp_path / 'stopped')
    stopped.set_chain(NAMES, FRAME)
    for sample in order[:k + 1]:
        stopped.receive(sample, now_ns=0)
    assert stopped.poll(now_ns=SECOND) == []
    assert [d.reason for d in stopped.poll(now_ns=2 * SECOND)] == ['no_joint_state']


def test_reset_archives_instead_of_deleting(tmp_path):
    joints, points = streams(2)
    store = MeasurementStore(tmp_path)
    store.set_chain(NAMES, FRAME)
    feed(store, live_order(joints, points))
    (tmp_path / 'calibration.yaml').write_text('rms_m: 1\n')
    (tmp_path / 'diagnosis').mkdir()
    (tmp_path / 'diagnosis' / 'report.md').write_text('# Model diagnosis\n')
    (tmp_path / 'design.yaml').write_text('criterion: kpi\n')
    # a sequential campaign's state and the prior a campaign at a later station took
    (tmp_path / 'campaign_state.yaml').write_text('version: 1\n')
    (tmp_path / 'campaign_prior.yaml').write_text('rms_m: 1\n')
    count, archive = store.reset()
    assert (archive / 'campaign_state.yaml').exists() and (archive / 'campaign_prior.yaml').exists()
    assert not (tmp_path / 'campaign_prior.yaml').exists()
    assert count == 2 and len(store) == 0 and store.counts()['rejected'] == 0
    assert (archive / 'calibration.yaml').exists() and list(archive.glob('measurements_*.mcap'))
    assert (archive / 'diagnosis' / 'report.md').exists()
    assert not (tmp_path / 'calibration.yaml').exists() and not (tmp_path / 'diagnosis').exists()
    assert (tmp_path / 'design.yaml').exists()  # the plan stays for the next campaign
    assert len(MeasurementStore(tmp_path)) == 0  # a restart does not bring archived data back
    assert len(MeasurementLog.load_all(archive)) == 2


def test_measurements_name_the_problem(tmp_path):
    store = MeasurementStore(tmp_path)
    with pytest.raises(DataError, match='no accepted measurement'):
        store.measurements(NAMES, FRAME)
    store.set_chain(NAMES, FRAME)
    joints, points = streams(1)
    feed(store, live_order(joints, points))
    with pytest.raises(DataError, match='joint_9'):
        store.measurements(NAMES[:2] + ['joint_9'], FRAME)


@pytest.mark.slow
def test_the_measurement_log_is_a_bag_every_command_reads(tmp_path, capsys):
    """identify and diagnose on the node's log give what they give on the recording."""
    import yaml

    from kpi_calib_ros.app.cell_model import build_cell_model
    from kpi_calib_ros.cli import main
    from kpi_calib_ros.io.bag import read_bag
    from kpi_calib_ros.io.cell import DEFAULT_CELL, load_cell
    cell = str(DEFAULT_CELL)
    bag = tmp_path / 'run.mcap'
    assert main(['simulate', '--cell', cell, '--n', '30', '--out', str(bag), '--seed', '5']) == 0
    cm = build_cell_model(load_cell(cell))
    store = MeasurementStore(tmp_path / 'data')
    store.set_chain(list(cm.joint_names), cm.cell.tracker_frame)
    feed(store, live_order(*read_bag(bag)))
    store.close()
    log = tmp_path / 'data' / 'measurements_1.mcap'
    for source, out in ((bag, tmp_path / 'from_bag'), (log, tmp_path / 'from_log')):
        assert main(['identify', '--cell', cell, '--bag', str(source), '--out', str(out)]) == 0
    from_bag, from_log = (yaml.safe_load((tmp_path / d / 'calibration.yaml').read_text())
                          for d in ('from_bag', 'from_log'))
    assert from_log['pairing'] == from_bag['pairing'] == {'accepted': 30, 'rejected': {}}
    np.testing.assert_allclose([p['value'] for p in from_log['parameters']],
                               [p['value'] for p in from_bag['parameters']], rtol=0, atol=1e-12)
    assert (tmp_path / 'from_log' / 'calibration.yaml').stat().st_mode & 0o777 == 0o644 & ~_umask()
    assert main(['diagnose', '--cell', cell, '--bag', str(log), '--out',
                 str(tmp_path / 'diagnosis')]) == 0
    capsys.readouterr()
    # Replaying it into a node would reject every point: refused, saying what to do.
    assert main(['replay', str(log)]) == 2
    err = capsys.readouterr().err
    assert 'measurement log' in err and 'kpi-calib identify --bag' in err and 'data_dir' in err


def _umask() -> int:
    import os
    mask = os.umask(0)
    os.umask(mask)
    return mask


def test_disk_full_then_restart_restores_exactly_what_was_acknowledged(tmp_path, monkeypatch):
    from test_bag import DiskFull
    joints, points = streams(12)
    store = MeasurementStore(tmp_path)
    store.set_chain(NAMES, FRAME)
    # The disk fills after a few measurements (torn writes, failed syncs), then is freed.
    DiskFull(monkeypatch, fail_writes={3, 4, 5, 9}, fail_syncs={7})
    decisions = feed(store, live_order(joints, points))
    monkeypatch.undo()
    acknowledged = sorted(d.stamp_ns for d in decisions if isinstance(d, PairedMeasurement))
    not_stored = store.counts()['rejected.not_stored']
    assert not_stored >= 4 and len(acknowledged) + not_stored == 12 == len(decisions)
    store.close()
    restarted = MeasurementStore(tmp_path)
    assert restarted.restored == len(acknowledged)
    data, _ = restarted.measurements(NAMES, FRAME)
    assert data.stamps_ns.tolist() == acknowledged
