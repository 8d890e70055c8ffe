"""Shared set-up of the MMDetection3D tests and benchmark: paths and the ``mmcv._ext`` stand-in.

mmcv-lite (what CI installs: no CUDA build) has no compiled ``mmcv._ext``, yet ``mmcv.ops``,
which mmdet3d's box structures import, looks its kernels up there at import time. None of them
is called by the data pipeline, so a stand-in module whose every kernel raises is enough.
"""

from __future__ import annotations

import importlib.machinery
import importlib.util
import sys
import types
from pathlib import Path

SHARED = Path(__file__).resolve().parents[1].parent / "shared"
KITTI_SAMPLE = SHARED / "data" / "kitti_sample"
CLASS_NAMES = ["Pedestrian", "Cyclist", "Car"]
#: mmdet3d's KittiDataset.METAINFO classes: the infos' labels index this list.
KITTI_CLASSES = ["Pedestrian", "Cyclist", "Car", "Van", "Truck", "Person_sitting", "Tram", "Misc"]
POINT_RANGE = [0, -40, -3, 70.4, 40, 1]


def _missing_kernel(name: str):
    if name.startswith("__"):
        raise AttributeError(name)

    def kernel(*args, **kwargs):
        raise RuntimeError(f"mmcv._ext.{name} is a test stand-in (mmcv-lite has no kernels)")

    return kernel


def install() -> None:
    """Put the ``mmcv._ext`` stand-in in place unless a compiled one exists. Idempotent."""
    if "mmcv._ext" in sys.modules or importlib.util.find_spec("mmcv") is None:
        return
    try:
        import mmcv._ext  # noqa: F401  (a full mmcv build: use its kernels)
    except ImportError:
        module = types.ModuleType("mmcv._ext")
        module.__getattr__ = _missing_kernel  # every kernel name resolves (PEP 562)
        module.__spec__ = importlib.machinery.ModuleSpec("mmcv._ext", None)  # for pkgutil
        sys.modules["mmcv._ext"] = module


def write_mmdet3d_dbinfos(kitti_sample: Path, root: Path) -> Path:
    """The sample's OpenPCDet database rewritten as MMDetection3D's ``create_data.py`` writes one
    (``root/kitti_dbinfos_train.pkl`` + ``root/kitti_gt_database/``): ``box3d_lidar`` z at the
    bottom centre, points minus the bottom centre, integer ``image_idx``. The labels are linked
    as ``root/training/label_2``. Returns the pickle's path."""
    import pickle

    import numpy as np

    from drcpo.database import safe_pickle

    (root / "kitti_gt_database").mkdir(parents=True)
    (root / "training").mkdir(exist_ok=True)
    (root / "training" / "label_2").symlink_to(kitti_sample / "training" / "label_2")
    infos = safe_pickle.load(kitti_sample / "kitti_dbinfos_train.pkl")
    for objects in infos.values():
        for info in objects:
            box = np.array(info["box3d_lidar"], dtype=np.float32)
            half = box[5] / np.float32(2.0)
            points = np.fromfile(kitti_sample / info["path"], np.float32).reshape(-1, 4)
            points[:, 2] += half
            path = Path("kitti_gt_database") / Path(info["path"]).name
            points.tofile(root / path)
            box[2] -= half
            info.update(path=str(path), box3d_lidar=box, image_idx=int(info["image_idx"]))
    out = root / "kitti_dbinfos_train.pkl"
    with open(out, "wb") as f:
        pickle.dump(infos, f)
    return out


