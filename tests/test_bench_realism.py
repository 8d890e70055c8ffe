"""benchmarks/bench_realism.py's scoring, on hand-made cases whose answers are known."""

from __future__ import annotations

import importlib.util
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from drcpo.frame import Frame
from drcpo.synth import Ground, LidarConfig, Solids, World, scan
from drcpo.synth.solids import BOX, make_solids
from drcpo.synth.truth import true_object_returns
from drcpo.synth.world import Street

SCRIPT = Path(__file__).resolve().parents[1] / "benchmarks" / "bench_realism.py"
_spec = importlib.util.spec_from_file_location("bench_realism", SCRIPT)
bench = importlib.util.module_from_spec(_spec)
sys.modules["bench_realism"] = bench
_spec.loader.exec_module(bench)

MOUNT = 1.73


# --- the pure helpers -------------------------------------------------------------------------
def test_match_rows_finds_exact_rows_only():
    rng = np.random.default_rng(0)
    before = rng.normal(size=(50, 4)).astype(np.float32)
    nudged = before[7].copy()
    nudged[0] = np.nextafter(nudged[0], np.float32(np.inf))  # one bit off: not the same row
    after = np.concatenate([before[[5, 3, 40]], rng.normal(size=(2, 4)).astype(np.float32)])
    after = np.concatenate([after, nudged[None]])
    np.testing.assert_array_equal(bench.match_rows(before, after), [5, 3, 40, -1, -1, -1])
    assert len(bench.match_rows(before[:0], after)) == 6
    with pytest.raises(ValueError, match="row shapes differ"):
        bench.match_rows(before, after[:, :3])


def test_box_sources_tells_the_stages_apart():
    original = np.array([[1.0, 0, 0, 1, 1, 1, 0], [2.0, 0, 0, 1, 1, 1, 0]])
    sampled = np.concatenate([original, [[3.0, 0, 0, 1, 1, 1, 0]]])
    # DR.CPO dropped original box 0 and appended one of its own
    output = np.array([[2.0, 0, 0, 1, 1, 1, 0], [3.0, 0, 0, 1, 1, 1, 0], [4.0, 0, 0, 1, 1, 1, 0]])
    assert bench.box_sources(original, sampled, output).tolist() == ["", "gt_sampling", "drcpo"]


def test_density_bins_count_only_medians_within_the_band():
    names = np.array(["Car", "Car", "Car", "Pedestrian", "Pedestrian", "Cyclist"])
    boxes = np.zeros((6, 7))
    boxes[:, 0] = [5.0, 6.0, 15.0, 25.0, 65.0, 75.0]  # the last beyond 70 m: no bin
    bins = bench.distance_bin(boxes)
    np.testing.assert_array_equal(bins, [0, 0, 1, 2, 6, -1])
    ratios = bench.density_ratios([100, 110, 50, 30, 0], [100, 100, 100, 40, 0])
    assert np.isnan(ratios[4])  # no true points: no ratio
    figures = bench.binned_medians(np.append(ratios, 1.0), names, bins)
    assert figures["bins"] == 21
    table = figures["table"]
    assert table["Car"][0] == {"median": 1.05, "n": 2} and table["Car"][1]["median"] == 0.5
    assert table["Pedestrian"][2]["median"] == 0.75 and table["Pedestrian"][6]["n"] == 0
    assert figures["bins_within"] == 2  # Car 0-10 m (1.05) and Pedestrian 20-30 m (0.75)


def test_on_beam_against_a_naive_loop():
    beams = np.radians(np.array([2.0, 1.0, -0.5, -3.0]))
    rng = np.random.default_rng(1)
    elevation = np.radians(rng.uniform(-4.0, 3.0, 300))
    distance = rng.uniform(2.0, 60.0, 300)
    azimuth = rng.uniform(-np.pi, np.pi, 300)
    points = np.column_stack(
        [
            distance * np.cos(elevation) * np.cos(azimuth),
            distance * np.cos(elevation) * np.sin(azimuth),
            distance * np.sin(elevation),
        ]
    )
    naive = [min(abs(np.degrees(e - b)) for b in beams) <= 0.1 for e in elevation]
    np.testing.assert_array_equal(bench.on_beam(points, beams, 0.1), naive)
    on = points * 0 + [[10.0 * np.cos(beams[1]), 0.0, 10.0 * np.sin(beams[1])]]
    assert bench.on_beam(on, beams, 0.1).all()


