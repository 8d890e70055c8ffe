"""The globals a foreign pickle may name, and drcpo's own rebuilding of each.

:mod:`~drcpo.database.safe_pickle`'s stack machine looks every global a file names up in
:data:`ALLOWED_GLOBALS` and, at REDUCE, calls drcpo's rebuilding of it here instead: nothing named
in the file is imported or called. Numpy objects are rebuilt from validated plain values, never by
numpy's ``__setstate__``: a dtype from its type string (its flags, size and alignment in the file
must be the ones numpy derives), an array with ``np.frombuffer(...).reshape(...)`` once its byte
count matches its shape (at most :data:`MAX_NDIM` dimensions). The builtins a pickle may call
(``set``, ``frozenset``, ``bytes``, ``bytearray``, ``complex``, ``OrderedDict`` and latin-1
``_codecs.encode``) only copy what the file already holds; every copy is charged to the machine's
budget.
"""

from __future__ import annotations

import collections
import re
from collections.abc import Callable
from typing import Any, Protocol

import numpy as np

from drcpo.errors import shown

__all__ = ["ALLOWED_GLOBALS", "MAX_NDIM"]

MAX_NDIM = 32
"""Most array dimensions accepted (numpy 1.x's own limit)."""

# numpy's type strings of the plain dtypes: bool, integers, floats up to 64 bits, complex up
# to 128 bits, fixed-width str and bytes. float128/complex256 differ between platforms.
_TYPESTR = re.compile(r"b1|[iu](?:1|2|4|8)|f(?:2|4|8)|c(?:8|16)|[US]\d{1,9}")
_BYTEORDERS = ("<", ">", "|", "=")


class _Invalid(Exception):
    """The pickle is malformed or asks for something not allowed (message says what)."""


class _Machine(Protocol):
    """What a rebuilding asks of the stack machine running the pickle (``safe_pickle._Machine``)."""

    def charge(self, nbytes: int, what: str) -> None: ...

    def values(self, items: list[Any], inside: str) -> list[Any]: ...

    def nest(self, container: Any, items: list[Any], floor: int = 0) -> Any: ...


class _Global:
    """A global the file may name: ``call`` rebuilds the object from the REDUCE arguments."""

    def __init__(self, name: str, call: Callable[[_Machine, tuple], Any] | None) -> None:
        self.name = name
        self.call = call

    def __repr__(self) -> str:
        return self.name


class _PendingDtype:
    """``numpy.dtype(typestr, align, copy)`` before its BUILD state arrives."""

    def __init__(self, typestr: str) -> None:
        self.typestr = typestr
        self.dtype: np.dtype | None = None
        self.used = False

    def build(self, state: Any) -> None:
        if self.dtype is not None or self.used:
            raise _Invalid("dtype state given twice or after the dtype was used")
        self.dtype = _dtype_from_state(self.typestr, state)

    def resolve(self) -> np.dtype:
        self.used = True
        if self.dtype is None:  # no state: numpy's default for the type string (native order)
            self.dtype = np.dtype(self.typestr)
        return self.dtype


class _PendingArray:
    """``_reconstruct(ndarray, (0,), b'b')`` before its BUILD state (shape, dtype, data)."""

    def __init__(self) -> None:
        self.array: np.ndarray | None = None

    def build(self, machine: _Machine, state: Any) -> None:
        if self.array is not None:
            raise _Invalid("array state given twice")
        if not isinstance(state, tuple) or len(state) not in (4, 5):
            raise _Invalid(f"array state must be a 4- or 5-tuple, got {_kind(state)}")
        if len(state) == 5:
            version, *state = state
            if version != 1:
                raise _Invalid(f"array state version {shown(version, 40)} is not 1")
        shape, dtype, fortran, raw = state
        if not isinstance(fortran, bool):
            raise _Invalid(f"array order flag must be a bool, got {_kind(fortran)}")
        array = _array(machine, dtype, shape, "F" if fortran else "C", raw)
        # numpy's own __setstate__ hands back native byte order; so does this.
        self.array = array.astype(array.dtype.newbyteorder("="), order="K", copy=False)

    def resolve(self) -> np.ndarray:
        if self.array is None:
            raise _Invalid("array used before its state (shape, dtype, data) was given")
        return self.array


def _kind(value: Any) -> str:
    return f"{type(value).__name__} {shown(value, 40)}"


