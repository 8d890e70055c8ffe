import struct

import numpy as np
import pytest
from scipy.spatial import Delaunay

from drcpo.database import safe_pickle
from drcpo.datasets.kitti import (
    KittiDataset,
    kitti_difficulty,
    read_calib,
    read_image_shape,
    read_labels,
    read_plane,
    read_points,
    read_split,
)
from drcpo.datasets.kitti_coordinates import (
    DEFAULT_IMAGE_SHAPE,
    Calibration,
    camera_boxes_to_lidar,
    fov_mask,
    lidar_boxes_to_camera,
)
from drcpo.errors import DataError
from drcpo.geometry import box_corners

CALIB_TEXT = """P0: 7.2e+02 0 6.0e+02 0 0 7.2e+02 1.7e+02 0 0 0 1 0
P2: 7.215377e+02 0 6.095593e+02 4.485728e+01 0 7.215377e+02 1.72854e+02 2.163791e-01 0 0 1 2.745884e-03
R0_rect: 9.999239e-01 9.83776e-03 -7.445048e-03 -9.869795e-03 9.999421e-01 -4.278459e-03 7.402527e-03 4.351614e-03 9.999631e-01
Tr_velo_to_cam: 7.533745e-03 -9.999714e-01 -6.16602e-04 -4.069766e-03 1.480249e-02 7.280733e-04 -9.998902e-01 -7.631618e-02 9.998621e-01 7.52379e-03 1.480755e-02 -2.717806e-01
"""  # noqa: E501

LABEL_TEXT = """Car 0.00 0 1.85 387.63 181.54 423.81 203.12 1.67 1.87 3.69 -16.53 2.39 58.49 1.57
DontCare -1 -1 -10 503.89 169.71 590.61 190.13 -1 -1 -1 -1000 -1000 -1000 -10
Pedestrian 0.20 1 -0.2 712.40 143.00 810.73 307.92 1.89 0.48 1.20 1.84 1.47 8.41 0.01 0.75
"""


@pytest.fixture
def calib(tmp_path) -> Calibration:
    path = tmp_path / "calib.txt"
    path.write_text(CALIB_TEXT)
    return read_calib(path)


def _infos(kitti_sample):
    infos = safe_pickle.load(kitti_sample / "kitti_infos_train.pkl")
    return {info["point_cloud"]["lidar_idx"]: info for info in infos}


# Point clouds -------------------------------------------------------------------------------
def test_read_points_round_trip(tmp_path, rng):
    points = rng.normal(size=(50, 4)).astype(np.float32)
    points.tofile(tmp_path / "000007.bin")
    np.testing.assert_array_equal(read_points(tmp_path / "000007.bin"), points)
    assert read_points(tmp_path / "000007.bin").dtype == np.float32


def test_bin_size_not_multiple_of_16_names_the_file(tmp_path):
    path = tmp_path / "000003.bin"
    np.zeros(4 * 5 + 3, np.float32).tofile(path)  # 92 bytes
    with pytest.raises(DataError, match=r"000003\.bin: size 92 bytes is not a multiple of 16"):
        read_points(path)


@pytest.mark.parametrize("extra", [1, 2, 3, 5, 15])
def test_partial_last_point_is_refused_with_the_true_size(tmp_path, extra):
    # 1-3 bytes past a whole point: not even a whole float32 more, which a count of the
    # float32 values read would miss.
    path = tmp_path / "000005.bin"
    path.write_bytes(np.ones((5, 4), np.float32).tobytes() + b"\x01" * extra)
    size = 80 + extra
    with pytest.raises(DataError, match=rf"000005\.bin: size {size} bytes is not a multiple of 16"):
        read_points(path)


def test_read_points_is_float32_and_native(tmp_path, rng):
    points = rng.normal(size=(7, 4)).astype(np.float32)
    points.tofile(tmp_path / "000008.bin")
    out = read_points(tmp_path / "000008.bin")
    assert out.dtype == np.float32 and out.dtype.isnative and out.flags.c_contiguous
    assert out.flags.writeable
    np.testing.assert_array_equal(
        read_points(tmp_path / "000008.bin", num_features=2), points.reshape(-1, 2)
    )


