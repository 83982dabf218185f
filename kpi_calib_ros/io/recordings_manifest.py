"""Which bags are the recordings of one identification: ``--bag`` repeated, or a manifest.

A manifest (``--recordings manifest.yaml``) lists the recordings, each a mapping::

    recordings:
      - bag: station_a.mcap          # relative to the manifest's folder
        name: station_a              # default: the bag's file stem
        reflector_remounted: false   # the probe was mounted again for this recording
        covariates: {payload.mass: 5.0}   # constant on every row of this recording
        split_at: [585.0]            # the placement changed here: two recordings
      - bag: station_a_loaded.mcap
        same_placement_as: station_a # nothing moved: more rows of that recording
        covariates: {payload.mass: 5.0}

(a bare list of such mappings is read the same). ``same_placement_as`` names an earlier
recording whose placement and probe this bag shares (the tracker and the robot stayed put,
the load or the day changed): its rows join that recording, each bag's covariates on its own
rows, so one placement is fitted to both and what the load changes is left to the robot.
``split_at`` (s from the bag's first paired measurement, increasing) makes the bag's rows
between the times recordings of their own, ``<name>_1``, ``<name>_2``, …, each with its own
placement (the tracker or the robot moved during the recording, as ``identify`` warns with
the time); the probe is the first part's (a remount is the first part's only). Every field
is checked here; a bad one is a :class:`ConfigError` naming ``recordings[i].<field>`` and
the fix.
"""
from __future__ import annotations

import dataclasses
import re
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from kpi_calib_ros.core.errors import ConfigError
from kpi_calib_ros.core.measurement.recordings import NAME_PATTERN, Recording, stated_conditions
from kpi_calib_ros.io.bag import BagError, is_measurement_log, scanned_bag
from kpi_calib_ros.io.measurement_log import log_station
from kpi_calib_ros.io.yaml_bounded import read_yaml_file

__all__ = ['RecordingSource', 'RecordingPart', 'sources_from_bags', 'read_manifest',
           'MANIFEST_FIX']

MANIFEST_FIX = ('give recordings: a list of {bag: file.mcap, name: text, '
                'reflector_remounted: true|false, covariates: {name: number}, '
                'split_at: [seconds], same_placement_as: an earlier name}')
_FIELDS = ('bag', 'name', 'reflector_remounted', 'covariates', 'split_at', 'same_placement_as')
Window = tuple[float | None, float | None]


@dataclass(frozen=True)
class RecordingPart:
    """A further bag of a recording (``same_placement_as``), the covariates of its rows."""

    bag: Path
    covariates: dict[str, float]


@dataclass(frozen=True)
class RecordingSource:
    """A recording's bag and what is stated about it.

    ``window``: the part of the bag's rows it holds, (from, until) in s from the bag's first
    paired measurement (``from`` included; None: open), from a manifest's ``split_at``;
    ``more``: further bags of the same placement, each with its covariates.
    """

    bag: Path
    recording: Recording
    window: Window = (None, None)
    more: tuple[RecordingPart, ...] = ()

    @property
    def fitted(self) -> Recording:
        """The recording as identified: with further bags, its conditions are on the rows."""
        return dataclasses.replace(self.recording, covariates={}) if self.more else \
            self.recording


def _split_times(value: Any, key: str, where: str) -> list[float]:
    """The times of ``split_at``: one number or a list, finite, > 0 and increasing."""
    times = value if isinstance(value, list) else [value]
    if not times or not all(isinstance(t, (int, float)) and not isinstance(t, bool)
                            and np.isfinite(t) and t > 0 for t in times) \
            or any(b <= a for a, b in zip(times, times[1:])):
        raise ConfigError(key, f'{where}must be times in s from the bag\'s first paired '
                          f'measurement, > 0 and increasing (e.g. [585.0]), got {value!r}')
    return [float(t) for t in times]


def _name_from_stem(path: Path, key: str) -> str:
    stem = path.stem if path.suffix else path.name
    name = re.sub(r'[^A-Za-z0-9_\-]', '_', stem)
    if not name or not name[0].isalpha():
        name = f'r_{name}'
    if not NAME_PATTERN.match(name):
        raise ConfigError(key, f'cannot name a recording after {str(path)!r}; give names in a '
                          'manifest (--recordings)')
    return name


