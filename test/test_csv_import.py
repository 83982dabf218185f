"""import-csv: posture tables as spreadsheets export them, and tables it must refuse.

The UR10 laser-tracker tables of ../shared/data/ipa_ur10 (';' separator, decimal commas,
the T-Mac probe's orientation as XYZ Euler angles in degrees, the cell temperature) are
read as they are and identified from; every malformed table is an exit code 2 naming
the file and the line or column, with no bag (or part of one) left behind.
"""
import codecs
import json
import tracemalloc
from pathlib import Path

import numpy as np
import pytest
import yaml
from mcap.reader import make_reader
from mcap_ros2.decoder import DecoderFactory
from scipy.spatial.transform import Rotation

from kpi_calib_ros.app.cell_model import build_cell_model
from kpi_calib_ros.app.measurements import measurements_from_bag
from kpi_calib_ros.app.placement import registered_start
from kpi_calib_ros.cli import main
from kpi_calib_ros.core.errors import ConfigError
from kpi_calib_ros.io.cell import load_cell
from kpi_calib_ros.io.csv_import import import_csv, load_mapping, mapping_from_dict, read_postures
from kpi_calib_ros.io.names import DEFAULT_POSE_TOPIC, DEFAULT_TEMPERATURE_TOPIC

from real_data import UR10_DATA

DATA = UR10_DATA
HERE = Path(__file__).resolve().parent / 'data'
CELL = HERE / 'ipa_ur10_cell.yaml'
MAPPING = HERE / 'ipa_ur10_mapping.yaml'


def _subset(source: Path, target: Path, rows: int, step: int) -> Path:
    """Header and every ``step``-th row of ``source`` (the bytes as they are)."""
    lines = source.read_bytes().split(b'\r\n')
    body = [line for line in lines[1:] if line][::step][:rows]
    target.write_bytes(b'\r\n'.join([lines[0], *body]) + b'\r\n')
    return target


def _messages(bag: Path, topic: str) -> list:
    with open(bag, 'rb') as f:
        return [m for _, channel, _, m in make_reader(
            f, decoder_factories=[DecoderFactory()]).iter_decoded_messages(topics=[topic])]


@pytest.mark.slow
def test_ur10_series_a_as_exported_is_imported_and_identified(tmp_path, capsys):
    table = _subset(DATA / 'Series_A' / 'measurements_grid.csv', tmp_path / 'grid.csv',
                    149, 80)
    bag = tmp_path / 'grid.mcap'
    assert main(['import-csv', str(table), '--mapping', str(MAPPING), '--out', str(bag)]) == 0
    out = capsys.readouterr().out
    assert "separator ';' detected" in out and 'decimal commas detected' in out
    assert '149 postures, 149 points, of which 149 6-DoF poses' in out
    assert 'time axis: stamps of' in out and '2020-07-14T16:39:04+02:00' in out
    # The probe pose as the table gives it: XYZ intrinsic Euler angles in degrees.
    first = next(iter(read_postures(table, load_mapping(MAPPING))))
    pose = _messages(bag, DEFAULT_POSE_TOPIC)[0].pose
    expected = Rotation.from_euler('XYZ', [-90.409151, -59.885105, -90.887438], degrees=True)
    got = Rotation.from_quat([pose.orientation.x, pose.orientation.y, pose.orientation.z,
                              pose.orientation.w])
    assert (expected.inv() * got).magnitude() < 1e-12
    assert np.allclose([pose.position.x, pose.position.y, pose.position.z],
                       [2.3619831, -1.3685474, 0.11939713], atol=1e-12)
    assert np.allclose(first.q, [-1.5708, -1.5708, 0.0, -1.5708, 0.0, 0.0])
    # The cell temperature on its own topic, one per posture, as recorded overnight.
    temperatures = [m.temperature for m in _messages(bag, DEFAULT_TEMPERATURE_TOPIC)]
    assert len(temperatures) == 149 and 22.9 < min(temperatures) < max(temperatures) < 23.7

    # The nominal model with the base pose and the probe origin registered misses by
    # 0.77-0.84 mm rms (data README); the probe origin lies about 93 mm along tool0's z.
    cm = build_cell_model(load_cell(CELL))
    data, _ = measurements_from_bag(cm, bag)
    _, registration = registered_start(cm, data)
    registered_rms = float(np.sqrt(np.mean(registration.residuals_m ** 2)))
    assert 0.7e-3 < registered_rms < 0.9e-3
    assert abs(registration.reflector_offset[2] - 0.093) < 2e-3
    assert np.linalg.norm(registration.reflector_offset[:2]) < 2e-3
    capsys.readouterr()
    rc = main(['identify', '--cell', str(CELL), '--bag', str(bag), '--out',
               str(tmp_path / 'cal')])
    assert rc in (0, 1)
    cal = yaml.safe_load(next((tmp_path / 'cal').glob('calibration*.yaml')).read_text())
    assert cal['status']['converged'] and cal['pairing']['accepted'] == 149
    # With outlier exclusion on (the default): the points beyond the threshold are the
    # model's misfit, one point a pose and too many to be faults: kept, and said so.
    text = capsys.readouterr()
    assert cal['robust']['excluded'] == [] and len(cal['robust']['misfit']) > 50
    assert 'taken as model misfit' in text.err and 'model misfit at poses' in text.out
    # A geometric calibration leaves about 0.4 mm (data README): well below registration.
    assert cal['rms_m'] < 0.6 * registered_rms


