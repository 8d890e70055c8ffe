"""drcpo: diversified and realistic 3D LiDAR augmentation (DR.CPO, Shin et al., AAAI 2023).

The names users need, importable from here::

    from drcpo import GroundTruthDatabase, build_index, build_pipeline, load_config

Everything but the frame, the errors and :func:`warmup` is imported on first use (PEP 562), so
``import drcpo`` stays cheap for the command line and for worker processes.
"""

import importlib
from typing import Any

# First: where numba caches the kernels must be settled before any kernel module is imported.
from drcpo import _numba_cache

_numba_cache.configure()

from drcpo.errors import ConfigError, DataError, DrcpoError, OutputError  # noqa: E402
from drcpo.frame import Frame  # noqa: E402
from drcpo.warmup import warmup  # noqa: E402

__version__ = "0.1.0"

#: Public name -> the module that defines it (imported when the name is first used).
_LAZY = {
    "load_config": "drcpo.config",
    "build_pipeline": "drcpo.pipeline",
    "Transform": "drcpo.transforms",
    "Compose": "drcpo.transforms",
    "Stats": "drcpo.transforms",
    "DRCPO": "drcpo.transforms",
    "GroundTruthSampling": "drcpo.transforms",
    "GlobalFlip": "drcpo.transforms",
    "GlobalRotation": "drcpo.transforms",
    "GlobalScaling": "drcpo.transforms",
    "transform_from_config": "drcpo.transforms",
    "GroundTruthDatabase": "drcpo.database",
    "build_database": "drcpo.database",
    "import_openpcdet": "drcpo.database",
    "import_mmdet3d": "drcpo.database",
    "CandidateIndex": "drcpo.index",
    "IndexConfig": "drcpo.index",
    "build_index": "drcpo.index_build",
    "load_index": "drcpo.index",
    "hidden_point_removal": "drcpo.occlusion",
    "augment_kitti": "drcpo.datasets.export",
}

__all__ = [
    "ConfigError",
    "DataError",
    "DrcpoError",
    "Frame",
    "OutputError",
    "__version__",
    "warmup",
    *_LAZY,
]


def __getattr__(name: str) -> Any:
    module = _LAZY.get(name)
    if module is None:
        raise AttributeError(f"module 'drcpo' has no attribute {name!r}")
    value = getattr(importlib.import_module(module), name)
    globals()[name] = value  # later lookups skip this function
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_LAZY))
