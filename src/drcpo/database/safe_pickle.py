"""A restricted reader for foreign infos pickles (OpenPCDet ``*_infos_*.pkl``, ``*_dbinfos_*``).

``pickle.load`` on a file from elsewhere runs arbitrary code, and even a pickle that names only
numpy's own helpers can crash the interpreter: numpy rebuilds a dtype's flags and an array's
memory from whatever the file says. So :func:`load` does not use :class:`pickle.Unpickler`. It
walks the opcodes (decoded by :func:`pickletools.genops`) with a small stack machine that knows
only what infos files hold: dicts, lists, tuples, sets, str, bytes, int, float, complex, bool,
None, numpy arrays and scalars of plain numeric, bool and string dtypes, and numpy dtypes.

Numpy objects are rebuilt by drcpo from validated plain values, never by numpy's
``__setstate__``: a dtype from its type string (its flags, size and alignment in the file must
be the ones numpy derives), an array with ``np.frombuffer(...).reshape(...)`` once its byte
count matches its shape. Nesting is bounded (:data:`MAX_DEPTH`), containers cannot be made
recursive, and every copy the file asks for is charged against a budget proportional to the
file's size, so a few bytes cannot claim gigabytes. Anything else stops the load with a
:class:`~drcpo.errors.DataError` naming the file, the byte offset and what was refused; no
global named in the file is imported or called.
"""

from __future__ import annotations

import collections
import os
import pickletools
import re
import struct
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from drcpo.errors import DataError, shown

__all__ = ["ALLOWED_GLOBALS", "MAX_DEPTH", "MAX_NDIM", "load", "loads"]

MAX_DEPTH = 64
"""Deepest nesting of containers accepted; OpenPCDet and MMDetection3D infos need under 10."""

MAX_NDIM = 32
"""Most array dimensions accepted (numpy 1.x's own limit)."""

# Bytes a pickle may make drcpo copy, per byte of file, plus a constant: each array's data
# is in the file once, at most twice counting protocol 0's latin-1 text form.
_BUDGET_PER_BYTE = 2
_BUDGET_SLACK = 1 << 16

# numpy's type strings of the plain dtypes: bool, integers, floats up to 64 bits, complex up
# to 128 bits, fixed-width str and bytes. float128/complex256 differ between platforms.
_TYPESTR = re.compile(r"b1|[iu](?:1|2|4|8)|f(?:2|4|8)|c(?:8|16)|[US]\d{1,9}")
_BYTEORDERS = ("<", ">", "|", "=")


class _Invalid(Exception):
    """The pickle is malformed or asks for something not allowed (message says what)."""


class _Refused(Exception):
    """The pickle names a global outside :data:`ALLOWED_GLOBALS`."""


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

# Exact types (the machine makes no subclasses): containers whose depth is tracked, those of
# them the opcodes can grow in place, and the machine's own stand-ins.
_TRACKED = frozenset({list, dict, set, frozenset, tuple, collections.OrderedDict})
_GROWABLE = frozenset({list, dict, set, collections.OrderedDict})
_PENDING = frozenset({_PendingDtype, _PendingArray})