def test_ground_figures_see_a_floating_and_a_sunk_box():
    boxes = np.array(
        [[10, 0, -1.73 + 0.75 + 0.5, 4, 2, 1.5, 0]] * 2 + [[10, 0, -0.98, 4, 2, 1.5, 0]]
    )
    boxes[1, 2] -= 1.0
    gaps = bench.ground_gaps(boxes, np.full(3, -1.73))
    np.testing.assert_allclose(gaps, [0.5, -0.5, 0.0])
    figures = bench.gap_figures(gaps)
    assert figures["above"] == pytest.approx(1 / 3, abs=1e-4)
    assert figures["below"] == pytest.approx(1 / 3, abs=1e-4)
    assert figures["p99"] == pytest.approx(np.percentile(gaps, 99), abs=1e-3)


def test_segments_cross_boxes_against_sampling_the_segment():
    from drcpo.geometry import points_in_boxes

    rng = np.random.default_rng(2)
    boxes = np.array([[10.0, 0.0, 0.0, 4.0, 2.0, 1.5, 0.5], [20.0, 8.0, -1.0, 1.0, 1.0, 2.0, 0.0]])
    points = rng.uniform([-5, -15, -3], [35, 15, 2], (400, 3))
    t = np.linspace(0.0, 1.0, 2001)
    samples = points[:, None, :] * t[None, :, None]
    naive = points_in_boxes(samples.reshape(-1, 3), boxes).any(axis=1).reshape(400, -1).any(1)
    got = bench.segments_cross_boxes(points, boxes)
    # sampling can miss a graze of under 1/2000 of the segment; never the other way round
    assert (got | ~naive).all() and (got != naive).sum() <= 2
    assert naive.sum() > 20


def test_frame_ground_heights_use_the_footprint_and_skip_labelled_boxes():
    rng = np.random.default_rng(3)
    xy = rng.uniform(0, 30, (20000, 2))
    z = np.where(xy[:, 0] < 15, -1.7, -1.2)  # a 0.5 m step at x = 15
    points = np.column_stack([xy, z + rng.normal(0, 0.01, len(z))])
    car = np.array([[8.0, 8.0, -0.9, 4.0, 2.0, 1.5, 0.0]])
    points = np.concatenate([points, rng.uniform([6, 7, -1.6], [10, 9, -0.2], (3000, 3))])
    boxes = np.array([[8.0, 8.0, -0.9, 4.0, 2.0, 1.5, 0.0], [25.0, 5.0, 0.0, 1, 1, 1, 0]])
    ground = bench.frame_ground_heights(points, boxes, car)
    np.testing.assert_allclose(ground, [-1.7, -1.2], atol=0.03)
    far = bench.frame_ground_heights(points, np.array([[80.0, 0, 0, 1, 1, 1, 0]]), car)
    assert np.isnan(far[0])


# --- a frame scored end to end against its truth ----------------------------------------------
def hand_case():
    """A flat street with a wall 40 m ahead, swept by the default sensor."""
    from drcpo.datasets.kitti_coordinates import fov_mask
    from drcpo.datasets.kitti_writer import reference_calibration

    wall = make_solids([(BOX, (40.5, 0.0, -MOUNT + 3.0), (0.5, 30.0, 3.0), 0.0, "facade")])
    world = World(
        ground=Ground.flat(-MOUNT),
        street=Street(0.0, 0.0, 6.0, 2.0, 0.15),
        static=wall,
        actors=(),
        boxes=np.zeros((0, 7)),
        names=np.zeros(0, dtype=str),
        sidewalks=Solids.empty(),
    )
    sweep = scan(world, np.random.default_rng(0), LidarConfig())
    calib = reference_calibration()
    rows = np.flatnonzero(fov_mask(sweep.points, calib))
    frame = Frame(sweep.points[rows], np.zeros((0, 7)), np.zeros(0, dtype=str), {"calib": calib})
    return bench.SynthCase(world, sweep, frame, rows, seed=0, index=0)


