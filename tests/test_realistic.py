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


def test_hidden_ground_truth_sampled_objects_are_dropped(synthetic_world):  # noqa: F811
    """An object that ground-truth sampling put behind a wall the sensor saw is occluded
    like DR.CPO's: it loses its points and its label (the paper's e-HPR would keep it)."""
    db, index, frames = synthetic_world
    frame = frames[0]
    paper = build_pipeline("paper", db, index=index, kind="drcpo").transforms[1]
    # a wall of returns 10 m ahead (dense enough to return on every ray), and an "added" car
    # 20 m ahead right behind it
    made, car_box = _walled_car(frame)
    # (the frame's sensor by name: the wall and car appended out of scan order are no sweep)
    out = _realistic(db, index, **{"sensor.model": "hdl64e"})(made, np.random.default_rng(0))
    assert not np.any(np.all(np.isclose(out.boxes, car_box), axis=1))
    assert points_in_boxes(out.points, car_box[None]).sum() == 0
    # the paper's scope-inserted e-HPR decides only DR.CPO's own objects: it keeps the car
    kept = paper(made, np.random.default_rng(0))
    assert np.any(np.all(np.isclose(kept.boxes, car_box), axis=1))


def _walled_car(frame: Frame, wall_height: float = 2.5) -> tuple[Frame, np.ndarray]:
    """``frame`` with a wall of returns 10 m ahead (``wall_height`` metres from z = -1.5) and
    a ground-truth-sampled car right behind it (20 m ahead), and the car's box."""
    ys, zs = np.meshgrid(np.linspace(-3, 3, 300), np.linspace(-1.5, -1.5 + wall_height, 125))
    wall = np.column_stack([np.full(ys.size, 10.0), ys.ravel(), zs.ravel(), np.zeros(ys.size)])
    car_box = np.array([20.0, 0.0, -0.95, 4.0, 1.8, 1.5, 0.0])
    xs, ys2 = np.meshgrid(np.linspace(18.0, 22.0, 30), np.linspace(-0.9, 0.9, 12))
    car = np.column_stack([xs.ravel(), ys2.ravel(), np.full(xs.size, -0.3), np.zeros(xs.size)])
    points = np.concatenate([frame.points, wall, car]).astype(np.float32)
    sources = np.concatenate([np.full(len(frame.boxes), ""), ["gt_sampling"]]).astype("<U11")
    made = Frame(
        points,
        np.concatenate([frame.boxes, car_box[None]]),
        np.concatenate([frame.names, ["Car"]]),
        {**frame.metadata, BOX_SOURCE: sources},
    )
    return made, car_box


def _cell_rule_kept(made: Frame, car_box: np.ndarray, sensor) -> int:
    """Naive reference of the cell rule: per point of the added car (within 0.2 m of its
    box), the nearest return of another owner in its ray cell (a dict of cells); the car's
    points left in its box."""
    owner = np.where(points_in_boxes(made.points, car_box[None], margin=0.2)[:, 0], 0, -1)
    beam, column, _ = sensor.cells(made.points)
    cells: dict = {}
    for i in np.flatnonzero(beam >= 0):
        d = np.asarray(made.points[i, :3], np.float64) - sensor.mount
        d[2] -= sensor.offsets[beam[i]]
        cells.setdefault((beam[i], column[i]), []).append((float(np.sqrt(d @ d)), owner[i], i))
    removed = np.zeros(len(made.points), dtype=bool)
    for entries in cells.values():
        for dist, own, i in entries:
            if own >= 0:
                removed[i] = any(o != own and r < dist - 0.1 for r, o, _ in entries)
    return int(points_in_boxes(made.points[~removed], car_box[None]).sum())


