"""Property-based fuzzing of every transform on random and degenerate frames.

Each call either returns a valid frame of the input's kind (finite values, positive box sizes,
names matching boxes, the point columns kept) or raises :class:`DataError`, and raises it
exactly when the input is invalid; never a crash or another exception. Cases per test:
``DRCPO_FUZZ_EXAMPLES`` (``fuzz_settings.py``).
"""

from __future__ import annotations

import numpy as np
import pytest
from fuzz_settings import FUZZ
from hypothesis import given
from hypothesis import strategies as st
from test_pipeline import synthetic_database

from drcpo.errors import DataError
from drcpo.frame import MAX_COORDINATE, Frame
from drcpo.index import IndexConfig
from drcpo.index_build import build_index
from drcpo.pipeline import build_pipeline
from drcpo.transforms import DRCPO, GlobalFlip, GlobalRotation, GlobalScaling, GroundTruthSampling

NAMES = ("Car", "Pedestrian", "Cyclist", "Van", "DontCare", "")
LAYOUTS = ("scene", "identical", "origin", "far", "line", "dense", "empty")
BOX_LAYOUTS = ("scene", "stacked", "tiny", "large", "far", "around_sensor")
# Corruptions that make the input invalid (a DataError is due), and changes that keep it valid.
INVALID = (
    "nan_point",
    "inf_point",
    "nan_feature",
    "nan_box",
    "inf_box",
    "zero_size",
    "negative_size",
    "huge_point",
    "huge_box",
    "points_2_columns",
    "points_1d",
    "boxes_6_columns",
    "names_short",
    "names_numeric",
    "points_strings",
    "points_complex",
    "nan_plane",
)
VALID = ("float64_points", "int_points", "float16_points", "boxes_8_columns", "big_features")
TRANSFORMS = ("flip", "rotation", "scaling", "gt_sampling", "drcpo", "cda", "drcpo_pipeline")
#: Seconds for their 200 cases on 2 cores: left out of the quick subset (``-m "not slow"``).
SLOW = ("drcpo", "drcpo_pipeline")


@pytest.fixture(scope="module")
def transforms():
    db = synthetic_database(np.random.default_rng(7), {"Car": 40, "Pedestrian": 20, "Cyclist": 10})
    index = build_index(db, IndexConfig(k=10))
    made = [
        GlobalFlip(probability=0.5, axes=("x", "y")),
        GlobalRotation(),
        GlobalScaling(),
        GroundTruthSampling(db),
        DRCPO(db, index),
        build_pipeline("default", db, index, kind="cda"),
        build_pipeline("default", db, index, kind="drcpo"),
    ]
    return dict(zip(TRANSFORMS, made, strict=True))


def _points(layout: str, rng: np.random.Generator, n: int, columns: int) -> np.ndarray:
    if layout == "empty":
        n = 0
    xyz = np.column_stack(
        [rng.uniform(0, 70, n), rng.uniform(-40, 40, n), rng.uniform(-1.8, 1.5, n)]
    )
    if layout == "identical":
        xyz[:] = xyz[:1] if n else xyz
    elif layout == "origin":
        xyz[:] = 0.0
    elif layout == "far":
        xyz *= rng.uniform(10, 0.9 * MAX_COORDINATE / 70)
    elif layout == "line":
        xyz = np.outer(rng.uniform(1, 50, n), [1.0, 0.2, -0.03])
    elif layout == "dense":
        xyz = rng.normal(0, 0.01, (n, 3)) + np.array([8.0, 1.0, -1.0])
    features = rng.uniform(0, 1, (n, columns - 3))
    return np.column_stack([xyz, features]).astype(np.float32)


def _boxes(layout: str, rng: np.random.Generator, m: int) -> np.ndarray:
    centre = np.column_stack([rng.uniform(2, 60, m), rng.uniform(-30, 30, m), np.full(m, -0.9)])
    size = rng.uniform(0.3, 5.0, (m, 3))
    heading = rng.uniform(-10, 10, (m, 1))
    if layout == "stacked":
        centre[:] = [10.0, 0.0, -0.9]
    elif layout == "tiny":
        size = rng.uniform(1e-6, 1e-3, (m, 3))
    elif layout == "large":
        size = rng.uniform(50, 500, (m, 3))
    elif layout == "far":
        centre *= rng.uniform(10, 0.9 * MAX_COORDINATE / 60)
    elif layout == "around_sensor":
        centre[:] = 0.0
    return np.column_stack([centre, size, heading])


