"""Measured inputs beyond temperature: a table's covariate columns imported in SI units (their
units checked, implausible values refused naming line and column), a real MCAP bag with an
inclinometer topic read by identify (readings paired by stamp, stale rows refused, readings
that are not finite never used), and the joint states' effort as the rows' torques."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import yaml
from mcap.writer import CompressionType
from mcap_ros2.writer import Writer

from kpi_calib_ros.app.cell_model import build_cell_model
from kpi_calib_ros.app.identify import calibrate_cell, with_effects
from kpi_calib_ros.app.measurements import measurements_from_bag
from kpi_calib_ros.cli import main
from kpi_calib_ros.core.acquisition.streams import synthesize_streams
from kpi_calib_ros.core.diagnosis.effect_signature import augmented_model
from kpi_calib_ros.core.effects.registry import parse_effect_spec
from kpi_calib_ros.core.errors import ConfigError, DataError
from kpi_calib_ros.core.measurement.covariates import InputSample, input_covariates
from kpi_calib_ros.core.model.robot import Payload
from kpi_calib_ros.core.simulation import random_configurations, true_parameters
from kpi_calib_ros.io.bag_writing import (
    JOINT_STATE_TYPE,
    POINT_STAMPED_TYPE,
    VECTOR3_STAMPED_TYPE,
    message_definition,
)
from kpi_calib_ros.io.cell import DEFAULT_CELL, cell_from_dict, read_cell_document
from kpi_calib_ros.io.csv_import import import_csv, mapping_from_dict
from kpi_calib_ros.io.mcap_scan import BagError
from kpi_calib_ros.io.ros_messages import (
    joint_state_fields,
    point_stamped_fields,
    vector3_stamped_fields,
)

SIGMA = 20e-6
S = 10**9
TILT = 'measured_tilt:joint_2:column'


def _tilted(cm, seed, n):
    """Poses of a column leaning by recorded angles (gains 1): q, points, the tilts (n, 2)."""
    rng = np.random.default_rng(seed)
    truth = augmented_model(cm.model, (parse_effect_spec(TILT, cm.robot),))
    p_true = np.concatenate([true_parameters(cm.model.params, rng), [1.0, 1.0]])
    q = random_configurations(cm.model, cm.model.params.nominal, n, rng)
    tilt = rng.uniform(-2e-3, 2e-3, (n, 2))
    eta = truth.predict(p_true, q, covariates={'tilt.column.x': tilt[:, 0],
                                               'tilt.column.y': tilt[:, 1]})
    return q, eta + rng.normal(0.0, SIGMA, eta.shape), tilt


def _cell(tmp_path: Path, **sections) -> Path:
    doc = read_cell_document(DEFAULT_CELL)
    doc['robot']['urdf'] = str((DEFAULT_CELL.parent / doc['robot']['urdf']).resolve())
    doc.update(sections)
    path = tmp_path / 'cell.yaml'
    path.write_text(yaml.safe_dump(doc))
    return path


def _table(path: Path, cm, q, eta, tilt, mass):
    names = cm.joint_names
    lines = [';'.join(names + ['x', 'y', 'z', 'incl_x', 'incl_y', 'load', 't'])]
    for i in range(len(q)):
        values = list(q[i]) + list(eta[i]) + list(tilt[i] * 1e3) + [mass[i], 1.7e9 + 4 * i]
        lines.append(';'.join(repr(float(v)) for v in values))
    path.write_text('\n'.join(lines) + '\n')
    return path


def _mapping(cm, **covariates):
    return mapping_from_dict({
        'frame_id': cm.cell.tracker_frame, 'joints': list(cm.joint_names),
        'markers': {'r': ['x', 'y', 'z']}, 'stamp_columns': ['t'],
        'covariates': covariates or {'tilt.column.x': {'column': 'incl_x', 'unit': 'mrad'},
                                     'tilt.column.y': {'column': 'incl_y', 'unit': 'mrad'},
                                     'payload.mass': 'load'}})


def test_table_covariates_are_imported_in_si_and_paired_to_their_rows(cm, tmp_path, capsys):
    q, eta, tilt = _tilted(cm, 5, 8)
    mass = np.array([0.0, 5.0] * 4)
    table = _table(tmp_path / 'postures.csv', cm, q, eta, tilt, mass)
    summary = import_csv(table, tmp_path / 'p.mcap', _mapping(cm))
    assert any(line.startswith('input tilt.column.x: ') and line.endswith('rad, written to '
                                                                         '/kpi_calib/inputs')
               for line in summary.lines())
    # the frame ids the points carry, and the cell's reflectors they call for (a cell with
    # one reflector: of no name refused every point as unknown_reflector)
    assert f"points written with frame_id '{cm.cell.tracker_frame}#r': the cell names these " \
           'reflectors, reflectors: [{name: r}]' in '\n'.join(summary.lines())
    doc = read_cell_document(_cell(tmp_path))
    doc['reflector'].pop('offset')
    doc['reflectors'] = [{'name': 'r', 'offset': [0.0, 0.0, 0.03]}]
    data, _ = measurements_from_bag(build_cell_model(cell_from_dict(doc, tmp_path)),
                                    tmp_path / 'p.mcap')
    assert len(data) == 8
    # mrad in the table, rad in the measurements; kg as written
    np.testing.assert_allclose(data.covariates['tilt.column.x'], tilt[:, 0], rtol=1e-12)
    np.testing.assert_allclose(data.covariates['tilt.column.y'], tilt[:, 1], rtol=1e-12)
    np.testing.assert_array_equal(data.covariates['payload.mass'], mass)


def test_table_covariates_are_validated(cm, tmp_path):
    with pytest.raises(ConfigError, match=r"mapping.covariates.tilt.column.x.unit.*'mrad'"):
        _mapping(cm, **{'tilt.column.x': {'column': 'incl_x', 'unit': 'mm'}})
    with pytest.raises(ConfigError, match='temperatures come from the temperature: section'):
        _mapping(cm, **{'temperature.arm': 'incl_x'})
    with pytest.raises(ConfigError, match="'tilt x' is not a covariate name"):
        _mapping(cm, **{'tilt x': 'incl_x'})
    with pytest.raises(ConfigError, match='mapping.covariates.payload.mass'):
        _mapping(cm, **{'payload.mass': {'col': 'load'}})
    q, eta, tilt = _tilted(cm, 6, 4)
    # degrees written as mrad (57 mrad for 57 mrad of lean, 1 rad), refused naming the
    # line and the column
    table = _table(tmp_path / 'deg.csv', cm, q, eta, np.full((4, 2), 1.0), np.zeros(4))
    with pytest.raises(DataError, match=r"line 2, column 'incl_x': tilt.column.x = .* outside "
                                        r'\[-0.5, 0.5\] rad'):
        import_csv(table, tmp_path / 'deg.mcap', _mapping(cm))
    assert not (tmp_path / 'deg.mcap').exists()
    table = _table(tmp_path / 'grams.csv', cm, q, eta, tilt, np.full(4, -5.0))
    with pytest.raises(DataError, match=r"column 'load': payload.mass = -5"):
        import_csv(table, tmp_path / 'grams.mcap', _mapping(cm))


def _write_bag(path: Path, cm, q, eta, tilt=None, efforts=None, skip_tilt=(), bad_tilt=()):
    """A real MCAP bag as a cell records it: joint states at 50 Hz held at every pose, one
    point per pose, and an inclinometer (Vector3Stamped on /column_tilt, rad) at 10 Hz
    around every point (none around the points ``skip_tilt``, NaN once at ``bad_tilt``);
    ``efforts(q) -> (n,)`` fills the joint states' effort."""
    joints, points = synthesize_streams(q, cm.joint_names, eta, cm.cell.tracker_frame)
    writer = Writer(str(path), compression=CompressionType.NONE)
    schema = {t: writer.register_msgdef(t, message_definition(t))
              for t in (JOINT_STATE_TYPE, POINT_STAMPED_TYPE, VECTOR3_STAMPED_TYPE)}
    messages = []
    for j in joints:
        fields = joint_state_fields(j)
        if efforts is not None:
            fields['effort'] = [float(v) for v in efforts(j.positions)]
        messages.append((j.stamp_ns, '/joint_states', JOINT_STATE_TYPE, fields))
    for i, p in enumerate(points):
        messages.append((p.stamp_ns, cm.cell.point_topic, POINT_STAMPED_TYPE,
                         point_stamped_fields(p)))
        if tilt is None or i in skip_tilt:
            continue
        for k in range(-5, 6):
            value = np.array([tilt[i, 0], tilt[i, 1], 0.0])
            if i in bad_tilt and k == 0:
                value[0] = np.nan
            t = p.stamp_ns + k * S // 10
            messages.append((t, '/column_tilt', VECTOR3_STAMPED_TYPE,
                             vector3_stamped_fields(t, 'column', value)))
    for stamp, topic, kind, fields in sorted(messages, key=lambda m: m[0]):
        writer.write_message(topic, schema[kind], fields, log_time=stamp, publish_time=stamp)
    writer.finish()
    return path


