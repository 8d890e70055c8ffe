"""The synthetic world's truth of inserted objects (drcpo.synth.truth), on hand-made worlds."""

from __future__ import annotations

import numpy as np
import pytest

from drcpo.synth import Ground, LidarConfig, Solids, World, make_actor, scan
from drcpo.synth.solids import BOX, CYLINDER, ELLIPSOID, MATERIAL_ID, make_solids
from drcpo.synth.truth import (
    boxes_cut_solids,
    solid_categories,
    solids_in_box,
    true_ground_height,
    true_inserted_returns,
    true_object_returns,
    truth_actor,
)
from drcpo.synth.world import Street

MOUNT = 1.73
# A coarse sensor keeps the casts cheap: 27 beams, 0.5 degree columns, no noise or dropout.
SENSOR = LidarConfig(
    elevations_deg=tuple(np.linspace(2.0, -24.0, 27)),
    azimuth_step_deg=0.5,
    range_noise=0.0,
    dropout=0.0,
    intensity_noise=0.0,
)


def hand_world(static: Solids | None = None, sidewalks: Solids | None = None) -> World:
    """A flat world (ground 1.73 m below the sensor) holding only the given solids."""
    return World(
        ground=Ground.flat(-MOUNT),
        street=Street(yaw=0.0, sensor_v=0.0, road_half=5.0, sidewalk=2.0, kerb=0.15),
        static=static if static is not None else Solids.empty(),
        actors=(),
        boxes=np.zeros((0, 7)),
        names=np.zeros(0, dtype=str),
        sidewalks=sidewalks if sidewalks is not None else Solids.empty(),
    )


def wall(x: float) -> Solids:
    """A facade 20 m wide, 6 m tall, facing the sensor at distance ``x``."""
    return make_solids([(BOX, (x + 0.5, 0.0, -MOUNT + 3.0), (0.5, 10.0, 3.0), 0.0, "facade")])


# --- ground ---------------------------------------------------------------------------------
def test_ground_height_is_the_ground_or_a_sidewalk_top():
    slab = make_solids([(BOX, (10.0, 6.0, -MOUNT - 0.2), (5.0, 1.0, 0.35), 0.0, "concrete")])
    world = hand_world(sidewalks=slab)
    z = true_ground_height(world, np.array([[10.0, 0.0], [10.0, 6.0], [20.0, 6.0]]))
    np.testing.assert_allclose(z, [-MOUNT, -MOUNT + 0.15, -MOUNT])
    assert true_ground_height(world, np.array([10.0, 6.0])).shape == (1,)


# --- solids in a box ------------------------------------------------------------------------
def test_box_against_each_solid_kind():
    solids = make_solids(
        [
            (BOX, (0.0, 0.0, 0.0), (1.0, 1.0, 1.0), 0.0, "facade"),
            (CYLINDER, (5.0, 0.0, 0.0), (0.1, 0.1, 2.0), 0.0, "metal"),
            (ELLIPSOID, (10.0, 0.0, 3.0), (2.0, 2.0, 1.0), 0.0, "foliage"),
        ]
    )
    cases = [  # box, which solids it cuts
        ([1.5, 0.0, 0.0, 1.2, 1.0, 1.0, 0.0], [True, False, False]),  # overlaps the cube 0.1 m
        ([2.5, 0.0, 0.0, 1.0, 1.0, 1.0, 0.0], [False, False, False]),  # 1 m clear of it
        ([5.0, 0.35, 0.0, 0.4, 0.4, 1.0, 0.0], [False, False, False]),  # 5 cm beside the pole
        ([5.0, 0.25, 0.0, 0.4, 0.4, 1.0, 0.0], [False, True, False]),  # 5 cm into the pole
        # a 45-degree box whose corner reaches 0.05 m into the pole's 0.1 m circle
        ([5.05 + 0.5 * np.sqrt(0.5), 0.0, 0.0, 0.5, 0.5, 1.0, np.pi / 4], [0, 1, 0]),
        # a corner at (5.08, 0.08): inside the pole's bounding square, outside its circle
        ([5.28, 0.28, 0.0, 0.4, 0.4, 1.0, 0.0], [False, False, False]),
        ([10.0, 0.0, 1.5, 1.0, 1.0, 1.2, 0.0], [False, False, True]),  # under the crown's belly
        ([10.0, 0.0, 1.3, 1.0, 1.0, 1.0, 0.0], [False, False, False]),  # top 0.2 m below it
        # beside the crown where its corner would be inside the crown's bounding box only
        ([11.7, 1.7, 3.0, 0.4, 0.4, 0.4, 0.0], [False, False, False]),
    ]
    boxes = np.array([b for b, _ in cases])
    got = boxes_cut_solids(solids, boxes)
    np.testing.assert_array_equal(got, np.array([c for _, c in cases], dtype=bool))


