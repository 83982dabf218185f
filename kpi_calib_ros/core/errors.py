"""Exception types shared by the whole package."""
from __future__ import annotations

__all__ = ['KpiCalibError', 'ConfigError', 'DataError']


class KpiCalibError(Exception):
    """Base class of every error this package raises on purpose."""


class ConfigError(KpiCalibError, ValueError):
    """Bad input from outside: names the offending key path and the fix.

    Parameters
    ----------
    key : str
        Dotted key path of the offending field, e.g. ``'robot.tip_frame'``.
    message : str
        What is wrong and how to fix it.
    """

    def __init__(self, key: str, message: str) -> None:
        self.key = key
        super().__init__(f'{key}: {message}')


class DataError(KpiCalibError, ValueError):
    """Measurement data that cannot support the requested computation."""