def _dtype_from_state(typestr: str, state: Any) -> np.dtype:
    """The dtype ``typestr`` in byte order ``state[1]``, once the state matches numpy's."""
    if not isinstance(state, tuple) or len(state) not in (8, 9) or state[0] not in (3, 4):
        raise _Invalid(f"dtype state must be a version 3 or 4 tuple, got {_kind(state)}")
    _, order, subarray, names, fields, elsize, alignment, flags, *metadata = state
    if order not in _BYTEORDERS:
        raise _Invalid(f"dtype byte order {shown(order, 40)} is not one of {''.join(_BYTEORDERS)}")
    if (subarray, names, fields, *metadata) != (None, None, None, *[None] * len(metadata)):
        raise _Invalid(f"dtype {typestr!r}: structured, subarray or metadata dtypes are refused")
    for field, value in (("size", elsize), ("alignment", alignment), ("flags", flags)):
        if type(value) is not int:
            raise _Invalid(f"dtype {typestr!r}: {field} must be an int, got {_kind(value)}")
    kind = typestr[0]
    if kind in "US" and elsize != -1:
        if not 0 <= elsize < 2**31 or (kind == "U" and elsize % 4):
            raise _Invalid(f"dtype {typestr!r}: size {shown(elsize, 40)} is not valid")
        typestr = f"{kind}{elsize // 4 if kind == 'U' else elsize}"
    dtype = np.dtype(typestr)
    if order in "<>" and dtype.itemsize > 1 and kind != "S":
        dtype = dtype.newbyteorder(order)
    # numpy derives size, alignment and flags from the type; a file that disagrees is corrupt
    # (foreign flags are what made numpy crash), so they are compared, never applied.
    expected = {"size": dtype.itemsize, "alignment": dtype.alignment, "flags": dtype.flags}
    for field, value in (("size", elsize), ("alignment", alignment), ("flags", flags)):
        if value != expected[field] and not (value == -1 and field != "flags"):
            raise _Invalid(
                f"dtype {dtype.str}: {field} {shown(value, 40)} is not numpy's {expected[field]}"
            )
    return dtype


def _plain_dtype(value: Any) -> np.dtype:
    if not isinstance(value, np.dtype) or value.kind not in "biufcUS" or value.fields:
        raise _Invalid(f"expected a plain numeric, bool or string dtype, got {_kind(value)}")
    return value


def _raw_bytes(value: Any, what: str) -> bytes | bytearray:
    if isinstance(value, str):  # protocols 0-2 of Python 2 store bytes as latin-1 text
        value = value.encode("latin1")
    if not isinstance(value, (bytes, bytearray)):
        raise _Invalid(f"{what} must be bytes, got {_kind(value)}")
    return value


def _array(machine: _Machine, dtype: Any, shape: Any, order: Any, raw: Any) -> np.ndarray:
    """A writeable array of ``shape`` over the bytes ``raw``, once all four agree."""
    dtype = _plain_dtype(dtype)
    raw = _raw_bytes(raw, "array data")
    if order not in ("C", "F"):
        raise _Invalid(f"array order must be 'C' or 'F', got {_kind(order)}")
    if not isinstance(shape, tuple) or len(shape) > MAX_NDIM:
        raise _Invalid(
            f"array shape must be a tuple of at most {MAX_NDIM} ints, got {_kind(shape)}"
        )
    count = 1
    for size in shape:
        if type(size) is not int or not 0 <= size < 2**63:
            raise _Invalid(f"array shape {_kind(shape)} holds a bad dimension {shown(size, 40)}")
        count = min(count * size, 2**63)  # capped: a product over the file size is refused
    if count and not dtype.itemsize:
        raise _Invalid(f"array of {count} elements of zero-size dtype {dtype.str}")
    if count * dtype.itemsize != len(raw):
        raise _Invalid(
            f"array of shape {shape} and dtype {dtype.str} needs {count * dtype.itemsize} bytes, "
            f"the file gives {len(raw)}"
        )
    machine.charge(len(raw), "array data")
    if not count:
        return np.empty(shape, dtype, order=order)
    return np.frombuffer(raw, dtype=dtype).reshape(shape, order=order).copy(order="K")


# Factories for the globals a file may name ---------------------------------------------------
def _arity(args: tuple, low: int, high: int, name: str) -> None:
    if not low <= len(args) <= high:
        raise _Invalid(f"{name} takes {low} to {high} arguments, got {len(args)}")


def _make_dtype(machine: _Machine, args: tuple) -> _PendingDtype:
    _arity(args, 1, 3, "numpy.dtype")
    typestr, *flags = args
    if not isinstance(typestr, str) or not _TYPESTR.fullmatch(typestr):
        raise _Invalid(f"numpy.dtype {_kind(typestr)} is not a plain numeric, bool or str type")
    if not all(isinstance(flag, bool) for flag in flags):
        raise _Invalid(f"numpy.dtype flags must be bools, got {shown(flags, 40)}")
    return _PendingDtype(typestr)