class Inserter:
    """A stand-in DR.CPO stage inserting the truth of one car (``perfect``) or a bad copy:
    floating 0.5 m, every other point, shifted off the beams, hidden points kept and 30
    visible ones deleted."""

    name = "drcpo"

    def __init__(self, case, seed: int, perfect: bool) -> None:
        self.case, self.seed, self.perfect = case, seed, perfect

    def __call__(self, frame: Frame, rng: np.random.Generator) -> Frame:
        box = np.array([15.0, 1.0, -MOUNT + 0.75, 4.2, 1.8, 1.5, 0.3])
        if not self.perfect:
            box[2] += 0.5
        truth = true_object_returns(
            self.case.world, self.case.sweep, "Car", box, np.random.default_rng([self.seed, 1])
        )
        hidden = truth.hidden[self.case.sweep_rows]
        keep = ~hidden
        inserted = truth.returns
        if not self.perfect:
            keep = np.ones(len(frame.points), dtype=bool)
            far = np.flatnonzero(np.linalg.norm(frame.points[:, :3], axis=1) > 38.0)
            keep[far[:30]] = False
            inserted = inserted[::2].copy()
            inserted[:, 2] += 0.04
        points = np.concatenate([frame.points[keep], inserted])
        return frame.replace(
            points=points, boxes=np.concatenate([frame.boxes, box[None]]), names=np.array(["Car"])
        )


@pytest.mark.parametrize("perfect", [True, False])
def test_scoring_a_frame_against_its_truth(perfect):
    case = hand_case()
    tally = bench.Tally()
    seed = 12
    bench.score_frame(case, [Inserter(case, seed, perfect)], seed, tally)
    summary = bench.summarise(tally)
    (car,) = tally.objects
    assert car["source"] == "drcpo" and car["true_points"] > 100
    frame = tally.frames[0]
    if perfect:
        # a return whose range noise takes it over 5 cm out of the box is not counted as its
        assert 0.99 * car["true_points"] <= car["points"] <= car["true_points"]
        assert summary["density"]["bins_within"] == 1
        assert summary["density"]["table"]["Car"][1]["median"] == pytest.approx(1.0, abs=0.01)
        assert summary["on_beam"]["drcpo"] == 1.0
        assert summary["ground"]["above"] == 0.0 and abs(car["gap"]) < 1e-9
        assert frame["deleted_visible"]["all"]["visible"] == 0 and frame["hidden"] > 100
        assert summary["hidden_removed"] == 1.0
        # the truth's returns in place of what it hides: its own rays left empty, no more
        emptied = frame["emptied"]
        assert emptied["all"] == emptied["drcpo"] == emptied["truth"]
        assert emptied["truth"][1] == frame["hidden"] and 0 < emptied["truth"][0] < frame["hidden"]
    else:
        assert car["points"] == pytest.approx(car["true_points"] / 2, rel=0.01)
        assert summary["density"]["bins_within"] == 0
        assert summary["on_beam"]["drcpo"] < 0.2
        assert summary["ground"]["above"] == 1.0 and car["gap"] == pytest.approx(0.5)
        deleted = frame["deleted_visible"]
        assert deleted["all"] == deleted["drcpo"] == {
            "visible": 30, "in_box": 0, "nothing_in_front": 30, "no_box_on_ray": 30,
            "behind_gt_sampling_only": 0,
        }  # fmt: skip
        assert deleted["gt_sampling"]["visible"] == 0
        assert summary["hidden_removed"] == 0.0
        # the 30 wall points deleted with nothing put on their rays
        assert frame["emptied"]["all"] == frame["emptied"]["drcpo"] == [30, 30]
        assert summary["emptied_rays"]["drcpo"] == {"per_frame": 30.0, "share": 1.0}
    assert summary["on_beam"]["truth"] == summary["on_beam"]["truth_fine"] == 1.0
    assert summary["solids"]["building"] == 0.0


class BoxesOnly:
    """A stand-in DR.CPO stage that only adds labels: two people in front of the wall (the
    hand world's sweep returns from the wall only)."""

    name = "drcpo"
    boxes = np.array(
        [
            [34.0, 0.5, -MOUNT + 0.87, 0.8, 0.6, 1.74, 0.4],
            [36.0, -1.5, -MOUNT + 0.87, 0.9, 0.6, 1.74, 2.0],
        ]
    )

    def __call__(self, frame: Frame, rng: np.random.Generator) -> Frame:
        return frame.replace(boxes=self.boxes, names=np.array(["Pedestrian"] * 2))


