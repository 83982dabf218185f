"""Every tutorial and guide page, built as `make doc` builds it, renders in a real headless
Chromium and every picture on it loads.

The site is built into a temporary folder; each page gets a small script that, once the
page has loaded, lists the images the browser could not decode (``complete`` and
``naturalWidth > 0``, the browser's own verdict). One Chromium run per page dumps the DOM
after load and takes a 1280 × 2000 screenshot, which must not be blank. Chromium is a
requirement of the documentation tests: without it they fail (``.ci/run`` installs it).
"""
from __future__ import annotations

import html
import json
import re
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
PAGES = [f'tutorials/{p.stem}' for p in sorted((ROOT / 'doc' / 'tutorials').glob('*.md'))] + \
        [f'guide/{p.stem}' for p in sorted((ROOT / 'doc' / 'guide').glob('*.md'))]
PROBE = """<script>window.addEventListener('load', function () {
  var imgs = Array.prototype.slice.call(document.images);
  var broken = imgs.filter(function (i) { return !(i.complete && i.naturalWidth > 0); })
                   .map(function (i) { return i.getAttribute('src'); });
  var out = document.createElement('pre');
  out.id = 'image-check';
  out.textContent = JSON.stringify({images: imgs.length, broken: broken});
  document.body.appendChild(out);
});</script>"""
CHECK = re.compile(r'<pre id="image-check">(.*?)</pre>', re.S)


def _chromium() -> str:
    found = shutil.which('chromium') or shutil.which('chromium-browser')
    assert found, ('chromium is not installed: the documentation tests look at every page '
                   'in it (Debian: apt-get install chromium; .ci/run does)')
    return found


def _look(page: Path, screenshot: Path) -> dict:
    """Load ``page`` (with the probe) in headless Chromium: the probe's report; the
    screenshot is written to ``screenshot``."""
    text = page.read_text()
    if 'id="image-check"' not in text:
        page.write_text(text.replace('</body>', PROBE + '</body>'))
    done = subprocess.run(
        [_chromium(), '--headless', '--no-sandbox', '--disable-gpu', '--hide-scrollbars',
         '--window-size=1280,2000', '--virtual-time-budget=10000',
         f'--screenshot={screenshot}', '--dump-dom', page.as_uri()],
        capture_output=True, text=True, timeout=120)
    found = CHECK.findall(done.stdout)
    assert found, f'{page.name}: no load report from Chromium (exit {done.returncode}): ' \
                  f'{done.stderr[-2000:]}'
    return json.loads(html.unescape(found[-1]))


def _not_blank(png: Path) -> float:
    """Share of the screenshot's pixels that are not the background colour."""
    import matplotlib.image
    pixels = matplotlib.image.imread(png)[:, :, :3]
    background = np.median(pixels.reshape(-1, 3), axis=0)
    return float(np.mean(np.any(np.abs(pixels - background) > 0.1, axis=2)))


@pytest.fixture(scope='module')
def site(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp('doc')
    subprocess.run([sys.executable, '-m', 'sphinx', '-q', '-W', '--keep-going', '-b', 'html',
                    str(ROOT / 'doc'), str(out)], check=True, cwd=ROOT)
    return out


@pytest.mark.slow
def test_the_probe_tells_a_broken_picture_from_a_loaded_one(site, tmp_path):
    good = next((site / '_images').glob('*.png'))
    page = site / 'probe.html'
    page.write_text(f'<html><body><h1>probe</h1><img src="_images/{good.name}">'
                    '<img src="_images/no_such_picture.png"></body></html>')
    report = _look(page, tmp_path / 'probe.png')
    assert report == {'images': 2, 'broken': ['_images/no_such_picture.png']}


@pytest.mark.slow
def test_every_tutorial_and_guide_page_renders_and_its_pictures_load(site, tmp_path):
    assert len(PAGES) == 10, PAGES
    failures = []
    for name in PAGES:
        shot = tmp_path / f'{name.replace("/", "_")}.png'
        report = _look(site / f'{name}.html', shot)
        if report['images'] == 0 or report['broken']:
            failures.append(f'{name}: {report}')
        ink = _not_blank(shot)
        if ink < 0.02:
            failures.append(f'{name}: the screenshot is blank ({ink:.1%} ink)')
    assert failures == []