def _empty_node_log(path: Path) -> bool:
    """Whether ``path`` is a node's measurement log that holds no message."""
    try:
        _, bag = scanned_bag(path)
    except (BagError, OSError):
        return False  # read_bag names what the file is not
    return is_measurement_log(bag) and not any(len(m) for m in bag.messages.values())


def _unique(sources: list[RecordingSource], key: str) -> list[RecordingSource]:
    names = [s.recording.name for s in sources]
    twice = sorted({n for n in names if names.count(n) > 1})
    if twice:
        raise ConfigError(key, f'recordings named {twice} more than once (a name comes from '
                          'the file stem): rename the bags or name them in a manifest '
                          '(--recordings)')
    files = [(b.resolve(), w) for s in sources
             for b, w in [(s.bag, s.window), *((m.bag, (None, None)) for m in s.more)]]
    sources_of = [s for s in sources for _ in range(1 + len(s.more))]
    again = next((i for i, f in enumerate(files) if f in files[:i]), None)
    if again is not None:
        first = files.index(files[again])
        raise ConfigError(key, f'the bag {str(files[again][0])!r} is given twice (recordings '
                          f'{sources_of[first].recording.name!r} and '
                          f'{sources_of[again].recording.name!r}): its rows would count twice '
                          'and the fit claim twice the data; list each bag once')
    return sources


def sources_from_bags(bags: Sequence[str | Path], remounted: Sequence[str] = ()
                      ) -> list[RecordingSource]:
    """The recordings of ``--bag`` given once or more, named by their file stems.

    ``remounted`` (``--remounted``): names of the recordings whose probe was mounted again;
    a node's measurement log that says its station's probe was remounted
    (:func:`~kpi_calib_ros.io.measurement_log.log_station`) is too, after the first, as the
    node's ``~/identify`` takes it.

    Raises
    ------
    ConfigError
        Two bags with one name (``--bag``), or ``--remounted`` names no recording, or names
        the first (the first recording's reflector is the cell's).
    """
    paths = [Path(b).resolve() for b in bags]  # stored absolute, as a manifest's are
    empty = [p for p in paths if _empty_node_log(p)]
    if len(empty) < len(paths):  # every one empty: read_bag says there is nothing
        for path in empty:
            # A node's station set and changed before any measurement leaves such a file.
            print(f'warning: {path} is a node measurement log with no measurement (a '
                  'station set and changed before any was taken): skipped', file=sys.stderr)
        paths = [p for p in paths if p not in empty]
    names = [_name_from_stem(p, '--bag') for p in paths]
    unknown = sorted(set(remounted) - set(names))
    if unknown:
        raise ConfigError('--remounted', f'names no recording: {unknown}; the recordings are '
                          f'{names} (the bags\' file stems)')
    if names and names[0] in remounted:
        raise ConfigError('--remounted', f'{names[0]!r} is the first recording, whose reflector '
                          'is the cell\'s: list a later one, or give the bags in another order')
    return _unique([RecordingSource(p, Recording(n, n in remounted or (
        i > 0 and log_station(p)[1]))) for i, (p, n) in enumerate(zip(paths, names))], '--bag')