def test_another_actor_inserts_a_second_truth_at_the_stages_boxes():
    from drcpo.datasets.kitti_coordinates import fov_mask
    from drcpo.synth.truth import true_inserted_returns

    case = hand_case()
    seed = 12
    floor = bench.AnotherActor([BoxesOnly()], case, seed)
    out = floor(case.frame, np.random.default_rng(seed))
    np.testing.assert_array_equal(out.boxes, BoxesOnly.boxes)
    assert list(out.metadata["box_source"]) == ["drcpo", "drcpo"]
    names = ["Pedestrian"] * 2
    scored, other = (
        true_inserted_returns(
            case.world, case.sweep, names, BoxesOnly.boxes, np.random.default_rng([seed, k])
        )
        for k in (1, 2)
    )
    hidden = other.hidden_by[case.sweep_rows] >= 0
    # the frame's points the other actors do not hide, bit for bit, then their returns in view
    returns = other.returns[fov_mask(other.returns, case.frame.metadata["calib"])]
    np.testing.assert_array_equal(out.points, np.concatenate([case.frame.points[~hidden], returns]))

    tally = bench.Tally()
    bench.score_frame(case, [floor], seed, tally)
    frame = tally.frames[0]
    # scored against a draw of its own (a person's stride and arms differ): points one hides
    # the other does not, most hidden by both
    truly_hidden = scored.hidden_by[case.sweep_rows] >= 0
    assert frame["deleted_visible"]["all"]["visible"] == int((hidden & ~truly_hidden).sum()) > 0
    assert frame["hidden"] == int(truly_hidden.sum())
    assert frame["hidden"] / 2 < frame["hidden_removed"] == int((hidden & truly_hidden).sum())
    assert frame["deleted_visible"]["gt_sampling"]["visible"] == 0


def test_against_floor_compares_each_preset_with_its_own_floor_only():
    def figures(deleted, hidden):
        return {
            "deleted_visible_per_frame": {"all": {"visible": deleted}},
            "hidden_removed": hidden,
        }

    presets = {
        "realistic": figures(2000.0, 0.96),
        "floor:realistic": figures(160.0, 0.97),
        "paper": figures(250.0, 0.15),
        "floor:other": figures(1.0, 1.0),
    }
    assert bench.against_floor(presets) == {
        "realistic": {"deleted_visible_over_floor": 12.5, "hidden_removed_below_floor": 0.01}
    }
    presets["floor:realistic"] = figures(0.0, None)
    assert bench.against_floor(presets)["realistic"] == {
        "deleted_visible_over_floor": None,
        "hidden_removed_below_floor": None,
    }


def test_floor_base_names_the_preset_whose_boxes_it_takes():
    assert bench.floor_base("floor:realistic") == "realistic"
    assert bench.floor_base("paper") == "paper"
    for bad in ("floor:", "floor:floor:paper"):
        with pytest.raises(SystemExit, match="floor:PRESET"):
            bench.floor_base(bad)
    case = hand_case()
    with pytest.raises(ValueError, match="its own case"):
        bench.AnotherActor([], case, 1)(case.frame.replace(), np.random.default_rng(0))


def test_behind_only_takes_sight_lines_through_boxes_of_one_source_alone():
    """A point behind a ground-truth-sampled box alone counts; behind one of each, behind a
    DR.CPO box alone, or behind none, it does not; a box beside the sight line is no matter."""
    boxes = np.array(
        [
            [10.0, 0.0, 0.0, 2.0, 2.0, 2.0, 0.0],  # gt sampling's, on the +x axis
            [20.0, 0.0, 0.0, 2.0, 2.0, 2.0, 0.0],  # DR.CPO's, further along it
            [10.0, 10.0, 0.0, 2.0, 2.0, 2.0, 0.7],  # DR.CPO's, on the diagonal
        ]
    )
    kinds = np.array(["gt_sampling", "drcpo", "drcpo"])
    points = np.array(
        [
            [15.0, 0.0, 0.0],  # behind the first only
            [30.0, 0.0, 0.0],  # behind the first and the second
            [20.0, 20.0, 0.0],  # behind the third only
            [0.0, 15.0, 0.0],  # behind none
            [15.0, 0.5, 0.5],  # behind the first only, off its axis
        ]
    )
    np.testing.assert_array_equal(
        bench.behind_only(points, boxes, kinds, "gt_sampling"), [True, False, False, False, True]
    )
    np.testing.assert_array_equal(
        bench.behind_only(points, boxes, kinds, "drcpo"), [False, False, True, False, False]
    )


