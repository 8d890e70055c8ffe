"""The benchmark detector (benchmarks/detection): BEV features, targets, decoding, KITTI result
lines and the heading error (numpy only), and the training loop (needs torch)."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))

from detection.bev import Grid, bev_features
from detection.heads import (
    CLASSES,
    STRIDE,
    Detections,
    decode,
    encode_targets,
    output_shape,
    result_lines,
)
from detection.scoring import heading_errors

from drcpo.datasets.kitti_coordinates import camera_boxes_to_lidar
from drcpo.datasets.kitti_writer import reference_calibration
from drcpo.evaluation import read_kitti_objects
from drcpo.frame import Frame
from drcpo.geometry import wrap_angle

SIZES = {"Car": (3.9, 1.6, 1.56), "Pedestrian": (0.8, 0.6, 1.73), "Cyclist": (1.76, 0.6, 1.73)}


def _boxes(rng: np.random.Generator, count: int) -> tuple[np.ndarray, np.ndarray]:
    """Boxes in the camera's view, at least 3 m apart (one per output cell)."""
    names = np.array(CLASSES)[np.arange(count) % len(CLASSES)]
    centres = []
    while len(centres) < count:
        x = rng.uniform(8, 45)
        c = np.array([x, rng.uniform(-0.5, 0.5) * x])  # within the camera's view
        if all(np.linalg.norm(c - d) > 3 for d in centres):
            centres.append(c)
    boxes = np.column_stack(
        [
            np.array(centres),
            rng.uniform(-1.2, -0.6, count),
            np.array([SIZES[n] for n in names]) * rng.uniform(0.9, 1.1, (count, 3)),
            rng.uniform(-np.pi, np.pi, count),
        ]
    )
    return boxes, names


def _naive_bev(points: np.ndarray, grid: Grid) -> np.ndarray:
    """The features cell by cell, point by point."""
    ny, nx = grid.shape
    out = np.zeros((grid.channels, ny, nx), dtype=np.float64)
    top = np.full((ny, nx), -np.inf)
    total, count = np.zeros((ny, nx)), np.zeros((ny, nx))
    depth = (grid.z_range[1] - grid.z_range[0]) / grid.slices
    for x, y, z, intensity in points.astype(np.float64):
        col = int(np.floor((x - grid.x_range[0]) / grid.cell))
        row = int(np.floor((y - grid.y_range[0]) / grid.cell))
        level = int(np.floor((z - grid.z_range[0]) / depth))
        if not (0 <= col < nx and 0 <= row < ny and 0 <= level < grid.slices):
            continue
        out[level, row, col] += 1
        top[row, col] = max(top[row, col], z)
        total[row, col] += intensity
        count[row, col] += 1
    out[: grid.slices] = np.log1p(out[: grid.slices])
    seen = count > 0
    span = grid.z_range[1] - grid.z_range[0]
    out[grid.slices][seen] = (top[seen] - grid.z_range[0]) / span
    out[grid.slices + 1][seen] = total[seen] / count[seen]
    return out


def test_bev_features_match_a_point_by_point_reference():
    rng = np.random.default_rng(0)
    grid = Grid(x_range=(0.0, 8.0), y_range=(-4.0, 4.0), cell=0.4)
    points = np.column_stack(
        [
            rng.uniform(-1, 9, 3000),
            rng.uniform(-5, 5, 3000),
            rng.uniform(-3.5, 1.5, 3000),
            rng.uniform(0, 1, 3000),
        ]
    ).astype(np.float32)
    features = bev_features(points, grid)
    assert features.shape == (grid.channels, 20, 20) and features.dtype == np.float32
    np.testing.assert_allclose(features, _naive_bev(points, grid), rtol=1e-5, atol=1e-6)


def test_default_grid_is_the_camera_view_range_at_0_4_m():
    grid = Grid()
    assert grid.shape == (200, 176) and output_shape(grid) == (100, 88)
    empty = bev_features(np.zeros((0, 4), np.float32))
    assert empty.shape == (10, 200, 176) and not empty.any()


def test_a_box_encoded_as_a_target_decodes_back_to_the_same_box():
    rng = np.random.default_rng(1)
    boxes, names = _boxes(rng, 9)
    heatmap, code, mask = encode_targets(boxes, names)
    assert mask.sum() == 9 and heatmap.max() == 1.0
    decoded, labels, scores = decode(heatmap, code, threshold=0.99)
    assert len(decoded) == 9 and (scores == 1.0).all()
    order = np.lexsort((boxes[:, 1], boxes[:, 0]))
    back = np.lexsort((decoded[:, 1], decoded[:, 0]))
    decoded, labels = decoded[back], labels[back]
    np.testing.assert_allclose(decoded[:, :6], boxes[order, :6], atol=1e-5)
    np.testing.assert_allclose(wrap_angle(decoded[:, 6] - boxes[order, 6]), 0, atol=1e-5)
    assert [CLASSES[k] for k in labels] == names[order].tolist()


