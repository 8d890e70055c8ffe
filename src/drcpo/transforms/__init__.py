"""Augmentation transforms: ``transform(frame, rng) -> frame``.

One module per step: :mod:`~drcpo.transforms.base` (the contract, composition, statistics,
registry), :mod:`~drcpo.transforms.global_aug` (flip, rotation, scaling),
:mod:`~drcpo.transforms.gt_sampling` (the conventional ground-truth sampling),
:mod:`~drcpo.transforms.drcpo` (DR.CPO) and the helpers they share
(:mod:`~drcpo.transforms.insertion`).
"""

from drcpo.transforms.base import (
    DRAW_KEYS,
    STATS_KEY,
    TRANSFORMS,
    Compose,
    FrameLike,
    Stats,
    Transform,
    register,
    transform_from_config,
)
from drcpo.transforms.drcpo import DRCPO
from drcpo.transforms.global_aug import GlobalFlip, GlobalRotation, GlobalScaling
from drcpo.transforms.gt_sampling import GroundTruthSampling

__all__ = [
    "DRAW_KEYS",
    "DRCPO",
    "STATS_KEY",
    "TRANSFORMS",
    "Compose",
    "FrameLike",
    "GlobalFlip",
    "GlobalRotation",
    "GlobalScaling",
    "GroundTruthSampling",
    "Stats",
    "Transform",
    "register",
    "transform_from_config",
]
