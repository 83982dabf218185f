"""kpi_calib_node ~/identify with identify_learned_residual, end to end (real rclpy and
Fast DDS, the node as a separate process): a robot with a smooth unknown map of two
joints is measured through the node's topics; with the parameter off ~/identify writes
no learned_residual.yaml and ~/tcp_query answers with the physical model; switched on,
the learned residual is chosen, written and used by ~/tcp_query, whose TCP at fresh
poses is far closer to the truth; off again, a new calibration removes the older file."""
from __future__ import annotations

import os

import numpy as np
import pytest
import yaml
from rclpy.parameter import Parameter
from rclpy.parameter_client import AsyncParameterClient
from test_learned_residual_file import dumped, fitted, hostile_files
from test_ros_tcp_query import learned

from kpi_calib_ros.app.cell_model import build_cell_model
from kpi_calib_ros.app.learned_residual import predict_stored, predict_tcp
from kpi_calib_ros.app.validate import calibrated_model
from kpi_calib_ros.core.acquisition.outcomes import PairingResult
from kpi_calib_ros.core.errors import ConfigError
from kpi_calib_ros.core.measurement.data import Measurements
from kpi_calib_ros.core.simulation import (
    random_configurations,
    simulate_measurements,
    smooth_joint_map,
    true_parameters,
)
from kpi_calib_ros.io.cell import DEFAULT_CELL, load_cell
from kpi_calib_ros.io.learned_residual_file import read_residual
from kpi_calib_ros.ros import job_work
from kpi_calib_ros.ros.parameters import PARAMETERS, settings_from_parameters

from ros_helpers import Queries, start_error

N_POSES = 100
N_FRESH = 30
AMPLITUDE_M = 2e-4   # 10 σ of the built-in cell's tracker
JOINTS = (1, 2)      # the map depends on joint_2 and joint_3
PARAMETER = 'identify_learned_residual'


@pytest.fixture
def spawn(tmp_path):
    """Start the node process; whatever the test leaves running is killed."""
    from ros_helpers import Spawner
    spawner = Spawner(tmp_path)
    yield spawner
    spawner.kill_all()


def robot(seed: int = 3):
    """The cell model, the true parameters and map, training and fresh poses."""
    cm = build_cell_model(load_cell(DEFAULT_CELL))
    rng = np.random.default_rng(seed)
    p = true_parameters(cm.model.params, rng)
    phase = rng.uniform(0, 2 * np.pi, 6)
    q = random_configurations(cm.model, p, N_POSES + N_FRESH, rng)

    def truth(qq: np.ndarray) -> np.ndarray:
        return cm.model.predict(p, qq) + smooth_joint_map(qq, JOINTS, AMPLITUDE_M, phase)
    eta = simulate_measurements(cm.model, p, q[:N_POSES], cm.cell.sigma, rng).eta
    eta = eta + smooth_joint_map(q[:N_POSES], JOINTS, AMPLITUDE_M, phase)
    return cm, q[:N_POSES], eta, q[N_POSES:], truth


def rms(e: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.sum(e ** 2, axis=1))))


def test_the_parameter_is_validated_by_name(tmp_path, ros_domain):
    """A value that is not a bool names the parameter, in the settings and at start-up."""
    values = {k: ([] if isinstance(v[0], Parameter.Type) else v[0])
              for k, v in PARAMETERS.items()}
    assert settings_from_parameters(values).identify_learned_residual is False
    with pytest.raises(ConfigError) as info:
        settings_from_parameters({**values, PARAMETER: 'yes'})
    assert info.value.key == PARAMETER and 'true or false' in str(info.value)
    error = start_error(tmp_path, ros_domain, Parameter(PARAMETER, value=1))
    assert error.key == PARAMETER and 'true or false' in str(error), error


