"""A restricted reader for foreign infos pickles (OpenPCDet ``*_infos_*.pkl``, ``*_dbinfos_*``).

``pickle.load`` on a file from elsewhere runs arbitrary code, and even a pickle that names only
numpy's own helpers can crash the interpreter: numpy rebuilds a dtype's flags and an array's
memory from whatever the file says. So :func:`load` does not use :class:`pickle.Unpickler`. It
walks the opcodes (decoded by :func:`pickletools.genops`) with a small stack machine that knows
only what infos files hold: dicts, lists, tuples, sets, str, bytes, int, float, complex, bool,
None, numpy arrays and scalars of plain numeric, bool and string dtypes, and numpy dtypes.

The globals a file may name, and drcpo's own rebuilding of each (numpy objects from validated
plain values, never by numpy's ``__setstate__``), are in :mod:`~drcpo.database.pickle_globals`.
Nesting is bounded (:data:`MAX_DEPTH`), containers cannot be made recursive, and every copy the
file asks for is charged against a budget proportional to the file's size, so a few bytes cannot
claim gigabytes. Anything else stops the load with a :class:`~drcpo.errors.DataError` naming the
file, the byte offset and what was refused; no global named in the file is imported or called.
"""

from __future__ import annotations

import collections
import os
import pickletools
import struct
from collections.abc import Callable
from pathlib import Path
from typing import Any

from drcpo.database.pickle_globals import (
    ALLOWED_GLOBALS,
    _Global,
    _Invalid,
    _kind,
    _PendingArray,
    _PendingDtype,
)
from drcpo.errors import DataError

__all__ = ["MAX_DEPTH", "load", "loads"]

MAX_DEPTH = 64
"""Deepest nesting of containers accepted; OpenPCDet and MMDetection3D infos need under 10."""

# Bytes a pickle may make drcpo copy, per byte of file, plus a constant: each array's data
# is in the file once, at most twice counting protocol 0's latin-1 text form.
_BUDGET_PER_BYTE = 2
_BUDGET_SLACK = 1 << 16


class _Refused(Exception):
    """The pickle names a global outside :data:`~drcpo.database.pickle_globals.ALLOWED_GLOBALS`."""


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