INPUTS = {'sources': [{'topic': '/column_tilt', 'type': 'geometry_msgs/msg/Vector3Stamped',
                       'fields': {'tilt.column.x': 'vector.x', 'tilt.column.y': 'vector.y'}}],
          'max_gap': 0.5}


def test_inclinometer_readings_are_paired_stale_rows_refused_bad_readings_unused(cm, tmp_path):
    q, eta, tilt = _tilted(cm, 7, 6)
    bag = _write_bag(tmp_path / 'tilt.mcap', cm, q, eta, tilt, skip_tilt=(2,), bad_tilt=(4,))
    cell = build_cell_model(cell_from_dict(read_cell_document(_cell(tmp_path, inputs=INPUTS)),
                                           tmp_path))
    with pytest.warns(UserWarning) as caught:
        data, _ = measurements_from_bag(cell, bag)
    text = ' '.join(str(w.message) for w in caught)
    assert '1 measured input reading(s) not finite, never used' in text
    # Row 2 has no reading within the gap; row 4's reading at its stamp has no value: its
    # neighbours' are not bridged over it (an input may step there).
    assert '2 of 6 measurement rows refused: no measured input at its stamp' in text
    assert 'next to a reading without a value' in text
    keep = [0, 1, 3, 5]
    assert len(data) == 4
    np.testing.assert_allclose(data.covariates['tilt.column.x'], tilt[keep, 0], rtol=1e-12)
    # a source whose field the type lacks, or a type the topic does not carry: exit 2
    wrong = dict(INPUTS, sources=[dict(INPUTS['sources'][0], fields={'tilt.column.x': 'point.x'})])
    with pytest.raises(BagError, match=r"topic '/column_tilt'.*has no field 'point'"):
        measurements_from_bag(build_cell_model(cell_from_dict(read_cell_document(
            _cell(tmp_path, inputs=wrong)), tmp_path)), bag)
    absent = dict(INPUTS, sources=[dict(INPUTS['sources'][0], topic='/nothing')])
    with pytest.raises(DataError, match=r"no finite reading of the measured input\(s\) "
                                        r"\['tilt.column.x', 'tilt.column.y'\]"):
        measurements_from_bag(build_cell_model(cell_from_dict(read_cell_document(
            _cell(tmp_path, inputs=absent)), tmp_path)), bag)