def test_a_prior_calibration_fits_no_learned_residual_and_removes_the_older_one(tmp_path):
    """With a prior (the last cycle's archived calibration) the learned residual is not
    fitted, as identify --learned-residual is not with --prior, and the older
    learned_residual.yaml is removed with the new calibration."""
    cm, q, eta, _, _ = robot()

    def measured(rows: slice, start_ns: int):
        stamps = start_ns + np.arange(len(q[rows]), dtype=np.int64) * 10 ** 9
        pairing = PairingResult(cm.joint_names, cm.cell.tracker_frame, q[rows], eta[rows],
                                stamps)
        return Measurements(q=q[rows], eta=eta[rows], stamps_ns=stamps), pairing
    first = measured(slice(0, 60), 10 ** 18)
    learned = job_work.identify_work(cm, *first, tmp_path, learned_residual=True).learned
    assert learned[0] == 'chosen' and (tmp_path / 'learned_residual.yaml').is_file(), learned
    cycle = measured(slice(60, N_POSES), 2 * 10 ** 18)
    out = job_work.identify_work(cm, *cycle, tmp_path, with_prior=True, learned_residual=True)
    cal, text, prior, learned = out.calibration, out.text, out.prior, out.learned
    assert cal is not None and cal.valid and prior, (prior, learned)
    assert learned[0] == 'not fitted' and 'reidentify_with_prior:=false' in learned[1]
    assert not (tmp_path / 'learned_residual.yaml').exists()
    assert 'learned_residual' not in yaml.safe_load(text)


@pytest.mark.slow
def test_identify_learns_the_residual_and_tcp_query_uses_it(client, spawn, tmp_path):
    cm, q, eta, fresh, truth = robot()
    data_dir = tmp_path / 'data'
    learned_file = data_dir / 'learned_residual.yaml'
    node = spawn(data_dir, 'node.log', 'auto_identify:=false')
    queries = Queries(client, cm, N_FRESH)
    client.spin_until(lambda: client.diagnostics().get('state') == 'idle'
                      and queries.connected(), 60, 'the model and the TCP query topics')
    try:
        client.publish_measurements(q, cm.joint_names, eta, cm.cell.tracker_frame, N_POSES)

        def tcp_answers(round_: int) -> np.ndarray:
            """The node's TCP (m) at the fresh poses: one query each, as a client asks
            (the next once the last is answered), stamps of this round."""
            return np.array([position for position, _ in
                             queries.ask(fresh, (round_ * 1000 + 1) * 10 ** 6)])

        # Off (the default): nothing learned, nothing written; the physical model answers.
        off = client.call('identify')
        print('identify (off):', off.message)
        assert off.success, off.message
        assert 'learned residual' not in off.message and not learned_file.exists()
        physical = tcp_answers(0)

        params = AsyncParameterClient(client.node, 'kpi_calib_node')
        assert params.wait_for_services(timeout_sec=10)
        future = params.set_parameters([Parameter(PARAMETER, value=True)])
        client.executor.spin_until_future_complete(future, timeout_sec=10)
        assert future.result().results[0].successful, future.result().results[0].reason

        on = client.call('identify')
        print('identify (on):', on.message)
        assert on.success, on.message
        assert "learned residual chosen: rms" in on.message, on.message
        assert learned_file.is_file(), node.output()
        client.spin_until(lambda: client.diagnostics().get('learned_residual') == 'chosen',
                          10, 'learned_residual in /diagnostics')
        calibrations = client.received['calibration']
        client.spin_until(lambda: 'learned_residual' in calibrations[-1], 10,
                          'the calibration with its learned residual')
        section = calibrations[-1]['learned_residual']
        assert section['chosen'] and section['file'] == 'learned_residual.yaml'
        assert section['cv_rms_learned_m'] < section['cv_rms_physical_m']
        corrected = tcp_answers(1)

        # The truth at the fresh poses: the learned residual brings the node's TCP closer.
        stored = read_residual(learned_file)
        inside = predict_stored(cm.model, stored, fresh).correction.inside
        error_physical, error_learned = rms(physical - truth(fresh)), rms(corrected - truth(fresh))
        print(f'fresh poses ({inside.mean():.0%} inside the fitted region): TCP error rms '
              f'{error_physical * 1e6:.1f} um physical, {error_learned * 1e6:.1f} um with the '
              f'learned residual ({error_learned / error_physical:.2f}x)')
        assert inside.mean() >= 0.8
        assert error_learned <= 0.6 * error_physical
        # The answer is the stored model's prediction, not the physical model's.
        np.testing.assert_allclose(corrected, predict_stored(cm.model, stored, fresh).position,
                                   rtol=0, atol=1e-9)

        # Off again: the new calibration removes the file it would otherwise be corrected by.
        future = params.set_parameters([Parameter(PARAMETER, value=False)])
        client.executor.spin_until_future_complete(future, timeout_sec=10)
        assert future.result().results[0].successful
        again = client.call('identify')
        assert again.success, again.message
        assert not learned_file.exists()
        client.spin_until(lambda: 'learned_residual' not in client.diagnostics(), 10,
                          'learned_residual gone from /diagnostics')
        np.testing.assert_allclose(tcp_answers(2), physical, rtol=0, atol=1e-9)
    finally:
        code = node.stop()
    assert code == 0, node.output()