def test_hidden_added_objects_go_before_placement(synthetic_world):  # noqa: F811
    """``placement.drop_hidden_added``: an added object the frame's returns leave with too few
    points is dropped, box and points, before DR.CPO places (against a naive reference of the
    cell rule and a per-box count); the rest of the frame stays as it was."""
    from drcpo.sensor_config import SensorConfig
    from drcpo.transforms.sensor_steps import SensorFrame

    db, index, frames = synthetic_world
    for wall_height, hidden in ((2.5, True), (0.3, False)):  # (a low wall hides nothing)
        made, car_box = _walled_car(frames[0], wall_height)
        seen = SensorFrame(made, SensorConfig(model="hdl64e"))
        kept = _cell_rule_kept(made, car_box, seen.sensor)
        assert (kept < 5) == hidden
        assert seen.hidden_added(5).tolist() == [hidden]
    made, car_box = _walled_car(frames[0])
    seen = SensorFrame(made, SensorConfig(model="hdl64e"))
    owner = np.where(points_in_boxes(made.points, car_box[None], margin=0.2)[:, 0], 0, -1)
    pruned, gone = seen.without_hidden_added(5)
    assert gone.tolist() == ["Car"]
    assert np.array_equal(pruned.frame.boxes, frames[0].boxes)
    assert np.array_equal(pruned.frame.points, made.points[owner < 0])
    assert pruned.sensor is seen.sensor and pruned.ground is seen.ground
    # nothing hidden: the same SensorFrame back
    assert seen.without_hidden_added(0)[0] is seen
    # in the transform: the car's label counted as dropped, its box and points gone
    drop = _realistic(db, index, **{"sensor.model": "hdl64e", "placement.drop_hidden_added": True})
    out = drop(made, np.random.default_rng(0))
    assert out.metadata["augment_stats"]["labels_dropped"].get("Car", 0) >= 1
    assert not np.any(np.all(np.isclose(out.boxes, car_box), axis=1))
    assert (
        points_in_boxes(out.points, car_box[None]).sum() == 0
        or np.isin(np.asarray(out.metadata[BOX_SOURCE]), ["drcpo"]).any()
    )


def test_unplaced_objects_displace_added_ones(synthetic_world):  # noqa: F811
    """``placement.displace_attempts``: objects the first pass left unplaced get a second pass
    through ground-truth sampling's objects; those whose box meets a box placed there go
    (box and points; against a naive reference: every pair's exact overlap area), the
    others and the frame's own boxes are never overlapped."""
    from drcpo.geometry import bev_overlap_area
    from drcpo.placement import REASONS, PlacementResult
    from drcpo.sensor_config import SensorConfig
    from drcpo.transforms.sensor_steps import SensorFrame, displace_added

    db, index, frames = synthetic_world
    gt = build_pipeline("realistic", db, index=index, kind="drcpo").transforms[0]
    sampled = gt(frames[0], np.random.default_rng(5))
    seen = SensorFrame(sampled, SensorConfig(model="hdl64e"))
    added = sampled.boxes[seen.added]
    assert len(added) > 0
    dims = np.tile([[4.2, 1.8, 1.6]], (12, 1))
    first = PlacementResult(  # a first pass that placed nothing
        boxes=np.zeros((0, 7)),
        accepted=np.zeros(0, dtype=np.int64),
        rejected=dict.fromkeys(REASONS, 0),
        reasons=np.full(len(dims), "slope").astype(str),  # shorter than the others
        attempts=0,
    )
    config = _realistic(db, index)._placement[True]
    source = np.zeros((len(dims), 7))
    merged, gone = displace_added(
        seen, first, dims, source, np.random.default_rng(1), config, 12, 0.7
    )
    assert len(merged.accepted) > 0 and (merged.reasons[merged.accepted] == "").all()
    unplaced = np.setdiff1d(np.arange(len(dims)), merged.accepted)
    assert len(unplaced) > 0 and np.isin(merged.reasons[unplaced], REASONS).all()
    grown = merged.boxes.copy()
    grown[:, 3:5] += 2.0 * config.clearance
    # naive reference: an added box goes iff it overlaps a placed one by a positive area
    expected = (bev_overlap_area(added, grown) > 0).any(axis=1)
    after = seen.after_placing.frame
    assert 0 < len(gone) == int(expected.sum()) == len(sampled.boxes) - len(after.boxes)
    assert not (bev_overlap_area(grown, after.boxes) > 1e-9).any()
    assert not (bev_overlap_area(grown, frames[0].boxes) > 1e-9).any()
    kept = np.flatnonzero(seen.added)[~expected]
    assert np.array_equal(after.boxes[len(frames[0].boxes) :], sampled.boxes[kept])
    gone_points = points_in_boxes(sampled.points, added[expected]).any(axis=1)
    assert len(after.points) <= len(sampled.points) - int(gone_points.sum())


