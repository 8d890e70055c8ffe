"""A restricted unpickler for foreign infos files (OpenPCDet ``*_infos_*.pkl``, ``*_dbinfos_*``).

A pickle can name any importable callable and make the loader call it, so ``pickle.load`` on a
file from elsewhere runs arbitrary code. :func:`load` admits only the globals needed to rebuild
numpy arrays, numpy scalars and dtypes plus builtin containers; any other global stops the load
with a :class:`~drcpo.errors.DataError` naming the file and the refused global, before it is
looked up, so nothing it names is imported or called.
"""

from __future__ import annotations

import builtins
import collections
import io
import os
import pickle
from pathlib import Path
from typing import Any

import numpy as np

from drcpo.errors import DataError

try:  # numpy >= 2 keeps the pickle helpers in numpy._core; numpy.core is a deprecated alias
    from numpy._core import multiarray as _multiarray
    from numpy._core import numeric as _numeric
except ImportError:  # pragma: no cover - numpy 1.x
    from numpy.core import multiarray as _multiarray
    from numpy.core import numeric as _numeric

_NUMPY_GLOBALS: dict[str, Any] = {
    "_reconstruct": _multiarray._reconstruct,
    "scalar": _multiarray.scalar,
}
_NUMERIC_GLOBALS: dict[str, Any] = {"_frombuffer": _numeric._frombuffer}


def _latin1_encode(text: str, encoding: str = "utf-8") -> bytes:
    """``_codecs.encode`` restricted to latin-1, which protocols 0-2 use to store bytes."""
    if encoding != "latin1" or not isinstance(text, str):
        raise pickle.UnpicklingError(f"_codecs.encode with {encoding!r} is not allowed")
    return text.encode("latin1")


# Pickles written under numpy 1.x name ``numpy.core.*``, under numpy 2.x ``numpy._core.*``;
# both spellings resolve to the objects of the installed numpy.
ALLOWED_GLOBALS: dict[tuple[str, str], Any] = {
    **{(module, name): obj for module in ("numpy.core.multiarray", "numpy._core.multiarray")
       for name, obj in _NUMPY_GLOBALS.items()},
    **{(module, name): obj for module in ("numpy.core.numeric", "numpy._core.numeric")
       for name, obj in _NUMERIC_GLOBALS.items()},
    ("numpy", "ndarray"): np.ndarray,
    ("numpy", "dtype"): np.dtype,
    ("_codecs", "encode"): _latin1_encode,
    **{
        (module, name): getattr(builtins, name)
        for module in ("builtins", "__builtin__")  # protocols 0-2 write __builtin__
        for name in (
            "dict", "list", "tuple", "set", "frozenset", "bytearray", "bytes", "complex",
            "slice", "range",
        )
    },
    ("collections", "OrderedDict"): collections.OrderedDict,
}  # fmt: skip


class _RestrictedUnpickler(pickle.Unpickler):
    def __init__(self, file: io.BufferedIOBase, source: str) -> None:
        super().__init__(file)
        self._source = source

    def find_class(self, module: str, name: str) -> Any:
        try:
            return ALLOWED_GLOBALS[(module, name)]
        except KeyError:
            raise DataError(
                f"{self._source}: refused to load global {module}.{name} "
                "(only numpy arrays, scalars, dtypes and builtin containers are allowed)"
            ) from None


def loads(data: bytes, source: str = "<bytes>") -> Any:
    """Unpickle ``data`` admitting only numpy arrays/scalars/dtypes and builtin containers.

    Raises :class:`DataError` naming ``source`` for a refused global or a corrupt pickle.
    """
    try:
        return _RestrictedUnpickler(io.BytesIO(data), source).load()
    except DataError:
        raise
    except (pickle.UnpicklingError, EOFError, ValueError, TypeError, IndexError,
            AttributeError, KeyError) as exc:  # fmt: skip
        raise DataError(f"{source}: not a readable pickle ({type(exc).__name__}: {exc})") from exc


def load(path: str | os.PathLike) -> Any:
    """Read the pickle file at ``path`` through the restricted unpickler (see :func:`loads`)."""
    path = Path(path)
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise DataError(f"{path}: cannot read ({exc.strerror or exc})") from exc
    return loads(data, source=str(path))