@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
def test_nan_or_inf_points_name_the_file_and_point(tmp_path, bad):
    points = np.zeros((6, 4), np.float32)
    points[4, 1] = bad
    path = tmp_path / "000004.bin"
    points.tofile(path)
    with pytest.raises(DataError, match=r"000004\.bin: point 4 holds a NaN or infinite value"):
        read_points(path)


def test_missing_point_cloud_names_the_file(tmp_path):
    with pytest.raises(DataError, match=r"absent\.bin: cannot read point cloud"):
        read_points(tmp_path / "absent.bin")


# Calibration --------------------------------------------------------------------------------
def test_read_calib_parses_named_fields(calib):
    assert calib.P2.shape == (3, 4) and calib.P2.dtype == np.float32
    assert calib.P2[0, 3] == np.float32(4.485728e01)
    assert calib.R0_rect[2, 2] == np.float32(9.999631e-01)
    assert calib.Tr_velo_to_cam[2, 3] == np.float32(-2.717806e-01)


def test_missing_calib_file_names_the_file(tmp_path):
    with pytest.raises(DataError, match=r"000042\.txt: calibration file missing"):
        read_calib(tmp_path / "calib" / "000042.txt")


def test_missing_calib_field_names_file_and_field(tmp_path):
    path = tmp_path / "000001.txt"
    path.write_text("\n".join(CALIB_TEXT.splitlines()[:3]))  # no Tr_velo_to_cam
    with pytest.raises(DataError, match=r"000001\.txt: calibration field\(s\) Tr_velo_to_cam"):
        read_calib(path)


def test_short_calib_field_names_file_and_line(tmp_path):
    path = tmp_path / "000001.txt"
    path.write_text(CALIB_TEXT.replace("R0_rect: 9.999239e-01 ", "R0_rect: "))
    with pytest.raises(DataError, match=r"000001\.txt:3: R0_rect needs 9 finite numbers"):
        read_calib(path)


_R0_LINE = CALIB_TEXT.splitlines()[2]
_TR_LINE = CALIB_TEXT.splitlines()[3]


@pytest.mark.parametrize(
    ("line", "replacement", "where"),
    [
        (_R0_LINE, "R0_rect: " + " ".join(["0"] * 9), r"000009\.txt:3: R0_rect"),
        (_TR_LINE, "Tr_velo_to_cam: " + " ".join(["0"] * 12), r"000009\.txt:4: Tr_velo_to_cam"),
        # Rank 2: the third row repeats the first (a copy-paste slip).
        (_R0_LINE, "R0_rect: 1 0 0 0 1 0 1 0 0", r"000009\.txt:3: R0_rect"),
        # The rotation part is singular even though the translation column is not zero.
        (_TR_LINE, "Tr_velo_to_cam: 0 0 0 1 0 0 0 2 0 0 0 3", r"000009\.txt:4: Tr_velo_to_cam"),
    ],
)
def test_singular_calibration_names_the_file_and_matrix(tmp_path, line, replacement, where):
    # Before: read_calib accepted it and the LiDAR conversion raised numpy's LinAlgError.
    path = tmp_path / "000009.txt"
    path.write_text(CALIB_TEXT.replace(line, replacement))
    with pytest.raises(DataError, match=where + r" is singular"):
        read_calib(path)


def test_singular_calibration_fails_a_kitti_frame_with_a_data_error(tmp_path):
    (tmp_path / "ImageSets").mkdir()
    (tmp_path / "ImageSets" / "train.txt").write_text("000000\n")
    base = tmp_path / "training"
    for sub in ("velodyne", "label_2", "calib"):
        (base / sub).mkdir(parents=True)
    np.zeros((3, 4), np.float32).tofile(base / "velodyne" / "000000.bin")
    (base / "label_2" / "000000.txt").write_text(LABEL_TEXT)
    (base / "calib" / "000000.txt").write_text(
        CALIB_TEXT.replace(_R0_LINE, "R0_rect: " + " ".join(["0"] * 9))
    )
    with pytest.raises(DataError, match=r"calib/000000\.txt:3: R0_rect is singular"):
        KittiDataset(tmp_path, "train")[0]