def test_a_payload_reading_without_a_value_is_not_bridged_by_its_neighbours():
    """A payload steps: 0 kg, then 5 kg picked up. One 5 kg reading is NaN; its row took
    0 kg from the readings around it and was used in the fit (only the count warned). It
    now has no payload: the row is refused, the others keep their readings."""
    S = 10 ** 9
    values = [0.0, 0.0, 0.0, np.nan, 5.0, 5.0]
    samples = [InputSample(i * S, 'payload.mass', v) for i, v in enumerate(values)]
    rows = np.arange(6, dtype=np.int64) * S
    cov, rejected = input_covariates(rows, samples, 2 * S)
    assert [r.stamp_ns for r in rejected] == [3 * S]
    np.testing.assert_array_equal(cov['payload.mass'], [0.0, 0.0, 0.0, np.nan, 5.0, 5.0])
    # a payload holds from its reading: a row before the valueless reading keeps the last
    # one, a row after it (before the next good one) has no value; one beyond the last good
    # reading keeps it
    cov, _ = input_covariates(np.array([2.5 * S, 3.5 * S, 5.5 * S], dtype=np.int64), samples,
                              2 * S)
    np.testing.assert_array_equal(cov['payload.mass'], [0.0, np.nan, 5.0])


def test_a_payload_reported_when_it_changes_holds_until_the_next_report():
    """A controller reports the payload when it changes, 0.3 s before the first point of
    each hold (a pick, a settle): every row carries the payload of its hold, whatever the
    gap between reports. Interpolated, rows got 0.94, 3.44 and 3.13 kg for 0, 2.5 and 5 kg.
    A row before the first report has none; a drifting input (a tilt) is still
    interpolated."""
    S = 10 ** 9
    loads = [0.0, 2.5, 5.0, 0.0, 2.5, 5.0]
    hold_starts = np.arange(6) * 40 * S            # a hold of 40 s per payload
    reports = [InputSample(int(t - 0.3 * S), 'payload.mass', m)
               for t, m in zip(hold_starts, loads)]
    rows = np.concatenate([t + np.array([0, 10, 20, 30]) * S for t in hold_starts])
    cov, rejected = input_covariates(np.concatenate([[-S], rows]), reports, 10 * S)
    assert not rejected
    np.testing.assert_array_equal(cov['payload.mass'][1:], np.repeat(loads, 4))
    assert np.isnan(cov['payload.mass'][0])
    tilt = [InputSample(0, 'tilt.column.x', 0.0), InputSample(4 * S, 'tilt.column.x', 0.004)]
    cov, _ = input_covariates(np.array([S], dtype=np.int64), tilt, 10 * S)
    assert cov['tilt.column.x'][0] == pytest.approx(0.001)


