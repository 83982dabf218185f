"""The node's ~/identify against its archive and its disk (in process, private context):
a junk file in data_dir/calibrations/ is skipped with a warning, the answer says which
prior was used or why none (a full disk: test_ros_full_disk.py)."""
from __future__ import annotations

import numpy as np
import pytest
import rclpy
from rclpy.context import Context
from rclpy.executors import SingleThreadedExecutor
from rclpy.parameter import Parameter

from kpi_calib_ros.core.measurement.data import Measurements
from kpi_calib_ros.core.simulation import (
    random_configurations,
    simulate_measurements,
    true_parameters,
)
from kpi_calib_ros.ros.node import CalibrationNode

from ros_helpers import KR15_URDF, SpinThread, run_job

FIRST_NS = 1_700_000_000_000_000_000


@pytest.fixture
def node(tmp_path, ros_domain, monkeypatch):
    """A node (re-identifying with its archived prior) whose accepted measurements are 40
    simulated points stamped from FIRST_NS on, and a runner of its ~/identify job."""
    context = Context()
    rclpy.init(context=context, domain_id=ros_domain)
    made = spinner = None
    executor = SingleThreadedExecutor(context=context)
    try:
        made = CalibrationNode(context=context, parameter_overrides=[
            Parameter('robot_description', value=KR15_URDF),
            Parameter('data_dir', value=str(tmp_path)),
            Parameter('reidentify_with_prior', value=True)])
        cm = made._cm
        rng = np.random.default_rng(3)
        p_true = true_parameters(cm.model.params, rng)
        q = random_configurations(cm.model, cm.model.params.nominal, 40, rng)
        data = simulate_measurements(cm.model, p_true, q, 2e-5, rng)
        stamps = FIRST_NS + 10 ** 9 * np.arange(len(data))
        monkeypatch.setattr(made.store, 'measurements', lambda *a, **k: (
            Measurements(q=data.q, eta=data.eta, stamps_ns=stamps), None))
        executor.add_node(made)
        spinner = SpinThread(executor)
        spinner.start()

        def identify() -> tuple[bool, str]:
            return run_job(made, executor, 'identifying', made._identify, 120)
        made.identify = identify
        yield made
    finally:
        if spinner is not None:
            spinner.stop()
        else:
            executor.shutdown()
        if made is not None:
            made.destroy_node()
        rclpy.shutdown(context=context)


def test_junk_in_the_archive_is_skipped_and_the_answer_says_why_no_prior(node):
    """An unreadable archived calibration (older than the data) and one dated after the
    data: ~/identify succeeds without a prior and says so, naming both files."""
    archive = node.data_dir / 'calibrations'
    archive.mkdir()
    junk = archive / f'{FIRST_NS - 3600 * 10 ** 9}.yaml'
    junk.write_text('parameters: [1, 2\nprecision: x\n')
    later = archive / f'{FIRST_NS + 2 * 3600 * 10 ** 9}.yaml'
    later.write_text('not read: dated after the data\n')
    ok, message = node.identify()
    assert ok, message
    assert f'{junk} skipped' in message and 'not valid YAML' in message
    assert 'no prior: 1 archived calibration(s)' in message and 'dated at or after' in message
    assert 'clock' in message and 'prior /' not in message


def test_a_nul_byte_in_an_archived_calibration_is_skipped_by_name(node):
    """A damaged archived calibration (a NUL byte, e.g. data_dir/calibrations/1.yaml):
    ~/identify goes on, without it, and the answer names the file and why."""
    archive = node.data_dir / 'calibrations'
    archive.mkdir()
    damaged = archive / '1.yaml'
    damaged.write_text('parameters: []\n\x00\n')
    ok, message = node.identify()
    assert ok, message
    assert f'{damaged} skipped' in message and 'character YAML does not allow' in message
    ok, message = node.identify()  # and again: nothing blocks the next one
    assert ok, message
