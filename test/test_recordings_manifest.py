"""The recordings manifest and ``--bag`` names: every bad field a named error (exit 2)."""
from __future__ import annotations

from pathlib import Path

import pytest
import yaml

from kpi_calib_ros.cli import main
from kpi_calib_ros.core.errors import ConfigError
from kpi_calib_ros.io.cell import DEFAULT_CELL
from kpi_calib_ros.io.recordings_manifest import read_manifest, sources_from_bags


@pytest.fixture
def bags(tmp_path: Path) -> Path:
    for name in ('station_a', 'station_b'):
        (tmp_path / f'{name}.mcap').write_bytes(b'')
    return tmp_path


def _manifest(folder: Path, entries) -> Path:
    path = folder / 'manifest.yaml'
    path.write_text(yaml.safe_dump({'recordings': entries}))
    return path


def test_a_manifest_gives_names_mounts_and_constant_conditions(bags):
    path = _manifest(bags, [{'bag': 'station_a.mcap', 'covariates': {'payload.mass': 5.0}},
                            {'bag': 'station_b.mcap', 'name': 'B-2',
                             'reflector_remounted': True,
                             'covariates': {'payload.mass': 0}}])
    a, b = read_manifest(path)
    assert a.bag == bags / 'station_a.mcap' and a.recording.name == 'station_a'
    assert a.recording.covariates == {'payload.mass': 5.0} and not a.recording.reflector_remounted
    assert b.recording.name == 'B-2' and b.recording.reflector_remounted
    assert b.recording.covariates == {'payload.mass': 0.0}


BAD = {
    'unknown field': ([{'bag': 'station_a.mcap', 'remounted': True}],
                      'recordings[0].remounted'),
    'missing bag': ([{'bag': 'nowhere.mcap'}], 'recordings[0].bag'),
    'bad name': ([{'bag': 'station_a.mcap', 'name': '1st station'}], 'recordings[0].name'),
    'remounted not a bool': ([{'bag': 'station_a.mcap'},
                              {'bag': 'station_b.mcap', 'reflector_remounted': 'yes'}],
                             'recordings[1].reflector_remounted'),
    'first remounted': ([{'bag': 'station_a.mcap', 'reflector_remounted': True}],
                        'recordings[0].reflector_remounted'),
    'covariate not a number': ([{'bag': 'station_a.mcap', 'covariates': {'payload.mass': 'five'}}],
                               'recordings[0].covariates.payload.mass'),
    'covariate not finite': ([{'bag': 'station_a.mcap',
                               'covariates': {'payload.mass': float('nan')}}],
                             'recordings[0].covariates.payload.mass'),
    'covariate of the recordings': ([{'bag': 'station_a.mcap',
                                      'covariates': {'recording.x': 1.0}}],
                                    'recordings[0].covariates'),
    'condition of some only': ([{'bag': 'station_a.mcap', 'covariates': {'payload.mass': 5.0}},
                                {'bag': 'station_b.mcap'}], 'recordings[1].covariates'),
    'one name twice': ([{'bag': 'station_a.mcap', 'name': 'x'},
                        {'bag': 'station_b.mcap', 'name': 'x'}], 'recordings'),
    'not a list': ({'bag': 'station_a.mcap'}, 'recordings'),
    # the same rows twice would halve every std the fit states
    'one bag twice': ([{'bag': 'station_a.mcap', 'name': 'x'},
                       {'bag': './station_a.mcap', 'name': 'y'}], 'recordings'),
    'split not increasing': ([{'bag': 'station_a.mcap', 'split_at': [60.0, 30.0]}],
                             'recordings[0].split_at'),
    'split not positive': ([{'bag': 'station_a.mcap', 'split_at': 0}],
                           'recordings[0].split_at'),
    'split not a number': ([{'bag': 'station_a.mcap', 'split_at': ['half']}],
                           'recordings[0].split_at'),
    # the entry is named, not its place among the recordings a split makes
    'condition of some only, after a split': (
        [{'bag': 'station_a.mcap', 'split_at': [100.0], 'covariates': {'payload.mass': 5.0}},
         {'bag': 'station_b.mcap'}], 'recordings[1].covariates'),
    'a misspelled payload': ([{'bag': 'station_a.mcap', 'covariates': {'payload.mas': 5.0}}],
                             'recordings[0].covariates.payload.mas'),
    'a payload centre in mm': ([{'bag': 'station_a.mcap',
                                 'covariates': {'payload.mass': 5.0, 'payload.com.z': 80}}],
                               'recordings[0].covariates.payload.com.z'),
}


@pytest.mark.parametrize('case', BAD)
def test_a_bad_manifest_is_a_named_error_and_exit_2(case, bags, capsys):
    entries, field = BAD[case]
    path = _manifest(bags, entries)
    with pytest.raises(ConfigError) as caught:
        read_manifest(path)
    assert caught.value.key == field, caught.value
    code = main(['identify', '--cell', str(DEFAULT_CELL), '--recordings', str(path), '--out',
                 str(bags / 'out')])
    err = capsys.readouterr().err
    assert code == 2 and field in err and 'Traceback' not in err, err


