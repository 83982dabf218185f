"""Bags of one placement (the tracker and the robot stayed put, the load changed) given as
one recording with ``same_placement_as``: one placement is fitted to every bag, each bag's
conditions on its own rows, and what the load changes is left to the robot. Against the same
bags as recordings of their own (a placement each), the compliance comes out within 3σ of
the truth in both, more precisely from one placement."""
from __future__ import annotations

import numpy as np
import pytest
import yaml

from kpi_calib_ros.app.simulate import simulate_campaign, truth_cell_model
from kpi_calib_ros.cli import main
from kpi_calib_ros.core.errors import ConfigError
from kpi_calib_ros.core.simulation import true_parameters
from kpi_calib_ros.io.cell import DEFAULT_CELL, load_cell
from kpi_calib_ros.io.recordings_manifest import read_manifest

C_TRUE = 4e-7  # rad/(N m), joint 2
LOADS = {'light': 0.0, 'heavy': 12.0}


@pytest.fixture(scope='module')
def bags(tmp_path_factory):
    folder = tmp_path_factory.mktemp('loads')
    doc = yaml.safe_load(DEFAULT_CELL.read_text())
    doc['robot']['urdf'] = str((DEFAULT_CELL.parent / doc['robot']['urdf']).resolve())
    doc['simulation'] = {'hidden_effects': {'joint_compliance:joint_2': {'c': C_TRUE}}}
    p_true = None
    for i, (name, mass) in enumerate(LOADS.items()):
        doc['payload']['mass'] = mass
        cell = folder / f'cell_{name}.yaml'
        cell.write_text(yaml.safe_dump(doc))
        cm, overrides = truth_cell_model(load_cell(cell))
        if p_true is None:  # one robot, one placement: the same true vector for both loads
            p_true = true_parameters(cm.model.params, np.random.default_rng(5),
                                     overrides=overrides)
        simulate_campaign(cell, 30, folder / f'{name}.mcap', 11 + i, cm=cm, p_true=p_true)
    return folder


def _manifest(folder, name, joined: bool):
    second = ({'bag': 'heavy.mcap', 'same_placement_as': 'station'} if joined
              else {'bag': 'heavy.mcap', 'name': 'heavy'})
    entries = [{'bag': 'light.mcap', 'name': 'station',
                'covariates': {'payload.mass': LOADS['light']}},
               dict(second, covariates={'payload.mass': LOADS['heavy']})]
    path = folder / name
    path.write_text(yaml.safe_dump({'recordings': entries}))
    return path


def test_bags_of_one_placement_fit_one_placement_and_the_load_to_the_robot(bags, capsys):
    fits = {}
    for joined in (True, False):
        out = bags / f'out_{joined}'
        argv = ['identify', '--cell', str(bags / 'cell_light.yaml'), '--recordings',
                str(_manifest(bags, f'm_{joined}.yaml', joined)), '--effects',
                'joint_compliance:joint_2', '--model', 'geometric', '--out', str(out)]
        assert main(argv) == 0, capsys.readouterr()
        doc = yaml.safe_load((out / 'calibration.yaml').read_text())
        c = next(p for p in doc['parameters'] if p['name'] == 'joint_compliance.joint_2.c')
        fits[joined] = c['value'], c['std']
        recordings = doc.get('recordings') or []
        if joined:
            assert [(r['name'], r['poses']) for r in recordings] == [('station', 60)]
            assert not any(p['name'].startswith('recording.') for p in doc['parameters'])
        else:
            assert [r['name'] for r in recordings] == ['station', 'heavy']
    print({k: (f'{v * 1e7:.3f}e-7', f'{s * 1e7:.3f}e-7') for k, (v, s) in fits.items()})
    for value, std in fits.values():
        assert abs(value - C_TRUE) < 3 * std
    assert fits[True][1] < fits[False][1]


def test_a_bag_of_a_placement_names_an_earlier_recording_and_shares_its_probe(bags):
    for extra, field in (({'same_placement_as': 'nowhere'}, 'recordings[1].same_placement_as'),
                         ({'same_placement_as': 'station', 'reflector_remounted': True},
                          'recordings[1].reflector_remounted'),
                         ({'same_placement_as': 'station', 'name': 'heavy'},
                          'recordings[1].name')):
        path = bags / 'bad.yaml'
        path.write_text(yaml.safe_dump({'recordings': [
            {'bag': 'light.mcap', 'name': 'station'}, dict({'bag': 'heavy.mcap'}, **extra)]}))
        with pytest.raises(ConfigError) as caught:
            read_manifest(path)
        assert caught.value.key == field
    # the same bag as a part of two recordings counts its rows twice: refused
    path.write_text(yaml.safe_dump({'recordings': [
        {'bag': 'light.mcap', 'name': 'station'},
        {'bag': 'heavy.mcap', 'name': 'heavy'},
        {'bag': 'heavy.mcap', 'same_placement_as': 'station'}]}))
    with pytest.raises(ConfigError, match='given twice'):
        read_manifest(path)
