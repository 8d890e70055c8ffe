"""Input validation at the transform boundary (:func:`drcpo.frame.validate_frame`)."""

from __future__ import annotations

import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest
from test_pipeline import synthetic_database, synthetic_frame

from drcpo.errors import DataError
from drcpo.frame import DICT_FIELDS, Frame, validate_frame
from drcpo.index import IndexConfig
from drcpo.index_build import build_index
from drcpo.pipeline import build_pipeline
from drcpo.transforms import DRCPO, GlobalFlip, GlobalRotation, GlobalScaling, GroundTruthSampling

TESTS = Path(__file__).resolve().parent

# The audited crash: a NaN in a box's y reached the box-membership kernel of DR.CPO's
# sparse-originals check, which then wrote out of bounds (exit 139) on some seeds.
NAN_BOX_SCRIPT = """
import sys
import numpy as np
sys.path.insert(0, {tests!r})
from drcpo.errors import DataError
from drcpo.pipeline import build_pipeline
{setup}
box = np.array([[10.0, np.nan, -1.0, 4.0, 1.8, 1.6, 0.0]])
for seed in range(6):
    try:
        pipeline(frame.replace(boxes=box, names=np.array(["Car"])), np.random.default_rng(seed))
    except DataError as exc:
        print("DataError:", exc)
    else:
        print("accepted")
"""

SYNTHETIC_SETUP = """
from test_pipeline import synthetic_database
from drcpo.frame import Frame
from drcpo.index import IndexConfig
from drcpo.index_build import build_index
db = synthetic_database(np.random.default_rng(7), {"Car": 60, "Pedestrian": 30, "Cyclist": 20})
pipeline = build_pipeline("default", db, build_index(db, IndexConfig(k=20)))
rng = np.random.default_rng(0)
xyz = rng.uniform((0, -20, -1.7), (60, 20, 0), (5000, 3))
frame = Frame(np.column_stack([xyz, rng.uniform(0, 1, 5000)]).astype(np.float32))
"""

KITTI_SETUP = """
from drcpo.database.build import build_database
from drcpo.datasets.kitti import KittiDataset
from drcpo.index import IndexConfig
from drcpo.index_build import build_index
root, out = sys.argv[1], sys.argv[2]
db = build_database(root, "train", out)
build_index(db, IndexConfig(k=20)).save(out)
pipeline = build_pipeline("default", db)
frame = KittiDataset(root, "train").frame("000001")
"""


def _run_nan_box(setup: str, *args: str) -> subprocess.CompletedProcess:
    script = NAN_BOX_SCRIPT.format(tests=str(TESTS), setup=textwrap.dedent(setup))
    return subprocess.run(
        [sys.executable, "-c", script, *args], capture_output=True, text=True, timeout=600
    )


def test_nan_box_gives_a_data_error_not_a_segfault():
    # In a subprocess, so that a crash fails this test instead of killing the test run.
    result = _run_nan_box(SYNTHETIC_SETUP)
    assert result.returncode == 0, (result.returncode, result.stderr[-2000:])
    lines = result.stdout.splitlines()
    assert len(lines) == 6
    assert all("boxes row 0 holds a NaN" in line for line in lines), lines


def test_nan_box_on_the_kitti_sample(kitti_sample, tmp_path):
    result = _run_nan_box(KITTI_SETUP, str(kitti_sample), str(tmp_path / "db"))
    assert result.returncode == 0, (result.returncode, result.stderr[-2000:])
    lines = result.stdout.splitlines()
    assert lines and all("frame 000001: boxes row 0 holds a NaN" in x for x in lines), lines


# --------------------------------------------------------------------------------------------
# Every transform refuses bad frames, naming the field and the row
# --------------------------------------------------------------------------------------------
TRANSFORMS = ("flip", "rotation", "scaling", "gt_sampling", "drcpo", "cda", "drcpo_pipeline")


@pytest.fixture(scope="module")
def transforms():
    db = synthetic_database(np.random.default_rng(7), {"Car": 40, "Pedestrian": 20, "Cyclist": 10})
    index = build_index(db, IndexConfig(k=10))
    return dict(
        zip(
            TRANSFORMS,
            [
                GlobalFlip(probability=1.0),
                GlobalRotation(),
                GlobalScaling(),
                GroundTruthSampling(db),
                DRCPO(db, index),
                build_pipeline("default", db, index, kind="cda"),
                build_pipeline("default", db, index, kind="drcpo"),
            ],
            strict=True,
        )
    )


def _with(frame: Frame, **changes) -> Frame:
    return frame.replace(**changes)


def _bad_point(frame):
    points = frame.points.copy()
    points[7, 2] = np.nan
    return _with(frame, points=points)


def _inf_feature(frame):
    points = frame.points.copy()
    points[9, 3] = np.inf
    return _with(frame, points=points)


def _bad_box(value, column):
    def change(frame):
        boxes = frame.boxes.copy()
        boxes[1, column] = value
        return _with(frame, boxes=boxes)

    return change


