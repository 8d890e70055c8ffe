"""drcpo as an OpenPCDet data augmentor (``- NAME: drcpo`` in ``DATA_AUGMENTOR``), no fork needed.

OpenPCDet looks its augmentors up by name on ``DataAugmentor`` (``getattr(self, cfg.NAME)``),
builds each with ``config=<the YAML entry>`` and calls it with ``data_dict=...``. :func:`register`
adds a ``drcpo`` method there (and importing ``pcdet`` happens only then). To enable it without
editing a training script::

    python -m drcpo.integrations.openpcdet tools/train.py --cfg_file cfgs/kitti_models/pv_rcnn.yaml

registers the augmentor and runs the script as ``__main__`` with the remaining arguments (as
``python tools/train.py ...`` would). In code, call :func:`register` before the dataset is built.

The YAML entry (keys in capitals, as OpenPCDet's)::

    - NAME: drcpo
      DB_PATH: drcpo_db          # drcpo database (`drcpo import-openpcdet`), relative to DATA_PATH
      PRESET: pv_rcnn_plusplus   # or CONFIG_FILE: a drcpo YAML config (relative to DATA_PATH)
      CONFIG: {drcpo: {sample: {Car: 15}}}   # drcpo keys on top, validated when it is built
      STAGES: [drcpo]            # any of gt_sampling, drcpo, global_augmentation, in drcpo's order
      USE_ROAD_PLANE: False      # put boxes on KITTI road planes (needs planes in the data)
      WARMUP: True               # load the compiled kernels when built (forked workers inherit)

Place it after OpenPCDet's ``gt_sampling`` and before its ``random_world_*`` entries to run the
paper's pipeline with OpenPCDet's own sampling and global augmentation (the default ``STAGES``).

Behaviour:

* Classes: only classes in the dataset's ``CLASS_NAMES`` are sampled or inserted.
* Difficulty: database objects of difficulty -1 are never drawn (OpenPCDet's KITTI configs
  filter them), unless ``CONFIG`` sets ``exclude_difficulty``.
* Camera view: with ``FOV_POINTS_ONLY`` in the dataset config (seen through :func:`register`;
  an entry key ``FOV_POINTS_ONLY`` overrides it) objects are placed in the camera's view.
* Calibration and road plane: OpenPCDet's ``calib`` (matrices ``P2``, ``R0``, ``V2C``) and
  ``road_plane`` are read even where OpenPCDet's ``gt_sampling`` ran first and removed them.
* Output: the keys that came in, with ``points``, ``gt_boxes`` (in their input dtypes),
  ``gt_names`` and ``gt_boxes_mask`` (kept in step with the boxes; inserted boxes get True)
  updated, plus ``flip_x``/``flip_y``, ``noise_rot`` and ``noise_scale`` when drcpo's global
  stages run (as OpenPCDet's ``random_world_*`` write them). drcpo's statistics are not passed on
  (``collate_batch`` cannot batch them).
* Randomness: OpenPCDet gives an augmentor no sample index, so each call draws its generator's
  seed from numpy's global state, which OpenPCDet's ``worker_init_fn`` (or PyTorch) seeds per
  worker: the same seed gives the same batches, as with OpenPCDet's own augmentors.
* Per-epoch fade: ``DISABLE_AUG_LIST: [drcpo]`` and OpenPCDet's ``DisableAugmentationHook`` work
  as for any augmentor.

* Velocities: 9-value boxes (nuScenes' ``gt_boxes``: x, y, z, dx, dy, dz, heading, vx, vy) are
  split into the boxes and their velocities (``metadata["velocity"]``) on the way in and joined
  on the way out: an inserted object's velocity is its database velocity turned to its new
  heading (0 when the database has none), and drcpo's global stages move them as OpenPCDet's
  ``random_world_*`` do.

Boxes of another width than 7 or 9 and 2D boxes (``gt_boxes2d``) are refused with a clear error:
drcpo does not move them.
"""

from __future__ import annotations

import runpy
import sys
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from drcpo.errors import ConfigError, DataError
from drcpo.frame import VELOCITY

__all__ = [
    "CONTEXT_KEY",
    "DEFAULT_EXCLUDE_DIFFICULTY",
    "DEFAULT_STAGES",
    "ENTRY_KEYS",
    "FOV_ATTRIBUTE",
    "NAME",
    "STAGES",
    "OpenPCDetAugmentor",
    "augment_config",
    "drcpo_calibration",
    "main",
    "openpcdet_draws",
    "register",
]