def test_sample_calib_matches_openpcdet_infos(kitti_sample):
    for frame_id, info in _infos(kitti_sample).items():
        calib = read_calib(kitti_sample / "training" / "calib" / f"{frame_id}.txt")
        np.testing.assert_array_equal(calib.P2, info["calib"]["P2"][:3])
        np.testing.assert_array_equal(calib.R0_rect, info["calib"]["R0_rect"][:3, :3])
        np.testing.assert_array_equal(calib.Tr_velo_to_cam, info["calib"]["Tr_velo_to_cam"][:3])


# Labels -------------------------------------------------------------------------------------
def test_read_labels_drops_dontcare_and_keeps_fields(tmp_path):
    path = tmp_path / "000001.txt"
    path.write_text(LABEL_TEXT)
    labels = read_labels(path)
    assert labels.names.tolist() == ["Car", "Pedestrian"]
    assert labels.lines.tolist() == [1, 3]
    np.testing.assert_allclose(labels.dimensions[1], [1.20, 1.89, 0.48])  # l, h, w
    np.testing.assert_allclose(labels.location[0], [-16.53, 2.39, 58.49], rtol=1e-6)
    np.testing.assert_allclose(labels.score, [-1.0, 0.75])
    assert labels.occlusion.tolist() == [0, 1]
    np.testing.assert_allclose(labels.truncation, [0.0, 0.2])
    # Car: 203.12 - 181.54 + 1 < 25 pixels; Pedestrian: tall, occlusion 1 -> moderate
    assert labels.difficulty.tolist() == [-1, 1]
    assert labels.camera_boxes.shape == (2, 7)


def test_empty_label_file_gives_no_objects(tmp_path, calib):
    path = tmp_path / "000009.txt"
    path.write_text("DontCare -1 -1 -10 1 2 3 4 -1 -1 -1 -1000 -1000 -1000 -10\n\n")
    labels = read_labels(path)
    assert len(labels) == 0
    assert labels.lidar_boxes(calib).shape == (0, 7)


@pytest.mark.parametrize(
    ("line", "expected"),
    [
        ("Car 0.00 0 1.85 387.63 181.54 423.81 203.12 1.67 1.87", r"expected 15 or 16 fields"),
        ("Car 0.00 0 1.85 387.63 181.54 423.81 203.12 1.67 1.87 3.69 -16.53 x 58.49 1.57", "not a"),
        ("Car 0.00 0 nan 387.63 181.54 423.81 203.12 1.67 1.87 3.69 -16.53 2.39 58.49 1.57", "NaN"),
        ("Car 0.00 0 1.85 387.63 181.54 423.81 203.12 0 1.87 3.69 -16.53 2.39 58.49 1.57", "size"),
    ],
)
def test_malformed_label_line_names_file_and_line(tmp_path, line, expected):
    path = tmp_path / "000005.txt"
    path.write_text(LABEL_TEXT + line + "\n")
    with pytest.raises(DataError, match=r"000005\.txt:4: ") as error:
        read_labels(path)
    assert expected in str(error.value)


def test_missing_label_file_names_the_file(tmp_path):
    with pytest.raises(DataError, match=r"000008\.txt: label file missing"):
        read_labels(tmp_path / "000008.txt")


