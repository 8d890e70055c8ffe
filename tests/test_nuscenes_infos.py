"""OpenPCDet's and MMDetection3D's nuScenes infos: pickles written here (plain pickle, tests
only) from a synthetic nuScenes-style data set the way the frameworks' converters lay them out,
with the sweep transforms computed by naive 4x4 products from the JSON tables; read back they
give the frames the tables reader gives."""

from __future__ import annotations

import json
import math
import pickle
from pathlib import Path

import numpy as np
import pytest

from drcpo.datasets.nuscenes import NuScenesDataset
from drcpo.datasets.nuscenes_infos import MMDet3DNuScenesInfos, OpenPCDetNuScenesInfos
from drcpo.errors import DataError
from drcpo.synth.nuscenes import NuScenesSynthConfig, write_synthetic_nuscenes

VERSION = "v1.0-mini"
MAX_SWEEPS = 10  # OpenPCDet's default: the key sweep plus 9
MMDET3D_CLASSES = (
    "car",
    "truck",
    "trailer",
    "bus",
    "construction_vehicle",
    "bicycle",
    "motorcycle",
    "pedestrian",
    "traffic_cone",
    "barrier",
)


def quat_matrix(q) -> np.ndarray:
    w, x, y, z = np.asarray(q, dtype=np.float64) / np.linalg.norm(q)
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )


def homogeneous(record) -> np.ndarray:
    m = np.eye(4)
    m[:3, :3] = quat_matrix(record["rotation"])
    m[:3, 3] = record["translation"]
    return m


class Tables:
    def __init__(self, root: Path):
        def load(name):
            return {
                r["token"]: r for r in json.loads((root / VERSION / f"{name}.json").read_text())
            }

        self.sd, self.pose, self.calib = (
            load("sample_data"),
            load("ego_pose"),
            load("calibrated_sensor"),
        )
        self.key = {r["sample_token"]: t for t, r in self.sd.items() if r["is_key_frame"]}

    def lidar_to_global(self, sd):
        record = self.sd[sd]
        return homogeneous(self.pose[record["ego_pose_token"]]) @ homogeneous(
            self.calib[record["calibrated_sensor_token"]]
        )

    def earlier(self, sd, count):
        out = []
        while len(out) < count and self.sd[sd]["prev"]:
            sd = self.sd[sd]["prev"]
            out.append(sd)
        return out


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    root = tmp_path_factory.mktemp("infos") / "nuscenes"
    config = NuScenesSynthConfig(samples=3, sweeps_before=3)
    write_synthetic_nuscenes(root, 1, seed=11, config=config, version=VERSION)
    dataset = NuScenesDataset(root, VERSION, keep_empty=True)
    tables = Tables(root)
    pcdet, mmdet = [], []
    for token in dataset.frame_ids:
        frame = dataset.frame(token)
        pcdet.append(openpcdet_info(tables, token, frame))
        mmdet.append(mmdet3d_info(tables, token, frame))
    (root / "pcdet.pkl").write_bytes(pickle.dumps(pcdet))
    meta = {"categories": {c: i for i, c in enumerate(MMDET3D_CLASSES)}, "version": VERSION}
    (root / "mmdet.pkl").write_bytes(pickle.dumps({"metainfo": meta, "data_list": mmdet}))
    return root, dataset, pcdet, mmdet


def _with_an_ignored_box(frame):
    """The frame's boxes plus one of a category the frameworks map to ``ignore``, and a nan
    velocity on the first box (unknown, as the devkit gives it)."""
    boxes = np.concatenate([frame.boxes, [[1.0, 2.0, 0.0, 1.0, 1.0, 1.0, 0.0]]])
    velocity = np.concatenate([frame.metadata["velocity"], [[0.0, 0.0]]])
    velocity[0] = np.nan
    names = np.array([*frame.names.tolist(), "ignore"])
    points = np.array([*frame.metadata["num_points_in_gt"].tolist(), 5])
    return boxes, velocity, names, points