NAME = "drcpo"
#: drcpo stages an entry can run, in the order they run.
STAGES = ("gt_sampling", "drcpo", "global_augmentation")
DEFAULT_STAGES = ("drcpo",)
ENTRY_KEYS = (
    "NAME",
    "DB_PATH",
    "INDEX_PATH",
    "PRESET",
    "CONFIG_FILE",
    "CONFIG",
    "STAGES",
    "USE_ROAD_PLANE",
    "FOV_POINTS_ONLY",
    "WARMUP",
)
#: Difficulty codes never drawn unless the config says otherwise (OpenPCDet's KITTI configs).
DEFAULT_EXCLUDE_DIFFICULTY = (-1,)
#: Data-dict key the pre-hook keeps ``calib`` and ``road_plane`` under until drcpo runs.
CONTEXT_KEY = "_drcpo_context"
#: Attribute of OpenPCDet's DataAugmentor that :func:`register` sets from the dataset config.
FOV_ATTRIBUTE = "_drcpo_fov_points_only"


# --------------------------------------------------------------------------------------------
# The entry's settings
# --------------------------------------------------------------------------------------------
def _entry_dict(entry: Mapping[str, Any]) -> dict[str, Any]:
    if not isinstance(entry, Mapping):
        raise ConfigError(
            f"the drcpo augmentor entry must be a mapping, got {type(entry).__name__}"
        )
    unknown = sorted(set(entry) - set(ENTRY_KEYS))
    if unknown:
        raise ConfigError(
            f"drcpo augmentor entry: unknown key(s) {unknown}; allowed: {', '.join(ENTRY_KEYS)}"
        )
    return dict(entry)


def _stages(value: Any) -> tuple[str, ...]:
    if value is None:
        return DEFAULT_STAGES
    if isinstance(value, str) or not isinstance(value, Sequence):
        raise ConfigError(f"drcpo augmentor entry: STAGES must be a list, got {value!r}")
    bad = [s for s in value if s not in STAGES]
    if bad or not value:
        raise ConfigError(
            f"drcpo augmentor entry: STAGES {list(value)!r} must list some of: {', '.join(STAGES)}"
        )
    return tuple(s for s in STAGES if s in value)


def _deep_merge(base: Mapping[str, Any], top: Mapping[str, Any]) -> dict[str, Any]:
    out = dict(base)
    for key, value in top.items():
        if isinstance(value, Mapping) and isinstance(out.get(key), Mapping):
            out[key] = _deep_merge(out[key], value)
        else:
            out[key] = value
    return out