@pytest.mark.slow
def test_identify_reads_an_inclinometer_topic_and_recovers_the_tilt_gains(cm, tmp_path, capsys):
    q, eta, tilt = _tilted(cm, 8, 50)
    bag = _write_bag(tmp_path / 'lean.mcap', cm, q, eta, tilt)
    cell = _cell(tmp_path, inputs=INPUTS, effects=[TILT])
    out = tmp_path / 'out'
    assert main(['identify', '--cell', str(cell), '--bag', str(bag), '--out', str(out),
                 '--model', 'geometric']) == 0
    doc = yaml.safe_load((out / 'calibration.yaml').read_text())
    gains = {p['name']: p for p in doc['parameters'] if p['name'].startswith('measured_tilt')}
    assert set(gains) == {'measured_tilt.joint_2.column.gx', 'measured_tilt.joint_2.column.gy'}
    for p in gains.values():
        assert abs(p['value'] - 1.0) < 3 * p['std'], p


def _loaded(cm, seed, n):
    """Poses of an arm whose joint_2 gives under its measured torque (the robot carried 8 kg,
    the cell states 5 kg): q, points, the torque function."""
    rng = np.random.default_rng(seed)
    effect = parse_effect_spec('joint_compliance:joint_2', cm.robot)
    truth = augmented_model(cm.model, (effect,))
    p_true = np.concatenate([true_parameters(cm.model.params, rng), [-3e-6]])
    heavy = Payload(8.0, cm.robot.payload.com)

    def torque(q):
        q = np.atleast_2d(q)
        return cm.robot.gravity_torques(q, [heavy] * len(q)).reshape(q.shape)
    q = random_configurations(cm.model, cm.model.params.nominal, n, rng)
    eta = truth.predict(p_true, q, torque(q))
    return q, eta + rng.normal(0.0, SIGMA, eta.shape), torque, effect


