"""The contracts every registered transform keeps, as one table: transforms x contracts.

The transforms come from the registry (:data:`TRANSFORMS`, what configs name), so a transform
registered later joins the table by itself, and fails there until :data:`MAKERS` says how to
build it: a transform is never left out silently.

Contracts, each on a small synthetic frame (ground, a wall, labelled objects; an intensity
column) that every transform changes:

* same seed, same output: bit-identical points, boxes, names, metadata and statistics (minus
  timings); another seed changes the output (the frame exercises the randomness);
* the :class:`Frame` and the OpenPCDet data-dict forms give the same result;
* config round trip: ``to_config()`` is plain JSON, and the transform it rebuilds is equal and
  gives the same output;
* empty frames (no points; no boxes; neither) are valid input and give a valid frame, with the
  point columns kept: a frame cut to the camera's field of view may hold no label, and a training
  loop must not stop on it (so a :class:`DataError` here would be a defect, not an option);
* extra point features (``(N, 3 + C)``, C = 0 and 3) keep the column count, and every original
  point in the output keeps its feature columns bit for bit;
* the input (the Frame's arrays and metadata, the dict and its arrays) is not modified;
* nuScenes-style frames (5 point columns: x, y, z, intensity, time lag; velocities per box)
  against a database of 5-column points with velocities: the original points keep their
  features bit for bit, inserted points carry the database's intensities and the key sweep's
  time lag (0), and the velocities stay one finite row per box.
"""

from __future__ import annotations

import dataclasses
import json
from collections.abc import Callable
from typing import Any

import numpy as np
import pytest
from test_pipeline import synthetic_database, synthetic_frame
from test_velocity import DB_INTENSITY, feature_database, feature_frame

from drcpo.frame import VELOCITY, Frame, validate_frame
from drcpo.index import IndexConfig
from drcpo.index_build import build_index
from drcpo.pipeline import build_pipeline
from drcpo.transforms import (
    DRCPO,
    TRANSFORMS,
    GlobalFlip,
    GlobalRotation,
    GlobalScaling,
    GroundTruthSampling,
    Transform,
    transform_from_config,
)

SEED = 3
#: How the table builds each registered transform from the shared world (database, index),
#: with parameters under which it changes the table's frame.
MAKERS: dict[str, Callable[[Any, Any], Transform]] = {
    "Compose": lambda db, index: build_pipeline("default", db, index, kind="drcpo"),
    "GlobalFlip": lambda db, index: GlobalFlip(probability=0.5, axes=("x", "y")),
    "GlobalRotation": lambda db, index: GlobalRotation(),
    "GlobalScaling": lambda db, index: GlobalScaling(),
    "GroundTruthSampling": lambda db, index: GroundTruthSampling(db),
    "DRCPO": lambda db, index: DRCPO(db, index),
}
REGISTERED = sorted(TRANSFORMS)


@pytest.fixture(scope="module")
def world():
    db = synthetic_database(np.random.default_rng(7), {"Car": 40, "Pedestrian": 20, "Cyclist": 10})
    return db, build_index(db, IndexConfig(k=10))


@pytest.fixture(scope="module")
def frame() -> Frame:
    return synthetic_frame(np.random.default_rng(5))


@pytest.fixture(scope="module", params=REGISTERED)
def made(request, world) -> Transform:
    name = request.param
    if name not in MAKERS:
        pytest.fail(f"transform {name!r} is registered but the contract table has no MAKERS entry")
    transform = MAKERS[name](*world)
    assert type(transform) is TRANSFORMS[name.partition("[")[0]]
    return transform


def rng(seed: int = SEED) -> np.random.Generator:
    return np.random.default_rng(seed)


def without_timings(value: Any) -> Any:
    """A comparable copy of ``value``: arrays as (dtype, shape, bytes), dataclasses and dicts
    as dicts, statistics' ``ms`` left out (timings differ between equal runs)."""
    if isinstance(value, np.ndarray):
        return ("array", value.dtype.str, value.shape, value.tobytes())
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        return (type(value).__name__, without_timings(dataclasses.asdict(value)))
    if isinstance(value, dict):
        return {k: without_timings(v) for k, v in value.items() if k != "ms"}
    if isinstance(value, list | tuple):
        return [without_timings(v) for v in value]
    return value


def assert_same_output(a: Frame, b: Frame) -> None:
    np.testing.assert_array_equal(a.points, b.points, strict=True)
    np.testing.assert_array_equal(a.boxes, b.boxes, strict=True)
    np.testing.assert_array_equal(a.names, b.names, strict=True)
    assert without_timings(a.metadata) == without_timings(b.metadata)


def test_every_registered_transform_is_in_the_table():
    registered = {name.partition("[")[0] for name in MAKERS}  # variants: "Name[variant]"
    assert registered == set(TRANSFORMS), "MAKERS must list exactly the registered transforms"


