"""The reference pages of doc/ are generated from the code: every subcommand and option of
the `kpi-calib` parser, every node parameter, topic and service, every library effect and
every cell key appears on its page, and a change in the code shows on the page."""
from __future__ import annotations

import argparse
import importlib.util
import re
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]


@pytest.fixture(scope='module')
def pages():
    spec = importlib.util.spec_from_file_location(
        'reference_pages', REPO / 'doc' / '_ext' / 'reference_pages.py')
    module = importlib.util.module_from_spec(spec)
    sys.modules['reference_pages'] = module
    spec.loader.exec_module(module)
    return module


def test_cli_page_lists_every_subcommand_and_option_of_the_parser(pages):
    from kpi_calib_ros.cli import build_parser
    text = pages.cli_page()
    sub = next(a for a in build_parser()._actions if isinstance(a, argparse._SubParsersAction))
    assert len(sub.choices) >= 10
    for name, parser in sub.choices.items():
        assert f'## `kpi-calib {name}`' in text
        section = text.split(f'## `kpi-calib {name}`', 1)[1].split('\n## ', 1)[0]
        for action in parser._actions:
            for flag in action.option_strings:
                if flag not in ('-h', '--help'):
                    assert f'`{flag}' in section, f'{name} {flag} missing from the CLI page'


def test_cli_page_follows_the_parser(pages, monkeypatch):
    from kpi_calib_ros import cli
    original = cli.build_parser

    def extended() -> argparse.ArgumentParser:
        parser = original()
        sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
        sub.choices['identify'].add_argument('--tracker-temperature', type=float, default=20.0,
                                             help='air temperature at the tracker (°C)')
        return parser

    monkeypatch.setattr(cli, 'build_parser', extended)
    text = pages.cli_page()
    assert ('| `--tracker-temperature TRACKER_TEMPERATURE` | `20.0` | air temperature at the '
            'tracker (°C) |') in text


def test_node_page_lists_every_parameter_topic_and_service(pages):
    from kpi_calib_ros.io import names
    from kpi_calib_ros.ros.parameters import PARAMETERS
    text = pages.node_page()
    for name in PARAMETERS:
        assert f'| `{name}` |' in text
    node_source = (REPO / 'kpi_calib_ros' / 'ros' / 'node.py').read_text()
    published = [k for k in vars(names) if k.endswith('_TOPIC') and k in node_source
                 and k != 'ROBOT_DESCRIPTION_TOPIC']
    assert len(published) >= 10
    for constant in published:
        assert f'`io.names.{constant}`' in text, constant
    for service in ('design', 'identify', 'diagnose', 'validate', 'reset'):
        assert f'| `~/{service}` | `std_srvs/srv/Trigger` |' in text
    assert '| `/joint_states` | `sensor_msgs/msg/JointState` |' in text
    assert '| `/laser_tracker/point/sigma` | `geometry_msgs/msg/Vector3Stamped` |' in text
    assert '| `~/tcp` | `geometry_msgs/msg/PoseWithCovarianceStamped` |' in text


def test_effects_page_gives_every_library_effect_with_units_and_plausible_range(pages):
    from kpi_calib_ros.core.effects.library import LIBRARY
    text = pages.effects_page()
    for effect in LIBRARY:
        row = next(line for line in text.splitlines() if line.startswith(f'| `{effect.name}` |'))
        for parameter, unit in zip(effect.parameters, effect.units):
            assert f'{parameter} [{unit}]' in row
        for bound in effect.plausible:
            assert f'{bound:g}' in row
    from kpi_calib_ros.core.effects.registry import CHAIN_EFFECTS
    assert 'gravity_compliance' in CHAIN_EFFECTS
    row = next(line for line in text.splitlines() if line.startswith('| `gravity_compliance:J` |'))
    assert 'g0 [rad]' in row
    row = next(line for line in text.splitlines() if line.startswith('| `link_bending:J` |'))
    assert 'cx [rad/(N m)], cz [rad/(N m)]' in row and '0.0001, 0.0001' in row
    row = next(line for line in text.splitlines()
               if line.startswith('| `periodic_joint_error:J:k=K` |'))
    assert 'a [rad], b [rad]' in row and '0.005, 0.005' in row and '17' in row


def test_cell_keys_page_lists_every_described_key(pages):
    from kpi_calib_ros.io.cell_schema import CELL_KEYS
    text = pages.cell_keys_page()
    for key in CELL_KEYS:
        assert f'| `{key.path}` |' in text


def test_code_in_the_generated_pages_is_shown_as_written(pages):
    """Angle brackets are escaped for HTML outside code spans only: inside one,
    `reflector.<name>.x` must stay as written."""
    text = pages.cell_keys_page() + pages.node_page() + pages.effects_page()
    spans = re.findall(r'`([^`]+)`', text)
    assert any('<name>' in s for s in spans)
    assert [s for s in spans if '&lt;' in s or '&gt;' in s] == []