def openpcdet_info(tables: Tables, token: str, frame) -> dict:
    """As OpenPCDet's ``fill_trainval_infos`` lays a sample out."""
    key = tables.key[token]
    ref_time = 1e-6 * tables.sd[key]["timestamp"]
    to_key = np.linalg.inv(tables.lidar_to_global(key))
    sweeps = []
    for sd in tables.earlier(key, MAX_SWEEPS - 1):
        sweeps.append(
            {
                "lidar_path": tables.sd[sd]["filename"],
                "sample_data_token": sd,
                "transform_matrix": to_key @ tables.lidar_to_global(sd),
                "time_lag": ref_time - 1e-6 * tables.sd[sd]["timestamp"],
            }
        )
    if not sweeps:
        sweeps.append(
            {
                "lidar_path": tables.sd[key]["filename"],
                "sample_data_token": key,
                "transform_matrix": None,
                "time_lag": 0,
            }
        )
    while len(sweeps) < MAX_SWEEPS - 1:
        sweeps.append(sweeps[-1])
    boxes, velocity, names, points = _with_an_ignored_box(frame)
    return {
        "lidar_path": tables.sd[key]["filename"],
        "token": token,
        "sweeps": sweeps,
        "timestamp": ref_time,
        "gt_boxes": np.concatenate([boxes, velocity], axis=1),
        "gt_names": names,
        "num_lidar_pts": points,
        "num_radar_pts": np.zeros(len(points), dtype=np.int64),
    }


def mmdet3d_info(tables: Tables, token: str, frame) -> dict:
    """As MMDetection3D's converter and ``update_infos_to_v2.py`` lay a sample out."""
    key = tables.key[token]

    def poses(sd):
        record = tables.sd[sd]
        return (
            homogeneous(tables.pose[record["ego_pose_token"]]).tolist(),
            homogeneous(tables.calib[record["calibrated_sensor_token"]]).tolist(),
        )

    ego2global, lidar2ego = poses(key)
    sweeps = []
    for sd in tables.earlier(key, 10):
        e2g, l2e = poses(sd)
        sweeps.append(
            {
                "timestamp": tables.sd[sd]["timestamp"] / 1e6,
                "ego2global": e2g,
                "lidar_points": {
                    "lidar_path": "data/nuscenes/" + tables.sd[sd]["filename"],
                    "lidar2ego": l2e,
                },
                "sample_data_token": sd,
            }
        )
    boxes, velocity, names, points = _with_an_ignored_box(frame)
    instances = [
        {
            "bbox_3d": boxes[i].tolist(),
            "bbox_label_3d": MMDET3D_CLASSES.index(n) if n in MMDET3D_CLASSES else -1,
            "velocity": velocity[i].tolist(),
            "num_lidar_pts": np.int64(points[i]),
            "num_radar_pts": 0,
            "bbox_3d_isvalid": bool(points[i] > 0),
        }
        for i, n in enumerate(names)
    ]
    return {
        "sample_idx": 0,
        "token": token,
        "timestamp": tables.sd[key]["timestamp"] / 1e6,
        "ego2global": ego2global,
        "lidar_points": {
            "num_pts_feats": 5,
            "lidar_path": Path(tables.sd[key]["filename"]).name,
            "lidar2ego": lidar2ego,
        },
        "lidar_sweeps": sweeps,
        "instances": instances,
    }


def _readers(root):
    return {
        "openpcdet": lambda **kw: OpenPCDetNuScenesInfos(root / "pcdet.pkl", root, **kw),
        "mmdet3d": lambda **kw: MMDet3DNuScenesInfos(root / "mmdet.pkl", root, **kw),
    }


@pytest.mark.parametrize("kind", ["openpcdet", "mmdet3d"])
@pytest.mark.parametrize(("sweeps", "close"), [(0, 0.0), (4, 0.0), (9, 0.0), (9, 1.0)])
def test_infos_give_the_frames_the_tables_give(data, kind, sweeps, close):
    root, _, _, _ = data
    tables = NuScenesDataset(root, VERSION, sweeps=sweeps, remove_close=close)
    infos = _readers(root)[kind](sweeps=sweeps, remove_close=close)
    assert infos.frame_ids == tables.frame_ids
    for token in tables.frame_ids:
        ours, theirs = tables.frame(token), infos.frame(token)
        np.testing.assert_allclose(theirs.points[:, :4], ours.points[:, :4], atol=1e-4, rtol=0)
        np.testing.assert_allclose(theirs.points[:, 4], ours.points[:, 4], atol=1e-6, rtol=0)
        np.testing.assert_allclose(theirs.boxes, ours.boxes, atol=1e-9)
        assert theirs.names.tolist() == ours.names.tolist()  # 'ignore' dropped
        expected = ours.metadata["velocity"].copy()
        expected[:1] = 0.0  # the infos' nan: unknown
        np.testing.assert_allclose(theirs.metadata["velocity"], expected, atol=1e-9)
        assert theirs.metadata["num_points_in_gt"].tolist() == (
            ours.metadata["num_points_in_gt"].tolist()
        )
        for key in ("sweep_origins", "sweep_time_lags"):
            np.testing.assert_allclose(theirs.metadata[key], ours.metadata[key], atol=1e-6)
        lags = theirs.metadata["sweep_time_lags"]
        if sweeps:  # each point names its sweep exactly
            row = np.searchsorted(lags, theirs.points[:, 4])
            assert (lags[row] == theirs.points[:, 4]).all()
        assert theirs.metadata["point_features"] == ours.metadata["point_features"]


