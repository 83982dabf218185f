"""The command-line guide has a section (H2) per subcommand, and every option of that
subcommand's parser is named in it: an option added to ``kpi-calib`` without a word in
doc/guide/command_line.md fails here."""
from __future__ import annotations

import argparse
import re
from pathlib import Path

from doc_sections import h2_sections

from kpi_calib_ros.cli import build_parser

PAGE = Path(__file__).resolve().parents[1] / 'doc' / 'guide' / 'command_line.md'


def _subcommands() -> dict[str, argparse.ArgumentParser]:
    for action in build_parser()._actions:  # argparse keeps its sub-parsers here only
        if isinstance(action, argparse._SubParsersAction):
            return dict(action.choices)
    raise AssertionError('kpi-calib has no subcommands')



def test_every_subcommand_has_its_section_naming_every_option():
    sections = h2_sections(PAGE.read_text())
    missing_sections, missing_options = [], {}
    for name, parser in _subcommands().items():
        body = sections.get(f'`kpi-calib {name}`')
        if body is None:
            missing_sections.append(name)
            continue
        options = [opt for action in parser._actions if action.option_strings
                   and not isinstance(action, argparse._HelpAction)
                   for opt in action.option_strings if opt.startswith('--')]
        absent = [opt for opt in options if not re.search(rf'{re.escape(opt)}(?![\w-])', body)]
        if absent:
            missing_options[name] = absent
    assert missing_sections == [], f'no "## `kpi-calib NAME`" section for {missing_sections}'
    assert missing_options == {}, f'options not named in their section: {missing_options}'


def test_every_section_states_its_exit_codes():
    sections = h2_sections(PAGE.read_text())
    silent = [name for name in _subcommands()
              if 'exit' not in sections.get(f'`kpi-calib {name}`', '').lower()]
    assert silent == [], f'sections without exit codes: {silent}'