def test_a_frame_without_some_added_objects_knows_their_points_as_a_fresh_one(
    synthetic_world,  # noqa: F811
):
    """:meth:`SensorFrame.without_added` hands on the added objects' points (renumbered, not
    found again) and :meth:`SensorFrame.added_counts` counts from one pass: both as a
    SensorFrame built afresh on the pruned frame and a per-box count find them, also where
    two added boxes overlap (a point's box is the last holding it); the parent's (point,
    box) pairs are handed on too, those of the kept ones."""
    from drcpo.sensor_config import SensorConfig
    from drcpo.transforms.insertion import BoxQuery, take_rows
    from drcpo.transforms.sensor_steps import SensorFrame

    db, index, frames = synthetic_world
    gt = build_pipeline("realistic", db, index=index, kind="drcpo").transforms[0]
    sampled = gt(frames[0], np.random.default_rng(5))
    first = np.flatnonzero(np.asarray(sampled.metadata[BOX_SOURCE]) != "")[0]
    twin = sampled.boxes[first] + np.array([0.6, 0.3, 0.0, 0.0, 0.0, 0.0, 0.2])
    made = Frame(
        sampled.points,
        np.concatenate([sampled.boxes, twin[None]]),
        np.concatenate([sampled.names, sampled.names[first : first + 1]]),
        {**sampled.metadata, BOX_SOURCE: np.append(sampled.metadata[BOX_SOURCE], "gt_sampling")},
    )
    config = SensorConfig(model="hdl64e")
    seen = SensorFrame(made, config)
    added = int(seen.added.sum())
    assert added >= 3
    shared = (seen.added_owner == 0).sum(), (seen.added_owner == added - 1).sum()
    assert min(shared) > 0
    keep = np.random.default_rng(2).random(len(made.points)) < 0.7
    expected = BoxQuery(take_rows(made.points, keep)).counts(made.boxes[seen.added])
    np.testing.assert_array_equal(seen.added_counts(keep), expected)
    for drop in ([0], [added - 1], [0, added - 1], list(range(1, added, 2))):
        mask = np.isin(np.arange(added), drop)
        pruned, names = seen.without_added(mask)
        fresh = SensorFrame(pruned.frame, config)
        assert len(names) == len(drop)
        np.testing.assert_array_equal(pruned.added_owner, fresh.added_owner)
        keep = np.random.default_rng(len(drop)).random(len(pruned.frame.points)) < 0.5
        np.testing.assert_array_equal(pruned.added_counts(keep), fresh.added_counts(keep))
        boxes = pruned.frame.boxes[pruned.added]
        reference = BoxQuery(take_rows(pruned.frame.points, keep)).counts(boxes)
        np.testing.assert_array_equal(pruned.added_counts(keep), reference)


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


def _arc_box(sensor, distance: float, azimuths_deg: tuple[float, float], depth: float = 0.4):
    """A box at ``distance`` facing the mount, spanning ``azimuths_deg``, 3 m high around the
    mount's height."""
    first, last = np.radians(azimuths_deg)
    middle = (first + last) / 2.0
    width = 2.0 * distance * math.tan((last - first) / 2.0)
    x, y, z = sensor.mount
    return np.array([x + distance * math.cos(middle), y + distance * math.sin(middle),
                     z - 1.0, depth, width, 3.0, middle])  # fmt: skip


def _returns_on_arc(sensor, distance: float, azimuths_deg: tuple[float, float]) -> np.ndarray:
    """Points on the rays of 5 beams just below the horizon and of the columns between
    ``azimuths_deg``, at ``distance`` from each beam's origin; ``(n, 4)``."""
    beams = np.flatnonzero((sensor.elevations < 0.0) & (sensor.elevations > math.radians(-4)))
    beams = beams[:5]
    lo, hi = (np.radians(azimuths_deg) - sensor.phase) / sensor.azimuth_step
    columns = np.arange(math.ceil(lo), math.floor(hi) + 1)
    b, c = np.repeat(beams, len(columns)), np.tile(columns, len(beams))
    xyz = sensor.ray_origins(b) + distance * sensor.ray_directions(b, c)
    return np.column_stack([xyz, np.zeros(len(xyz))]).astype(np.float32)


def test_visible_returns_count_what_neither_the_frame_nor_another_box_hides():
    """:func:`visible_returns`: returns behind the frame's own (a wall), behind an added
    object's box though it holds no point there (the added objects are solid), or behind
    another object's box are hidden; an object in the clear keeps them all, and one in front
    of another is not hidden by it."""
    from drcpo.sensor_config import SensorConfig
    from drcpo.transforms.sensor_steps import SensorFrame, visible_returns

    sensor = sensor_preset("hdl64e")
    wall = _returns_on_arc(sensor, 20.0, (-6.0, -2.0))
    added = _arc_box(sensor, 8.0, (9.0, 15.0))
    frame = Frame(wall, added[None], np.array(["Car"]), {BOX_SOURCE: np.array(["gt_sampling"])})
    seen = SensorFrame(frame, SensorConfig(model="hdl64e"))
    arcs = {
        "behind the wall": (25.0, (-5.0, -3.0)),
        "behind the added box": (15.0, (10.0, 14.0)),
        "in the clear": (12.0, (30.0, 33.0)),
        "behind the clear one": (25.0, (31.0, 32.0)),
    }
    rendered = [(_returns_on_arc(sensor, d, a), _arc_box(sensor, d, a)) for d, a in arcs.values()]
    assert all(len(r[0]) > 10 for r in rendered)
    counts = visible_returns(seen, rendered)
    np.testing.assert_array_equal(counts, [0, 0, len(rendered[2][0]), 0])
    assert visible_returns(seen, []).shape == (0,)