def test_ellipsoid_test_against_dense_sampling():
    """The projected-gradient ellipsoid test agrees with sampling the box densely."""
    rng = np.random.default_rng(5)
    crown = make_solids([(ELLIPSOID, (0.0, 0.0, 0.0), (2.0, 1.0, 0.8), 0.4, "foliage")])
    boxes = np.column_stack(
        [
            rng.uniform(-3.5, 3.5, (60, 3)),
            rng.uniform(0.3, 1.5, (60, 3)),
            rng.uniform(-np.pi, np.pi, 60),
        ]
    )
    got = boxes_cut_solids(crown, boxes)[:, 0]
    grid = np.stack(np.meshgrid(*[np.linspace(-0.5, 0.5, 25)] * 3, indexing="ij"), -1)
    for box, verdict in zip(boxes, got, strict=True):
        local = grid.reshape(-1, 3) * box[3:6]
        c, s = np.cos(box[6]), np.sin(box[6])
        world = np.column_stack(
            [c * local[:, 0] - s * local[:, 1], s * local[:, 0] + c * local[:, 1], local[:, 2]]
        )
        sampled = crown.contains(world + box[:3])[:, 0].any()
        if sampled:  # a sample inside proves the cut; without one it may be very shallow
            assert verdict


def test_solids_in_box_names_categories_and_ignores_touching():
    static = Solids.concatenate(
        [
            wall(20.0),
            make_solids([(CYLINDER, (10.0, 5.0, -MOUNT + 2.0), (0.1, 0.1, 2.0), 0.0, "metal")]),
            make_solids([(CYLINDER, (10.0, -5.0, -MOUNT + 1.0), (0.2, 0.2, 1.0), 0.0, "bark")]),
        ]
    )
    world = hand_world(static)
    assert solid_categories(world).tolist() == ["building", "pole", "trunk"]
    car = np.array([20.0, 0.0, -MOUNT + 0.75, 4.0, 1.8, 1.5, 0.0])  # half of it in the wall
    assert solids_in_box(world, car) == {"building"}
    standing = car.copy()
    standing[0] = 18.0  # its front face touches the facade: not a cut
    assert solids_in_box(world, standing) == frozenset()
    assert solids_in_box(world, np.array([10.0, 5.2, -1.0, 0.8, 0.6, 1.7, 0.0])) == {"pole"}
    assert solids_in_box(world, np.array([10.0, -5.0, -1.0, 0.8, 0.6, 1.7, 0.3])) == {"trunk"}
    assert solids_in_box(world, np.array([10.0, 0.0, -1.0, 0.8, 0.6, 1.7, 0.0])) == frozenset()


def test_solids_in_box_names_the_worlds_actors_by_class():
    actor = make_actor("Car", np.random.default_rng(0))
    box = actor.box(15.0, 3.0, -MOUNT, 0.2)
    world = World(
        ground=Ground.flat(-MOUNT),
        street=Street(0.0, 0.0, 5.0, 2.0, 0.15),
        static=Solids.empty(),
        actors=(actor,),
        boxes=box[None],
        names=np.array(["Car"]),
    )
    assert solids_in_box(world, box) == {"car"}
    beside = box.copy()
    beside[1] += 3.0
    assert solids_in_box(world, beside) == frozenset()


