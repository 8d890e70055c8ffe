"""KITTI layout writer: files read back by our KITTI reader give what was written."""

from __future__ import annotations

import os
import stat

import numpy as np
import pytest

from drcpo.datasets.kitti import KittiDataset, read_calib, read_labels, read_points, read_split
from drcpo.datasets.kitti_coordinates import Calibration, lidar_boxes_to_camera
from drcpo.datasets.kitti_writer import (
    calib_text,
    calibration_matrices,
    label_lines,
    project_boxes,
    reference_calibration,
    write_calib,
    write_frame,
    write_image_sets,
    write_points,
)
from drcpo.errors import DataError
from drcpo.geometry import box_corners, wrap_angle


def _boxes_in_view(rng, n):
    x = rng.uniform(8, 60, n)
    y = rng.uniform(-0.4, 0.4, n) * x
    dims = rng.uniform([0.5, 0.4, 1.2], [5.0, 2.0, 2.0], (n, 3))
    z = -1.73 + dims[:, 2] / 2 + rng.uniform(-0.2, 0.2, n)
    return np.column_stack([x, y, z, dims, rng.uniform(-np.pi, np.pi, n)])


def test_reference_calibration_reproduces_a_kitti_calib_file(kitti_sample):
    original = kitti_sample / "training" / "calib" / "000001.txt"
    assert calib_text(calibration_matrices(reference_calibration())) == original.read_text()


def test_calib_round_trip(tmp_path):
    calib = reference_calibration()
    perturbed = {
        "P2": calib.P2 + 1e-3,
        "R0_rect": calib.R0_rect,
        "Tr_velo_to_cam": calib.Tr_velo_to_cam,
    }
    other = Calibration(**perturbed)
    path = write_calib(tmp_path / "calib.txt", calibration_matrices(other))
    back = read_calib(path)
    for key in ("P2", "R0_rect", "Tr_velo_to_cam"):
        np.testing.assert_array_equal(getattr(back, key), getattr(other, key))
    text = path.read_text()
    assert all(f"{key}:" in text for key in ("P0", "P1", "P3", "Tr_imu_to_velo"))


def test_calib_text_names_a_missing_matrix():
    matrices = calibration_matrices(reference_calibration())
    del matrices["Tr_imu_to_velo"]
    with pytest.raises(DataError, match="Tr_imu_to_velo"):
        calib_text(matrices)


def test_points_round_trip_and_bad_points_leave_no_file(tmp_path, rng):
    points = rng.normal(size=(1000, 4)).astype(np.float32)
    path = write_points(tmp_path / "v" / "000000.bin", points)
    np.testing.assert_array_equal(read_points(path), points)
    points[3, 1] = np.nan
    with pytest.raises(DataError, match="NaN"):
        write_points(tmp_path / "v" / "000001.bin", points)
    assert sorted(p.name for p in (tmp_path / "v").iterdir()) == ["000000.bin"]


def test_labels_round_trip_to_the_boxes_written(tmp_path, rng):
    calib = reference_calibration()
    boxes = _boxes_in_view(rng, 40)
    names = rng.choice(["Car", "Pedestrian", "Cyclist"], 40).tolist()
    occlusion = rng.integers(0, 4, 40)
    path = tmp_path / "label.txt"
    path.write_text("".join(f"{x}\n" for x in label_lines(boxes, names, calib, occlusion)))
    labels = read_labels(path)
    back = labels.lidar_boxes(calib)
    np.testing.assert_allclose(back[:, :6], boxes[:, :6], atol=1e-4)
    np.testing.assert_allclose(wrap_angle(back[:, 6] - boxes[:, 6]), 0.0, atol=1e-5)
    assert labels.names.tolist() == names
    np.testing.assert_array_equal(labels.occlusion, occlusion)
    # alpha agrees with OpenPCDet's definition (-arctan2(-y, x) + ry) to the rig's offsets.
    ry = lidar_boxes_to_camera(boxes, calib)[:, 6]
    openpcdet_alpha = -np.arctan2(-boxes[:, 1], boxes[:, 0]) + ry
    np.testing.assert_allclose(wrap_angle(labels.alpha - openpcdet_alpha), 0.0, atol=0.02)