# The stack machine ----------------------------------------------------------------------------
class _Machine:
    """Runs the opcodes of one pickle; see the module docstring for what it admits."""

    def __init__(self, source: str, size: int) -> None:
        self.source = source
        self.size = size
        self.budget = _BUDGET_PER_BYTE * size + _BUDGET_SLACK
        self.stack: list[Any] = []
        self.marks: list[int] = []
        self.memo: dict[int, Any] = {}
        # id -> (depth, object): the object is kept so that its id is not reused
        self.depths: dict[int, tuple[int, Any]] = {}
        self.sealed: set[int] = set()  # mutable containers already placed inside another
        self.carries_global: set[int] = set()  # tuples holding a global (REDUCE arguments)
        self.result: Any = None

    # accounting ---------------------------------------------------------------------------
    def charge(self, nbytes: int, what: str) -> None:
        if nbytes > self.size:
            raise _Invalid(f"{what} of {nbytes} bytes is more than the {self.size}-byte file holds")
        self.budget -= nbytes
        if self.budget < 0:
            raise _Invalid(f"{what}: the file asks for more copies than its size allows")

    def depth(self, value: Any) -> int:
        entry = self.depths.get(id(value))
        return entry[0] if entry is not None and entry[1] is value else 0

    def nest(self, container: Any, items: list[Any], floor: int = 0) -> Any:
        """Record ``container`` holding ``items`` one level above its deepest item.

        ``floor``: the container's depth so far, when items are added to it in place. Mutable
        items are sealed: a container placed in another may not change any more, which keeps
        the recorded depths exact and makes cycles impossible.
        """
        deepest = max(floor - 1, 0)
        depths, sealed = self.depths, self.sealed
        for item in items:  # a plain loop: this runs for every item of the file
            kind = type(item)
            if kind in _TRACKED:
                if item is container:
                    raise _Invalid("a container cannot be put inside itself")
                entry = depths.get(id(item))
                if entry is not None and entry[1] is item and entry[0] > deepest:
                    deepest = entry[0]
                if kind in _GROWABLE:
                    sealed.add(id(item))
        if deepest >= MAX_DEPTH:
            raise _Invalid(f"containers nested deeper than {MAX_DEPTH}")
        depths[id(container)] = (deepest + 1, container)
        return container

    def values(self, items: list[Any], inside: str) -> list[Any]:
        """``items`` (a fresh list, changed in place) as stored in an ``inside`` container.

        Pending numpy objects are resolved; globals may only sit in tuples (REDUCE arguments).
        """
        carries = self.carries_global
        for index, item in enumerate(items):
            kind = type(item)
            if kind in _PENDING:
                items[index] = item.resolve()
            elif inside != "tuple" and (kind is _Global or (kind is tuple and id(item) in carries)):
                raise _Invalid(f"global {item!r} can only be called, not stored")
        return items

    def value(self, item: Any, inside: str) -> Any:
        return self.values([item], inside)[0]

    def grow(self, target: Any, items: list[Any], kinds: tuple[type, ...], opcode: str) -> None:
        """Check that ``target`` may take ``items`` in place (no cycles, no changes once nested)."""
        if not isinstance(target, kinds):
            raise _Invalid(f"{opcode} on a {type(target).__name__}")
        if id(target) in self.sealed:
            raise _Invalid(f"{opcode} changes a container already placed in another")
        self.nest(target, items, floor=self.depth(target))

    # stack --------------------------------------------------------------------------------
    def fence(self) -> int:
        return self.marks[-1] if self.marks else 0

    def pop(self) -> Any:
        if len(self.stack) <= self.fence():
            raise _Invalid("stack underflow")
        return self.stack.pop()

    def top(self) -> Any:
        if len(self.stack) <= self.fence():
            raise _Invalid("stack underflow")
        return self.stack[-1]

    def pop_mark(self) -> list[Any]:
        if not self.marks:
            raise _Invalid("no MARK to pop to")
        start = self.marks.pop()
        items = self.stack[start:]
        del self.stack[start:]
        return items

    def push_new(self, container: Any, items: list[Any]) -> None:
        self.stack.append(self.nest(container, items))

    def push_tuple(self, items: list[Any]) -> None:
        items = self.values(items, "tuple")
        made = self.nest(tuple(items), items)
        carries = self.carries_global
        if any(type(i) is _Global or (type(i) is tuple and id(i) in carries) for i in items):
            carries.add(id(made))
        self.stack.append(made)

    def pairs(self, items: list[Any], opcode: str) -> list[tuple[Any, Any]]:
        if len(items) % 2:
            raise _Invalid(f"{opcode} with an odd number of items")
        items = self.values(items, "dict")
        return list(zip(items[::2], items[1::2], strict=True))

    # opcodes ------------------------------------------------------------------------------
    def op_stop(self, arg: Any) -> bool:
        self.result = self.value(self.pop(), "result")
        return True

    def op_proto(self, arg: Any) -> None:
        if not 0 <= arg <= 5:
            raise _Invalid(f"unsupported pickle protocol {arg}")

    def op_ignore(self, arg: Any) -> None:
        """FRAME only tells the reader how much to buffer."""

    def op_push(self, arg: Any) -> None:
        self.stack.append(arg)

    def op_none(self, arg: Any) -> None:
        self.stack.append(None)

    def op_true(self, arg: Any) -> None:
        self.stack.append(True)

    def op_false(self, arg: Any) -> None:
        self.stack.append(False)

    def op_mark(self, arg: Any) -> None:
        self.marks.append(len(self.stack))

    def op_pop(self, arg: Any) -> None:
        if len(self.stack) > self.fence():
            self.stack.pop()
        else:  # as pickle: POP at a mark discards the mark
            self.pop_mark()

    def op_pop_mark(self, arg: Any) -> None:
        self.pop_mark()

    def op_dup(self, arg: Any) -> None:
        self.stack.append(self.top())

    def op_empty_list(self, arg: Any) -> None:
        self.push_new([], [])

    def op_empty_dict(self, arg: Any) -> None:
        self.push_new({}, [])

    def op_empty_set(self, arg: Any) -> None:
        self.push_new(set(), [])

    def op_empty_tuple(self, arg: Any) -> None:
        self.push_tuple([])

    def op_list(self, arg: Any) -> None:
        items = self.values(self.pop_mark(), "list")
        self.push_new(items, items)

    def op_tuple(self, arg: Any) -> None:
        self.push_tuple(self.pop_mark())

    def op_tuple_n(self, count: int) -> None:
        stack = self.stack
        if len(stack) - count < self.fence():
            raise _Invalid("stack underflow")
        items = stack[-count:]
        del stack[-count:]
        self.push_tuple(items)

    def op_dict(self, arg: Any) -> None:
        pairs = self.pairs(self.pop_mark(), "DICT")
        self.push_new(dict(pairs), [item for pair in pairs for item in pair])

    def op_frozenset(self, arg: Any) -> None:
        items = self.values(self.pop_mark(), "frozenset")
        self.push_new(frozenset(items), items)

    def op_append(self, arg: Any) -> None:
        item = self.value(self.pop(), "list")
        self._appends([item])

    def op_appends(self, arg: Any) -> None:
        self._appends(self.values(self.pop_mark(), "list"))

    def _appends(self, items: list[Any]) -> None:
        target = self.top()
        self.grow(target, items, (list,), "APPEND")
        target.extend(items)

    def op_setitem(self, arg: Any) -> None:
        value = self.pop()
        self._setitems(self.pairs([self.pop(), value], "SETITEM"))

    def op_setitems(self, arg: Any) -> None:
        self._setitems(self.pairs(self.pop_mark(), "SETITEMS"))

    def _setitems(self, pairs: list[tuple[Any, Any]]) -> None:
        target = self.top()
        self.grow(target, [item for pair in pairs for item in pair], (dict,), "SETITEM")
        for key, value in pairs:
            target[key] = value

    def op_additems(self, arg: Any) -> None:
        items = self.values(self.pop_mark(), "set")
        target = self.top()
        self.grow(target, items, (set,), "ADDITEMS")
        target.update(items)

    def op_get(self, index: int) -> None:
        if index not in self.memo:
            raise _Invalid(f"memo entry {index} was never stored")
        self.stack.append(self.memo[index])

    def op_put(self, index: int) -> None:
        if index < 0:
            raise _Invalid(f"negative memo index {index}")
        self.memo[index] = self.top()

    def op_memoize(self, arg: Any) -> None:
        self.memo[len(self.memo)] = self.top()

    def op_global(self, arg: str) -> None:
        module, _, name = arg.partition(" ")
        self._push_global(module, name)

    def op_stack_global(self, arg: Any) -> None:
        name, module = self.pop(), self.pop()
        if not isinstance(module, str) or not isinstance(name, str):
            raise _Invalid("STACK_GLOBAL needs two strings")
        self._push_global(module, name)

    def _push_global(self, module: str, name: str) -> None:
        found = ALLOWED_GLOBALS.get((module, name))
        if found is None:
            raise _Refused(f"{module}.{name}")
        self.stack.append(found)

    def op_reduce(self, arg: Any) -> None:
        args, function = self.pop(), self.pop()
        if not isinstance(function, _Global) or function.call is None:
            raise _Invalid(f"REDUCE calls {_kind(function)}, which is not callable here")
        if not isinstance(args, tuple):
            raise _Invalid(f"REDUCE arguments must be a tuple, got {_kind(args)}")
        self.stack.append(function.call(self, args))

    def op_build(self, arg: Any) -> None:
        state = self.value(self.pop(), "state")
        target = self.top()
        if isinstance(target, _PendingDtype):
            target.build(state)
        elif isinstance(target, _PendingArray):
            target.build(self, state)
        else:
            raise _Invalid(f"BUILD on a {type(target).__name__}")


