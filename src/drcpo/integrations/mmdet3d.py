"""drcpo as an MMDetection3D 1.x data transform (``DRCPOAugment``) and a hook to fade it out.

Importing this module registers ``DRCPOAugment`` in mmdet3d's ``TRANSFORMS`` and
``DRCPOFadeHook`` in its ``HOOKS`` (it imports only mmdet3d's registries, mmengine and mmcv's
transform base class; mmdet3d's datasets and structures are not imported). In a config::

    custom_imports = dict(imports=['drcpo.integrations.mmdet3d'], allow_failed_imports=False)
    train_pipeline = [
        dict(type='LoadPointsFromFile', coord_type='LIDAR', load_dim=4, use_dim=4),
        dict(type='LoadAnnotations3D', with_bbox_3d=True, with_label_3d=True),
        dict(type='DRCPOAugment', db_path=data_root + 'drcpo_db', classes=class_names,
             preset='pv_rcnn_plusplus', fov_points_only=True),   # in place of ObjectSample
        dict(type='RandomFlip3D', flip_ratio_bev_horizontal=0.5),
        ...
    ]
    custom_hooks = [dict(type='DRCPOFadeHook', num_last_epochs=5)]

Arguments of ``DRCPOAugment`` (the OpenPCDet entry's keys in lower case, with the same meaning
and validation, see :mod:`drcpo.integrations.openpcdet`): ``db_path`` (a drcpo database: ``drcpo
import-mmdet3d`` converts mmdet3d's own), ``classes`` (the dataset's ``metainfo['classes']``:
label ``i`` is ``classes[i]``; only these classes are sampled), ``preset`` or ``config_file``,
``config`` (drcpo keys on top), ``stages`` (default ``['gt_sampling', 'drcpo']``: ObjectSample's
job and DR.CPO's; mmdet3d's RandomFlip3D and GlobalRotScaleTrans follow), ``index_path``,
``fov_points_only`` (place objects in the camera's view: mmdet3d's KITTI configs read
``velodyne_reduced``), ``warmup`` and ``seed``.

Types in and out are mmdet3d's: ``points`` (``LiDARPoints``), ``gt_bboxes_3d``
(``LiDARInstance3DBoxes``, z at the bottom centre: converted exactly to drcpo's centre and back)
and ``gt_labels_3d`` (int64; labels -1, classes the dataset ignores, stay obstacles and stay -1).
Boxes with velocities (``box_dim=9``, nuScenes: vx, vy last) keep them, an inserted object's
turned with its heading (see :mod:`drcpo.integrations.openpcdet`).

Randomness: with ``seed`` set, each sample gets its own generator from ``(seed, epoch,
sample_idx)``, the same whatever the worker count or order (``DRCPOFadeHook`` tells the transform
the epoch); without it each call draws its generator's seed from numpy's global state, which
mmengine's ``worker_init_fn`` seeds per worker (``randomness=dict(seed=...)``), as mmdet3d's own
transforms do. Either way the same config and seed give the same samples.

Warm-up: the compiled kernels are loaded when the transform is built (``warmup=True``), in the
main process, so forked data-loader workers inherit them.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from drcpo.errors import ConfigError, DataError
from drcpo.integrations.openpcdet import OpenPCDetAugmentor

try:
    from mmcv.transforms import BaseTransform
    from mmdet3d.registry import HOOKS, TRANSFORMS
    from mmengine.hooks import Hook
except ImportError as _exc:  # pragma: no cover - exercised without mmdet3d only
    raise ImportError(
        "drcpo.integrations.mmdet3d needs MMDetection3D 1.x with mmengine and mmcv "
        f"({_exc}); see docs/mmdet3d.md for the installs"
    ) from _exc

__all__ = [
    "DEFAULT_STAGES",
    "IGNORED_NAME",
    "DRCPOAugment",
    "DRCPOFadeHook",
    "drcpo_transforms",
    "from_drcpo_boxes",
    "to_drcpo_boxes",
]

#: ``DRCPOAugment`` argument -> the OpenPCDet entry key it stands for.
_ARGUMENTS = {
    "db_path": "DB_PATH",
    "index_path": "INDEX_PATH",
    "preset": "PRESET",
    "config_file": "CONFIG_FILE",
    "config": "CONFIG",
    "stages": "STAGES",
    "fov_points_only": "FOV_POINTS_ONLY",
    "warmup": "WARMUP",
}
DEFAULT_STAGES = ("gt_sampling", "drcpo")
#: drcpo name of boxes labelled -1 (a class the dataset ignores): obstacles, never sampled.
IGNORED_NAME = "__ignored__"


def to_drcpo_boxes(boxes: np.ndarray) -> np.ndarray:
    """``float64 (M, 7)`` drcpo boxes (z at the centre) from mmdet3d LiDAR box values ``(M, 7)``
    (``LiDARInstance3DBoxes.tensor``: x, y, z of the bottom centre, dx, dy, dz, yaw). The heading
    conventions agree (yaw about +z from +x), so only z moves, by dz / 2 (exact in float64 for
    float32 inputs)."""
    out = np.array(boxes, dtype=np.float64).reshape(-1, 7)
    out[:, 2] += out[:, 5] / 2.0
    return out


def from_drcpo_boxes(boxes: np.ndarray) -> np.ndarray:
    """mmdet3d LiDAR box values ``float64 (M, 7)`` (z at the bottom centre) from drcpo's."""
    out = np.array(boxes, dtype=np.float64).reshape(-1, 7)
    out[:, 2] -= out[:, 5] / 2.0
    return out


