"""Exceptions raised on bad input or an output that cannot be written.

Every error raised for a user's data or configuration derives from :class:`DrcpoError`, so a
training loop can catch one type, and its message names the culprit (file, line, field).
"""

from __future__ import annotations

from typing import Any

import numpy as np

__all__ = ["ConfigError", "DataError", "DrcpoError", "OutputError", "OutputExistsError", "shown"]


class DrcpoError(Exception):
    """Base class of drcpo's errors about input data or configuration."""


class DataError(DrcpoError, ValueError):
    """A data file or array is malformed (wrong size, NaN/inf, bad line, missing file)."""


class ConfigError(DrcpoError, ValueError):
    """A configuration value is missing, unknown or out of range."""


class OutputError(DrcpoError, OSError):
    """An output cannot be written: it exists, it is not drcpo's to replace, it overlaps an
    input, another run is writing it, or the operating system refused (permission, disk full).

    An ``OSError`` too, so code that caught the system's errors of a failed write still does.
    """


class OutputExistsError(OutputError, FileExistsError):
    """The output path already exists and ``overwrite`` was not asked for."""


def shown(value: Any, limit: int = 60) -> str:
    """``repr(value)`` for an error message, cut to ``limit`` characters; an int too long for
    ``repr`` (Python's digit limit) is shown by its size, an array by its dtype and shape."""
    if isinstance(value, np.ndarray):
        return f"<array {value.dtype} {value.shape}>"
    try:
        text = repr(value)
    except ValueError:  # over sys.get_int_max_str_digits() digits, or a container holding one
        return f"<an int of {value.bit_length()} bits>" if isinstance(value, int) else "<too large>"
    return text if len(text) <= limit else f"{text[: limit - 3]}..."