def test_series_d_truncated_stamps_say_the_time_axis_is_the_row_order(tmp_path, capsys):
    table = _subset(DATA / 'Series_D' / 'measurements_iso_cubes.csv', tmp_path / 'cubes.csv',
                    40, 1)
    doc = yaml.safe_load(MAPPING.read_text())
    doc['stamp_format'] = 'unix'
    doc['markers']['tmac']['sigma'] = ['measurement_std_x', 'measurement_std_y',
                                       'measurement_std_z']
    with_stamps, without = tmp_path / 'stamps.yaml', tmp_path / 'rows.yaml'
    with_stamps.write_text(yaml.safe_dump(doc))
    del doc['stamp_columns']
    without.write_text(yaml.safe_dump(doc))
    bag = tmp_path / 'cubes.mcap'
    assert main(['import-csv', str(table), '--mapping', str(with_stamps), '--out',
                 str(bag)]) == 2
    err = capsys.readouterr().err
    # '2,02103E+13' (a spreadsheet's truncation of YYYYMMDDhhmmss) is no Unix stamp.
    assert f'{table}: line 2' in err and "'Timestamp'" in err and 'row order' in err
    assert not bag.exists() and sorted(p.name for p in tmp_path.iterdir()) == [
        'cubes.csv', 'rows.yaml', 'stamps.yaml']
    assert main(['import-csv', str(table), '--mapping', str(without), '--out', str(bag)]) == 0
    out = capsys.readouterr().out
    assert 'time axis: row order' in out
    # The per-point σ the table gives (mm): reported, in µm.
    sigma = np.array([[float(v.replace(',', '.')) for v in line.split(';')[15:20:2]]
                      for line in table.read_text().splitlines()[1:]]) * 1e3
    assert f'mean {np.round(sigma.mean(axis=0), 1).tolist()} µm' in out


