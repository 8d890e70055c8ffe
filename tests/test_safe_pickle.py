import os
import pickle

import numpy as np
import pytest

from drcpo import safe_pickle
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
