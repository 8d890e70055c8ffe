import os
import pickle
import subprocess
import sys
import warnings
from pathlib import Path

import numpy as np
import pytest

from drcpo.database import safe_pickle
from drcpo.errors import DataError


class _Exploit:
    """Unpickling this calls ``os.system`` (if the loader lets it)."""

    def __init__(self, command: str) -> None:
        self.command = command

    def __reduce__(self):
        return (os.system, (self.command,))


class _Evaluator:
    def __reduce__(self):
        return (eval, ("1 + 1",))


def _payload():
    return {
        "Car": [
            {
                "name": np.str_("Car"),
                "box3d_lidar": np.arange(7, dtype=np.float64),
                "bbox": np.ones(4, dtype=np.float32),
                "difficulty": np.int32(-1),
                "score": np.float64(-1.0),
                "gt_idx": 3,
                "path": "gt_database/000001_Car_3.bin",
                "shape": (2, 3),
                "tags": {"a", "b"},
                "dtype": np.dtype("<U10"),
                "matrix": np.eye(3, dtype=np.float32)[::2],
                "empty": np.zeros((0, 4), np.float32),
                "strings": np.array(["Car", "Van"]),
                "complex": 1 + 2j,
                "raw": b"\x00\x01",
                "mutable": bytearray(b"xy"),
            }
        ]
    }


@pytest.mark.parametrize("protocol", [2, 3, 4, 5])
def test_numpy_and_builtins_round_trip(protocol):
    original = _payload()
    loaded = safe_pickle.loads(pickle.dumps(original, protocol=protocol))
    entry, expected = loaded["Car"][0], original["Car"][0]
    assert entry.keys() == expected.keys()
    for key, value in expected.items():
        if isinstance(value, np.ndarray):
            np.testing.assert_array_equal(entry[key], value)
            assert entry[key].dtype == value.dtype
        else:
            assert entry[key] == value
            assert type(entry[key]) is type(value)


def test_malicious_pickle_is_refused_and_never_executed(tmp_path):
    marker = tmp_path / "pwned"
    path = tmp_path / "kitti_dbinfos_train.pkl"
    path.write_bytes(pickle.dumps({"Car": [_Exploit(f"touch {marker}")]}))
    with pytest.raises(DataError) as error:
        safe_pickle.load(path)
    message = str(error.value)
    assert str(path) in message
    assert f"{os.system.__module__}.system" in message
    assert not marker.exists()


@pytest.mark.parametrize("protocol", [0, 2, 4])
def test_builtin_callables_outside_the_whitelist_are_refused(protocol):
    refused = r"x\.pkl: refused to load global (__builtin__|builtins)\.eval"
    with pytest.raises(DataError, match=refused):
        safe_pickle.loads(pickle.dumps(_Evaluator(), protocol=protocol), source="x.pkl")


def test_numpy_functions_outside_the_whitelist_are_refused():
    # numpy.load could itself unpickle a file; only array-rebuilding helpers are admitted.
    crafted = b"cnumpy\nload\n(S'/tmp/evil.npy'\ntR."
    with pytest.raises(DataError, match=r"infos\.pkl: refused to load global numpy\.load"):
        safe_pickle.loads(crafted, source="infos.pkl")


def test_corrupt_and_missing_files_name_the_file(tmp_path):
    path = tmp_path / "broken.pkl"
    path.write_bytes(pickle.dumps(_payload())[:50])
    with pytest.raises(DataError, match="broken.pkl: not a readable pickle"):
        safe_pickle.load(path)
    with pytest.raises(DataError, match="absent.pkl: cannot read"):
        safe_pickle.load(tmp_path / "absent.pkl")


def test_reads_the_openpcdet_sample(kitti_sample):
    dbinfos = safe_pickle.load(kitti_sample / "kitti_dbinfos_train.pkl")
    assert sorted(dbinfos) == ["Car", "Cyclist", "Misc", "Pedestrian", "Truck"]
    car = dbinfos["Car"][0]
    assert car["box3d_lidar"].shape == (7,)
    assert isinstance(car["num_points_in_gt"], int)
    infos = safe_pickle.load(kitti_sample / "kitti_infos_train.pkl")
    assert [info["point_cloud"]["lidar_idx"] for info in infos] == [f"{i:06d}" for i in range(6)]


def test_codecs_encode_is_admitted_only_for_latin1():
    crafted = b"c_codecs\nencode\n(Vabc\nVrot13\ntR."
    with pytest.raises(DataError, match="x.pkl: not a readable pickle"):
        safe_pickle.loads(crafted, source="x.pkl")
    assert safe_pickle.loads(b"c_codecs\nencode\n(Vab\nVlatin1\ntR.") == b"ab"