@pytest.mark.slow
def test_stamps_that_number_the_rows_are_no_clock_past_pairing(tmp_path, capsys):
    """A table without times is stamped in row order to pair its columns; the bag says so,
    and past pairing those stamps are no clock: the calibration states no date (a later
    --prior would take drift time from a made-up one) and the residual analysis offers no
    'time' input (it ranked the row order third on the real Series D)."""
    table = _subset(DATA / 'Series_D' / 'measurements_iso_cubes.csv', tmp_path / 'cubes.csv',
                    60, 1)
    doc = yaml.safe_load(MAPPING.read_text())
    del doc['stamp_columns']
    mapping = tmp_path / 'rows.yaml'
    mapping.write_text(yaml.safe_dump(doc))
    bag = tmp_path / 'cubes.mcap'
    assert main(['import-csv', str(table), '--mapping', str(mapping), '--out', str(bag)]) == 0
    cm = build_cell_model(load_cell(CELL))
    data, pairing = measurements_from_bag(cm, bag)
    assert len(data) >= 60 and data.stamps_ns is None and not pairing.stamps_are_times
    out = tmp_path / 'cal'
    assert main(['identify', '--cell', str(CELL), '--bag', str(bag), '--out', str(out)]) in (0, 1)
    cal = yaml.safe_load(next(out.glob('calibration*.yaml')).read_text())
    assert 'identified_at_ns' not in cal and cal['pairing']['accepted'] == 60
    assert len(cal['training_configurations']['joints']) == 6
    diag = tmp_path / 'diag'
    capsys.readouterr()
    assert main(['diagnose', '--cell', str(CELL), '--bag', str(bag), '--out', str(diag)]) == 0
    inputs = json.loads((diag / 'diagnosis.json').read_text())['residual_inputs']['inputs']
    assert inputs and 'time' not in {i['name'] for i in inputs}


def _plain_table(rows: int, stamps: bool = True) -> list[str]:
    rng = np.random.default_rng(0)
    header = 'stamp,joint_1,joint_2,x,y,z' if stamps else 'joint_1,joint_2,x,y,z'
    lines = [header]
    for i in range(rows):
        values = ([1.7e9 + 5 * i] if stamps else []) + list(rng.uniform(-1, 1, 5))
        lines.append(','.join(repr(float(v)) for v in values))
    return lines


_PLAIN = ['--frame', 'laser_tracker', '--joints', 'joint_1,joint_2', '--marker', 'r=x,y,z']


@pytest.mark.parametrize('name, write, says', [
    ('field', lambda p: p.write_text('\n'.join(_plain_table(3)) + '\n1,"' + 'x' * 140_000 +
                                     '\n'), 'after line 4: a field longer than'),
    ('negative', lambda p: p.write_text('\n'.join(
        _plain_table(3)[:1] + ['-5.0,0.1,0.2,1.0,2.0,3.0'] + _plain_table(3)[1:]) + '\n'),
     "line 2, column 'stamp': '-5.0' is -5 s since 1970"),
    ('duplicate', lambda p: p.write_text('\n'.join(
        ['stamp,joint_1,joint_2,x,y,joint_2'] + _plain_table(3)[1:]) + '\n'),
     "column 'joint_2' appears twice (columns 3 and 6)"),
    ('utf16_without_bom', lambda p: p.write_bytes(
        '\n'.join(_plain_table(3)).encode('utf-16-le')), 'UTF-16 without a byte-order mark'),
    ('short_row', lambda p: p.write_text('\n'.join(_plain_table(3) + ['1.0,2.0']) + '\n'),
     'line 5 has 2 fields, the header 6'),
])
def test_a_malformed_table_is_exit_2_naming_file_and_place_and_leaves_nothing(
        tmp_path, capsys, name, write, says):
    table = tmp_path / f'{name}.csv'
    write(table)
    out = tmp_path / 'out.mcap'
    assert main(['import-csv', str(table), *_PLAIN, '--stamp-columns', 'stamp',
                 '--out', str(out)]) == 2
    err = capsys.readouterr().err
    assert str(table) in err and says in err
    assert [p.name for p in tmp_path.iterdir()] == [table.name]


