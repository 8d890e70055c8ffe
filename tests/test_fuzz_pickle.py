"""Property-based fuzzing of the restricted pickle reader and of the dbinfos checks.

The only allowed outcomes for any input are a valid result (made only of the admitted types)
or a :class:`DataError` naming the source: never another exception, never a crash. The runs are
in-process (a crash would kill pytest, failing the run loudly); the known crashers run in a
child process in ``test_safe_pickle.py``.

Examples per test: ``DRCPO_FUZZ_EXAMPLES`` (default 200), e.g. ``DRCPO_FUZZ_EXAMPLES=20000
python -m pytest -q -s tests/test_fuzz_pickle.py`` for a long run; ``-s`` prints the outcome
counts per test.
"""

from __future__ import annotations

import collections
import pickle

import numpy as np
import pytest
from conftest import KITTI_SAMPLE
from fuzz_settings import FUZZ
from hypothesis import given
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp
from test_safe_pickle import assert_same_tree

from drcpo.database import safe_pickle
from drcpo.database.dbinfos import validate_dbinfos
from drcpo.database.pickle_globals import ALLOWED_GLOBALS
from drcpo.errors import DataError

SOURCE = "fuzz.pkl"
DBINFOS = KITTI_SAMPLE / "kitti_dbinfos_train.pkl"
OUTCOMES: dict[str, collections.Counter] = collections.defaultdict(collections.Counter)

_LEAVES = (str, bytes, bytearray, int, float, complex, bool, type(None), np.dtype)
_CONTAINERS = (dict, list, tuple, set, frozenset, collections.OrderedDict)


@pytest.fixture(scope="module", autouse=True)
def _report_outcomes():
    yield
    for test, counts in sorted(OUTCOMES.items()):
        print(f"\n{test}: {sum(counts.values())} cases, {dict(sorted(counts.items()))}")


def assert_plain(value) -> None:
    """``value`` holds only admitted types, nested at most ``MAX_DEPTH`` deep (no recursion)."""
    pending, seen = [(value, 0)], set()
    while pending:
        item, depth = pending.pop()
        assert depth <= safe_pickle.MAX_DEPTH
        if isinstance(item, np.ndarray):
            assert item.dtype.kind in "biufcUS" and item.flags.writeable and item.ndim <= 32
        elif isinstance(item, np.generic):
            assert item.dtype.kind in "biufcUS"
        elif isinstance(item, _CONTAINERS):
            assert id(item) not in seen or not isinstance(item, (list, dict, set)), "shared"
            seen.add(id(item))
            children = [*item.keys(), *item.values()] if isinstance(item, dict) else list(item)
            pending.extend((child, depth + 1) for child in children)
        else:
            assert isinstance(item, _LEAVES), type(item)


def outcome(test: str, data: bytes, check=None) -> str:
    """Load ``data``; ``valid`` or ``DataError`` (any other exception fails the test)."""
    try:
        value = safe_pickle.loads(data, source=SOURCE)
        assert_plain(value)
        if check is not None:
            check(value)
    except DataError as exc:
        assert str(exc).startswith(f"{SOURCE}: "), str(exc)
        result = "DataError"
    else:
        result = "valid"
    OUTCOMES[test][result] += 1
    return result


def _dbinfos_check(value) -> None:
    validate_dbinfos(value, SOURCE)


# Byte mutations -------------------------------------------------------------------------------
@st.composite
def mutated(draw, original: bytes) -> bytes:
    """``original`` with a few bytes replaced, inserted or deleted, perhaps truncated."""
    data = bytearray(original)
    for _ in range(draw(st.integers(1, 6))):
        kind = draw(st.sampled_from(["replace", "replace", "insert", "delete", "truncate"]))
        at = draw(st.integers(0, max(len(data) - 1, 0)))
        byte = draw(st.integers(0, 255))
        if kind == "replace" and data:
            data[at] = byte
        elif kind == "insert":
            data.insert(at, byte)
        elif kind == "delete" and data:
            del data[at]
        elif kind == "truncate":
            del data[at:]
    return bytes(data)