def read_manifest(path: str | Path) -> list[RecordingSource]:
    """The recordings a manifest lists, bags relative to its folder (module docstring).

    Raises
    ------
    ConfigError
        The file, a field or a value is not as the module docstring says; the key names the
        field (``recordings[1].covariates.payload.mass``) and the fix.
    """
    path = Path(path)
    if not path.is_file():
        raise ConfigError('--recordings', f'file {str(path)!r} does not exist; {MANIFEST_FIX}')
    doc = read_yaml_file(path, '--recordings', MANIFEST_FIX)
    entries: Any = doc.get('recordings') if isinstance(doc, dict) else doc
    if not isinstance(entries, list) or not entries:
        raise ConfigError('recordings', f'in {path}: must be a non-empty list; {MANIFEST_FIX}')
    out: list[RecordingSource] = []
    for i, entry in enumerate(entries):
        key = f'recordings[{i}]'
        if not isinstance(entry, dict):
            raise ConfigError(key, f'in {path}: must be a mapping; {MANIFEST_FIX}')
        extra = sorted(set(map(str, entry)) - set(_FIELDS))
        if extra:
            raise ConfigError(f'{key}.{extra[0]}', f'in {path}: unknown field; the fields are '
                              f'{list(_FIELDS)}')
        bag = entry.get('bag')
        if not isinstance(bag, str) or not bag:
            raise ConfigError(f'{key}.bag', f'in {path}: give the bag file (text)')
        bag_path = Path(bag) if Path(bag).is_absolute() else path.parent / bag
        if not bag_path.exists():
            raise ConfigError(f'{key}.bag', f'in {path}: {str(bag_path)!r} does not exist')
        if 'same_placement_as' in entry:
            out = _joined(out, entry, key, bag_path, f'in {path}: ')
            continue
        name = entry.get('name', _name_from_stem(bag_path, f'{key}.bag'))
        if not isinstance(name, str) or not NAME_PATTERN.match(name):
            raise ConfigError(f'{key}.name', f'in {path}: {name!r} must start with a letter '
                              'and hold letters, digits, _ or - only')
        # unstated: as a node's measurement log says (its station's probe remounted); the
        # bag is scanned for it only then
        remounted = (entry['reflector_remounted'] if 'reflector_remounted' in entry
                     else i > 0 and log_station(bag_path)[1])
        if not isinstance(remounted, bool):
            raise ConfigError(f'{key}.reflector_remounted', f'in {path}: must be true or '
                              f'false, got {remounted!r}')
        if remounted and i == 0:
            raise ConfigError(f'{key}.reflector_remounted', f'in {path}: the first '
                              'recording\'s reflector is the cell\'s; list a remounted '
                              'recording after it')
        values = stated_conditions(entry.get('covariates') or {}, f'{key}.covariates',
                                   f'in {path}: ')
        if 'split_at' not in entry:
            out.append(RecordingSource(bag_path, Recording(name, remounted, values)))
            continue
        edges = [None, *_split_times(entry['split_at'], f'{key}.split_at', f'in {path}: '), None]
        out.extend(RecordingSource(bag_path, Recording(f'{name}_{j + 1}', remounted and j == 0,
                                                       values), (lo, hi))
                   for j, (lo, hi) in enumerate(zip(edges, edges[1:])))
    # by manifest entry: a split or joined entry is not one recording of ``out``
    stated = [set(map(str, entry.get('covariates') or {})) for entry in entries]
    every = set().union(*stated)
    for i, have in enumerate(stated):
        if have != every:
            raise ConfigError(f'recordings[{i}].covariates', f'in {path}: lacks '
                              f'{sorted(every - have)}, given for other recordings: a '
                              'condition must be stated for every recording (0 is one too)')
    return _unique(out, 'recordings')


def _joined(out: list[RecordingSource], entry: dict, key: str, bag: Path, where: str
            ) -> list[RecordingSource]:
    """``out`` with ``entry``'s bag a further part of the recording it names
    (``same_placement_as``), its covariates on its own rows."""
    name = entry['same_placement_as']
    names = [s.recording.name for s in out]
    if not isinstance(name, str) or name not in names:
        raise ConfigError(f'{key}.same_placement_as', f'{where}must name a recording listed '
                          f'before it, one of {names}, got {name!r}')
    clash = sorted({'name', 'reflector_remounted', 'split_at'} & set(map(str, entry)))
    if clash:
        raise ConfigError(f'{key}.{clash[0]}', f'{where}a bag of the placement of {name!r} '
                          'shares its name, probe and times; give it as a recording of its own '
                          'instead when any of them differs')
    values = stated_conditions(entry.get('covariates') or {}, f'{key}.covariates', where)
    i = names.index(name)
    part = RecordingPart(bag, dict(values))
    return [*out[:i], dataclasses.replace(out[i], more=(*out[i].more, part)), *out[i + 1:]]