def test_projected_box_of_a_box_in_view_is_its_corners_bounds(rng):
    calib = reference_calibration()
    boxes = _boxes_in_view(rng, 10)
    boxes[:, 1] = rng.uniform(-0.15, 0.15, 10) * boxes[:, 0]  # well inside the image
    bbox, truncation = project_boxes(boxes, calib)
    corners = box_corners(boxes).reshape(-1, 3)
    pixels, _ = calib.rect_to_image(calib.lidar_to_rect(corners))
    pixels = pixels.reshape(-1, 8, 2)
    np.testing.assert_allclose(bbox[:, :2], pixels.min(axis=1), atol=1e-3)
    np.testing.assert_allclose(bbox[:, 2:], pixels.max(axis=1), atol=1e-3)
    np.testing.assert_array_equal(truncation, 0.0)


def test_truncation_of_boxes_leaving_the_image():
    calib = reference_calibration()
    boxes = np.array(
        [
            [10.0, 0.0, -0.9, 4.0, 1.6, 1.5, 0.0],  # in view
            [6.0, 5.5, -0.9, 4.0, 1.6, 1.5, 0.0],  # crosses the left image border
            [2.0, 6.0, -0.9, 4.0, 1.6, 1.5, 0.0],  # mostly beside the camera
            [-10.0, 0.0, -0.9, 4.0, 1.6, 1.5, 0.0],  # behind
        ]
    )
    bbox, truncation = project_boxes(boxes, calib)
    assert truncation[0] == 0.0
    assert 0.05 < truncation[1] < 0.95
    assert truncation[2] > truncation[1]
    assert truncation[3] == 1.0 and np.isnan(bbox[3]).all()
    assert bbox[1, 0] == 0.0  # clipped at the border
    lines = label_lines(boxes, ["Car"] * 4, calib)
    assert [float(line.split()[1]) for line in lines] == pytest.approx(truncation, abs=0.005)
    assert all(int(line.split()[2]) == 3 for line in lines)  # occlusion unknown by default


def test_label_lines_reject_bad_boxes():
    calib = reference_calibration()
    with pytest.raises(DataError, match="positive"):
        label_lines(np.array([[10, 0, 0, 0, 1, 1, 0.0]]), ["Car"], calib)
    with pytest.raises(DataError, match="names"):
        label_lines(np.array([[10, 0, 0, 1, 1, 1, 0.0]]), [], calib)


def test_write_frame_reads_back_through_the_dataset(tmp_path, rng):
    calib = reference_calibration()
    boxes = _boxes_in_view(rng, 5)
    points = rng.normal(size=(500, 4)).astype(np.float32)
    names = ["Car", "Car", "Pedestrian", "Cyclist", "Car"]
    write_frame(
        tmp_path, "000007", points, boxes, names, calib, occlusion=np.array([0, 1, 2, 0, 1])
    )
    write_image_sets(tmp_path, {"train": ["000007"], "val": []})
    assert read_split(tmp_path, "train") == ["000007"] and read_split(tmp_path, "val") == []
    frame = KittiDataset(tmp_path, "train")[0]
    np.testing.assert_array_equal(frame.points, points)
    np.testing.assert_allclose(frame.boxes[:, :6], boxes[:, :6], atol=1e-4)
    assert frame.names.tolist() == names
    np.testing.assert_array_equal(frame.metadata["occlusion"], [0, 1, 2, 0, 1])
    leftovers = [p for p in tmp_path.rglob("*") if p.name.startswith(".")]
    assert leftovers == []


def test_written_files_get_the_usual_permissions(tmp_path, rng):
    umask = os.umask(0o022)
    try:
        path = write_points(tmp_path / "000000.bin", rng.normal(size=(10, 4)).astype(np.float32))
    finally:
        os.umask(umask)
    assert stat.S_IMODE(path.stat().st_mode) == 0o644