@pytest.mark.skipif(not DBINFOS.is_file(), reason=f"real OpenPCDet sample not found at {DBINFOS}")
@FUZZ
@given(data=st.data())
def test_mutated_openpcdet_dbinfos(data):
    original = DBINFOS.read_bytes()
    outcome("mutated dbinfos", data.draw(mutated(original)), check=_dbinfos_check)


# Synthetic pickles ----------------------------------------------------------------------------
_DTYPES = [
    np.dtype(name).newbyteorder(order)
    for name in ("?", "i1", "u1", "i2", "u4", "i8", "f2", "f4", "f8", "c8", "c16", "U3", "S2")
    for order in ("<", ">")
]


@st.composite
def numpy_values(draw):
    array = draw(hnp.arrays(st.sampled_from(_DTYPES), hnp.array_shapes(min_dims=0, max_dims=3)))
    choice = draw(st.sampled_from(["array", "fortran", "strided", "scalar"]))
    if choice == "fortran":
        return np.asfortranarray(array)
    if choice == "strided" and array.ndim:
        return array[::2]
    if choice == "scalar":
        return array[()] if array.ndim == 0 else array.reshape(-1)[:1].reshape(())[()]
    return array


_leaves = st.one_of(
    st.none(),
    st.booleans(),
    st.integers(),
    st.floats(),
    st.text(max_size=20),
    st.binary(max_size=20),
    numpy_values(),
)
payloads = st.recursive(
    _leaves,
    lambda inner: st.one_of(
        st.lists(inner, max_size=5),
        st.tuples(inner, inner),
        st.dictionaries(st.text(max_size=8), inner, max_size=5),
    ),
    max_leaves=15,
)


@FUZZ
@given(payload=payloads, protocol=st.integers(0, 5), data=st.data())
def test_synthetic_pickles_round_trip_and_survive_mutation(payload, protocol, data):
    pickled = pickle.dumps(payload, protocol=protocol)
    assert_same_tree(safe_pickle.loads(pickled), pickle.loads(pickled))
    outcome("mutated synthetic", data.draw(mutated(pickled)))


# Crafted opcode streams -----------------------------------------------------------------------
_GLOBALS = [f"c{module}\n{name}\n".encode() for module, name in ALLOWED_GLOBALS] + [
    b"cos\nsystem\n",
    b"cnumpy\nload\n",
    b"cbuiltins\neval\n",
    b"cnumpy.core.multiarray\n_reconstruct\n",
]
_OPCODES = [
    b"N", b"\x88", b"\x89", b"K\x05", b"K\x00", b"J\xff\xff\xff\xff", b"M\xff\xff",
    b"\x8a\x05\x00\x00\x00\x80\x00", b"\x8a\x09" + bytes(8) + b"\x01", b"G\x7f\xf8" + bytes(6),
    b"(", b"t", b"\x85", b"\x86", b"\x87", b")", b"]", b"}", b"\x8f", b"a", b"e", b"s", b"u",
    b"l", b"d", b"\x90", b"\x91", b"0", b"1", b"2", b"\x94", b"h\x00", b"h\x01", b"h\x02",
    b"q\x00", b"q\x01", b"R", b"b", b"\x81", b"\x92", b"\x97", b"\x98", b".",
    b"C\x00", b"C\x04abcd", b"C\x08" + bytes(8), b"C\x0cC\x00\x00\x00a\x00\x00\x00r\x00\x00\x00",
    b"\x8c\x02f8", b"\x8c\x02U3", b"\x8c\x01O", b"\x8c\x02V8", b"\x8c\x02M8", b"\x8c\x01<",
    b"\x8c\x01>", b"\x8c\x01|", b"\x8c\x01C", b"\x8c\x01F", b"\x8c\x06latin1", b"\x8c\x01b",
    b"\x8c\x05numpy", b"\x8c\x05dtype", b"\x93", b"VU3\n", b"I01\n", b"I3\n", b"I-1\n",
    b"\x96\x04\x00\x00\x00\x00\x00\x00\x00abcd", b"\x96\x00\x00\x00\x00\x00\x01\x00\x00",
]  # fmt: skip