def _handlers() -> dict[str, Callable[[_Machine, Any], Any]]:
    m = _Machine
    table: dict[str, Callable[[_Machine, Any], Any]] = {
        "STOP": m.op_stop,
        "PROTO": m.op_proto,
        "FRAME": m.op_ignore,
        "MARK": m.op_mark,
        "POP": m.op_pop,
        "POP_MARK": m.op_pop_mark,
        "DUP": m.op_dup,
        "NONE": m.op_none,
        "NEWTRUE": m.op_true,
        "NEWFALSE": m.op_false,
        "EMPTY_LIST": m.op_empty_list,
        "EMPTY_DICT": m.op_empty_dict,
        "EMPTY_SET": m.op_empty_set,
        "EMPTY_TUPLE": m.op_empty_tuple,
        "LIST": m.op_list,
        "TUPLE": m.op_tuple,
        "TUPLE1": lambda self, arg: self.op_tuple_n(1),
        "TUPLE2": lambda self, arg: self.op_tuple_n(2),
        "TUPLE3": lambda self, arg: self.op_tuple_n(3),
        "DICT": m.op_dict,
        "FROZENSET": m.op_frozenset,
        "APPEND": m.op_append,
        "APPENDS": m.op_appends,
        "SETITEM": m.op_setitem,
        "SETITEMS": m.op_setitems,
        "ADDITEMS": m.op_additems,
        "GLOBAL": m.op_global,
        "STACK_GLOBAL": m.op_stack_global,
        "REDUCE": m.op_reduce,
        "BUILD": m.op_build,
        "MEMOIZE": m.op_memoize,
    }
    # Opcodes whose argument, decoded by pickletools, is the value to push: ints, floats,
    # str and bytes read from the file (so no larger than it). Not STRING: Python 2's quoted
    # text, which no OpenPCDet file holds and whose escapes Python 3 is deprecating.
    for name in (
        "INT", "BININT", "BININT1", "BININT2", "LONG", "LONG1", "LONG4", "FLOAT", "BINFLOAT",
        "BINSTRING", "SHORT_BINSTRING", "BINBYTES", "SHORT_BINBYTES", "BINBYTES8",
        "BYTEARRAY8", "UNICODE", "BINUNICODE", "SHORT_BINUNICODE", "BINUNICODE8",
    ):  # fmt: skip
        table[name] = m.op_push
    for name in ("GET", "BINGET", "LONG_BINGET"):
        table[name] = m.op_get
    for name in ("PUT", "BINPUT", "LONG_BINPUT"):
        table[name] = m.op_put
    return table