def test_openpcdet_repeats_are_joined_once(data):
    root, dataset, pcdet, _ = data
    first = pcdet[0]["sweeps"]
    assert len(first) == 9 and first[-1] is first[-2]  # the list was filled with repeats
    frame = OpenPCDetNuScenesInfos(root / "pcdet.pkl", root, sweeps=9).frame(dataset.frame_ids[0])
    assert len(frame.metadata["sweep_time_lags"]) == 4  # the key sweep and the 3 before it


def test_classes_and_empty_boxes(data):
    root, dataset, _, _ = data
    token = dataset.frame_ids[1]
    for make in _readers(root).values():
        everything = make(keep_empty=True).frame(token)
        cars = make(classes=["car"]).frame(token)
        assert set(cars.names) <= {"car"} and len(cars.boxes) < len(everything.boxes)
        points = everything.metadata["num_points_in_gt"]
        assert len(make().frame(token).boxes) == (points > 0).sum()


# Errors --------------------------------------------------------------------------------------
def _write(tmp_path, content) -> Path:
    path = tmp_path / "bad.pkl"
    path.write_bytes(pickle.dumps(content))
    return path


def _pcdet_error(tmp_path, data, edit, match, frame=True):
    root, _, pcdet, _ = data
    infos = [dict(info) for info in pcdet]
    edit(infos)
    path = _write(tmp_path, infos)
    with pytest.raises(DataError, match=match):
        reader = OpenPCDetNuScenesInfos(path, root, sweeps=3)
        if frame:
            reader.frame(reader.frame_ids[1])


@pytest.mark.parametrize(
    ("edit", "match"),
    [
        (lambda i: i.__setitem__(1, {**i[1], "token": 5}), r"sample 1 'token': expected a str"),
        (lambda i: i.__setitem__(1, {**i[1], "token": i[0]["token"]}), "appears twice"),
        (lambda i: i[1].pop("token"), "sample 1: key 'token' missing"),
        (lambda i: i.__setitem__(1, {**i[1], "gt_boxes": np.zeros((2, 5))}), r"expected \(N, 9\)"),
        (lambda i: i.__setitem__(1, {**i[1], "gt_boxes": i[1]["gt_boxes"] * np.nan}), "NaN"),
        (lambda i: i.__setitem__(1, {**i[1], "gt_names": i[1]["gt_names"][:-1]}), "class names"),
        (lambda i: i[1].pop("num_lidar_pts"), "'num_lidar_pts': expected"),
        (lambda i: i.__setitem__(1, {**i[1], "lidar_path": "/etc/x.bin"}), "inside the data root"),
        (lambda i: i.__setitem__(1, {**i[1], "lidar_path": "samples/none.bin"}), "cannot read"),
        (
            lambda i: i.__setitem__(
                1, {**i[1], "sweeps": [{**i[1]["sweeps"][0], "transform_matrix": np.eye(3)}]}
            ),
            r"sweeps\[0\] 'transform_matrix': expected a \(4, 4\)",
        ),
        (
            lambda i: i.__setitem__(1, {**i[1], "sweeps": [i[1]["sweeps"][1], i[1]["sweeps"][0]]}),
            "sweeps must go back in time",
        ),
        (
            lambda i: i.__setitem__(
                1, {**i[1], "sweeps": [{**i[1]["sweeps"][0], "time_lag": "1"}]}
            ),
            "'time_lag': expected a number",
        ),
    ],
)
def test_openpcdet_errors_name_the_sample_and_key(tmp_path, data, edit, match):
    _pcdet_error(tmp_path, data, edit, match)