def test_an_out_path_that_is_a_folder_is_exit_2_naming_out(tmp_path, capsys):
    table = tmp_path / 'plain.csv'
    table.write_text('\n'.join(_plain_table(3)) + '\n')
    (tmp_path / 'folder.mcap').mkdir()
    assert main(['import-csv', str(table), *_PLAIN, '--out', str(tmp_path / 'folder.mcap')]) == 2
    assert f"--out: '{tmp_path / 'folder.mcap'}' is a folder" in capsys.readouterr().err
    assert sorted(p.name for p in tmp_path.iterdir()) == ['folder.mcap', 'plain.csv']


@pytest.mark.parametrize('encoding, note', [
    ('utf-8-sig', 'UTF-8 byte-order mark stripped'),
    ('utf-16', 'UTF-16 by its byte-order mark'),
    ('cp1252', 'not UTF-8 (byte 0xb0'),
])
def test_bom_utf16_and_cp1252_tables_give_the_bag_of_the_utf8_table(tmp_path, capsys,
                                                                    encoding, note):
    lines = _plain_table(4)
    lines[0] += ',temp_°C'
    lines[1:] = [line + ',23.5' for line in lines[1:]]
    text = '\n'.join(lines) + '\n'
    (tmp_path / 'plain.csv').write_text(text, encoding='utf-8')
    (tmp_path / 'other.csv').write_bytes(text.encode(encoding))
    if encoding == 'utf-16':
        assert (tmp_path / 'other.csv').read_bytes()[:2] in (codecs.BOM_UTF16_LE,
                                                             codecs.BOM_UTF16_BE)
    for stem in ('plain', 'other'):
        assert main(['import-csv', str(tmp_path / f'{stem}.csv'), *_PLAIN, '--stamp-columns',
                     'stamp', '--out', str(tmp_path / f'{stem}.mcap')]) == 0
    assert note in capsys.readouterr().out
    assert (tmp_path / 'plain.mcap').read_bytes() == (tmp_path / 'other.mcap').read_bytes()


def test_unix_iso8601_serial_and_pattern_stamps_agree(tmp_path):
    moment = '2020-06-18T14:00:00+02:00'  # 12:00 UTC: spreadsheet serial day 44000.5
    expected = 1592481600 * 10 ** 9
    for how, text, zone in (('unix', '1592481600', 'UTC'), ('iso8601', moment, 'UTC'),
                            ('serial', '44000.5', 'UTC'),
                            ('%Y%m%d%H%M%S', '20200618140000', 'Europe/Berlin')):
        table = tmp_path / 't.csv'
        table.write_text(f't;j;x;y;z\n{text};0,5;1;2;3\n')
        mapping = mapping_from_dict({'frame_id': 'f', 'joints': ['j'],
                                     'markers': {'r': ['x', 'y', 'z']}, 'stamp_columns': ['t'],
                                     'stamp_format': how, 'stamp_timezone': zone})
        row = next(iter(read_postures(table, mapping)))
        assert row.stamp_ns == expected, how
        assert row.q.tolist() == [0.5]


def _peak_bytes(tmp_path: Path, rows: int) -> int:
    table = tmp_path / f'{rows}.csv'
    table.write_text('\n'.join(_plain_table(rows)) + '\n')
    mapping = mapping_from_dict({'frame_id': 'f', 'joints': ['joint_1', 'joint_2'],
                                 'markers': {'r': ['x', 'y', 'z']}, 'stamp_columns': ['stamp']})
    tracemalloc.start()
    try:
        import_csv(table, tmp_path / f'{rows}.mcap', mapping, rate_hz=2.0)
        return tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()


@pytest.mark.slow
def test_memory_does_not_grow_with_the_rows(tmp_path):
    # Both tables fill several 768 KiB chunks of the bag (about 480 bytes a row).
    small, large = _peak_bytes(tmp_path, 2000), _peak_bytes(tmp_path, 8000)
    # Four times the rows; what may grow is the stamp index (16 bytes a row, 32 while
    # it is sorted at the end).
    assert large < small + 6000 * 32 + 64 * 1024, (small, large)