def test_emptied_rays_counts_deleted_points_whose_cell_holds_no_output_point():
    """Points on known rays of a small sensor: a deleted point is counted unless some output
    point (at any distance) lies in its ray cell; one outside every beam never is."""
    from drcpo.sensor import Sensor

    sensor = Sensor(
        elevations=np.radians(np.linspace(4.0, -10.0, 8)), offsets=np.zeros(8),
        azimuth_step=np.radians(1.0), phase=0.0, mount=(0.0, 0.0, 0.0),
        range_noise=0.0, dropout=0.0,
    )  # fmt: skip

    def on(beam, column, distance):
        b, c = np.array([beam]), np.array([column])
        return (sensor.ray_origins(b) + distance * sensor.ray_directions(b, c))[0]

    deleted = np.array([on(3, 10, 20.0), on(3, 11, 20.0), on(4, 10, 20.0), [20.0, 0.0, 15.0]])
    output = np.array([on(3, 10, 8.0), on(5, 11, 30.0), on(4, 12, 20.0)])
    assert bench.emptied_rays(sensor, deleted, output) == 2  # (3, 11) and (4, 10)
    assert bench.emptied_rays(sensor, deleted, np.zeros((0, 3))) == 3
    assert bench.emptied_rays(sensor, deleted[:0], output) == 0


def test_solids_share_sees_a_box_in_a_building():
    objects = [
        {"name": "Car", "source": "drcpo", "distance": 12.0, "points": 10, "true_points": 10,
         "gap": 0.0, "solids": ["building"]},
        {"name": "Car", "source": "drcpo", "distance": 12.0, "points": 10, "true_points": 0,
         "gap": 0.0, "solids": []},
    ]  # fmt: skip
    figures = bench.object_figures(objects)
    assert figures["solids"]["building"] == 0.5 and figures["solids"]["pole"] == 0.0
    assert figures["truly_unseen_kept"] == 1


@pytest.mark.slow
def test_quick_run_prints_the_figures_as_json(tmp_path):
    done = subprocess.run(
        [sys.executable, str(SCRIPT), "--quick", "--presets", "paper", "default",
         "floor:default", "--work", str(tmp_path)],
        capture_output=True, text=True, timeout=1200,
    )  # fmt: skip
    assert done.returncode == 0, done.stderr[-3000:]
    report = json.loads(done.stdout.strip().splitlines()[-1])
    # the two presets run on the same frames with the same seeds: paper = default, bit for bit
    assert report["presets"]["paper"] == report["presets"]["default"] | {
        "ms_median": report["presets"]["paper"]["ms_median"]
    }
    figures = report["presets"]["default"]
    assert figures["frames"] == 3 and figures["density"]["bins"] == 21
    assert figures["on_beam"]["truth"] == 1.0
    assert set(figures["counts"]) == {"Car", "Pedestrian", "Cyclist"}
    # the floor: the default preset's boxes, each object another true actor of its box
    floor = report["presets"]["floor:default"]
    assert floor["objects"] == figures["objects"] > 0 and floor["counts"] == figures["counts"]
    assert floor["ground"] == figures["ground"] and floor["solids"] == figures["solids"]
    assert floor["on_beam"]["drcpo"] == 1.0
    assert floor["deleted_visible_per_frame"]["gt_sampling"]["visible"] == 0
    assert set(report["against_floor"]) == {"default"}
    assert "default against its floor" in done.stdout


@pytest.mark.slow
def test_kitti_mode_scores_the_truth_free_figures(tmp_path):
    sample = Path(__file__).resolve().parents[2] / "shared" / "data" / "kitti_sample"
    if not (sample / "kitti_dbinfos_train.pkl").is_file():
        pytest.skip(f"the KITTI sample is not at {sample}")
    done = subprocess.run(
        [sys.executable, str(SCRIPT), "--kitti", str(sample), "--work", str(tmp_path)],
        capture_output=True, text=True, timeout=1200,
    )  # fmt: skip
    assert done.returncode == 0, done.stderr[-3000:]
    figures = json.loads(done.stdout.strip().splitlines()[-1])["presets"]["default"]
    assert figures["frames"] == 6
    ground = figures["ground_vs_frame"]["drcpo"]
    assert ground["n"] + ground["unobserved"] > 0
    assert set(figures["counts"]) == {"Car", "Pedestrian", "Cyclist"}


def test_nothing_nearer_looks_along_each_ray_only():
    points = np.array([[20.0, 0.0, 0.0], [20.0, 5.0, 0.0], [10.0, 0.0, -1.0]])
    others = np.array([[10.0, 0.01, 0.0], [30.0, 7.5, 0.0]])  # 0.06 deg off ray 0; behind 1
    np.testing.assert_array_equal(bench.nothing_nearer(points, others), [False, True, True])
    assert bench.nothing_nearer(points, others[:0]).all()