_HANDLERS = _handlers()

# What a corrupt file can raise from pickletools' decoding or numpy's checks of values we
# already validated (every other failure is an _Invalid of ours).
# DeprecationWarning: pickletools decodes a STRING's escapes before we can refuse the opcode,
# and warnings may be set to raise.
_DECODE_ERRORS = (
    ValueError, TypeError, OverflowError, KeyError, IndexError, struct.error, DeprecationWarning
)  # fmt: skip


def loads(data: bytes, source: str = "<bytes>") -> Any:
    """Rebuild the object pickled in ``data``, admitting only what infos files hold.

    Raises :class:`DataError` naming ``source``, the byte offset of the opcode at fault and what
    was refused, for a refused global, a malformed or truncated pickle, or one that asks for
    more memory than its size accounts for.
    """
    machine = _Machine(source, len(data))
    position, opcode = 0, "start"
    try:
        for op, arg, at in pickletools.genops(bytes(data)):
            position, opcode = at, op.name
            handler = _HANDLERS.get(opcode)
            if handler is None:
                raise _Invalid(f"opcode {opcode} is not allowed")
            if handler(machine, arg):  # True at STOP
                return machine.result
    except _Refused as exc:
        raise DataError(
            f"{source}: refused to load global {exc} at byte {position} (only numpy arrays, "
            "scalars, dtypes and builtin containers are allowed)"
        ) from None
    except _Invalid as exc:
        raise DataError(
            f"{source}: not a readable pickle: {exc} (byte {position}, {opcode})"
        ) from None
    except _DECODE_ERRORS as exc:
        raise DataError(
            f"{source}: not a readable pickle ({type(exc).__name__}: {exc}; after byte {position})"
        ) from None
    raise DataError(f"{source}: not a readable pickle (no STOP opcode)")  # pragma: no cover


def load(path: str | os.PathLike) -> Any:
    """Read the pickle file at ``path`` through the restricted reader (see :func:`loads`)."""
    path = Path(path)
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise DataError(f"{path}: cannot read ({exc.strerror or exc})") from exc
    return loads(data, source=str(path))
