"""The ``realistic`` preset end to end (DR.CPO's sensor-true steps, issue 14) and the ``paper``
preset's promise: today's behaviour, bit for bit.

Figures against the synthetic world's ray-cast truth are the business of
``benchmarks/bench_realism.py``; these tests check the invariants each step must keep on every
frame, each of which fails without the step.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from test_pipeline import synthetic_world  # noqa: F401  (a fixture)

from drcpo.config import load_config, to_dict
from drcpo.frame import Frame
from drcpo.geometry import points_in_boxes
from drcpo.pipeline import build_pipeline
from drcpo.sensor import sensor_preset
from drcpo.transforms import DRCPO
from drcpo.transforms.insertion import BOX_SOURCE

SEEDS = (0, 1)
# metres beyond an object's box that its surface elements may reach: a sampled object's points
# count as its own up to 0.2 m outside its box, each an element of radius <= 0.15 m
_ELEMENT = 0.35


def _realistic(db, index, **changes):
    config = to_dict(load_config("realistic").drcpo)
    for key, value in changes.items():
        section, name = key.split(".")
        config[section][name] = value
    return DRCPO(db, index, config)


@pytest.fixture(scope="module")
def realistic_runs(synthetic_world):  # noqa: F811
    db, index, frames = synthetic_world
    pipeline = build_pipeline("realistic", db, index=index, kind="drcpo")
    stages = pipeline.transforms
    runs = []
    for i, frame in enumerate(frames):
        for seed in SEEDS:
            rng = np.random.default_rng([seed, i])
            sampled = stages[0](frame, rng)  # ground-truth sampling
            out = stages[1](sampled, rng)  # DR.CPO
            runs.append((frame, sampled, out))
    return runs


def test_paper_preset_is_todays_default(synthetic_world):  # noqa: F811
    db, index, frames = synthetic_world
    assert to_dict(load_config("paper")) == to_dict(load_config(None))
    paper = build_pipeline("paper", db, index=index)
    default = build_pipeline("default", db, index=index)
    for seed in SEEDS:
        a = paper(frames[0], np.random.default_rng(seed))
        b = default(frames[0], np.random.default_rng(seed))
        assert np.array_equal(a.points, b.points) and np.array_equal(a.boxes, b.boxes)


def _drcpo_boxes(out: Frame) -> np.ndarray:
    return np.asarray(out.metadata[BOX_SOURCE]) == "drcpo"


def test_inserted_points_lie_on_the_frames_scan_lines(realistic_runs):
    """Rendered through the sensor estimated from the frame (``auto``), the inserted points lie
    on the synthetic sensor's true beams (its elevations: the ``hdl64e`` preset)."""
    true_sensor = sensor_preset("hdl64e")
    on_beam, total = 0, 0
    for _, _, out in realistic_runs:
        inside = points_in_boxes(out.points, out.boxes[_drcpo_boxes(out)]).any(axis=1)
        xyz = out.points[inside, :3].astype(np.float64)
        elevation = np.arctan2(xyz[:, 2], np.hypot(xyz[:, 0], xyz[:, 1]))
        miss = np.abs(elevation[:, None] - true_sensor.elevations[None, :]).min(axis=1)
        on_beam += int((miss < math.radians(0.1)).sum())
        total += len(xyz)
    assert total > 500
    assert on_beam / total >= 0.98


def _crosses(points: np.ndarray, boxes: np.ndarray) -> np.ndarray:
    """``bool (N,)``: the segment from the origin to each point passes through one of
    ``boxes`` before reaching it (sampled every 5 cm: a naive reference)."""
    out = np.zeros(len(points), dtype=bool)
    if len(boxes) == 0:
        return out
    for k, p in enumerate(points[:, :3].astype(np.float64)):
        length = float(np.linalg.norm(p))
        t = np.arange(0.5, max(length - 0.15, 0.5), 0.05) / length
        out[k] = points_in_boxes(t[:, None] * p[None, :], boxes, margin=_ELEMENT).any()
    return out


