"""A small tmpfs for tests of a full disk: a real file system that fills up, mounted
for the test and unmounted after it. Needs root (``.ci/run`` runs ``make test`` as
root); without it the test fails and says so, it never skips."""
from __future__ import annotations

import os
import subprocess
from contextlib import contextmanager
from pathlib import Path
from typing import Iterator

import pytest

CHUNK = 2 ** 20


@contextmanager
def small_tmpfs(path: Path, size: str = '32m') -> Iterator[Path]:
    """A tmpfs of ``size`` mounted at ``path`` (created) for the block."""
    path.mkdir(parents=True, exist_ok=True)
    mounted = subprocess.run(['mount', '-t', 'tmpfs', '-o', f'size={size},mode=0755',
                              'tmpfs', str(path)], capture_output=True, text=True)
    if mounted.returncode != 0:
        pytest.fail(f'cannot mount a tmpfs at {path} for this full-disk test: '
                    f'{mounted.stderr.strip()} (uid {os.getuid()}); the test needs root, '
                    'as .ci/run has', pytrace=False)
    try:
        yield path
    finally:
        subprocess.run(['umount', str(path)], check=True)


def free_bytes(path: Path) -> int:
    st = os.statvfs(path)
    return st.f_bavail * st.f_frsize


def fill(path: Path, leave: int) -> Path:
    """Write a filler file on the file system of ``path`` until ``leave`` bytes are free."""
    filler = path / 'filler'
    todo = free_bytes(path) - leave
    assert todo > 0, f'{path}: only {free_bytes(path)} bytes free, {leave} to leave'
    with open(filler, 'wb') as f:
        while todo > 0:
            todo -= f.write(b'\0' * min(CHUNK, todo))
    assert abs(free_bytes(path) - leave) <= 8192, (free_bytes(path), leave)
    return filler


def snapshot(folder: Path) -> dict[str, bytes]:
    """Every file under ``folder`` (relative name: content), the filler left out."""
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob('*'))
            if p.is_file() and p.name != 'filler'}