def test_lidar_boxes_equal_openpcdet_gt_boxes_lidar(kitti_sample):
    dataset = KittiDataset(kitti_sample, "train")
    for frame_id, info in _infos(kitti_sample).items():
        labels = dataset.labels(frame_id)
        annos = info["annos"]
        expected = annos["gt_boxes_lidar"]
        boxes = labels.lidar_boxes(dataset.calib(frame_id))
        np.testing.assert_allclose(boxes, expected, rtol=0, atol=1e-4)
        # the float32 path reproduces OpenPCDet exactly
        np.testing.assert_array_equal(boxes, expected)
        assert labels.names.tolist() == annos["name"][: len(expected)].tolist()
        np.testing.assert_array_equal(labels.difficulty, annos["difficulty"][: len(expected)])
        np.testing.assert_array_equal(labels.bbox2d, annos["bbox"][: len(expected)])


def test_camera_lidar_conversions_are_inverse(kitti_sample):
    dataset = KittiDataset(kitti_sample, "train")
    for frame_id in dataset.frame_ids:
        calib, labels = dataset.calib(frame_id), dataset.labels(frame_id)
        lidar = camera_boxes_to_lidar(labels.camera_boxes, calib)
        np.testing.assert_allclose(lidar, labels.lidar_boxes(calib), atol=1e-4)
        np.testing.assert_allclose(
            lidar_boxes_to_camera(lidar, calib), labels.camera_boxes, atol=1e-4
        )


# Difficulty ---------------------------------------------------------------------------------
def _box(height):
    return [100.0, 200.0, 150.0, 200.0 + height]


@pytest.mark.parametrize(
    ("height", "occlusion", "truncation", "openpcdet", "devkit"),
    [
        (60, 0, 0.0, 0, 0),
        (39.5, 0, 0.0, 0, 1),  # 39.5 + 1 pixels reach easy only with OpenPCDet's +1
        (60, 1, 0.0, 1, 1),
        (60, 0, 0.16, 1, 1),
        (60, 0, 0.15, 0, 0),
        (30, 0, 0.0, 1, 1),
        (60, 2, 0.0, 2, 2),
        (60, 0, 0.4, 2, 2),
        (60, 3, 0.0, -1, -1),
        (60, 0, 0.51, -1, -1),
        (23.5, 0, 0.0, -1, -1),
        (24.0, 0, 0.0, 1, -1),
    ],
)
def test_kitti_difficulty_levels(height, occlusion, truncation, openpcdet, devkit):
    args = ([_box(height)], [occlusion], [truncation])
    assert kitti_difficulty(*args).tolist() == [openpcdet]
    assert kitti_difficulty(*args, convention="devkit").tolist() == [devkit]


def test_kitti_difficulty_rejects_unknown_convention():
    with pytest.raises(ValueError, match="convention"):
        kitti_difficulty([_box(50)], [0], [0.0], convention="waymo")


# Splits, planes, images ---------------------------------------------------------------------
def test_read_split(kitti_sample):
    assert read_split(kitti_sample, "train") == [f"{i:06d}" for i in range(6)]


def test_unknown_split_names_the_file_and_lists_available(kitti_sample):
    with pytest.raises(DataError) as error:
        read_split(kitti_sample, "trainval")
    message = str(error.value)
    assert "ImageSets/trainval.txt" in message
    assert "available: test, train, val" in message


def test_split_without_image_sets(tmp_path):
    with pytest.raises(DataError, match=r"unknown split 'train' \(available: none"):
        read_split(tmp_path, "train")


def test_read_plane_flips_and_normalises(tmp_path):
    path = tmp_path / "000000.txt"
    path.write_text("# Matrix\nWIDTH 4\nHEIGHT 1\n0.0 2.0 0.0 -3.4\n")
    np.testing.assert_allclose(read_plane(path), [0.0, -1.0, 0.0, 1.7])
    path.write_text("# Matrix\nWIDTH 4\nHEIGHT 1\n0.0 -1.0\n")
    with pytest.raises(DataError, match=r"000000\.txt:4: expected 4 finite coefficients"):
        read_plane(path)


def test_read_image_shape_from_png_header(tmp_path):
    path = tmp_path / "000000.png"
    path.write_bytes(
        b"\x89PNG\r\n\x1a\n" + struct.pack(">I", 13) + b"IHDR" + struct.pack(">II", 1224, 370)
    )
    assert read_image_shape(path) == (370, 1224)
    path.write_bytes(b"GIF89a" + bytes(30))
    with pytest.raises(DataError, match=r"000000\.png: not a PNG image"):
        read_image_shape(path)