def test_targets_peak_at_the_centre_cell_with_a_radius_by_size():
    car = np.array([[20.2, 0.2, -0.9, 3.9, 1.6, 1.5, 0.3]])
    heatmap, code, mask = encode_targets(car, ["Car"])
    size = Grid().cell * STRIDE
    row, col = int((0.2 + 40) / size), int(20.2 / size)
    assert heatmap[0, row, col] == 1.0 and mask[row, col] == 1.0
    assert heatmap[0, row, col + 2] > 0 and heatmap[0, row, col + 3] == 0  # radius 2 for a car
    assert not heatmap[1:].any()
    ped = np.array([[20.2, 0.2, -0.9, 0.8, 0.6, 1.7, 0.3]])
    heatmap, _, _ = encode_targets(ped, ["Pedestrian"])
    assert heatmap[1, row, col + 1] > 0 and heatmap[1, row, col + 2] == 0  # radius 1
    np.testing.assert_allclose(code[6:, row, col], [np.sin(0.3), np.cos(0.3)], rtol=1e-6)


def test_targets_leave_out_other_classes_and_objects_off_the_grid():
    boxes = np.array([[20, 0, -1, 4, 1.7, 1.5, 0], [-5, 0, -1, 4, 1.7, 1.5, 0]], dtype=float)
    heatmap, code, mask = encode_targets(boxes, ["Van", "Car"])
    assert not heatmap.any() and not code.any() and not mask.any()


def test_result_lines_read_back_as_the_same_lidar_boxes(tmp_path):
    calib = reference_calibration()
    rng = np.random.default_rng(2)
    boxes, names = _boxes(rng, 6)
    boxes = np.vstack([boxes, [[-20.0, 0.0, -1.0, 4.0, 1.7, 1.5, 0.0]]])  # behind the camera
    labels = np.array([CLASSES.index(n) for n in names] + [0])
    scores = np.linspace(0.9, 0.3, 7)
    lines = result_lines(boxes, labels, scores, calib)
    assert len(lines) == 6  # the box behind the camera is left out
    path = tmp_path / "000000.txt"
    path.write_text("".join(f"{line}\n" for line in lines))
    read = read_kitti_objects(path, results=True)
    assert read.names.tolist() == names.tolist()
    np.testing.assert_allclose(read.score, scores[:6], atol=1e-4)
    assert (read.truncated == -1).all() and (read.occluded == -1).all()
    assert (read.bbox[:, 3] > read.bbox[:, 1]).all()  # 2D boxes for the devkit's height rule
    lidar = camera_boxes_to_lidar(read.boxes, calib)
    np.testing.assert_allclose(lidar[:, :6], boxes[:6, :6], atol=2e-4)
    np.testing.assert_allclose(wrap_angle(lidar[:, 6] - boxes[:6, 6]), 0, atol=1e-5)


def test_heading_error_is_modulo_180_degrees_of_matched_detections():
    truth = np.array([[20, 0, -1, 3.9, 1.6, 1.5, 0.2], [30, 5, -1, 0.8, 0.6, 1.7, 1.0]])
    frame = Frame(np.zeros((1, 4), np.float32), truth, np.array(["Car", "Pedestrian"]))
    found = truth.copy()
    found[0, 6] += np.radians(10)
    found[1, 6] += np.pi + np.radians(4)  # a reversed pedestrian overlaps as well
    far = truth[0] + [3, 0, 0, 0, 0, 0, 0]  # unmatched: 3 m away
    detections = Detections(np.vstack([found, far]), np.array([0, 1, 0]), np.array([0.9, 0.8, 1]))
    errors = heading_errors([frame], [detections])
    assert errors["Car"]["matched"] == 1 and errors["Car"]["mean_deg"] == pytest.approx(10)
    assert errors["Pedestrian"]["mean_deg"] == pytest.approx(4)
    assert errors["Cyclist"] == {"matched": 0, "mean_deg": None, "median_deg": None}


# Training (torch) ------------------------------------------------------------------------------


