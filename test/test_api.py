"""The front door's examples (kpi_calib_ros.api docstrings) run and print what they say:
a calibration of the simulated cell valid, its TCP error within its predicted std, the
same robot's fresh poses validated, a design and a simulated campaign of the stated
shapes."""
from __future__ import annotations

import doctest
import re

import pytest

from kpi_calib_ros import api


@pytest.mark.slow
def test_the_front_door_examples_hold():
    result = doctest.testmod(api, optionflags=doctest.ELLIPSIS, raise_on_error=False)
    assert result.attempted >= 15
    assert result.failed == 0


def test_every_public_name_of_the_front_door_is_documented_with_an_example():
    for name in api.__all__:
        doc = getattr(api, name).__doc__ or ''
        assert doc.strip(), f'api.{name} has no docstring'
    examples = doctest.DocTestFinder().find(api)
    assert {t.name.rsplit('.', 1)[-1] for t in examples if t.examples} >= {
        'api', 'load_cell', 'simulate', 'design'}


def test_the_api_page_documents_every_public_name():
    from pathlib import Path
    page = (Path(__file__).resolve().parents[1] / 'doc' / 'reference' / 'api.md').read_text()
    members = page.split('.. automodule:: kpi_calib_ros.api', 1)[1].split('```', 1)[0]
    listed = set(re.findall(r'\w+', members.split(':members:', 1)[1]))
    assert set(api.__all__) <= listed, set(api.__all__) - listed