# Field of view ------------------------------------------------------------------------------
def test_fov_mask_reproduces_openpcdet_num_points_in_gt(kitti_sample):
    # OpenPCDet counts num_points_in_gt in its infos on FOV-filtered points with a Delaunay
    # in-hull test; the same counts come out of our FOV filter.
    dataset = KittiDataset(kitti_sample, "train")
    for frame_id, info in _infos(kitti_sample).items():
        frame = dataset.frame(frame_id)
        shape = tuple(int(s) for s in info["image"]["image_shape"])
        visible = frame.points[fov_mask(frame.points, frame.metadata["calib"], shape)]
        counts = [
            int((Delaunay(corners).find_simplex(visible[:, :3]) >= 0).sum())
            for corners in box_corners(frame.boxes)
        ]
        assert counts == info["annos"]["num_points_in_gt"][: len(frame.boxes)].tolist()


def test_products_in_blocks_equal_one_product(rng):
    # Large point sets go through the calibration's products in blocks (so that BLAS keeps to
    # one thread); every row must come out as from one product.
    from drcpo.datasets.kitti_coordinates import _PRODUCT_ROWS, _product  # test seam: the blocks

    rows = (rng.normal(size=(2 * _PRODUCT_ROWS + 123, 4)) * 30).astype(np.float32)
    matrix = rng.normal(size=(4, 3)).astype(np.float32)
    np.testing.assert_array_equal(_product(rows, matrix), rows @ matrix)
    np.testing.assert_array_equal(_product(rows[:10], matrix), rows[:10] @ matrix)


def test_fov_mask_keeps_points_in_front_within_the_image(calib):
    points = np.array(
        [
            [20.0, 0.0, 0.0, 0.0],  # straight ahead
            [-20.0, 0.0, 0.0, 0.0],  # behind
            [5.0, 30.0, 0.0, 0.0],  # far left of the image
            [0.0, 0.0, 0.0, 0.0],  # at the sensor
        ],
        dtype=np.float32,
    )
    assert fov_mask(points, calib).tolist() == [True, False, False, False]
    assert fov_mask(points, calib, image_shape=(0, 0)).tolist() == [False] * 4


# Whole frames -------------------------------------------------------------------------------
def test_dataset_frames(kitti_sample):
    dataset = KittiDataset(kitti_sample, "train")
    assert len(dataset) == 6
    frame = dataset[1]
    assert frame.frame_id == "000001"
    assert frame.points.dtype == np.float32 and frame.points.shape[1] == 4
    assert frame.names.tolist() == ["Truck", "Car", "Cyclist"]
    assert frame.boxes.shape == (3, 7)
    assert frame.metadata["image_shape"] == DEFAULT_IMAGE_SHAPE  # the sample has no image_2
    assert frame.metadata["plane"] is None
    assert frame.metadata["difficulty"].tolist() == [1, -1, -1]
    assert [f.frame_id for f in dataset] == dataset.frame_ids
    frame.validate()


@pytest.mark.parametrize("bad", ["../../../escape", "/abs/path", "a/b", ".hidden", "a b"])
def test_split_frame_ids_cannot_name_paths_outside_their_directory(tmp_path, bad):
    (tmp_path / "ImageSets").mkdir()
    (tmp_path / "ImageSets" / "train.txt").write_text(f"000000\n\n{bad}\n")
    with pytest.raises(DataError, match=r"train\.txt:3: .* is not a frame id"):
        read_split(tmp_path, "train")


def test_split_keeps_ordinary_frame_ids_in_order(tmp_path):
    (tmp_path / "ImageSets").mkdir()
    (tmp_path / "ImageSets" / "val.txt").write_text("000002\n  000001  \n\nsynth_0.v2\n")
    assert read_split(tmp_path, "val") == ["000002", "000001", "synth_0.v2"]