BAD_FRAMES = {
    "nan_point": (_bad_point, r"points row 7 holds a NaN or infinite value: \[.*nan"),
    "inf_feature": (_inf_feature, r"points row 9 holds a NaN or infinite value: \[.*inf"),
    "nan_box_y": (_bad_box(np.nan, 1), r"boxes row 1 holds a NaN or infinite value"),
    "inf_heading": (_bad_box(np.inf, 6), r"boxes row 1 holds a NaN or infinite value"),
    "zero_width": (_bad_box(0.0, 4), r"boxes row 1 \(class 'Pedestrian'\) has a non-positive size"),
    "negative_length": (_bad_box(-2.0, 3), r"boxes row 1 .*non-positive size .*-2\.0"),
    "nan_plane": (
        lambda f: _with(f, metadata={**f.metadata, "plane": [0.0, -1.0, np.nan, 1.65]}),
        r"metadata plane must be 4 finite numbers",
    ),
}


@pytest.mark.parametrize("name", TRANSFORMS)
@pytest.mark.parametrize("bad", list(BAD_FRAMES))
def test_every_transform_refuses_bad_values(transforms, name, bad):
    frame = synthetic_frame(np.random.default_rng(3), objects=3)
    change, message = BAD_FRAMES[bad]
    broken = change(frame)
    with pytest.raises(DataError, match=r"^frame synthetic: " + message):
        transforms[name](broken, np.random.default_rng(0))
    # the dict form names OpenPCDet's keys
    with pytest.raises(DataError, match=message.replace("boxes", "gt_boxes")):
        transforms[name](broken.to_dict(), np.random.default_rng(0))


@pytest.mark.parametrize(
    ("data", "message"),
    [
        ({"points": np.zeros((5, 2), np.float32)}, r"points must have shape \(N, 3 \+ C\)"),
        ({"points": np.zeros(12, np.float32)}, r"points must have shape"),
        ({"points": np.array([["a", "b", "c"]])}, r"points: must hold real numbers, got dtype"),
        ({"points": np.zeros((3, 4), complex)}, r"points: must hold real numbers"),
        ({"points": np.zeros((3, 4), bool)}, r"points: must hold real numbers"),
        ({"points": [[1, 2, 3], [4, 5]]}, r"points: not a rectangular array"),
        (
            {"points": np.zeros((3, 4), np.float32), "gt_boxes": np.ones((2, 6))},
            r"boxes must have shape \(M, 7\)",
        ),
        (
            {"points": np.zeros((3, 4), np.float32), "gt_boxes": [["x"] * 7]},
            r"gt_boxes: must hold real numbers",
        ),
        (
            {
                "points": np.zeros((3, 4), np.float32),
                "gt_boxes": np.ones((2, 7)),
                "gt_names": np.array(["Car"]),
            },
            r"names must have shape \(2,\)",
        ),
        (
            {
                "points": np.zeros((3, 4), np.float32),
                "gt_boxes": np.ones((2, 7)),
                "gt_names": np.array([1, 2]),
            },
            r"names: must be strings",
        ),
        (
            {
                "points": np.zeros((3, 4), np.float32),
                "gt_boxes": np.ones((1, 7)),
                "gt_names": np.array([None], dtype=object),
            },
            r"names: must be strings",
        ),
    ],
)
@pytest.mark.parametrize("name", TRANSFORMS)
def test_every_transform_refuses_bad_shapes_and_dtypes(transforms, name, data, message):
    with pytest.raises(DataError, match=message):
        transforms[name](dict(data), np.random.default_rng(0))


@pytest.mark.parametrize(
    ("column", "value", "field"),
    [(0, 2e6, "points"), (2, -1e30, "points"), (1, 3e6, "boxes"), (4, 1e7, "boxes")],
)
def test_huge_coordinates_are_refused(column, value, field):
    frame = synthetic_frame(np.random.default_rng(3), objects=3)
    points, boxes = frame.points.copy(), frame.boxes.copy()
    (points if field == "points" else boxes)[2, column] = value
    with pytest.raises(DataError, match=rf"^frame synthetic: {field} row 2 holds a value beyond"):
        GlobalFlip()(frame.replace(points=points, boxes=boxes), np.random.default_rng(0))
    # large features are fine (only coordinates are bounded)
    points = frame.points.copy()
    points[:, 3] = 1e9
    assert len(GlobalFlip()(frame.replace(points=points), np.random.default_rng(0))) == len(points)


def test_huge_float64_points_overflowing_float32_are_refused():
    points = np.zeros((4, 4))
    points[2, 0] = 1e300  # finite in float64, inf once stored as float32
    with pytest.raises(DataError, match=r"points row 2 holds a NaN or infinite value"):
        GlobalRotation()({"points": points}, np.random.default_rng(0))


def test_valid_frames_pass_unchanged():
    frame = synthetic_frame(np.random.default_rng(3), objects=3)
    assert validate_frame(frame) is frame
    assert frame.validate() is frame
    assert (
        validate_frame(
            frame.replace(points=frame.points[:0], boxes=np.zeros((0, 7)), names=np.zeros(0, str))
        )
        is not None
    )
    names = np.array(["Car", "Pedestrian", "Cyclist"], dtype=object)
    assert Frame(frame.points, frame.boxes, names).names.dtype.kind == "U"
    with pytest.raises(DataError, match=r"^lidar 7: gt_boxes row 0"):
        bad = frame.boxes.copy()
        bad[0, 5] = -1
        validate_frame(frame.replace(boxes=bad), "lidar 7", DICT_FIELDS)