def test_objects_hidden_once_rendered_get_new_poses(synthetic_world):  # noqa: F811
    """``placement.repose_attempts``: a placed object left with no visible return gets a new
    pose (placed as the first pass places: on the frame's ground, clear of every box) and is
    rendered again there; the others keep theirs; with 0 attempts nothing moves."""
    import dataclasses

    from drcpo.geometry import bev_overlap_area
    from drcpo.placement import PlacementRounds
    from drcpo.sensor_config import SensorConfig
    from drcpo.transforms.sensor_steps import Placing, SensorFrame, visible_returns

    db, index, frames = synthetic_world
    seen = SensorFrame(frames[0], SensorConfig(model="hdl64e"))
    dims = np.tile([[0.8, 0.6, 1.7]], (4, 1))
    source = np.zeros((4, 7))
    config = _realistic(db, index)._placement[True]
    rng = np.random.default_rng(3)

    def placing(attempts: int) -> Placing:
        settings = dataclasses.replace(config, repose_attempts=attempts)
        rounds = PlacementRounds(seen.frame, dims, source, rng, settings, seen.ground)
        out = Placing(seen, rounds, dims, source, rng, settings, 12, 0.7)
        out.first_pass()
        return out

    calls = []

    def render(k: int, box: np.ndarray):
        calls.append(k)
        points = np.tile(np.append(box[:3], 0.5), (12, 1)).astype(np.float32)
        return points, box

    first = placing(20)
    boxes = first.rounds.result().boxes
    assert len(boxes) >= 3
    rendered = [render(k, box) for k, box in enumerate(boxes)]
    rendered[1] = (np.zeros((0, 4), np.float32), boxes[1])  # hidden: no return left
    calls.clear()
    moved, again = first.repose(seen, boxes, rendered, render, 5)
    assert calls[:1] == [1] and set(calls) == {1}
    assert not np.array_equal(moved[1], boxes[1])
    np.testing.assert_array_equal(np.delete(moved, 1, axis=0), np.delete(boxes, 1, axis=0))
    assert len(again[1][0]) == 12 and visible_returns(seen, again)[1] > 0
    others = np.concatenate([np.delete(moved, 1, axis=0), seen.frame.boxes])
    assert not (bev_overlap_area(moved[1:2], others) > 1e-9).any()
    still, same = placing(0).repose(seen, boxes, rendered, render, 5)
    np.testing.assert_array_equal(still, boxes)
    assert same[1][0].shape == (0, 4)


def test_new_poses_are_rendered_with_either_self_occlusion(synthetic_world, monkeypatch):  # noqa: F811
    """``repose_attempts`` renders a moved object as the first pass does, with the paper's
    s-HPR as with the sensor (with ``self_occlusion.mode=hpr`` it crashed: the per-object
    render seeds exist only in mode ``sensor``)."""
    from drcpo.transforms import sensor_steps

    db, index, frames = synthetic_world
    real = sensor_steps.Placing.repose
    rendered = []

    def repose(self, seen, boxes, visible, render, min_points):
        if len(boxes):  # test seam: object 0 rendered again where it stands
            rendered.append((render(0, boxes[0]), visible[0]))
        return real(self, seen, boxes, visible, render, min_points)

    monkeypatch.setattr(sensor_steps.Placing, "repose", repose)
    for mode in ("hpr", "sensor"):
        rendered.clear()
        drcpo = _realistic(db, index, **{"self_occlusion.mode": mode})
        drcpo(frames[0], np.random.default_rng(0))
        assert rendered, mode  # the seam ran
        (points, label), (first_points, first_label) = rendered[0]
        np.testing.assert_array_equal(label, first_label)
        if mode == "hpr":  # deterministic: the same points as the first pass
            np.testing.assert_array_equal(points, first_points)
        else:
            assert points.shape[1] == first_points.shape[1]
