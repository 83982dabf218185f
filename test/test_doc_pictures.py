"""The documentation's pictures are the tool's current output and every page shows its step.

``make pictures`` (doc/pictures.py) runs ``kpi-calib`` and records, per picture, the sha256
of the code that drew it; these checks compare those hashes with the files as they are now
(no picture drawn by an older plotting module survives), draw every picture again and
compare it byte for byte (slow: a change elsewhere in the code that moves a picture), match
the pictures with the pages
that show them, and keep every line of code on a page within what the theme shows
without scrolling.
"""
from __future__ import annotations

import hashlib
import importlib.util
import json
import re
import sys
from pathlib import Path

import pytest

from real_data import TIAGO_DATA, UR10_DATA

ROOT = Path(__file__).resolve().parents[1]
DOC = ROOT / 'doc'
PICTURES = DOC / '_static' / 'pictures'
MANIFEST = PICTURES / 'manifest.json'
# Tutorials and guides: every one shows the pictures of its step.
STEP_PAGES = sorted((DOC / 'tutorials').glob('*.md')) + sorted((DOC / 'guide').glob('*.md'))
# Characters of a code line Furo shows without scrolling at a 1280 px wide window (the
# screenshot of guide/command_line.html shows 91; a few are kept for narrower windows).
CODE_WIDTH = 88
PNG_SIGNATURE = b'\x89PNG\r\n\x1a\n'
# ```{figure} ../_static/pictures/NAME.png, its options, a blank line and its caption.
FIGURE = re.compile(r'^```\{figure\} \.\./_static/pictures/([\w.-]+\.png)\n'
                    r'((?::[^\n]*\n)*)\n(.*?)\n```$', re.M | re.S)
REFERENCE = re.compile(r'_static/pictures/([\w.-]+\.png)')


def _sha256(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def _manifest() -> dict[str, dict]:
    return json.loads(MANIFEST.read_text())


def _shown() -> dict[str, list[str]]:
    """Picture name -> the pages (relative paths) that show it."""
    shown: dict[str, list[str]] = {}
    for page in DOC.rglob('*.md'):
        for name in REFERENCE.findall(page.read_text()):
            shown.setdefault(name, []).append(str(page.relative_to(DOC)))
    return shown


def test_every_picture_was_drawn_by_the_plotting_code_as_it_is_now():
    manifest = _manifest()
    assert manifest, 'manifest.json lists no picture: run make pictures'
    stale = {name: [src for src, digest in entry['sources'].items()
                    if _sha256(ROOT / src) != digest]
             for name, entry in manifest.items()}
    stale = {name: sources for name, sources in stale.items() if sources}
    assert stale == {}, (f'pictures drawn before these files changed: {stale}; '
                         'run make pictures and commit doc/_static/pictures/')
    for name, entry in manifest.items():
        png = PICTURES / name
        assert png.read_bytes()[:8] == PNG_SIGNATURE, f'{png} is not a PNG'
        assert _sha256(png) == entry['png_sha256'], f'{png} differs from what make pictures wrote'
        assert 'kpi_calib_ros/io/' in ' '.join(entry['sources']), \
            f'{name}: not drawn by the tool\'s own plotting code'


@pytest.mark.slow
def test_every_picture_is_what_the_code_draws_now(tmp_path, monkeypatch):
    """Every picture drawn again (doc/pictures.py into a temporary folder, about 90 s) is
    the committed one, byte for byte: a change anywhere in the code that moves a picture
    (a fit, a held-out figure, a design), not only in its plotting module, fails here."""
    spec = importlib.util.spec_from_file_location('doc_pictures', DOC / 'pictures.py')
    assert spec is not None and spec.loader is not None
    pictures = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(pictures)
    monkeypatch.setattr(pictures, 'OUT', tmp_path)
    monkeypatch.setattr(pictures, 'MANIFEST', tmp_path / 'manifest.json')
    data = UR10_DATA.parent
    assert (data / TIAGO_DATA.name).is_dir(), f'{data} holds the UR10 data but not the TIAGo'
    assert pictures.main([str(data)]) == 0
    drawn = json.loads((tmp_path / 'manifest.json').read_text())
    committed = _manifest()
    assert set(drawn) == set(committed)
    moved = sorted(name for name, entry in committed.items()
                   if drawn[name]['png_sha256'] != entry['png_sha256'])
    assert moved == [], f'{moved}: the code draws them differently now; run make pictures'


def test_pages_show_exactly_the_pictures_that_exist():
    pngs = {p.name for p in PICTURES.glob('*.png')}
    shown = _shown()
    assert set(_manifest()) == pngs, 'doc/_static/pictures/ and manifest.json disagree'
    missing = {name: pages for name, pages in shown.items() if name not in pngs}
    assert missing == {}, f'pages show pictures that do not exist: {missing}'
    unshown = sorted(pngs - set(shown))
    assert unshown == [], f'pictures no page shows: {unshown}'


def test_every_tutorial_and_guide_page_shows_the_pictures_of_its_step():
    counts = {str(p.relative_to(DOC)): len(FIGURE.findall(p.read_text())) for p in STEP_PAGES}
    assert len(counts) == 10, counts
    assert all(n >= 1 for n in counts.values()), f'pages without a picture: {counts}'
    names = [name for name, _, _ in FIGURE.findall(
        (DOC / 'tutorials' / 'find_the_missing_effect.md').read_text())]
    assert any(n.startswith('sim_') for n in names), names
    assert any(n.startswith(('ur10_', 'tiago_')) for n in names), names


def test_a_real_data_picture_names_its_data_and_their_licence():
    manifest = _manifest()
    for page in DOC.rglob('*.md'):
        for name, _, caption in FIGURE.findall(page.read_text()):
            if not name.startswith(('ur10_', 'tiago_')):
                continue
            assert 'licence' in caption and 'shared/data' in caption, \
                f'{page.name}: the caption of {name} names no data source and licence'
            assert 'licence' in manifest[name]['data'], name


def _written_and_generated() -> dict[str, str]:
    """The text of every page: the written ones, and the reference pages as
    doc/_ext/reference_pages.py generates them now (not a stale copy of an older build)."""
    spec = importlib.util.spec_from_file_location(
        'reference_pages', DOC / '_ext' / 'reference_pages.py')
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules['reference_pages'] = module
    spec.loader.exec_module(module)
    generated = {f'reference/_generated/{name}': page() for name, page in module.PAGES.items()}
    written = {str(p.relative_to(DOC)): p.read_text() for p in DOC.rglob('*.md')
               if '_generated' not in p.parts}
    return written | generated


def test_every_line_of_code_on_a_page_fits_the_page():
    long = []
    for name, text in sorted(_written_and_generated().items()):
        fence: tuple[str, str] | None = None
        for number, line in enumerate(text.splitlines(), 1):
            start = re.match(r'^(`{3,}|~{3,})(.*)$', line)
            if fence is None and start:
                fence = (start.group(1), start.group(2).strip())
            elif fence is not None and line.strip() == fence[0]:
                fence = None
            elif fence is not None and not fence[1].startswith('{') \
                    and len(line) > CODE_WIDTH:
                long.append(f'{name}:{number} ({len(line)} characters)')
    assert long == [], f'code lines longer than {CODE_WIDTH} characters: {long}'


def test_no_page_pastes_a_whole_script():
    included = [str(p.relative_to(DOC)) for p in DOC.rglob('*.md')
                if '{literalinclude}' in p.read_text()]
    assert included == [], f'pages pasting a file instead of linking it: {included}'