# Crafted and corrupted files ------------------------------------------------------------------
# numpy.scalar of a dtype '<U3' whose BUILD state carries flags 120 instead of numpy's 8: numpy
# would apply them and crash on the resulting object (protocol 0, 100 bytes).
FOREIGN_FLAGS = (
    b"cnumpy.core.multiarray\nscalar\n(cnumpy\ndtype\n(VU3\nI00\nI01\ntR(I3\nV<\nNNNI12\nI4\n"
    b"I120\ntbC\x0cC\x00\x00\x00a\x00\x00\x00r\x00\x00\x00tR."
)
# {((...((),)...),): 1}: a tuple 200,000 deep used as a dict key (hashing it recurses in C).
DEEP_KEY = b"\x80\x04}" + b")" + b"\x85" * 200_000 + b"K\x01s."
# bytearray(2**31): 34 bytes asking for 2 GiB.
BYTEARRAY_BOMB = b"c__builtin__\nbytearray\n(\x8a\x05\x00\x00\x00\x80\x00tR."

_ISOLATED = """
import resource, sys
from drcpo.database import safe_pickle
from drcpo.errors import DataError

if sys.argv[2] != "0":  # cap the address space: an allocation bomb fails instead of swapping
    with open("/proc/self/statm") as statm:
        used = int(statm.read().split()[0]) * resource.getpagesize()
    resource.setrlimit(resource.RLIMIT_AS, (used + int(sys.argv[2]), resource.RLIM_INFINITY))
try:
    loaded = safe_pickle.load(sys.argv[1])
    repr(loaded)
except DataError as exc:
    print("DataError:", exc)
else:
    print("loaded")
"""


def load_isolated(data: bytes, tmp_path, memory: int = 0) -> str:
    """Load ``data`` in a child process (a crash fails the test, not pytest); its one-line result.

    ``memory``: bytes the child may allocate beyond what it holds after importing (0: no cap).
    """
    path = tmp_path / "crafted.pkl"
    path.write_bytes(data)
    child = subprocess.run(
        [sys.executable, "-c", _ISOLATED, str(path), str(memory)],
        capture_output=True,
        text=True,
        timeout=300,
        env={**os.environ, "OPENBLAS_NUM_THREADS": "1"},
    )
    assert child.returncode == 0, f"child died (status {child.returncode}): {child.stderr[-2000:]}"
    return child.stdout.strip()


def test_foreign_dtype_flags_are_refused_not_applied(tmp_path):
    result = load_isolated(FOREIGN_FLAGS, tmp_path)
    assert result.startswith("DataError: ") and "crafted.pkl: not a readable pickle" in result
    assert "dtype <U3: flags 120 is not numpy's 8 (byte 82, BUILD)" in result


def test_corrupted_dtype_flags_in_the_openpcdet_sample(kitti_sample, tmp_path):
    data = bytearray((kitti_sample / "kitti_dbinfos_train.pkl").read_bytes())
    assert data[2318] == 0x08  # the flags of a '<U3' dtype (a Car's name)
    data[2318] = 0x78
    assert "flags 120 is not numpy's 8 (byte 2321, BUILD)" in load_isolated(bytes(data), tmp_path)


def test_deep_nesting_is_refused(tmp_path):
    result = load_isolated(DEEP_KEY, tmp_path)
    assert result.endswith("containers nested deeper than 64 (byte 67, TUPLE1)"), result
    nested = 1
    for _ in range(safe_pickle.MAX_DEPTH - 1):
        nested = [nested]
    assert safe_pickle.loads(pickle.dumps({"a": nested}))["a"] == nested  # 64 levels
    with pytest.raises(DataError, match="nested deeper than 64"):
        safe_pickle.loads(pickle.dumps({"a": [nested]}))


@pytest.mark.skipif(not Path("/proc/self/statm").exists(), reason="needs Linux /proc")
def test_allocation_bomb_is_refused_before_allocating(tmp_path):
    result = load_isolated(BYTEARRAY_BOMB, tmp_path, memory=1 << 30)
    assert "bytes()/bytearray() take bytes, got int 2147483648 (byte 32, REDUCE)" in result