def test_delimiter_and_decimal_given_read_a_tab_table_with_decimal_commas(tmp_path, capsys):
    lines = _plain_table(4)
    (tmp_path / 'plain.csv').write_text('\n'.join(lines) + '\n')
    (tmp_path / 'tab.csv').write_text('\n'.join(
        line.replace(',', '\t').replace('.', ',') for line in lines) + '\n')
    assert main(['import-csv', str(tmp_path / 'plain.csv'), *_PLAIN, '--stamp-columns',
                 'stamp', '--out', str(tmp_path / 'plain.mcap')]) == 0
    assert main(['import-csv', str(tmp_path / 'tab.csv'), *_PLAIN, '--stamp-columns', 'stamp',
                 '--delimiter', 'tab', '--decimal', ',', '--out', str(tmp_path / 'tab.mcap')]) == 0
    out = capsys.readouterr().out
    assert "separator '\\t', decimal ','" in out and 'detected' not in out.split('tab.csv')[-1]
    assert (tmp_path / 'plain.mcap').read_bytes() == (tmp_path / 'tab.mcap').read_bytes()


def test_a_temperature_no_arm_can_have_is_not_written_and_counted(tmp_path, capsys):
    # A sensor fault among plausible readings: below absolute zero and 1e12 °C.
    table = tmp_path / 'warm.csv'
    rows = [(22.0, ''), (-500.0, ''), (22.2, ''), (1e12, ''), (22.4, '')]
    table.write_text('t;j;x;y;z;temp\n' + ''.join(
        f'{1592481600 + 10 * k};0.{k};1;2;3;{c!r}\n' for k, (c, _) in enumerate(rows)))
    mapping = tmp_path / 'mapping.yaml'
    mapping.write_text(yaml.safe_dump({
        'frame_id': 'f', 'joints': ['j'], 'markers': {'r': ['x', 'y', 'z']},
        'stamp_columns': ['t'], 'stamp_format': 'unix', 'temperature': 'temp'}))
    bag = tmp_path / 'warm.mcap'
    assert main(['import-csv', str(table), '--mapping', str(mapping), '--out', str(bag)]) == 0
    out = capsys.readouterr().out
    assert ('temperature f: 2 reading(s) outside [-273.15, 1000] °C not written (first: '
            f'{table}: line 3, -500 °C)') in out
    assert 'temperature f: 22.00 to 22.40 °C' in out
    assert [m.temperature for m in _messages(bag, DEFAULT_TEMPERATURE_TOPIC)] == [22.0, 22.2,
                                                                                 22.4]


def test_a_prismatic_joint_of_a_table_in_degrees_keeps_its_own_unit(tmp_path):
    """``joint_unit: deg`` scaled every column, a lifting column's 0.35 m too (to 6.1 mm);
    a joint now states its own unit, and one column read as two joints is refused."""
    table = tmp_path / 't.csv'
    table.write_text('lift;a1;x;y;z\n350;90;1;2;3\n')
    mapping = mapping_from_dict({'frame_id': 'f', 'joint_unit': 'deg',
                                 'joints': {'torso_lift_joint': {'column': 'lift', 'unit': 'mm'},
                                            'arm_1_joint': 'a1'},
                                 'markers': {'r': ['x', 'y', 'z']}})
    row = next(iter(read_postures(table, mapping)))
    np.testing.assert_allclose(row.q, [0.35, np.pi / 2], rtol=1e-15)
    for joints, named in (({'torso_lift_joint': {'column': 'lift', 'unit': 'inch'}},
                           'mapping.joints.torso_lift_joint.unit'),
                          ({'torso_lift_joint': 'a1', 'arm_1_joint': 'a1'}, 'mapping.joints'),
                          ({'torso_lift_joint': {'colum': 'lift'}},
                           'mapping.joints.torso_lift_joint')):
        with pytest.raises(ConfigError) as info:
            mapping_from_dict({'frame_id': 'f', 'joints': joints,
                               'markers': {'r': ['x', 'y', 'z']}})
        assert info.value.key == named