def _plain(value: Any) -> Any:
    """EasyDict/tuple trees as plain dicts and lists (what drcpo's config reader takes)."""
    if isinstance(value, Mapping):
        return {str(k): _plain(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_plain(v) for v in value]
    return value


def augment_config(
    entry: Mapping[str, Any], root_path: str | Path, class_names: Sequence[str]
) -> Any:
    """The validated :class:`~drcpo.config.AugmentConfig` an entry describes.

    Layers, each on top of the one before: the paper defaults; difficulty -1 excluded
    (:data:`DEFAULT_EXCLUDE_DIFFICULTY`); ``PRESET`` or ``CONFIG_FILE``; ``CONFIG``; then the
    entry's ``STAGES`` and ``USE_ROAD_PLANE``, and the per-class keys cut to ``class_names``.
    """
    from drcpo.config import _read_yaml, load_config

    entry = _entry_dict(entry)
    if "PRESET" in entry and "CONFIG_FILE" in entry:
        raise ConfigError("drcpo augmentor entry: give PRESET or CONFIG_FILE, not both")
    layers: dict[str, Any] = {
        "gt_sampling": {"exclude_difficulty": list(DEFAULT_EXCLUDE_DIFFICULTY)},
        "drcpo": {"exclude_difficulty": list(DEFAULT_EXCLUDE_DIFFICULTY)},
    }
    origin = "drcpo augmentor entry"
    if entry.get("PRESET") is not None:
        layers["preset"] = entry["PRESET"]
    if entry.get("CONFIG_FILE") is not None:
        path = Path(root_path) / str(entry["CONFIG_FILE"])
        if not path.is_file():
            raise ConfigError(f"drcpo augmentor entry: CONFIG_FILE {path} not found")
        layers = _deep_merge(layers, _read_yaml(path))
        origin = f"{origin} (CONFIG_FILE {path})"
    extra = _plain(entry.get("CONFIG") or {})
    if not isinstance(extra, dict):
        raise ConfigError(f"drcpo augmentor entry: CONFIG must be a mapping, got {extra!r}")
    layers = _deep_merge(layers, extra)
    try:
        config = load_config(layers)
    except ConfigError as exc:
        raise ConfigError(f"{origin}: {exc}") from None
    data = config.to_dict()
    stages = _stages(entry.get("STAGES"))
    for stage in STAGES:  # each stage is the config section of that name
        data[stage]["enabled"] = stage in stages
    use_plane = bool(entry.get("USE_ROAD_PLANE", False))
    data["gt_sampling"]["use_road_plane"] = use_plane
    names = set(class_names)
    data["gt_sampling"]["targets"] = {
        k: v for k, v in data["gt_sampling"]["targets"].items() if k in names
    }
    data["drcpo"]["sample"] = {k: v for k, v in data["drcpo"]["sample"].items() if k in names}
    data["pipeline"] = "drcpo"
    data.pop("preset", None)
    return load_config(data)


# --------------------------------------------------------------------------------------------
# The augmentor
# --------------------------------------------------------------------------------------------
class OpenPCDetAugmentor:
    """drcpo's pipeline on OpenPCDet data dicts: ``augmentor(data_dict) -> data_dict``.

    Args:
        entry: the YAML entry (see the module docstring).
        root_path: OpenPCDet's ``DATA_PATH`` (``DB_PATH`` and ``CONFIG_FILE`` are relative to it).
        class_names: the dataset's ``CLASS_NAMES``.
        fov_points_only: the dataset's ``FOV_POINTS_ONLY`` (the entry's key overrides it).
    """

    def __init__(
        self,
        entry: Mapping[str, Any],
        root_path: str | Path,
        class_names: Sequence[str],
        fov_points_only: bool | None = None,
    ) -> None:
        from drcpo.database import GroundTruthDatabase
        from drcpo.index import load_index
        from drcpo.pipeline import build_pipeline

        entry = _entry_dict(entry)
        self.config = augment_config(entry, root_path, class_names)
        self.class_names = tuple(class_names)
        fov = entry.get("FOV_POINTS_ONLY", fov_points_only)
        self.fov_points_only = bool(fov)
        self.use_road_plane = bool(entry.get("USE_ROAD_PLANE", False))
        database = index = None
        if self.config.gt_sampling.enabled or self.config.drcpo.enabled:
            if entry.get("DB_PATH") is None:
                raise ConfigError("drcpo augmentor entry: DB_PATH (a drcpo database) is required")
            database = GroundTruthDatabase.open(Path(root_path) / str(entry["DB_PATH"]))
            if self.config.drcpo.enabled:
                where = entry.get("INDEX_PATH")
                index = load_index(database, None if where is None else Path(root_path) / where)
        self.pipeline = build_pipeline(self.config, database, index)
        if entry.get("WARMUP", True):
            from drcpo.warmup import warmup

            warmup(self.pipeline)

    def remember(self, data_dict: dict[str, Any]) -> dict[str, Any]:
        """Pre-hook run first in the augmentor queue: keeps ``calib`` and ``road_plane``, which
        OpenPCDet's ``gt_sampling`` removes, for :meth:`__call__`."""
        data_dict[CONTEXT_KEY] = {k: data_dict.get(k) for k in ("calib", "road_plane")}
        return data_dict

    def generator(self) -> np.random.Generator:
        """This call's generator, seeded from numpy's global state (seeded per worker)."""
        # OpenPCDet's augmentors draw from numpy's global state and its worker_init_fn seeds
        # it; drawing the seed there keeps drcpo in step with them (the one legacy call).
        seed = np.random.randint(0, 2**63 - 1, dtype=np.int64)  # noqa: NPY002
        return np.random.default_rng(seed)

    def __call__(
        self, data_dict: dict[str, Any], rng: np.random.Generator | None = None
    ) -> dict[str, Any]:
        """The augmented data dict; ``rng``: the generator to use (default: :meth:`generator`,
        which OpenPCDet's calls get)."""
        from drcpo.transforms import STATS_KEY

        data_dict = dict(data_dict)
        context = data_dict.pop(CONTEXT_KEY, None) or {}
        boxes = _check_input(data_dict)
        frame: dict[str, Any] = {
            "points": data_dict["points"],
            "gt_boxes": boxes[:, :7],
            "gt_names": np.asarray(data_dict["gt_names"]),
            "fov_only": self.fov_points_only,
        }
        if boxes.shape[1] == 9:
            frame[VELOCITY] = np.asarray(boxes[:, 7:9], dtype=np.float64)
        if "gt_boxes_mask" in data_dict:
            frame["gt_boxes_mask"] = np.asarray(data_dict["gt_boxes_mask"], dtype=bool)
        calib = data_dict.get("calib", context.get("calib"))
        plane = data_dict.get("road_plane", context.get("road_plane"))
        if self.use_road_plane and plane is not None and calib is not None:
            frame["calib"] = drcpo_calibration(calib)
            frame["plane"] = np.asarray(plane, dtype=np.float64)
        out = self.pipeline(frame, self.generator() if rng is None else rng)
        stats = out.get(STATS_KEY, {}).get("stages", {})
        data_dict["points"] = out["points"].astype(data_dict["points"].dtype, copy=False)
        joined = out["gt_boxes"]
        if boxes.shape[1] == 9:
            joined = np.column_stack([joined, out[VELOCITY]])
        data_dict["gt_boxes"] = joined.astype(boxes.dtype, copy=False)
        data_dict["gt_names"] = np.asarray(out["gt_names"])
        if "gt_boxes_mask" in frame:
            data_dict["gt_boxes_mask"] = np.asarray(out["gt_boxes_mask"], dtype=bool)
        data_dict.update(openpcdet_draws(stats, self.config.global_augmentation.flip.axes))
        return data_dict


def _check_input(data_dict: Mapping[str, Any]) -> np.ndarray:
    """The dict's ``gt_boxes`` ``(M, 7)`` or ``(M, 9)`` (velocities last); refuses what drcpo
    cannot keep consistent."""
    for key in ("points", "gt_boxes", "gt_names"):
        if key not in data_dict:
            raise DataError(f"drcpo augmentor: the data dict has no {key!r}")
    boxes = np.asarray(data_dict["gt_boxes"])
    if boxes.ndim != 2 or boxes.shape[1] not in (7, 9):
        raise DataError(
            f"drcpo augmentor: gt_boxes has shape {boxes.shape}; drcpo moves (M, 7) boxes and "
            "(M, 9) ones with velocities (x, y, z, dx, dy, dz, heading, vx, vy) only (other "
            "columns would go stale)"
        )
    if "gt_boxes2d" in data_dict:
        raise DataError(
            "drcpo augmentor: the data dict has 'gt_boxes2d', which drcpo does not update; "
            "drop 'gt_boxes2d' from GET_ITEM_LIST"
        )
    return boxes


def drcpo_calibration(calib: Any) -> Any:
    """drcpo's :class:`~drcpo.datasets.kitti_coordinates.Calibration` from OpenPCDet's (``P2``,
    ``R0``, ``V2C``) or drcpo's own."""
    from drcpo.datasets.kitti_coordinates import Calibration

    if isinstance(calib, Calibration):
        return calib
    try:
        return Calibration(calib.P2, calib.R0, calib.V2C)
    except AttributeError as exc:
        raise DataError(
            f"drcpo augmentor: calib {type(calib).__name__} has no KITTI matrices "
            "P2, R0, V2C (OpenPCDet's Calibration)"
        ) from exc


def openpcdet_draws(stages: Mapping[str, Any], flip_axes: Sequence[str]) -> dict[str, Any]:
    """OpenPCDet's keys for the global augmentation that drcpo's statistics ``stages`` record:
    ``flip_x``/``flip_y`` (``numpy.bool_``, one per axis the flip stage draws), ``noise_rot``
    (radians, the angles added up) and ``noise_scale`` (the factors multiplied), as OpenPCDet's
    ``random_world_*`` write them; only for the stages that ran."""
    out: dict[str, Any] = {}
    flip = stages.get("global_flip")
    if flip is not None:
        for axis in flip_axes:
            odd = sum(axis in run for run in flip.get("flipped", [])) % 2 == 1
            out[f"flip_{axis}"] = np.bool_(odd)
    rotation = stages.get("global_rotation")
    if rotation is not None:
        out["noise_rot"] = float(np.sum(rotation.get("angle", [0.0])))
    scaling = stages.get("global_scaling")
    if scaling is not None:
        out["noise_scale"] = float(np.prod(scaling.get("scale", [1.0])))
    return out


# --------------------------------------------------------------------------------------------
# Registration in OpenPCDet
# --------------------------------------------------------------------------------------------
def _augmentor_method(self: Any, data_dict: Any = None, config: Any = None) -> Any:
    """``DataAugmentor.drcpo``: with ``config`` builds the augmentor (as OpenPCDet's own
    methods return a callable when called without ``data_dict``)."""
    if data_dict is not None:
        raise TypeError("DataAugmentor.drcpo builds the augmentor; call what it returns")
    augmentor = OpenPCDetAugmentor(
        config, self.root_path, self.class_names, getattr(self, FOV_ATTRIBUTE, None)
    )
    if self.data_augmentor_queue:
        # An augmentor before drcpo (gt_sampling) may remove calib and road_plane.
        self.data_augmentor_queue.insert(0, augmentor.remember)
    return augmentor


def register() -> None:
    """Add the ``drcpo`` augmentor to OpenPCDet's ``DataAugmentor`` (imports ``pcdet``).

    Also lets it see the dataset's ``FOV_POINTS_ONLY``: ``DatasetTemplate.__init__`` is wrapped to
    set it on the dataset's ``DataAugmentor`` before the augmentors are built. Idempotent.
    """
    from pcdet.datasets import dataset as dataset_module
    from pcdet.datasets.augmentor import data_augmentor

    augmentor_cls = data_augmentor.DataAugmentor
    augmentor_cls.drcpo = _augmentor_method
    if getattr(augmentor_cls.__init__, "_drcpo_wrapped", False):
        return
    original = augmentor_cls.__init__
    template = dataset_module.DatasetTemplate
    template_init = template.__init__

    def init_augmentor(self, root_path, augmentor_configs, class_names, logger=None):
        setattr(self, FOV_ATTRIBUTE, _pending_fov.get(id(augmentor_configs)))
        original(self, root_path, augmentor_configs, class_names, logger=logger)

    def init_dataset(self, dataset_cfg=None, *args, **kwargs):
        key = None
        if dataset_cfg is not None and dataset_cfg.get("DATA_AUGMENTOR") is not None:
            key = id(dataset_cfg.DATA_AUGMENTOR)
            _pending_fov[key] = bool(dataset_cfg.get("FOV_POINTS_ONLY", False))
        try:
            template_init(self, dataset_cfg, *args, **kwargs)
        finally:
            _pending_fov.pop(key, None)

    init_augmentor._drcpo_wrapped = True  # type: ignore[attr-defined]
    augmentor_cls.__init__ = init_augmentor
    template.__init__ = init_dataset


#: FOV_POINTS_ONLY of the dataset being built, by ``id`` of its DATA_AUGMENTOR config.
_pending_fov: dict[int, bool] = {}


def main(argv: Sequence[str] | None = None) -> None:
    """``python -m drcpo.integrations.openpcdet SCRIPT [ARGS...]``: register, then run SCRIPT as
    ``__main__`` (its directory first on ``sys.path``, ``sys.argv`` = SCRIPT ARGS...)."""
    args = list(sys.argv[1:] if argv is None else argv)
    if not args or args[0] in ("-h", "--help"):
        print(
            "usage: python -m drcpo.integrations.openpcdet SCRIPT [ARGS...]\n"
            "registers drcpo's OpenPCDet augmentor (- NAME: drcpo), then runs SCRIPT"
        )
        raise SystemExit(0 if args else 2)
    script = Path(args[0])
    if not script.is_file():
        print(f"error: {script}: no such script", file=sys.stderr)
        raise SystemExit(2)
    try:
        register()
    except ImportError as exc:
        print(f"error: cannot import OpenPCDet (pcdet) to register drcpo: {exc}", file=sys.stderr)
        raise SystemExit(1) from None
    sys.argv = [str(script), *args[1:]]
    sys.path.insert(0, str(script.resolve().parent))
    runpy.run_path(str(script), run_name="__main__")


if __name__ == "__main__":
    main()