def _renamed(exc: ConfigError) -> ConfigError:
    """The OpenPCDet entry's error in this transform's words."""
    message = str(exc).replace("drcpo augmentor entry", "DRCPOAugment")
    for argument, key in _ARGUMENTS.items():
        message = message.replace(key, argument)
    return ConfigError(message)


@TRANSFORMS.register_module()
class DRCPOAugment(BaseTransform):
    """drcpo's pipeline on mmdet3d's results dict (see the module docstring for the arguments).

    Required keys: ``points``, ``gt_bboxes_3d``, ``gt_labels_3d``; optional ``sample_idx``.
    Modified keys: ``points``, ``gt_bboxes_3d``, ``gt_labels_3d``.
    """

    def __init__(
        self,
        db_path: str | None = None,
        classes: Sequence[str] | None = None,
        preset: str | None = None,
        config_file: str | None = None,
        config: Mapping[str, Any] | None = None,
        stages: Sequence[str] = DEFAULT_STAGES,
        index_path: str | None = None,
        fov_points_only: bool = False,
        warmup: bool = True,
        seed: int | None = None,
    ) -> None:
        if classes is None or isinstance(classes, str) or not len(classes):
            raise ConfigError(
                "DRCPOAugment: classes must list the dataset's class names "
                f"(metainfo['classes']), got {classes!r}"
            )
        if seed is not None and (isinstance(seed, bool) or not isinstance(seed, int | np.integer)):
            raise ConfigError(f"DRCPOAugment: seed must be an integer or None, got {seed!r}")
        given = {
            "db_path": db_path,
            "index_path": index_path,
            "preset": preset,
            "config_file": config_file,
            "config": None if config is None else dict(config),
            "stages": list(stages),
            "fov_points_only": bool(fov_points_only),
            "warmup": bool(warmup),
        }
        entry = {"NAME": "drcpo"}
        entry.update({_ARGUMENTS[k]: v for k, v in given.items() if v is not None})
        self.classes = tuple(str(c) for c in classes)
        try:
            # Relative paths are the caller's (mmdet3d configs spell out data_root + ...).
            self.augmentor = OpenPCDetAugmentor(entry, ".", self.classes)
        except ConfigError as exc:
            raise _renamed(exc) from None
        self.seed = None if seed is None else int(seed)
        #: Set by :class:`DRCPOFadeHook` before each epoch (part of the per-sample seed).
        self.epoch = 0
        #: Set by :class:`DRCPOFadeHook` for the last epochs: the transform passes data through.
        self.disabled = False

    def generator(self, results: Mapping[str, Any]) -> np.random.Generator:
        """The sample's generator: from ``(seed, epoch, sample_idx)`` with a seed and an index,
        else seeded from numpy's global state."""
        index = results.get("sample_idx")
        if self.seed is None or index is None:
            return self.augmentor.generator()
        return np.random.default_rng([self.seed, self.epoch, int(index)])

    def transform(self, results: dict) -> dict:
        if self.disabled:
            return results
        for key in ("points", "gt_bboxes_3d", "gt_labels_3d"):
            if key not in results:
                raise DataError(f"DRCPOAugment: the results dict has no {key!r}")
        if len(results.get("gt_bboxes", ())):
            raise DataError(
                "DRCPOAugment: the results hold 2D boxes 'gt_bboxes', which drcpo does not "
                "update; load 3D annotations only (LoadAnnotations3D(with_bbox=False))"
            )
        points, boxes = results["points"], results["gt_bboxes_3d"]
        labels = np.asarray(results["gt_labels_3d"])
        values = boxes.tensor.numpy()
        if values.ndim != 2 or values.shape[1] not in (7, 9):
            raise DataError(
                f"DRCPOAugment: gt_bboxes_3d has box_dim {values.shape[-1]}; drcpo moves 7-value "
                "boxes and 9-value ones with velocities (vx, vy last) only (other columns would "
                "go stale)"
            )
        drcpo_boxes = to_drcpo_boxes(values[:, :7])
        if values.shape[1] == 9:  # velocities ride along as OpenPCDet's 9-value boxes
            drcpo_boxes = np.column_stack([drcpo_boxes, values[:, 7:9].astype(np.float64)])
        data = {
            "points": points.tensor.numpy(),
            "gt_boxes": drcpo_boxes,
            "gt_names": self._names(labels),
        }
        out = self.augmentor(data, self.generator(results))
        results["points"] = points.new_point(out["points"])
        moved = from_drcpo_boxes(out["gt_boxes"][:, :7])
        if values.shape[1] == 9:
            moved = np.column_stack([moved, out["gt_boxes"][:, 7:9]])
        results["gt_bboxes_3d"] = boxes.new_box(moved)
        results["gt_labels_3d"] = self._labels(out["gt_names"]).astype(labels.dtype, copy=False)
        return results

    def _names(self, labels: np.ndarray) -> np.ndarray:
        bad = (labels < -1) | (labels >= len(self.classes))
        if labels.ndim != 1 or bad.any():
            raise DataError(
                f"DRCPOAugment: gt_labels_3d {labels.tolist()} must be -1 or indices into "
                f"classes {list(self.classes)}"
            )
        names = np.array([*self.classes, IGNORED_NAME])
        return names[np.where(labels < 0, len(self.classes), labels)]

    def _labels(self, names: np.ndarray) -> np.ndarray:
        lookup = {name: i for i, name in enumerate(self.classes)}
        return np.array([lookup.get(str(n), -1) for n in names], dtype=np.int64)

    def __repr__(self) -> str:
        return (
            f"DRCPOAugment(classes={list(self.classes)}, seed={self.seed}, "
            f"pipeline={self.augmentor.pipeline!r})"
        )


