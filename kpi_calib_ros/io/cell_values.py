"""Generic readers of cell-file values: numbers, vectors, mappings and strings, each
raising a :class:`~kpi_calib_ros.core.errors.ConfigError` that names the key path, the
unit and the fix (a number written as text gets a hint why)."""
from __future__ import annotations

from typing import Any, Mapping

import numpy as np

from kpi_calib_ros.core.errors import ConfigError


def number(section: Mapping[str, Any], name: str, path: str,
           default: float | None = None, unit: str = '') -> float:
    """The finite number ``section[name]`` (``default`` when absent); the one reader of
    numeric cell values, so a wrong type (``beam_radius: wide``) names its key path
    ``path.name`` and the unit."""
    key = f'{path}.{name}' if path else name
    value = section.get(name, default)
    if value is None:
        raise ConfigError(key, f'missing; give a number{f" ({unit})" if unit else ""}')
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not np.isfinite(value):
        raise ConfigError(key, f'must be a finite number{f" in {unit}" if unit else ""} '
                          f'(SI units), got {value!r}')
    return float(value)


def refuse_unknown(section: Any, path: str, allowed: Any) -> None:
    """Raise for a key of the mapping ``section`` (at ``path``) that is not in ``allowed``: a
    misspelled key (``payload.cog``) would otherwise be ignored and its default used."""
    if not isinstance(section, Mapping):
        return
    unknown = sorted(str(k) for k in set(section) - set(allowed))
    if unknown:
        raise ConfigError(f'{path}.{unknown[0]}' if path else unknown[0],
                          f'unknown key; allowed keys are {sorted(allowed)} (check the spelling)')


def non_negative(value: float, key: str, unit: str) -> float:
    if value < 0:
        raise ConfigError(key, f'must be >= 0 {unit}, got {value}')
    return value


def optional_mapping(doc: dict, key: str) -> dict:
    value = doc.get(key)
    if value is None:
        return {}
    if not isinstance(value, dict):
        raise ConfigError(key, f'must be a mapping, got {value!r}')
    return value


def required_mapping(doc: dict, key: str) -> dict:
    value = doc.get(key)
    if not isinstance(value, dict):
        raise ConfigError(key, 'missing or not a mapping')
    return value


def required_string(doc: dict, path: str, key: str) -> str:
    value = doc.get(key)
    if not isinstance(value, str) or not value:
        raise ConfigError(path, 'missing; give a non-empty string')
    return value


def vector(value: Any, path: str, n: int) -> np.ndarray:
    try:
        arr = np.asarray(value, dtype=float)
    except (TypeError, ValueError):
        arr = np.array([])
    if value is None or arr.shape != (n,) or not np.all(np.isfinite(arr)):
        raise ConfigError(path, f'must be a list of {n} finite numbers (SI units), got '
                          f'{value!r}{text_number_hint(value)}')
    return arr


def optional_vector(value: Any, path: str, n: int) -> np.ndarray:
    """``vector``, or zeros when the key is left out (registered from the data later)."""
    return np.zeros(n) if value is None else vector(value, path, n)


def text_number_hint(value: Any) -> str:
    """Why a number arrived as text: quoted, or YAML 1.1's float rule (``2e-06`` is a
    string for PyYAML; ``2.0e-06`` a number), and the fix."""
    try:
        number = float(value) if isinstance(value, str) else None
    except ValueError:
        number = None
    if number is None:
        return ''
    return (f' (a string: a quoted number, or YAML 1.1 reading an exponent without a '
            f'decimal point as text; write {number:.1e} unquoted, e.g. sigma: {number:.1e})')


def number_or_vector(value: Any, path: str) -> Any:
    if isinstance(value, (int, float)) and not isinstance(value, bool):
        return float(value)
    return vector(value, path, 3)


def joint_value(v: Any, key: str) -> float:
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not np.isfinite(v):
        raise ConfigError(key, f'must be a finite number (rad), got {v!r}')
    return float(v)