@pytest.mark.parametrize(
    ("content", "match"),
    [
        ({"infos": []}, "expected a list of per-sample dicts"),
        ([1, 2], "expected a list of per-sample dicts"),
    ],
)
def test_openpcdet_wrong_files(tmp_path, content, match):
    with pytest.raises(DataError, match=match):
        OpenPCDetNuScenesInfos(_write(tmp_path, content), tmp_path)


def test_a_pickle_naming_code_is_refused(tmp_path):
    path = _write(tmp_path, [{"token": "a", "lidar_path": Path("x")}])
    with pytest.raises(DataError, match="bad.pkl"):
        OpenPCDetNuScenesInfos(path, tmp_path)


def test_an_unknown_frame_id_is_named(data):
    root = data[0]
    with pytest.raises(DataError, match=r"pcdet.pkl: no sample with token 'nope'"):
        OpenPCDetNuScenesInfos(root / "pcdet.pkl", root).frame("nope")


def _mmdet_error(tmp_path, data, edit, match):
    root, _, _, mmdet = data
    samples = [dict(s) for s in mmdet]
    meta = {"categories": {c: i for i, c in enumerate(MMDET3D_CLASSES)}}
    content = {"metainfo": meta, "data_list": samples}
    edit(content)
    path = _write(tmp_path, content)
    with pytest.raises(DataError, match=match):
        reader = MMDet3DNuScenesInfos(path, root, sweeps=3)
        reader.frame(reader.frame_ids[1])


def _instance(c, **change):
    sample = c["data_list"][1]
    sample["instances"] = [{**sample["instances"][0], **change}, *sample["instances"][1:]]


@pytest.mark.parametrize(
    ("edit", "match"),
    [
        (lambda c: c.pop("metainfo"), "expected MMDetection3D's v2 infos"),
        (lambda c: c["metainfo"].__setitem__("categories", {"car": "x"}), "is not a label"),
        (lambda c: c.__setitem__("data_list", {}), "'data_list': expected a list"),
        (lambda c: c["data_list"][1].pop("lidar_points"), "key 'lidar_points' missing"),
        (lambda c: c["data_list"][1].pop("ego2global"), "'ego2global': expected"),
        (lambda c: _instance(c, bbox_3d=[1.0, 2.0]), r"instances\[0\] 'bbox_3d': expected 7"),
        (lambda c: _instance(c, bbox_3d=[1, 2, 3, 0, 1, 1, 0]), "box 0 has a size <= 0"),
        (lambda c: _instance(c, velocity=[1.0]), r"instances\[0\] 'velocity': expected 2"),
        (lambda c: _instance(c, bbox_label_3d=None, bbox_label=None), "expected an integer label"),
        (lambda c: _instance(c, num_lidar_pts=-1), "counts >= 0"),
        (
            lambda c: c["data_list"][1].__setitem__("timestamp", float("nan")),
            "'timestamp': expected a finite number",
        ),
    ],
)
def test_mmdet3d_errors_name_the_sample_and_key(tmp_path, data, edit, match):
    _mmdet_error(tmp_path, data, edit, match)


def test_bad_arguments_are_named(data):
    root = data[0]
    with pytest.raises(DataError, match="sweeps must be an integer from 0 to 30"):
        OpenPCDetNuScenesInfos(root / "pcdet.pkl", root, sweeps=40)
    with pytest.raises(DataError, match="not among the nuScenes detection classes"):
        MMDet3DNuScenesInfos(root / "mmdet.pkl", root, classes=["Car"])


def test_sweeps_found_by_name_as_mmdet3d_finds_them(data):
    """Whatever directory the infos name (an absolute path of the converting machine here),
    the file is looked up by name under samples/ or sweeps/."""
    root, dataset, _, mmdet = data
    assert all(
        s["lidar_points"]["lidar_path"].startswith("data/") for s in mmdet[1]["lidar_sweeps"]
    )
    reader = MMDet3DNuScenesInfos(root / "mmdet.pkl", root, sweeps=10)
    frame = reader.frame(dataset.frame_ids[2])
    assert len(frame.metadata["sweep_time_lags"]) == 11
    assert math.isclose(frame.metadata["sweep_time_lags"][10], 0.5, abs_tol=1e-6)


def test_the_key_sweeps_path_is_relative_to_the_root(data):
    root, dataset, _, _ = data
    token = dataset.frame_ids[0]
    expected = dataset.frame(token).metadata["lidar_path"]
    for make in _readers(root).values():
        assert make().frame(token).metadata["lidar_path"] == expected