@pytest.mark.parametrize(
    ("crafted", "message"),
    [
        # bytes(2**64): OverflowError in Python
        (b"c__builtin__\nbytes\n(\x8a\x09" + bytes(8) + b"\x01tR.", "bytearray() take bytes"),
        # numpy.dtype flags 63 (object): numpy raises RuntimeError
        (FOREIGN_FLAGS.replace(b"I120", b"I63"), "flags 63 is not numpy's 8"),
        # an array whose shape needs more bytes than given: numpy would raise ValueError
        (pickle.dumps(np.arange(3.0), protocol=2).replace(b"K\x03\x85", b"K\x09\x85"), "needs 72"),
        # protocol 5 array over a buffer claiming 2**40 bytes
        (b"\x80\x05\x96" + (1 << 40).to_bytes(8, "little") + b"ab.", "bytes in a bytearray8"),
        # set() of a list referenced many times: copies beyond the file's size
        (b"\x80\x04c__builtin__\nset\n\x94](" + b"K\x01" * 300 + b"e\x9400"
         + b"h\x00h\x01\x85R0" * 1000 + b"N.", "the file asks for more copies than its size"),
        (b"\x80\x04]\x94h\x00a.", "a container cannot be put inside itself"),
        (b"\x80\x04]\x94]\x94h\x00a0h\x01a.", "APPEND changes a container already placed"),
        (b"\x80\x04cnumpy\nndarray\n.", "global numpy.ndarray can only be called"),
        (b"\x80\x04cnumpy\ndtype\n(VO\ntR.", "is not a plain numeric, bool or str type"),
        (b"\x80\x04cnumpy\ndtype\n(Vf8\ntR(K\x03V<\nNNNJ\xff\xff\xff\xffJ\xff\xff\xff\xffK\x01"
         b"tb.", "flags 1 is not numpy's 0"),
        (b"\x80\x04h\x05.", "memo entry 5 was never stored"),
        # a 4000-byte int (too long for repr) as an array dimension
        (b"\x80\x04cnumpy.core.numeric\n_frombuffer\n(C\x00cnumpy\ndtype\n(Vf8\ntR\x8b\xa0\x0f"
         + b"\x00\x00" + b"\x01" * 4000 + b"\x85VC\ntR.", "bad dimension <an int of 31993 bits>"),
        (b"\x80\x04K\x01\x81.", "opcode NEWOBJ is not allowed"),
        (b"\x80\x04}]K\x01s.", "unhashable type: 'list'"),
    ],
)  # fmt: skip
def test_malformed_pickles_raise_data_error(crafted, message):
    with pytest.raises(DataError, match="^x.pkl: ") as error:
        safe_pickle.loads(crafted, source="x.pkl")
    assert message in str(error.value)


def test_same_result_as_pickle_on_numpy_edge_cases():
    payload = {
        "fortran": np.asfortranarray(np.arange(6.0).reshape(2, 3)),
        "big_endian": np.arange(4, dtype=">i4"),
        "strided": np.arange(12.0).reshape(3, 4)[:, ::2],
        "bool": np.array([True, False]),
        "bytes": np.array([b"ab", b"c"]),
        "empty_str": np.zeros(3, "U0"),
        "scalars": [np.float16(1.5), np.uint8(3), np.complex64(1j), np.bool_(True), np.str_("")],
        "nan": np.float64("nan"),
    }
    for protocol in range(6):
        data = pickle.dumps(payload, protocol=protocol)
        ours, theirs = safe_pickle.loads(data), pickle.loads(data)
        for key, value in theirs.items():
            if isinstance(value, np.ndarray):
                assert ours[key].dtype == value.dtype, (protocol, key)
                assert ours[key].flags.f_contiguous == value.flags.f_contiguous
                assert ours[key].flags.writeable
                np.testing.assert_array_equal(ours[key], value)
            elif key == "nan":
                assert type(ours[key]) is np.float64 and np.isnan(ours[key])
            else:
                assert ours[key] == value and [type(v) for v in ours[key]] == [
                    type(v) for v in value
                ]


def test_openpcdet_samples_load_as_pickle_loads_them(kitti_sample):
    # The sample is trusted: pickle.loads gives the reference to compare against.
    for name in ("kitti_dbinfos_train.pkl", "kitti_infos_train.pkl"):
        data = (kitti_sample / name).read_bytes()
        assert_same_tree(safe_pickle.loads(data), pickle.loads(data))


def assert_same_tree(ours, theirs):
    pending = [(ours, theirs)]
    while pending:
        a, b = pending.pop()
        assert type(a) is type(b)
        if isinstance(a, dict):
            assert list(a) == list(b)
            pending.extend((a[key], b[key]) for key in a)
        elif isinstance(a, (list, tuple)):
            assert len(a) == len(b)
            pending.extend(zip(a, b, strict=True))
        elif isinstance(a, (np.ndarray, np.generic)):
            assert a.dtype == b.dtype and np.shape(a) == np.shape(b)
            assert np.asarray(a).tobytes() == np.asarray(b).tobytes()
        else:
            assert a == b or (a != a and b != b)  # NaN equals NaN here


@pytest.mark.parametrize("action", ["ignore", "error"])
def test_python2_text_is_refused_whatever_the_warning_filters(action):
    # pickletools decodes the escapes of a STRING (deprecated: '\d') before it is refused.
    with warnings.catch_warnings():
        warnings.simplefilter(action)
        with pytest.raises(DataError, match=r"^x\.pkl: not a readable pickle"):
            safe_pickle.loads(b"S'\\d'\n.", source="x.pkl")
