"""The node guide has a section (H2) per service, names every ``~/`` topic in a service's
section and every parameter: a service, topic or parameter added to the node without a
word in doc/guide/node.md fails here."""
from __future__ import annotations

import ast
from pathlib import Path

from doc_sections import h2_sections

from kpi_calib_ros.io import names
from kpi_calib_ros.ros.parameters import PARAMETERS

ROOT = Path(__file__).resolve().parents[1]
PAGE = ROOT / 'doc' / 'guide' / 'node.md'


def _loop_names(loop: ast.For) -> list[str]:
    """The first strings of a ``for name, ... in (('design', ...), ...)`` loop."""
    if isinstance(loop.iter, (ast.Tuple, ast.List)):
        return [e.elts[0].value for e in loop.iter.elts
                if isinstance(e, ast.Tuple) and isinstance(e.elts[0], ast.Constant)]
    return []


def created_services() -> set[str]:
    """Every service name the node's code creates (``create_service(type, name, ...)``),
    a name made in a loop expanded over the loop's tuple."""
    found: set[str] = set()
    for path in (ROOT / 'kpi_calib_ros' / 'ros').glob('*.py'):
        tree = ast.parse(path.read_text())
        parents = {child: node for node in ast.walk(tree) for child in ast.iter_child_nodes(node)}
        for call in ast.walk(tree):
            if not (isinstance(call, ast.Call) and isinstance(call.func, ast.Attribute)
                    and call.func.attr == 'create_service'):
                continue
            arg = call.args[1]
            if isinstance(arg, ast.Constant):
                found.add(arg.value)
                continue
            assert isinstance(arg, ast.JoinedStr), f'{path.name}: service name {ast.dump(arg)}'
            prefix = ''.join(v.value for v in arg.values if isinstance(v, ast.Constant))
            node = call
            while node in parents and not isinstance(node, ast.For):
                node = parents[node]
            assert isinstance(node, ast.For), f'{path.name}: a computed service name'
            found |= {prefix + n for n in _loop_names(node)}
    return found



def test_the_services_are_found():
    assert created_services() >= {'~/design', '~/identify', '~/diagnose', '~/validate',
                                  '~/reset'}


def test_every_service_has_its_section():
    titles = list(h2_sections(PAGE.read_text()))
    missing = [s for s in sorted(created_services())
               if not any(t.startswith(f'`{s}`') for t in titles)]
    assert missing == [], f'no "## `~/NAME` ..." section for {missing}'


def test_every_node_topic_is_named_in_a_service_section():
    sections = h2_sections(PAGE.read_text())
    services = {t: body for t, body in sections.items() if t.startswith('`~/')}
    topics = sorted(v for k, v in vars(names).items()
                    if k.endswith('_TOPIC') and isinstance(v, str) and v.startswith('~/'))
    assert topics
    missing = [t for t in topics
               if not any(f'`{t}`' in title + body for title, body in services.items())]
    assert missing == [], f'topics no service section names: {missing}'


def test_every_parameter_is_named():
    text = PAGE.read_text()
    missing = [p for p in PARAMETERS if f'`{p}`' not in text]
    assert missing == [], f'parameters the node guide does not name: {missing}'
