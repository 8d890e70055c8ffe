"""drcpo: diversified and realistic 3D LiDAR augmentation (DR.CPO, Shin et al., AAAI 2023)."""

from drcpo.errors import ConfigError, DataError, DrcpoError
from drcpo.frame import Frame
from drcpo.warmup import warmup

__version__ = "0.1.0"

__all__ = ["ConfigError", "DataError", "DrcpoError", "Frame", "__version__", "warmup"]
