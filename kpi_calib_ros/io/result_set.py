"""Files that belong together (calibration.yaml, the calibrated URDF, learned_residual.yaml,
the archived copy) written as one unit: after any failure the folder holds the complete
new set or the complete old one, never a learned residual of one calibration beside
another calibration.

Every new file is first written into a temporary folder inside the results folder (the
same file system) and fsynced; a full disk or a lost permission fails here and the old
files are untouched. The temporary folder is then renamed to :data:`PENDING_DIR` -- the
commit point, one ``rename(2)`` -- and its files are renamed into place, a member the new
set does not have (an old learned_residual.yaml) removed. Renames allocate nothing, so
they do not fail for a full disk; a process killed among them leaves :data:`PENDING_DIR`,
and the next write or read of the folder (:func:`complete_pending`) finishes the moves
before anything else, so no reader after it sees a mix.

One writer per folder at a time (a node's jobs run one at a time; a CLI run owns its
``--out``).
"""
from __future__ import annotations

import json
import os
import shutil
import tempfile
from pathlib import Path
from typing import Mapping

from kpi_calib_ros.core.errors import ConfigError

# A committed set whose files are being moved into place (see the module docstring).
PENDING_DIR = '.result_set.pending'
STAGING_PREFIX = '.result_set.'
MANIFEST = 'manifest.json'


def write_result_set(folder: str | Path, files: Mapping[str, str | None],
                     key: str = '--out') -> dict[str, Path]:
    """Write ``files`` into ``folder`` as one unit.

    Parameters
    ----------
    folder : path
        The results folder (created if needed).
    files : mapping of relative path to text or None
        The set, moved into place in this order; None: the member must not be there
        (removed if it is). A relative path may name a subfolder (``calibrations/1.yaml``).
    key : str
        The option or parameter that named ``folder``, for the error.

    Returns
    -------
    dict of relative path to Path
        The files written (the members with text).

    Raises
    ------
    ConfigError
        A file could not be written (a full disk, permissions): the message names the
        folder, the cause and that the previous files are intact.
    """
    folder = Path(folder)
    staging: Path | None = None
    try:
        folder.mkdir(parents=True, exist_ok=True)
        complete_pending(folder)
        staging = Path(tempfile.mkdtemp(dir=folder, prefix=STAGING_PREFIX))
        manifest: list[tuple[str, str | None]] = []
        for i, (name, text) in enumerate(files.items()):
            if Path(name).is_absolute() or '..' in Path(name).parts:
                raise ValueError(f'result set member {name!r} must be a path inside the folder')
            (folder / name).parent.mkdir(parents=True, exist_ok=True)
            if text is None:
                manifest.append((name, None))
                continue
            _write_synced(staging / str(i), text)
            manifest.append((name, str(i)))
        _write_synced(staging / MANIFEST, json.dumps(manifest))
        _sync_dir(staging)
        os.rename(staging, folder / PENDING_DIR)  # the commit point
        staging = None
        _sync_dir(folder)
    except OSError as exc:
        raise ConfigError(key, f'cannot write the results to {folder}: '
                          f'{exc.strerror or exc}; nothing there was replaced, the previous '
                          'results (calibration.yaml, its URDF and learned residual) are '
                          'intact; free space or give a writable folder, then run again'
                          ) from None
    finally:
        if staging is not None:
            shutil.rmtree(staging, ignore_errors=True)
    complete_pending(folder)
    return {name: folder / name for name, text in files.items() if text is not None}


def complete_pending(folder: str | Path) -> None:
    """Finish moving a committed set into place (a writer killed among the renames), and
    remove the temporary folders of sets that were never committed. Call before reading
    a set's files back; a folder without either is left as it is."""
    folder = Path(folder)
    pending = folder / PENDING_DIR
    if pending.is_dir():
        manifest = json.loads((pending / MANIFEST).read_text())
        for name, staged in manifest:
            target = folder / name
            if staged is None:
                target.unlink(missing_ok=True)
            elif (pending / staged).exists():  # not moved yet
                os.replace(pending / staged, target)
            _sync_dir(target.parent)
        shutil.rmtree(pending)
        _sync_dir(folder)
    if folder.is_dir():
        for stale in folder.glob(STAGING_PREFIX + '*'):
            if stale.name != PENDING_DIR and stale.is_dir():
                shutil.rmtree(stale, ignore_errors=True)


def _write_synced(path: Path, text: str) -> None:
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o644)  # less umask
    with os.fdopen(fd, 'w') as f:
        f.write(text)
        f.flush()
        os.fsync(f.fileno())


def _sync_dir(path: Path) -> None:
    """fsync a folder, so the names in it (a rename) are on disk."""
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


__all__ = ['PENDING_DIR', 'complete_pending', 'write_result_set']