def test_measured_efforts_are_the_rows_torques_when_the_cell_asks(cm, tmp_path):
    q, eta, torque, _ = _loaded(cm, 9, 5)
    bag = _write_bag(tmp_path / 'effort.mcap', cm, q, eta, efforts=lambda x: torque(x)[0])
    measured = build_cell_model(cell_from_dict(read_cell_document(
        _cell(tmp_path, compliance={'torque_source': 'measured'})), tmp_path))
    data, _ = measurements_from_bag(measured, bag)
    np.testing.assert_allclose(data.tau, torque(q), rtol=1e-12, atol=1e-9)
    model, _ = measurements_from_bag(cm, bag)
    assert model.tau is None
    # joint states without efforts: refused naming the fix
    bare = _write_bag(tmp_path / 'bare.mcap', cm, q, eta)
    with pytest.raises(DataError, match=r"no finite reading of the measured input\(s\) "
                                        r"\['effort.joint_1'.*name every chain joint"), \
            pytest.warns(UserWarning, match='reading.s. not finite, never used'):
        measurements_from_bag(measured, bare)
    with pytest.raises(ConfigError, match='compliance.torque_source'):
        cell_from_dict(read_cell_document(_cell(tmp_path, compliance={'torque_source': 'x'})),
                       tmp_path)


@pytest.mark.slow
def test_compliance_reads_the_measured_torques(cm, tmp_path):
    q, eta, torque, effect = _loaded(cm, 10, 40)
    bag = _write_bag(tmp_path / 'effort.mcap', cm, q, eta, efforts=lambda x: torque(x)[0])
    name = 'joint_compliance.joint_2.c'
    measured = with_effects(build_cell_model(cell_from_dict(read_cell_document(
        _cell(tmp_path, compliance={'torque_source': 'measured'})), tmp_path)), (effect,))
    data, _ = measurements_from_bag(measured, bag)
    cal = calibrate_cell(measured, data, model='geometric')
    assert abs(cal.result.value(name) + 3e-6) < 3 * cal.result.std_of(name)
    # the model's torques (5 kg, not the 8 kg carried) put the compliance elsewhere
    model = with_effects(cm, (effect,))
    plain = calibrate_cell(model, measurements_from_bag(model, bag)[0], model='geometric')
    assert abs(plain.result.value(name) + 3e-6) > 3 * plain.result.std_of(name)


def test_the_node_campaign_logs_each_measurements_efforts_and_pairs_them(cm, tmp_path):
    """With measured torques the node's campaign buffers the joint states' efforts and logs,
    per accepted measurement, every chain joint's effort at its stamp (one record, not one per
    joint state); its jobs pair them as the rows' torques, as identify does from a bag."""
    from kpi_calib_ros.core.acquisition.streams import JointSample, PointSample
    from kpi_calib_ros.io.measurement_log import MeasurementLog
    from kpi_calib_ros.ros.measurement_store import MeasurementStore
    from kpi_calib_ros.ros.stored_measurements import model_measurements
    q, eta, torque, _ = _loaded(cm, 12, 5)
    measured = build_cell_model(cell_from_dict(read_cell_document(
        _cell(tmp_path, compliance={'torque_source': 'measured'})), tmp_path))
    joints, points = synthesize_streams(q, cm.joint_names, eta, cm.cell.tracker_frame)
    campaign = MeasurementStore(tmp_path / 'data', inputs_topic=measured.cell.inputs.topic,
                        record_efforts=True)
    try:
        campaign.set_chain(cm.joint_names, cm.cell.tracker_frame)
        stream: list[JointSample | PointSample] = sorted(
            joints + points, key=lambda s: (s.stamp_ns, isinstance(s, PointSample)))
        for sample in stream:
            if isinstance(sample, JointSample):
                campaign.receive_efforts(sample.stamp_ns, sample.names,
                                         torque(sample.positions)[0])
            campaign.receive(sample)
        campaign.poll(2**62)
        assert len(campaign) == 5
        data, _ = model_measurements(campaign, measured)
        np.testing.assert_allclose(data.tau, torque(q), rtol=1e-9, atol=1e-9)
    finally:
        campaign.close()
    logged = MeasurementLog.load_inputs(tmp_path / 'data', measured.cell.inputs.topic)
    assert len(logged) == 5 * len(cm.joint_names)
    with pytest.raises(ValueError, match='record_efforts needs an inputs_topic'):
        MeasurementStore(tmp_path / 'other', record_efforts=True)