@st.composite
def dtype_fragment(draw) -> bytes:
    """``numpy.dtype(typestr)`` with a BUILD state of drawn (often wrong) values, protocol 0."""
    typestr = draw(st.sampled_from(["f8", "i4", "U3", "S2", "b1", "O", "c16", "f16", "U0"]))
    order = draw(st.sampled_from(["<", ">", "|", "=", "x"]))
    sizes = st.one_of(st.sampled_from([-1, 0, 1, 4, 8, 12]), st.integers(-(2**40), 2**40))
    elsize, alignment = draw(sizes), draw(sizes)
    flags = draw(st.one_of(st.sampled_from([0, 8, 63, 120]), st.integers(-1, 2**16)))
    version = draw(st.sampled_from([3, 3, 4, 2]))
    return (
        f"cnumpy\ndtype\n(V{typestr}\nI00\nI01\ntR(I{version}\nV{order}\nNNN"
        f"I{elsize}\nI{alignment}\nI{flags}\ntb"
    ).encode()


@st.composite
def array_fragment(draw) -> bytes:
    """``_reconstruct`` + BUILD of a drawn shape, dtype and data length (often inconsistent)."""
    shape = draw(st.lists(st.one_of(st.integers(0, 4), st.integers(0, 2**63)), max_size=3))
    nbytes = draw(st.integers(0, 64))
    fortran = draw(st.sampled_from(["I00", "I01", "I2"]))
    dims = "".join(f"I{size}\n" for size in shape)
    return (
        b"cnumpy.core.multiarray\n_reconstruct\n(cnumpy\nndarray\n(I0\ntC\x01btR(I1\n("
        + dims.encode()
        + b"t"
        + draw(dtype_fragment())
        + fortran.encode()
        + b"\nC"
        + bytes([nbytes])
        + draw(st.binary(min_size=nbytes, max_size=nbytes))
        + b"tb"
    )


_fragments = st.one_of(
    st.sampled_from(_OPCODES), st.sampled_from(_GLOBALS), dtype_fragment(), array_fragment()
)


@FUZZ
@given(
    proto=st.sampled_from([b"", b"\x80\x02", b"\x80\x04", b"\x80\x05", b"\x80\x09"]),
    body=st.lists(_fragments, max_size=30),
)
def test_crafted_opcode_streams(proto, body):
    outcome("crafted", proto + b"".join(body) + b".")


# Field values of dbinfos records ----------------------------------------------------------------
def _record(index: int) -> dict:
    return {
        "name": np.str_("Car"),
        "path": f"gt_database/000000_Car_{index}.bin",
        "image_idx": "000000",
        "gt_idx": index,
        "box3d_lidar": np.array([1.0, 2.0, -1.0, 4.0, 1.8, 1.5, 0.3]),
        "num_points_in_gt": 12,
        "difficulty": np.int32(0),
        "bbox": np.array([1.0, 2.0, 30.0, 40.0], np.float32),
        "score": np.float64(-1.0),
    }


_field_values = st.one_of(
    _leaves,
    st.lists(
        st.one_of(st.integers(), st.floats(), st.just(10**400), st.text(max_size=3)), max_size=9
    ),
    st.sampled_from(["../x.bin", "/etc/passwd", "", "a/../../b", "000000", "Car", "Van"]),
    st.sampled_from([-1, 0, 2, 3, 2**31, -(2**63), 10**400, np.int64(-5), np.uint8(1), np.nan]),
)


@FUZZ
@given(
    field=st.sampled_from([*_record(0), "extra"]),
    value=_field_values,
    drop=st.booleans(),
    protocol=st.integers(0, 5),
)
def test_dbinfos_fields(field, value, drop, protocol):
    records = [_record(0), _record(1)]
    if drop and field in records[1]:
        del records[1][field]
    else:
        records[1][field] = value
    data = pickle.dumps({"Car": records}, protocol=protocol)
    outcome("dbinfos fields", data, check=_dbinfos_check)