def drcpo_transforms(dataset: Any) -> list[DRCPOAugment]:
    """The ``DRCPOAugment`` transforms of a dataset's pipeline, through mmengine's dataset
    wrappers (``dataset`` of RepeatDataset/ClassBalancedDataset/CBGS, ``datasets`` of
    ConcatDataset)."""
    found: list[DRCPOAugment] = []
    stack = [dataset]
    while stack:
        current = stack.pop()
        pipeline = getattr(current, "pipeline", None)
        found += [t for t in getattr(pipeline, "transforms", ()) if isinstance(t, DRCPOAugment)]
        stack += list(getattr(current, "datasets", ()))
        if getattr(current, "dataset", None) is not None:
            stack.append(current.dataset)
    return found


@HOOKS.register_module()
class DRCPOFadeHook(Hook):
    """Turns ``DRCPOAugment`` off for the last ``num_last_epochs`` epochs (mmdet3d's
    ``DisableObjectSampleHook`` only knows its own ``ObjectSample``), and tells seeded transforms
    the epoch. Persistent workers are restarted when what they hold changes (as mmdet3d's hook
    does), so the change reaches them.

    Args:
        num_last_epochs: epochs at the end trained without drcpo (0: never off).
    """

    priority = "NORMAL"

    def __init__(self, num_last_epochs: int = 0) -> None:
        if isinstance(num_last_epochs, bool) or not isinstance(num_last_epochs, int):
            raise ConfigError(
                f"DRCPOFadeHook: num_last_epochs must be an int, got {num_last_epochs!r}"
            )
        if num_last_epochs < 0:
            raise ConfigError(f"DRCPOFadeHook: num_last_epochs must be >= 0, got {num_last_epochs}")
        self.num_last_epochs = num_last_epochs

    def before_train_epoch(self, runner: Any) -> None:
        loader = runner.train_dataloader
        transforms = drcpo_transforms(loader.dataset)
        if not transforms:
            raise ConfigError("DRCPOFadeHook: the training pipeline has no DRCPOAugment")
        disabled = runner.epoch >= runner.max_epochs - self.num_last_epochs
        changed = False
        for transform in transforms:
            changed |= transform.disabled != disabled
            changed |= transform.seed is not None and transform.epoch != runner.epoch
            transform.disabled = disabled
            transform.epoch = runner.epoch
        if disabled and changed:
            runner.logger.info(f"DRCPOFadeHook: drcpo off from epoch {runner.epoch}")
        if changed and getattr(loader, "persistent_workers", False):
            # Persistent workers hold copies of the old pipeline: without its iterator the
            # loader forks new workers (the old ones shut down when it is collected).
            loader._iterator = None