def write_mmdet3d_infos(kitti_sample: Path, out: Path) -> Path:
    """mmdet3d 1.x KITTI infos (``kitti_infos_train.pkl``: ``metainfo`` + ``data_list``) of the
    sample's training frames, from drcpo's KITTI reader, as mmdet3d's converter writes them:
    camera boxes ``(x, y, z bottom centre, l, h, w, ry)``, labels indexing
    :data:`KITTI_CLASSES`, ``lidar2cam = R0_rect @ Tr_velo_to_cam``."""
    import numpy as np

    from drcpo.datasets.kitti import read_calib, read_labels, read_split

    data_list = []
    for frame_id in read_split(kitti_sample, "train"):
        calib = read_calib(kitti_sample / "training" / "calib" / f"{frame_id}.txt")
        labels = read_labels(kitti_sample / "training" / "label_2" / f"{frame_id}.txt")
        r0, v2c, cam2img = np.eye(4), np.eye(4), np.eye(4)
        r0[:3, :3], v2c[:3, :4], cam2img[:3, :4] = calib.R0_rect, calib.Tr_velo_to_cam, calib.P2
        lidar2cam = r0 @ v2c
        instances = []
        for i, name in enumerate(labels.names):
            label = KITTI_CLASSES.index(name) if name in KITTI_CLASSES else -1
            box = [*labels.location[i].tolist(), *labels.dimensions[i].tolist()]
            instances.append(
                {
                    "bbox": labels.bbox2d[i].tolist(),
                    "bbox_label": label,
                    "bbox_3d": [*box, float(labels.rotation_y[i])],
                    "bbox_label_3d": label,
                    "difficulty": int(labels.difficulty[i]),
                    "truncated": float(labels.truncation[i]),
                    "occluded": int(labels.occlusion[i]),
                }
            )
        camera = {
            "img_path": f"{frame_id}.png",
            "cam2img": cam2img.tolist(),
            "lidar2cam": lidar2cam.tolist(),
            "lidar2img": (cam2img @ lidar2cam).tolist(),
        }
        data_list.append(
            {
                "sample_idx": int(frame_id),
                "lidar_points": {"num_pts_feats": 4, "lidar_path": f"{frame_id}.bin"},
                "images": {"CAM2": camera},
                "instances": instances,
            }
        )
    import mmengine

    metainfo = {"categories": {c: i for i, c in enumerate(KITTI_CLASSES)}, "dataset": "kitti"}
    mmengine.dump({"metainfo": metainfo, "data_list": data_list}, str(out))
    return out


def pipeline(augment: dict) -> list[dict]:
    """mmdet3d's KITTI 3-class train pipeline (configs/_base_/datasets/kitti-3d-3class.py) with
    ``augment`` where ObjectSample stands."""
    return [
        dict(type="LoadPointsFromFile", coord_type="LIDAR", load_dim=4, use_dim=4),
        dict(type="LoadAnnotations3D", with_bbox_3d=True, with_label_3d=True),
        augment,
        dict(type="RandomFlip3D", flip_ratio_bev_horizontal=0.5),
        dict(
            type="GlobalRotScaleTrans",
            rot_range=[-0.78539816, 0.78539816],
            scale_ratio_range=[0.95, 1.05],
        ),
        dict(type="PointsRangeFilter", point_cloud_range=POINT_RANGE),
        dict(type="ObjectRangeFilter", point_cloud_range=POINT_RANGE),
        dict(type="PointShuffle"),
        dict(type="Pack3DDetInputs", keys=["points", "gt_bboxes_3d", "gt_labels_3d"]),
    ]


def dataset(infos: Path, transforms: list, packed: bool = True):
    """mmdet3d's KittiDataset (training) of the sample with ``transforms`` as its pipeline;
    ``packed``: the pipeline ends in Pack3DDetInputs (else the dataset cannot skip empty
    samples, as it does by default)."""
    from mmdet3d.datasets import KittiDataset

    return KittiDataset(
        filter_empty_gt=packed,
        data_root=str(KITTI_SAMPLE),
        ann_file=str(infos),
        data_prefix=dict(pts="training/velodyne"),
        pipeline=transforms,
        modality=dict(use_lidar=True, use_camera=False),
        metainfo=dict(classes=CLASS_NAMES),
        test_mode=False,
    )


def object_sample(tmp_path: Path) -> dict:
    """mmdet3d's own ObjectSample on an mmdet3d database of the sample."""
    pkl = write_mmdet3d_dbinfos(KITTI_SAMPLE, tmp_path / "mmdet3d")
    sampler = dict(
        data_root=str(pkl.parent),
        info_path=str(pkl),
        rate=1.0,
        prepare=dict(filter_by_difficulty=[-1], filter_by_min_points=dict(Car=5)),
        classes=CLASS_NAMES,
        # The sample's one Cyclist has difficulty -1: an empty pool crashes mmdet3d's sampler.
        sample_groups=dict(Car=15, Pedestrian=15),
        points_loader=dict(type="LoadPointsFromFile", coord_type="LIDAR", load_dim=4, use_dim=4),
    )
    return dict(type="ObjectSample", db_sampler=sampler)
