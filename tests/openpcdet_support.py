"""Run OpenPCDet's real data pipeline on the CPU, from the read-only snapshot in ``../shared``.

OpenPCDet's compiled CUDA extension modules are absent there (and need CUDA to build). The data
pipeline calls two of their functions: the BEV IoU of ``gt_sampling``'s collision test and the
points-in-boxes test that removes points under sampled boxes. :func:`install` puts CPU stand-ins
for them in ``sys.modules`` (checked against plain geometry in the tests), plus:

* ``pcdet.version`` (written by OpenPCDet's ``setup.py``, not part of its repository);
* ``torchvision``: PyPI's torchvision wheels are CUDA builds that do not load with the CPU torch;
  OpenPCDet's data processor imports it for image normalisation only, which KITTI LiDAR training
  never calls (any use raises);
* ``pcdet.datasets`` as a bare package: its ``__init__`` imports every dataset (ONCE needs cv2,
  Argoverse 2 needs av2 and pandas); the KITTI modules are imported from it directly.
"""

from __future__ import annotations

import ast
import sys
import types
from pathlib import Path
from typing import Any

import numpy as np

SHARED = Path(__file__).resolve().parents[1].parent / "shared"
OPENPCDET = SHARED / "third_party" / "OpenPCDet"
KITTI_SAMPLE = SHARED / "data" / "kitti_sample"
CLASS_NAMES = ["Car", "Pedestrian", "Cyclist"]


def sample_database(out: Path) -> Path:
    """drcpo's database of the KITTI sample at ``out``, imported from OpenPCDet's dbinfos (as
    the README says) and indexed with a small K; the tests' and benchmarks' shared fixture."""
    from drcpo.database import import_openpcdet
    from drcpo.index import IndexConfig
    from drcpo.index_build import build_index

    database = import_openpcdet(KITTI_SAMPLE / "kitti_dbinfos_train.pkl", out)
    build_index(database, IndexConfig(k=20)).save(out)
    return out


# CPU stand-ins ------------------------------------------------------------------------------
def bev_corners(boxes: np.ndarray) -> np.ndarray:
    """``(M, 4, 2)`` BEV corners of ``(M, 7+)`` boxes (centre, dx along the heading)."""
    boxes = np.asarray(boxes, dtype=np.float64)
    half = boxes[:, None, 3:5] / 2.0 * np.array([[1, 1], [-1, 1], [-1, -1], [1, -1]])
    cos, sin = np.cos(boxes[:, 6])[:, None], np.sin(boxes[:, 6])[:, None]
    x = half[..., 0] * cos - half[..., 1] * sin + boxes[:, None, 0]
    y = half[..., 0] * sin + half[..., 1] * cos + boxes[:, None, 1]
    return np.stack([x, y], axis=-1)


def bev_iou(boxes_a: np.ndarray, boxes_b: np.ndarray) -> np.ndarray:
    """``(N, M)`` BEV IoU of rotated boxes (shapely polygons)."""
    from shapely.geometry import Polygon

    a = [Polygon(c) for c in bev_corners(boxes_a)]
    b = [Polygon(c) for c in bev_corners(boxes_b)]
    out = np.zeros((len(a), len(b)), dtype=np.float32)
    for i, pa in enumerate(a):
        for j, pb in enumerate(b):
            inter = pa.intersection(pb).area
            union = pa.area + pb.area - inter
            out[i, j] = inter / union if union > 0 else 0.0
    return out


def points_in_boxes(boxes: np.ndarray, points: np.ndarray) -> np.ndarray:
    """``int32 (M, N)``: 1 where point n lies strictly inside box m (heights within dz / 2)."""
    boxes = np.asarray(boxes, dtype=np.float64)
    points = np.asarray(points, dtype=np.float64)
    d = points[None, :, :3] - boxes[:, None, :3]
    cos, sin = np.cos(boxes[:, 6])[:, None], np.sin(boxes[:, 6])[:, None]
    local_x = d[..., 0] * cos + d[..., 1] * sin
    local_y = -d[..., 0] * sin + d[..., 1] * cos
    inside = (
        (np.abs(d[..., 2]) <= boxes[:, None, 5] / 2.0)
        & (np.abs(local_x) < boxes[:, None, 3] / 2.0)
        & (np.abs(local_y) < boxes[:, None, 4] / 2.0)
    )
    return inside.astype(np.int32)


