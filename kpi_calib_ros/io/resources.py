"""``package://`` and ``file://`` URIs of a robot description, resolved the way ROS does.

A package ``pkg`` is looked up, first hit wins, in:

1. the caller's ``package_dirs`` (the cell key ``robot.package_dirs``): a directory
   that *is* the package (its name is ``pkg`` or its ``package.xml`` says so) or
   that holds ``<dir>/pkg``;
2. ``ROS_PACKAGE_PATH`` (ROS 1 style, same rule per entry);
3. the ament index: every prefix of ``AMENT_PREFIX_PATH`` with a marker
   ``share/ament_index/resource_index/packages/pkg`` gives ``<prefix>/share/pkg``
   (via ``ament_index_python`` when importable, else the same files read here);
4. the prefixes of pip-installed cmeel packages (``<site-packages>/cmeel.prefix``),
   which ship an ament index but are not on ``AMENT_PREFIX_PATH`` unless sourced.
   This is how ``pip install example-robot-data`` resolves with no configuration.

Errors name the URI, the file that referenced it and every path that was tried.
"""
from __future__ import annotations

import os
import re
import site
import sys
import xml.etree.ElementTree as ET
from pathlib import Path
from typing import Iterable, Sequence
from urllib.parse import unquote, urlparse

from kpi_calib_ros.core.errors import ConfigError

_INDEX = Path('share') / 'ament_index' / 'resource_index' / 'packages'
_PACKAGE_NAME = re.compile(r'<name>\s*([^<\s]+)\s*</name>')


def _split(env: str) -> list[Path]:
    return [Path(p) for p in os.environ.get(env, '').split(os.pathsep) if p]


def cmeel_prefixes() -> list[Path]:
    """``cmeel.prefix`` directories of the site-packages on ``sys.path`` (existing only)."""
    roots: list[str] = list(sys.path)
    try:
        roots += site.getsitepackages() + [site.getusersitepackages()]
    except AttributeError:  # virtualenv's old site.py lacks them
        pass
    seen: list[Path] = []
    for root in roots:
        prefix = Path(root or '.') / 'cmeel.prefix'
        if prefix.is_dir() and prefix.resolve() not in [p.resolve() for p in seen]:
            seen.append(prefix)
    return seen


def ament_prefixes() -> list[Path]:
    """``AMENT_PREFIX_PATH`` entries followed by the cmeel prefixes not already on it."""
    prefixes = _split('AMENT_PREFIX_PATH')
    resolved = {p.resolve() for p in prefixes if p.exists()}
    return prefixes + [p for p in cmeel_prefixes() if p.resolve() not in resolved]


def _is_package(directory: Path, package: str) -> bool:
    if directory.name == package and directory.is_dir():
        return True
    manifest = directory / 'package.xml'
    if manifest.is_file():
        found = _PACKAGE_NAME.search(manifest.read_text(errors='replace'))
        return found is not None and found.group(1) == package
    return False


def find_package(package: str, package_dirs: Sequence[str | Path] = ()) -> tuple[Path | None,
                                                                                 list[str]]:
    """Directory of ROS package ``package`` and the candidates tried in order.

    Parameters
    ----------
    package : str
        Package name, e.g. ``'example-robot-data'``.
    package_dirs : sequence of path
        Extra directories searched first (each the package itself or its parent).

    Returns
    -------
    (Path or None, list of str)
        The package directory (None if not found) and every candidate path looked at.
    """
    tried: list[str] = []
    for source in (list(package_dirs), _split('ROS_PACKAGE_PATH')):
        for entry in source:
            directory = Path(entry).expanduser()
            for candidate in (directory, directory / package):
                tried.append(str(candidate))
                if _is_package(candidate, package):
                    return candidate, tried
    ament_env = _split('AMENT_PREFIX_PATH')
    prefixes = ament_prefixes()
    if ament_env:
        try:  # the ROS implementation when it is there, so both always agree
            from ament_index_python.packages import (
                PackageNotFoundError,
                get_package_share_directory,
            )
        except ImportError:
            pass
        else:
            tried.append(f'ament index of AMENT_PREFIX_PATH {[str(p) for p in ament_env]}')
            try:
                return Path(get_package_share_directory(package)), tried
            except PackageNotFoundError:
                prefixes = prefixes[len(ament_env):]
    for prefix in prefixes:
        marker = prefix / _INDEX / package
        tried.append(str(marker))
        if marker.is_file() and (prefix / 'share' / package).is_dir():
            return prefix / 'share' / package, tried
    return None, tried


def resolve_uri(uri: str, package_dirs: Sequence[str | Path] = (),
                base_dir: str | Path | None = None, key: str = 'robot.package_dirs',
                referenced_by: str = 'the URDF') -> Path:
    """Absolute path of an existing file named by ``uri``.

    ``package://pkg/rel`` -> ``<package dir>/rel``; ``file:///abs`` -> ``/abs``; a
    plain path, and a relative entry of ``package_dirs``, is taken relative to
    ``base_dir`` (default: current directory).

    Raises
    ------
    ConfigError
        Under ``key``: the package or file is missing; the message names the URI,
        ``referenced_by`` and every path tried.
    """
    if uri.startswith('package://'):
        package, _, rel = uri[len('package://'):].partition('/')
        # Relative package_dirs are relative to base_dir (the cell file's folder).
        dirs = [d if Path(d).expanduser().is_absolute() else Path(base_dir or '.') / d
                for d in package_dirs]
        directory, tried = find_package(package, dirs)
        if directory is None:
            raise ConfigError(key, f'{uri} (in {referenced_by}): package {package!r} not found; '
                              f'tried {tried}; install it, source its workspace, or add its '
                              f'parent directory to {key}')
        path = directory / rel
        if not path.is_file():
            raise ConfigError(key, f'{uri} (in {referenced_by}): no file {path} in package '
                              f'{package!r} found at {directory} (searched {tried})')
        return path.resolve()
    if uri.startswith('file://'):
        path = Path(unquote(urlparse(uri).path))
    else:
        path = Path(uri)
        if not path.is_absolute():
            path = Path(base_dir or '.') / path
    if not path.is_file():
        raise ConfigError(key, f'{uri} (in {referenced_by}): no file {path}')
    return path.resolve()


def mesh_uris(urdf_xml: str) -> list[str]:
    """Every ``<mesh filename=...>`` of the URDF, in document order, without repeats."""
    root = ET.fromstring(urdf_xml)
    out: list[str] = []
    for mesh in root.iter('mesh'):
        name = mesh.get('filename')
        if name and name not in out:
            out.append(name)
    return out


def resolve_mesh_uris(urdf_xml: str, package_dirs: Sequence[str | Path] = (),
                      base_dir: str | Path | None = None, key: str = 'robot.package_dirs',
                      referenced_by: str = 'the URDF', elements: Iterable[str] = (
                          'collision',)) -> str:
    """The URDF with the mesh URIs under ``elements`` replaced by absolute paths.

    Core code (Pinocchio, coal) then loads the meshes with no search path. Meshes
    of other elements (``visual`` by default) are left as they are: an unresolvable
    visual mesh must not stop a computation that never reads it.

    Raises
    ------
    ConfigError
        A collision mesh cannot be found (see :func:`resolve_uri`).
    """
    root = ET.fromstring(urdf_xml)
    for tag in elements:
        for element in root.iter(tag):
            for mesh in element.iter('mesh'):
                uri = mesh.get('filename')
                if uri:
                    mesh.set('filename', str(resolve_uri(uri, package_dirs, base_dir, key,
                                                         referenced_by)))
    return ET.tostring(root, encoding='unicode')