def test_same_seed_same_output(made, frame):
    first = made(frame, rng())
    assert_same_output(first, made(frame, rng()))
    assert not np.array_equal(first.boxes, frame.boxes) or len(first) != len(frame)
    others = [made(frame, rng(seed)) for seed in range(SEED + 1, SEED + 4)]
    moved = [
        not np.array_equal(first.points, o.points) or not np.array_equal(first.boxes, o.boxes)
        for o in others
    ]
    assert any(moved), "other seeds gave the same frame: the table's frame does not exercise it"


def test_frame_and_dict_forms_agree(made, frame):
    frame = frame.replace(metadata={**frame.metadata, "custom": ["kept"]})
    data = frame.to_dict()
    out = made(data, rng())
    assert isinstance(out, dict) and out["custom"] is data["custom"]
    from_frame = made(frame, rng())
    assert isinstance(from_frame, Frame)
    assert_same_output(Frame.from_dict(out), from_frame)


def test_config_round_trip(made, world, frame):
    db, index = world
    config = made.to_config()
    assert json.loads(json.dumps(config)) == config  # plain JSON types
    rebuilt = transform_from_config(config, database=db, index=index)
    assert type(rebuilt) is type(made) and rebuilt == made
    assert rebuilt.to_config() == config
    assert_same_output(rebuilt(frame, rng()), made(frame, rng()))


@pytest.mark.parametrize("empty", ["no points", "no boxes", "nothing"])
def test_empty_frames_give_valid_frames(made, frame, empty):
    points = frame.points[:0] if empty in ("no points", "nothing") else frame.points
    keep = 0 if empty in ("no boxes", "nothing") else len(frame.boxes)
    given = frame.replace(points=points, boxes=frame.boxes[:keep], names=frame.names[:keep])
    out = made(given, rng())
    validate_frame(out, f"{type(made).__name__} output ({empty})")
    assert out.points.shape[1] == frame.points.shape[1] and out.points.dtype == np.float32
    assert_same_output(out, made(given, rng()))


@pytest.mark.parametrize("features", [0, 3])
def test_extra_point_features_are_carried(made, frame, features):
    xyz = frame.points[:, :3]
    columns = [xyz]
    if features:
        # intensity, then the row number + 1 and a marker: database points carry zeros there
        row = np.arange(1, len(xyz) + 1, dtype=np.float32)
        columns += [frame.points[:, 3:4], row[:, None], np.full((len(xyz), 1), 7.0, np.float32)]
    given = frame.replace(points=np.column_stack(columns).astype(np.float32))
    out = made(given, rng())
    assert out.points.shape[1] == 3 + features and out.points.dtype == np.float32
    if features:
        original = out.points[:, 5] == 7.0
        assert original.any()
        rows = out.points[original, 4].astype(np.int64) - 1
        assert len(np.unique(rows)) == len(rows) and rows.min() >= 0 and rows.max() < len(xyz)
        np.testing.assert_array_equal(out.points[original, 3:], given.points[rows, 3:])
        assert (out.points[~original, 4:] == 0).all()


@pytest.mark.parametrize("form", ["Frame", "dict"])
def test_input_is_not_modified(made, frame, form):
    frame = frame.replace(metadata={**frame.metadata, "tags": ["a"]})
    data = frame if form == "Frame" else {**frame.to_dict(), "custom": {"x": [1]}}

    def fields() -> dict[str, Any]:
        return without_timings(dataclasses.asdict(data) if form == "Frame" else dict(data))

    before = fields()
    made(data, rng())
    after = fields()
    changed = sorted(k for k in before.keys() | after.keys() if before.get(k) != after.get(k))
    assert not changed, f"the input's {changed} changed"


@pytest.fixture(scope="module")
def feature_world():
    db = feature_database(np.random.default_rng(7))
    return db, build_index(db, IndexConfig(k=10))


@pytest.mark.parametrize("name", REGISTERED)
def test_five_feature_points_and_velocities_are_carried(name, feature_world):
    transform = MAKERS[name](*feature_world)
    frame = feature_frame(np.random.default_rng(5))
    out = transform(frame, rng())
    validate_frame(out, f"{name} output")
    assert out.points.shape[1] == 5 and out.points.dtype == np.float32
    velocity = out.metadata[VELOCITY]
    assert velocity.shape == (len(out.boxes), 2) and velocity.dtype == np.float64
    inserted = out.points[:, 3] >= DB_INTENSITY  # frame intensities are below 1
    # the frame's points: every feature bit for bit (intensity is unique per frame point)
    by_intensity = {float(v): r for r, v in enumerate(frame.points[:, 3])}
    rows = [by_intensity[float(v)] for v in out.points[~inserted, 3]]
    assert len(set(rows)) == len(rows)
    np.testing.assert_array_equal(out.points[~inserted, 3:], frame.points[rows, 3:])
    # inserted points: the database's intensities, the key sweep's time lag
    assert np.isin(out.points[inserted, 3], feature_world[0].points[:, 3]).all()
    assert (out.points[inserted, 4] == 0).all()
    inserts = name in ("Compose", "GroundTruthSampling") or name.startswith("DRCPO")
    assert inserted.any() == inserts