# --- the truth of an inserted object ----------------------------------------------------------
@pytest.mark.parametrize("name", ["Car", "Pedestrian", "Cyclist"])
def test_truth_actor_fits_its_box(name):
    box = np.array([0.0, 0.0, 0.0, 1.9, 0.75, 1.8, 0.0])
    if name == "Car":
        box[3:6] = (4.4, 1.75, 1.45)
    actor = truth_actor(name, box, np.random.default_rng(1))
    low, high = actor.solids.bounds()
    np.testing.assert_allclose(high - low, box[3:6], rtol=0.02)
    np.testing.assert_allclose((high + low) / 2, 0.0, atol=0.02 * box[3:6].max())
    assert actor.name == name


def test_object_returns_match_an_independent_cast():
    """An inserted car's true returns are the rays whose first hit is the car: checked against
    casting the same rays at the car's solids alone and then at the world without it."""
    world = hand_world(wall(30.0))
    sweep = scan(world, np.random.default_rng(0), SENSOR)
    box = np.array([12.0, 0.0, -MOUNT + 0.75, 4.2, 1.8, 1.5, 0.4])
    truth = true_object_returns(world, sweep, "Car", box, np.random.default_rng(3), SENSOR)
    assert truth.counts.shape == (1,) and truth.counts[0] == len(truth.returns) > 50
    assert (truth.owner == 0).all()
    # the returns lie on the car's surface: inside its box (a hair grown), on their own rays
    from drcpo.geometry import points_in_boxes

    assert points_in_boxes(truth.returns, box[None], margin=1e-3).all()
    direction = sweep.grid.directions[truth.ray]
    unit = truth.returns[:, :3] / np.linalg.norm(truth.returns[:, :3], axis=1, keepdims=True)
    np.testing.assert_allclose(unit, direction, atol=1e-5)
    # the wall's returns behind the car are hidden; exactly those whose ray now hits the car
    from drcpo.synth.raycast import MISS, Scene

    alone = Scene(truth.solids, None, num_bins=64).cast(sweep.grid.directions[sweep.ray], 200.0)
    np.testing.assert_array_equal(truth.hidden, alone.hit != MISS)
    assert truth.hidden.sum() > 20


def test_objects_hide_each_other_and_hidden_points_lie_behind():
    world = hand_world(wall(40.0))
    sweep = scan(world, np.random.default_rng(0), SENSOR)
    near = np.array([10.0, 0.0, -MOUNT + 0.85, 0.8, 0.6, 1.7, 0.0])
    far = np.array([20.0, 0.0, -MOUNT + 0.85, 0.8, 0.6, 1.7, 0.0])  # straight behind it
    rng = np.random.default_rng(4)
    both = true_inserted_returns(world, sweep, ["Pedestrian", "Car"], [near, far], rng, SENSOR)
    alone = true_object_returns(world, sweep, "Car", far, np.random.default_rng(4), SENSOR)
    assert both.counts[0] > 0 and 0 < both.counts[1] < alone.counts[0]
    hidden_points = sweep.points[both.hidden]
    assert (np.linalg.norm(hidden_points[:, :3], axis=1) > 10.0 - 0.5).all()
    assert set(np.unique(both.hidden_by[both.hidden])) <= {0, 1}


def test_object_inside_a_building_has_no_returns():
    world = hand_world(wall(20.0))
    sweep = scan(world, np.random.default_rng(0), SENSOR)
    buried = np.array([20.5, 0.0, -MOUNT + 0.85, 0.6, 0.6, 1.7, 0.0])
    truth = true_object_returns(
        world, sweep, "Pedestrian", buried, np.random.default_rng(0), SENSOR
    )
    assert truth.counts[0] == 0 and not truth.hidden.any()


def test_truth_is_deterministic_and_checks_its_input():
    world = hand_world(wall(30.0))
    sweep = scan(world, np.random.default_rng(0), SENSOR)
    box = np.array([12.0, 3.0, -MOUNT + 0.75, 4.0, 1.7, 1.5, 0.0])
    a = true_object_returns(world, sweep, "Car", box, np.random.default_rng(9), SENSOR)
    b = true_object_returns(world, sweep, "Car", box, np.random.default_rng(9), SENSOR)
    np.testing.assert_array_equal(a.returns, b.returns)
    with pytest.raises(ValueError, match="2 names for 1 boxes"):
        true_inserted_returns(world, sweep, ["Car", "Car"], box[None], np.random.default_rng(0))
    assert MATERIAL_ID["facade"] == world.static.material[0]
