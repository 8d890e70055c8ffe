"""Exceptions raised on bad input.

Every error raised for a user's data or configuration derives from :class:`DrcpoError`, so a
training loop can catch one type, and its message names the culprit (file, line, field).
"""

from __future__ import annotations


class DrcpoError(Exception):
    """Base class of drcpo's errors about input data or configuration."""


class DataError(DrcpoError, ValueError):
    """A data file or array is malformed (wrong size, NaN/inf, bad line, missing file)."""


class ConfigError(DrcpoError, ValueError):
    """A configuration value is missing, unknown or out of range."""