def _frames(count: int) -> list[Frame]:
    rng = np.random.default_rng(3)
    out = []
    for _ in range(count):
        boxes, names = _boxes(rng, 3)
        ground = np.column_stack(
            [rng.uniform(0, 60, 3000), rng.uniform(-20, 20, 3000), np.full(3000, -1.7)]
        )
        local = rng.uniform(-0.5, 0.5, (3, 300, 3)) * boxes[:, None, 3:6]
        cos, sin = np.cos(boxes[:, 6])[:, None], np.sin(boxes[:, 6])[:, None]
        inside = (
            np.stack(
                [
                    cos * local[..., 0] - sin * local[..., 1],
                    sin * local[..., 0] + cos * local[..., 1],
                    local[..., 2],
                ],
                axis=-1,
            )
            + boxes[:, None, :3]
        )
        xyz = np.vstack([ground, inside.reshape(-1, 3)])
        points = np.column_stack([xyz, rng.uniform(0, 1, len(xyz))]).astype(np.float32)
        out.append(Frame(points, boxes, names, {"calib": reference_calibration()}))
    return out


def test_training_repeats_exactly_for_a_seed_and_hands_each_sample_its_generator():
    pytest.importorskip("torch", reason="the detector needs torch (pip install -e '.[detection]')")
    from detection.model import BevDetector, parameter_count
    from detection.train import TrainConfig, augment_samples, sample_order, train

    assert 120_000 < parameter_count(BevDetector()) < 180_000
    frames = _frames(3)
    seen: list[tuple[int, float]] = []

    def record(frame: Frame, rng: np.random.Generator) -> Frame:
        seen.append((id(frame), rng.random()))
        return frame

    config = TrainConfig(steps=2, batch_size=2, seed=5)
    grid = Grid(x_range=(0.0, 64.0), y_range=(-24.0, 24.0))
    first = augment_samples(frames, record, config)
    order = sample_order(3, 2, 2, 5).reshape(-1, 2)
    expected = [
        (id(frames[i]), np.random.default_rng([5, e, i]).random()) for e, i in order.tolist()
    ]
    assert seen == expected
    plain = augment_samples(frames, None, config)
    second, again = train(plain, config, grid), train(plain, config, grid)
    other_config = TrainConfig(steps=2, batch_size=2, seed=6)
    other = train(augment_samples(frames, None, other_config), other_config, grid)
    assert second.losses == again.losses and second.losses != other.losses
    weights, repeated = second.model.state_dict(), again.model.state_dict()
    assert all((weights[key] == repeated[key]).all() for key in weights)
    assert first.count == 4 and first.labels == {"Car": 4, "Pedestrian": 4, "Cyclist": 4}
    with pytest.raises(ValueError, match="1 batches for 2 steps"):
        train(augment_samples(frames, None, TrainConfig(steps=1, batch_size=2)), config, grid)


def test_the_samples_digest_changes_with_any_point_box_or_name_and_only_then():
    pytest.importorskip("torch", reason="the detector needs torch (pip install -e '.[detection]')")
    from detection.train import TrainConfig, augment_samples

    frames = _frames(2)
    config = TrainConfig(steps=2, batch_size=2, seed=1)
    digest = augment_samples(frames, None, config).digest
    assert digest == augment_samples(_frames(2), None, config).digest
    assert (
        digest != augment_samples(frames, None, TrainConfig(steps=3, batch_size=2, seed=1)).digest
    )

    def nudge(field: str):
        def augment(frame: Frame, rng: np.random.Generator) -> Frame:
            if field == "points":
                return frame.replace(points=frame.points + np.float32(1e-3))
            if field == "boxes":
                return frame.replace(boxes=frame.boxes[:, [0, 1, 2, 3, 4, 5, 6]] * 1.0001)
            return frame.replace(names=np.array(["Van", *frame.names[1:]]))

        return augment

    changed = {
        augment_samples(frames, nudge(f), config).digest for f in ("points", "boxes", "names")
    }
    assert digest not in changed and len(changed) == 3


def test_training_fits_a_frame_and_predicts_its_objects():
    pytest.importorskip("torch", reason="the detector needs torch (pip install -e '.[detection]')")
    from detection.train import TrainConfig, augment_samples, predict, train

    frames = _frames(1)
    grid = Grid(x_range=(0.0, 64.0), y_range=(-24.0, 24.0))
    config = TrainConfig(steps=60, batch_size=1, learning_rate=1e-2, seed=0)
    result = train(augment_samples(frames, None, config), config, grid)
    assert np.mean(result.losses[-5:]) < 0.3 * np.mean(result.losses[:5])
    (found,) = predict(result.model, frames, grid, threshold=0.3)
    truth = frames[0].boxes
    nearest = np.linalg.norm(truth[:, None, :2] - found.boxes[None, :, :2], axis=2).min(axis=1)
    assert (nearest < 1.0).all()