def _make_scalar(machine: _Machine, args: tuple) -> np.generic:
    _arity(args, 2, 2, "numpy scalar")
    dtype = _plain_dtype(args[0])
    raw = _raw_bytes(args[1], "scalar data")
    if len(raw) != dtype.itemsize:
        raise _Invalid(f"scalar of dtype {dtype.str} needs {dtype.itemsize} bytes, got {len(raw)}")
    machine.charge(len(raw), "scalar data")
    if not dtype.itemsize:
        return np.zeros((), dtype)[()]
    return np.frombuffer(raw, dtype=dtype)[0]


def _make_reconstruct(machine: _Machine, args: tuple) -> _PendingArray:
    _arity(args, 3, 3, "numpy _reconstruct")
    cls, shape, typecode = args
    if cls is not _NDARRAY:
        raise _Invalid(f"_reconstruct builds numpy.ndarray only, got {_kind(cls)}")
    if not isinstance(shape, tuple) or not isinstance(typecode, (bytes, str)):
        raise _Invalid("_reconstruct takes (ndarray, shape tuple, typecode)")
    return _PendingArray()


def _make_frombuffer(machine: _Machine, args: tuple) -> np.ndarray:
    _arity(args, 4, 4, "numpy _frombuffer")
    raw, dtype, shape, order = args
    return _array(machine, dtype, shape, order, raw)


def _make_collection(kind: type) -> Callable[[_Machine, tuple], Any]:
    def make(machine: _Machine, args: tuple) -> Any:
        _arity(args, 0, 1, kind.__name__)
        if not args:
            return kind()
        items = args[0]
        if not isinstance(items, (list, tuple, set, frozenset)):
            raise _Invalid(f"{kind.__name__}() takes a list, got {_kind(items)}")
        machine.charge(len(items), f"{kind.__name__} items")
        items = machine.values(list(items), kind.__name__)
        return machine.nest(kind(items), items)

    return make


def _make_bytes(machine: _Machine, args: tuple) -> bytes | bytearray:
    # Only copies of bytes already in the file: bytes(n) / bytearray(n) would allocate n bytes.
    _arity(args, 0, 1, "bytes")
    if args and not isinstance(args[0], (bytes, bytearray)):
        raise _Invalid(f"bytes()/bytearray() take bytes, got {_kind(args[0])}")
    raw = args[0] if args else b""
    machine.charge(len(raw), "bytes")
    return bytes(raw)


def _make_bytearray(machine: _Machine, args: tuple) -> bytearray:
    return bytearray(_make_bytes(machine, args))


def _make_complex(machine: _Machine, args: tuple) -> complex:
    _arity(args, 0, 2, "complex")
    if not all(type(part) in (int, float) for part in args):
        raise _Invalid(f"complex() takes numbers, got {shown(args, 40)}")
    return complex(*args)


def _make_ordered_dict(machine: _Machine, args: tuple) -> collections.OrderedDict:
    _arity(args, 0, 0, "OrderedDict")
    return collections.OrderedDict()


def _latin1_encode(machine: _Machine, args: tuple) -> bytes:
    """``_codecs.encode`` restricted to latin-1, which protocols 0-2 use to store bytes."""
    _arity(args, 2, 2, "_codecs.encode")
    text, encoding = args
    if encoding != "latin1" or not isinstance(text, str):
        raise _Invalid(f"_codecs.encode with {shown(encoding, 40)} is not allowed")
    machine.charge(len(text), "encoded text")
    return text.encode("latin1")


_NDARRAY = _Global("numpy.ndarray", None)  # only an argument of _reconstruct


def _globals() -> dict[tuple[str, str], _Global]:
    table: dict[tuple[str, str], _Global] = {}
    # numpy 1.x writes numpy.core.*, numpy 2.x numpy._core.*: both name the same helpers.
    for package in ("numpy.core", "numpy._core"):
        for name, make in (("scalar", _make_scalar), ("_reconstruct", _make_reconstruct)):
            table[f"{package}.multiarray", name] = _Global(f"numpy {name}", make)
        table[f"{package}.numeric", "_frombuffer"] = _Global("numpy _frombuffer", _make_frombuffer)
    table["numpy", "ndarray"] = _NDARRAY
    table["numpy", "dtype"] = _Global("numpy.dtype", _make_dtype)
    table["_codecs", "encode"] = _Global("_codecs.encode", _latin1_encode)
    table["collections", "OrderedDict"] = _Global("OrderedDict", _make_ordered_dict)
    builtins = {
        "set": _make_collection(set),
        "frozenset": _make_collection(frozenset),
        "bytes": _make_bytes,
        "bytearray": _make_bytearray,
        "complex": _make_complex,
    }
    for module in ("builtins", "__builtin__"):  # protocols 0-2 write __builtin__
        for name, make in builtins.items():
            table[module, name] = _Global(name, make)
    return table


ALLOWED_GLOBALS = _globals()
"""``(module, name)`` pairs a pickle may name, with drcpo's own rebuilding of each."""