def _iou3d_module() -> types.ModuleType:
    module = types.ModuleType("pcdet.ops.iou3d_nms.iou3d_nms_cuda")

    def boxes_iou_bev_cpu(boxes_a, boxes_b, out):
        out.copy_(_torch().from_numpy(bev_iou(boxes_a.numpy(), boxes_b.numpy())))

    module.boxes_iou_bev_cpu = boxes_iou_bev_cpu
    return module


def _roiaware_module() -> types.ModuleType:
    module = types.ModuleType("pcdet.ops.roiaware_pool3d.roiaware_pool3d_cuda")

    def points_in_boxes_cpu(boxes, points, out):
        out.copy_(_torch().from_numpy(points_in_boxes(boxes.numpy(), points.numpy())))

    module.points_in_boxes_cpu = points_in_boxes_cpu
    return module


def _torchvision_module() -> types.ModuleType:
    module = types.ModuleType("torchvision")

    def missing(name: str) -> Any:
        raise AttributeError(f"torchvision.{name}: not available in drcpo's CPU test environment")

    module.__getattr__ = missing  # type: ignore[attr-defined]
    return module


def _torch() -> Any:
    import torch

    return torch


def install() -> None:
    """Make ``pcdet`` importable from the snapshot with the CPU stand-ins (idempotent)."""
    if str(OPENPCDET) not in sys.path:
        sys.path.insert(0, str(OPENPCDET))
    version = types.ModuleType("pcdet.version")
    version.__version__ = "0.6.0"
    datasets = types.ModuleType("pcdet.datasets")
    datasets.__path__ = [str(OPENPCDET / "pcdet" / "datasets")]
    stand_ins = {
        "pcdet.version": version,
        "pcdet.ops.iou3d_nms.iou3d_nms_cuda": _iou3d_module(),
        "pcdet.ops.roiaware_pool3d.roiaware_pool3d_cuda": _roiaware_module(),
        "pcdet.datasets": datasets,
    }
    try:
        import torchvision  # noqa: F401
    except Exception:  # the CUDA wheel fails in many ways without CUDA torch
        sys.modules.pop("torchvision", None)
        stand_ins["torchvision"] = _torchvision_module()
    for name, module in stand_ins.items():
        sys.modules.setdefault(name, module)


def load_data_to_gpu() -> Any:
    """OpenPCDet's ``pcdet.models.load_data_to_gpu``, compiled from its source on its own: its
    package ``__init__`` builds the detectors (spconv, CUDA)."""
    import torch

    source = (OPENPCDET / "pcdet" / "models" / "__init__.py").read_text()
    tree = ast.parse(source)
    func = next(
        n for n in tree.body if isinstance(n, ast.FunctionDef) and n.name == "load_data_to_gpu"
    )
    namespace: dict[str, Any] = {"np": np, "torch": torch}
    exec(
        compile(ast.Module([func], []), str(OPENPCDET / "pcdet/models/__init__.py"), "exec"),
        namespace,
    )
    return namespace["load_data_to_gpu"]


def dataset_config(drcpo_entry: dict[str, Any] | None = None, position: int = 1) -> Any:
    """OpenPCDet's own ``kitti_dataset.yaml`` on the KITTI sample: road planes off (the sample
    has none), no Cyclist in ``gt_sampling`` (the sample's only one has difficulty -1, which the
    config filters out, and OpenPCDet's sampler fails on a class left empty), no voxelisation
    (it needs spconv); ``drcpo_entry`` inserted at ``position``."""
    import yaml
    from easydict import EasyDict

    path = OPENPCDET / "tools" / "cfgs" / "dataset_configs" / "kitti_dataset.yaml"
    cfg = EasyDict(yaml.safe_load(path.read_text()))
    cfg.DATA_PATH = str(KITTI_SAMPLE)
    entries = cfg.DATA_AUGMENTOR.AUG_CONFIG_LIST
    for entry in entries:
        if entry.NAME == "gt_sampling":
            entry.USE_ROAD_PLANE = False
            entry.SAMPLE_GROUPS = [g for g in entry.SAMPLE_GROUPS if not g.startswith("Cyclist")]
    if drcpo_entry is not None:
        entries.insert(position, EasyDict(drcpo_entry))
    cfg.DATA_PROCESSOR = [p for p in cfg.DATA_PROCESSOR if p.NAME != "transform_points_to_voxels"]
    return cfg
