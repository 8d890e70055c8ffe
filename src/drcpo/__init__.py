"""drcpo: diversified and realistic 3D LiDAR augmentation (DR.CPO, Shin et al., AAAI 2023)."""

# First: where numba caches the kernels must be settled before any kernel module is imported.
from drcpo import _numba_cache

_numba_cache.configure()

from drcpo.errors import ConfigError, DataError, DrcpoError  # noqa: E402
from drcpo.frame import Frame  # noqa: E402
from drcpo.warmup import warmup  # noqa: E402

__version__ = "0.1.0"

__all__ = ["ConfigError", "DataError", "DrcpoError", "Frame", "__version__", "warmup"]