def test_original_points_go_only_behind_inserted_objects(realistic_runs):
    """Every original point removed has an inserted box (DR.CPO's or ground-truth
    sampling's) on its ray in front of it: nothing visible is deleted."""
    removed_total = 0
    for _, sampled, out in realistic_runs:
        added = np.asarray(sampled.metadata[BOX_SOURCE]) != ""
        own = ~points_in_boxes(sampled.points, sampled.boxes[added], margin=0.2).any(axis=1)
        kept = {row.tobytes() for row in np.ascontiguousarray(out.points)}
        originals = sampled.points[own]
        removed = np.array([row.tobytes() not in kept for row in originals])
        removed_total += int(removed.sum())
        inserted = out.boxes[np.asarray(out.metadata[BOX_SOURCE]) != ""]
        assert _crosses(originals[removed], inserted).all()
    assert removed_total > 0


def test_each_added_object_is_seen_and_stands_on_observed_ground(realistic_runs):
    for _, _, out in realistic_runs:
        stats = out.metadata["augment_stats"]
        added = sum(c["added"] for c in stats["objects"]["drcpo"].values())
        boxes = out.boxes[_drcpo_boxes(out)]
        assert len(boxes) == added > 0
        counts = points_in_boxes(out.points, boxes).sum(axis=0)
        assert (counts >= load_config("realistic").drcpo.min_points_after).all()
        assert stats["sensor"]["model"] == "auto" and stats["sensor"]["fallback"] == ""


def test_radius_share_caps_the_rendered_elements(synthetic_world):  # noqa: F811
    """``self_occlusion.radius_share``: a person-sized object is rendered with its elements
    clipped at the share of its box's width (the preset's 0.09 x 0.6 m), fewer rays hitting
    its thin silhouette than with the plain 15 cm clip."""
    from drcpo.occlusion.render import render_object
    from drcpo.transforms.insertion import placed_object

    db, index, _ = synthetic_world
    capped = _realistic(db, index)
    plain = _realistic(db, index, **{"self_occlusion.radius_share": None})
    assert capped.config.self_occlusion.radius_share == 0.09
    rng = np.random.default_rng(5)
    canonical = np.column_stack(
        [rng.uniform(-0.5, 0.5, (150, 3)) * [0.8, 0.6, 1.7], rng.uniform(0, 1, 150)]
    ).astype(np.float32)
    box = np.array([9.0, 3.0, -0.9, 0.8, 0.6, 1.7, 0.4])
    sensor = sensor_preset("hdl64e")
    points, _ = capped._object_s_hpr(canonical, box, 4, sensor, 7)
    placed = placed_object(canonical, box, 4)
    expected, _ = render_object(placed, sensor, np.random.default_rng(7), max_radius=0.054)
    np.testing.assert_array_equal(points, expected)
    wide, _ = plain._object_s_hpr(canonical, box, 4, sensor, 7)
    assert 0 < len(points) < len(wide)


def test_the_sensor_true_steps_see_the_frame_without_added_objects(synthetic_world):  # noqa: F811
    """The sensor and the ground are estimated from the frame's own points: those of an object
    an earlier stage added (within 0.2 m of its box) are left out, and where an estimate
    cannot be made the model's base sensor is used, the reason recorded."""
    from drcpo.sensor_config import SensorConfig
    from drcpo.transforms.sensor_steps import frame_sensor, own_points

    _, _, frames = synthetic_world
    frame = frames[0]
    assert own_points(frame) is frame.points  # nothing added: the frame's own array
    car_box = np.array([20.0, 0.0, -0.95, 4.0, 1.8, 1.5, 0.0])
    xs, ys = np.meshgrid(np.linspace(18.0, 22.0, 30), np.linspace(-0.9, 0.9, 12))
    car = np.column_stack([xs.ravel(), ys.ravel(), np.full(xs.size, -0.3), np.zeros(xs.size)])
    sources = np.concatenate([np.full(len(frame.boxes), ""), ["gt_sampling"]]).astype("<U11")
    made = Frame(
        np.concatenate([frame.points, car]).astype(np.float32),
        np.concatenate([frame.boxes, car_box[None]]),
        np.concatenate([frame.names, ["Car"]]),
        {**frame.metadata, BOX_SOURCE: sources},
    )
    outside = ~points_in_boxes(made.points, car_box[None], margin=0.2)[:, 0]
    np.testing.assert_array_equal(own_points(made), made.points[outside])
    sensor, used = frame_sensor(own_points(made), SensorConfig(model="auto"))
    assert used["fallback"] == "" and used["beams"] == sensor.num_beams
    sparse, used = frame_sensor(made.points[:20], SensorConfig(model="auto"))
    assert used["fallback"] and sparse.num_beams == sensor_preset("hdl64e").num_beams