def test_bag_names_come_from_the_file_stems_and_must_differ(bags, capsys):
    a, b = sources_from_bags([bags / 'station_a.mcap', bags / 'station_b.mcap'], ['station_b'])
    assert (a.recording.name, b.recording.name) == ('station_a', 'station_b')
    assert b.recording.reflector_remounted and not a.recording.reflector_remounted
    for bags_given, remounted, key in (
            ([bags / 'station_a.mcap', bags / 'other' / 'station_a.mcap'], [], '--bag'),
            ([bags / 'station_a.mcap', bags / 'station_b.mcap'], ['station_c'], '--remounted'),
            ([bags / 'station_a.mcap', bags / 'station_b.mcap'], ['station_a'], '--remounted')):
        with pytest.raises(ConfigError) as caught:
            sources_from_bags(bags_given, remounted)
        assert caught.value.key == key
    for argv, key in ((['--bag', str(bags / 'station_a.mcap'), '--recordings',
                        str(bags / 'm.yaml')], '--recordings'),
                      ([], '--bag'),
                      (['--bag', str(bags / 'station_a.mcap'), '--bag',
                        str(bags / 'station_b.mcap'), '--prior', str(bags / 'c.yaml')],
                       '--prior')):
        code = main(['identify', '--cell', str(DEFAULT_CELL), '--out', str(bags / 'out')]
                    + argv)
        err = capsys.readouterr().err
        assert code == 2 and key in err and 'Traceback' not in err, err


@pytest.mark.parametrize('name, close', [('paylaod.mass', 'payload.mass'),
                                         ('payload_mass', 'payload.mass')])
def test_a_condition_misspelled_is_refused_naming_the_one_meant(name, close, bags, capsys):
    """A condition close to one the model reads is a slip: before, it was stored with the
    calibration and read by nothing (the payload fitted as none)."""
    path = _manifest(bags, [{'bag': 'station_a.mcap', 'covariates': {name: 5.0}},
                            {'bag': 'station_b.mcap', 'covariates': {name: 0.0}}])
    code = main(['identify', '--cell', str(DEFAULT_CELL), '--recordings', str(path),
                 '--effects', 'joint_compliance:joint_2', '--out', str(bags / 'out')])
    err = capsys.readouterr().err
    assert code == 2 and f'recordings[0].covariates.{name}' in err, err
    assert f'did you mean {close!r}' in err


def test_a_condition_nothing_reads_is_said(bags, capsys):
    path = _manifest(bags, [{'bag': 'station_a.mcap', 'covariates': {'hall.humidity': 0.4}},
                            {'bag': 'station_b.mcap', 'covariates': {'hall.humidity': 0.5}}])
    main(['identify', '--cell', str(DEFAULT_CELL), '--recordings', str(path), '--out',
          str(bags / 'out')])
    err = capsys.readouterr().err
    assert ('warning: recordings[0].covariates.hall.humidity: no effect of the model reads it'
            in err), err


def test_a_payload_no_effect_reads_yet_is_not_said_to_change_no_prediction(bags, capsys):
    """A payload per recording with a geometric model: an effect of the gravity torque that
    --model auto adds reads it, so the warning must not say it changes no prediction (it
    did, while auto's compliance fitted 182 µm with the payloads and 2956 µm without)."""
    path = _manifest(bags, [{'bag': 'station_a.mcap', 'covariates': {'payload.mass': 0.0}},
                            {'bag': 'station_b.mcap', 'covariates': {'payload.mass': 5.0}}])
    main(['identify', '--cell', str(DEFAULT_CELL), '--recordings', str(path), '--out',
          str(bags / 'out')])
    err = capsys.readouterr().err
    said = [line for line in err.splitlines() if 'covariates.payload.mass' in line]
    assert said and all('changes no prediction' not in line and 'joint_compliance' in line
                        for line in said), err


def test_a_rejection_names_its_recording(capsys):
    """With several bags a rejection said which one it came from only by its stamp."""
    import numpy as np

    from kpi_calib_ros.app.measurements import print_rejections
    from kpi_calib_ros.core.acquisition.outcomes import PairingResult, Rejection
    pairing = PairingResult(('j',), 'tracker', np.zeros((0, 1)), np.zeros((0, 3)),
                            np.zeros(0, np.int64), {'no_joint_state': 1},
                            [Rejection(5, 'no_joint_state', 'no joint state within 5 ms')])
    print_rejections(pairing, "recording 'b': ")
    assert ("recording 'b': rejected 1 sample(s): no_joint_state (first: no joint state "
            'within 5 ms)') in capsys.readouterr().err


def test_bags_given_relative_are_stored_absolute(bags, monkeypatch):
    """calibration.yaml names each recording's bag; a manifest's were absolute, --bag's as
    typed, relative to wherever the command ran."""
    monkeypatch.chdir(bags)
    a, b = sources_from_bags(['station_a.mcap', 'station_b.mcap'])
    assert a.bag == bags / 'station_a.mcap' and b.bag.is_absolute()


def test_an_empty_node_log_among_the_bags_is_skipped_and_said(tmp_path, capsys):
    """A node whose station was set, then its remount, leaves a log with no measurement
    between the two; identify --bag over the node's logs stopped on it (exit 2). It is
    skipped with a warning; a bag that is no node log, or every log empty, is not."""
    from kpi_calib_ros.io.measurement_log import MeasurementLog
    logs = tmp_path / 'data_dir'
    for station in ('a', 'b', 'b'):
        with MeasurementLog(logs, station=station, reflector_remounted=False):
            pass
    files = sorted(logs.glob('measurements_*.mcap'))
    (tmp_path / 'other.mcap').write_bytes(b'')
    sources = sources_from_bags([*files[:2], tmp_path / 'other.mcap'])
    assert [s.bag for s in sources] == [tmp_path / 'other.mcap']
    err = capsys.readouterr().err
    assert err.count('is a node measurement log with no measurement') == 2, err
    assert [s.bag for s in sources_from_bags(files[:2])] == files[:2]
