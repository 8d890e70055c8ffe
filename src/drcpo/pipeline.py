"""The augmentation pipeline a configuration describes (:func:`build_pipeline`)."""

from __future__ import annotations

from typing import Any

from drcpo.config import PIPELINES, load_config
from drcpo.database import GroundTruthDatabase
from drcpo.errors import ConfigError
from drcpo.index import load_index
from drcpo.transforms.base import Compose, Transform
from drcpo.transforms.drcpo import DRCPO
from drcpo.transforms.global_aug import GlobalFlip, GlobalRotation, GlobalScaling
from drcpo.transforms.gt_sampling import GroundTruthSampling

__all__ = ["build_pipeline"]


def build_pipeline(
    config: Any = None,
    database: GroundTruthDatabase | None = None,
    index: Any = None,
    kind: str | None = None,
) -> Compose:
    """The augmentation pipeline a configuration describes.

    Args:
        config: an :class:`~drcpo.config.AugmentConfig`, a mapping, a YAML path or a preset name
            (anything :func:`drcpo.config.load_config` reads); ``None``: the paper defaults.
        database: the ground-truth database (needed by ground-truth sampling and DR.CPO).
        index: its candidate index; loaded from ``database.path / "index"`` when ``None`` and
            DR.CPO is enabled.
        kind: ``"drcpo"`` (ground-truth sampling, DR.CPO, global augmentation: the paper's
            reference configuration) or
            ``"cda"`` (the conventional baseline: ground-truth sampling, global augmentation);
            default: the config's ``pipeline`` key.

    Stages whose ``enabled`` key is false are left out.
    """
    config = load_config(config)
    kind = kind or config.pipeline
    if kind not in PIPELINES:
        raise ConfigError(f"pipeline {kind!r} is unknown; choose one of: {', '.join(PIPELINES)}")
    needs_db = config.gt_sampling.enabled or (kind == "drcpo" and config.drcpo.enabled)
    if needs_db and database is None:
        raise ConfigError(f"the {kind} pipeline needs a ground-truth database")
    transforms: list[Transform] = []
    if config.gt_sampling.enabled:
        transforms.append(GroundTruthSampling.from_settings(config.gt_sampling, database))
    if kind == "drcpo" and config.drcpo.enabled:
        if index is None:
            index = load_index(database)
        transforms.append(DRCPO(database, index, config.drcpo))
    aug = config.global_augmentation
    if aug.enabled:
        transforms += [
            GlobalFlip(aug.flip.probability, aug.flip.axes),
            GlobalRotation(aug.rotation.range),
            GlobalScaling(aug.scaling.range),
        ]
    return Compose(transforms)