def _corrupt(change: str | None, rng: np.random.Generator, frame: dict) -> tuple[dict, bool]:
    points, boxes = frame["points"], frame["gt_boxes"]
    n, m = len(points), len(boxes)
    if change in ("nan_point", "inf_point", "huge_point") and n:
        value = {"nan_point": np.nan, "inf_point": -np.inf, "huge_point": 3e6}[change]
        points[rng.integers(n), rng.integers(3)] = value
    elif change == "nan_feature" and n and points.shape[1] > 3:
        points[rng.integers(n), 3] = np.nan
    elif change in ("nan_box", "inf_box", "huge_box") and m:
        value = {"nan_box": np.nan, "inf_box": np.inf, "huge_box": -2e6}[change]
        boxes[rng.integers(m), rng.integers(7)] = value
    elif change in ("zero_size", "negative_size") and m:
        boxes[rng.integers(m), 3 + rng.integers(3)] = 0.0 if change == "zero_size" else -1.0
    elif change == "points_2_columns":
        frame["points"] = points[:, :2]
    elif change == "points_1d":
        frame["points"] = points.reshape(-1)
    elif change == "boxes_6_columns" and m:
        frame["gt_boxes"] = boxes[:, :6]
    elif change == "names_short" and m:
        frame["gt_names"] = frame["gt_names"][:-1]
    elif change == "names_numeric" and m:
        frame["gt_names"] = np.arange(m)
    elif change == "points_strings":
        frame["points"] = points.astype(str)
    elif change == "points_complex":
        frame["points"] = points.astype(complex)
    elif change == "nan_plane":
        frame["plane"] = np.array([0.0, -1.0, 0.0, np.nan])
    elif change == "float64_points":
        frame["points"] = points.astype(np.float64)
    elif change == "int_points":
        frame["points"] = np.round(points).astype(np.int32)
    elif change == "float16_points":
        with np.errstate(over="ignore"):
            frame["points"] = points.astype(np.float16)
        return frame, not np.isfinite(frame["points"]).all()  # beyond 65504 m: inf
    elif change == "boxes_8_columns":  # OpenPCDet's class column: cut off
        frame["gt_boxes"] = np.column_stack([boxes, np.ones(m)])
    elif change == "big_features" and points.shape[1] > 3:
        points[:, 3:] = 1e20
    else:
        return frame, False  # the change does not apply to this frame: it stays valid
    return frame, change in INVALID


@st.composite
def frames(draw):
    rng = np.random.default_rng(draw(st.integers(0, 2**32 - 1)))
    n = draw(st.sampled_from([0, 1, 3, 50, 400, 3000]))
    columns = draw(st.integers(3, 5))
    m = draw(st.integers(0, 6))
    frame = {
        "points": _points(draw(st.sampled_from(LAYOUTS)), rng, n, columns),
        "gt_boxes": _boxes(draw(st.sampled_from(BOX_LAYOUTS)), rng, m),
        "gt_names": np.array([NAMES[i] for i in rng.integers(0, len(NAMES), m)], dtype=str),
        "frame_id": "fuzz",
    }
    if draw(st.booleans()):
        frame["plane"] = np.array([0.0, -1.0, 0.0, 1.73])  # flat road 1.73 m below the sensor
    change = draw(st.sampled_from([None] * 4 + list(INVALID) + list(VALID)))
    frame, invalid = _corrupt(change, rng, frame)
    return frame, invalid, draw(st.booleans()), change


def _check_outcome(transform, case, seed: int) -> None:
    data, invalid, as_dict, change = case
    if as_dict:
        given_data = data
    else:
        try:
            given_data = Frame.from_dict(data)
        except DataError:
            assert invalid, change  # a valid input must make a frame
            return
    if invalid:
        with pytest.raises(DataError):
            transform(given_data, np.random.default_rng(seed))
        return
    out = transform(given_data, np.random.default_rng(seed))
    frame = Frame.from_dict(out) if as_dict else out
    assert isinstance(out, dict) == as_dict
    # validate_frame's checks but its coordinate limit (a rotated or scaled frame near it
    # may pass it: the limit guards inputs)
    assert np.isfinite(frame.points).all() and np.isfinite(frame.boxes).all()
    assert (frame.boxes[:, 3:6] > 0).all()
    assert frame.points.dtype == np.float32
    assert frame.points.shape[1] == np.asarray(data["points"]).shape[1]
    assert frame.names.shape == (len(frame.boxes),)


@pytest.mark.parametrize(
    "name", [pytest.param(n, marks=pytest.mark.slow) if n in SLOW else n for n in TRANSFORMS]
)
def test_transform_returns_a_valid_frame_or_a_data_error(transforms, name):
    @FUZZ
    @given(case=frames(), seed=st.integers(0, 2**16))
    def run(case, seed):
        _check_outcome(transforms[name], case, seed)

    run()