def test_a_table_of_measured_torques_is_the_rows_torques(cm, tmp_path):
    """import-csv refused effort columns and wrote joint states without efforts, so a
    campaign recorded as a table could not use its measured torques
    (``compliance.torque_source: measured`` then refused every row). ``efforts:`` maps a
    joint's torque column (N m, or kN m scaled) into the joint states' effort, and the rows'
    torques are the table's; a joint not of the table, or an unknown unit, is refused."""
    q, eta, torque, _ = _loaded(cm, 13, 6)
    tau = torque(q)
    names = cm.joint_names
    lines = [';'.join(names + ['x', 'y', 'z', 't'] + [f'tau_{j}' for j in names])]
    for i in range(len(q)):
        values = list(q[i]) + list(eta[i]) + [1.7e9 + 4 * i] + list(tau[i] / 1e3)
        lines.append(';'.join(repr(float(v)) for v in values))
    table = tmp_path / 'efforts.csv'
    table.write_text('\n'.join(lines) + '\n')
    doc = {'frame_id': cm.cell.tracker_frame, 'joints': list(names),
           'markers': {'r': ['x', 'y', 'z']}, 'stamp_columns': ['t'],
           'efforts': {j: {'column': f'tau_{j}', 'unit': 'kN m'} for j in names}}
    import_csv(table, tmp_path / 'efforts.mcap', mapping_from_dict(doc))
    cell = read_cell_document(_cell(tmp_path, compliance={'torque_source': 'measured'}))
    cell['reflector'].pop('offset')
    cell['reflectors'] = [{'name': 'r', 'offset': [0.0, 0.0, 0.03]}]
    measured = build_cell_model(cell_from_dict(cell, tmp_path))
    data, _ = measurements_from_bag(measured, tmp_path / 'efforts.mcap')
    assert len(data) == len(q)
    np.testing.assert_allclose(data.tau, tau, rtol=1e-12, atol=1e-9)
    with pytest.raises(ConfigError, match=r"mapping.efforts.elbow: 'elbow' is not in "
                                          r'mapping.joints'):
        mapping_from_dict({**doc, 'efforts': {'elbow': 'tau_joint_1'}})
    with pytest.raises(ConfigError, match=r"mapping.efforts.joint_1.unit: 'Nm'"):
        mapping_from_dict({**doc, 'efforts': {'joint_1': {'column': 'a', 'unit': 'Nm'}}})


def test_an_expected_input_that_never_arrives_stops_the_job(cm, tmp_path):
    """``inputs.expect`` names what the named-values topic must give: a payload published on
    another topic was fitted as the cell's 0 kg (compliance 4.7σ off, published as a
    success). A bag without it now stops naming the input, the topic and the fix; a bag
    with it reads as before; a bad ``expect`` names the key."""
    q, eta, tilt = _tilted(cm, 7, 6)
    tilt_only = _mapping(cm, **{'tilt.column.x': {'column': 'incl_x', 'unit': 'mrad'},
                                'tilt.column.y': {'column': 'incl_y', 'unit': 'mrad'}})
    table = _table(tmp_path / 'postures.csv', cm, q, eta, tilt, np.full(6, 2.5))
    import_csv(table, tmp_path / 'tilt.mcap', tilt_only)
    import_csv(table, tmp_path / 'both.mcap', _mapping(cm))

    def model(inputs):
        doc = read_cell_document(_cell(tmp_path, inputs=inputs))
        doc['reflector'].pop('offset')
        doc['reflectors'] = [{'name': 'r', 'offset': [0.0, 0.0, 0.03]}]
        return build_cell_model(cell_from_dict(doc, tmp_path))

    expecting = model({'expect': ['payload.mass']})
    with pytest.raises(DataError, match=r"no finite reading of the measured input\(s\) "
                                        r"\['payload.mass'\].*publish \['payload.mass'\] on "
                                        r'/kpi_calib/inputs.*or remove them from inputs.expect'):
        measurements_from_bag(expecting, tmp_path / 'tilt.mcap')
    data, _ = measurements_from_bag(expecting, tmp_path / 'both.mcap')
    np.testing.assert_array_equal(data.covariates['payload.mass'], np.full(6, 2.5))
    with pytest.raises(ConfigError, match=r'inputs.expect.*a list of covariate names'):
        model({'expect': 'payload.mass'})
    with pytest.raises(ConfigError, match=r"inputs.expect.*'payload mass' is not a covariate"):
        model({'expect': ['payload mass']})