def replace_file(path, text: str) -> None:
    """Write ``path`` as identify does: a new file moved over the old one."""
    part = path.with_suffix('.part')
    part.write_text(text)
    os.replace(part, path)


@pytest.mark.slow
def test_a_foreign_or_hostile_learned_residual_is_not_used(client, spawn, tmp_path):
    """The node identifies its calibration; a learned_residual.yaml then written into its
    data_dir for another robot (as ``identify --learned-residual --out data_dir`` would
    while it runs) is the check validate makes: ~/tcp_query answers with the node's own
    physical calibration, and the log and /diagnostics (``tcp_query``) say why. Hostile
    files (a kernel that cannot be factored, a training set above the bound, 60 000 rows,
    a non-finite number) are refused by name: the node stays alive and answers the same."""
    cm, q, eta, fresh, _ = robot()
    fresh = fresh[:3]
    data_dir = tmp_path / 'data'
    learned_file = data_dir / 'learned_residual.yaml'
    node = spawn(data_dir, 'node.log', 'auto_identify:=false')
    queries = Queries(client, cm, 10)
    client.spin_until(lambda: client.diagnostics().get('state') == 'idle'
                      and queries.connected(), 60, 'the model and the TCP query topics')
    try:
        client.publish_measurements(q, cm.joint_names, eta, cm.cell.tracker_frame, N_POSES)
        done = client.call('identify')
        assert done.success, done.message
        doc = yaml.safe_load((data_dir / 'calibration.yaml').read_text())
        cal_cm, values = calibrated_model(load_cell(DEFAULT_CELL), doc)
        cov = doc['parameter_covariance']
        physical = predict_tcp(cal_cm.model, values, tuple(cov['names']),
                               np.array(cov['matrix'], float), None, fresh)

        def answers_physical(round_: int) -> None:
            answered = queries.ask(fresh, (round_ * 1000 + 1) * 10 ** 6)
            np.testing.assert_allclose([p for p, _ in answered], physical.position,
                                       rtol=0, atol=1e-12)
            np.testing.assert_allclose([c for _, c in answered], physical.covariance,
                                       rtol=1e-9, atol=0)

        def said(text: str) -> str:
            client.spin_until(lambda: text in client.diagnostics().get('tcp_query', ''), 10,
                              f'{text!r} in tcp_query on /diagnostics')
            return client.diagnostics()['tcp_query']

        answers_physical(0)
        assert said('physical calibration') == 'physical calibration'
        # Another robot's learned residual (same cell, other parameter values).
        other = tmp_path / 'other'
        other.mkdir()
        learned(cm, other, 5, 1e-4)
        replace_file(learned_file, (other / 'learned_residual.yaml').read_text())
        foreign = predict_stored(cm.model, read_residual(learned_file), fresh).position
        print(f'the foreign file would move the TCP by '
              f'{np.abs(foreign - physical.position).max() * 1e3:.1f} mm')
        answers_physical(1)
        assert said('written for another calibration').startswith(
            'physical calibration only, learned residual not used: learned_residual.yaml '
            'was written for another calibration than the one in use'), client.diagnostics()
        assert 'TCP query answered with the physical calibration only, learned residual not ' \
               'used: learned_residual.yaml was written for another calibration' \
               in node.output()
        # Hostile files: refused by name, the node alive and answering.
        choice = fitted()
        for i, (name, (hostile, field)) in enumerate(hostile_files(choice).items()):
            replace_file(learned_file, dumped(hostile))
            answers_physical(2 + i)
            text = said(field)
            assert str(learned_file) in text, (name, text)
            assert 'learned residual not used: ' in node.output()
            assert node.process.poll() is None, node.output()
    finally:
        code = node.stop()
    assert code == 0, node.output()
