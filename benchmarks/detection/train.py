"""Training loop and inference of :class:`~.model.BevDetector` on drcpo frames.

All samples of a run are augmented before training (:func:`augment_samples`), so that a run is
known by what it trains on. They are drawn in epochs (a fresh permutation per epoch from
``(seed, epoch)``), each augmented with its own generator
``np.random.default_rng([seed, epoch, index])`` (``index`` = the frame's position in the
training set), so an arm's samples do not depend on the batch size or on what other arms do,
and runs of different arms with one seed see the same frames in the same order. One torch
thread, deterministic algorithms, and ``torch.manual_seed`` make a run repeat exactly for a seed.
"""

from __future__ import annotations

import hashlib
import os
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch

from drcpo.datasets.kitti import KittiDataset
from drcpo.datasets.kitti_coordinates import DEFAULT_IMAGE_SHAPE, fov_mask
from drcpo.frame import Frame
from drcpo.geometry import box_members
from drcpo.transforms import STATS_KEY

from .bev import Grid, bev_features
from .heads import Detections, decode, encode_targets
from .model import BevDetector, detection_loss

Augment = Callable[[Frame, np.random.Generator], Frame]


@dataclass(frozen=True)
class TrainConfig:
    """Optimisation settings: AdamW with a one-cycle learning rate over ``steps`` steps."""

    steps: int = 600
    batch_size: int = 4
    learning_rate: float = 3e-3
    weight_decay: float = 1e-2
    code_weight: float = 0.5
    seed: int = 0
    device: str = "cpu"


@dataclass
class Samples:
    """What a run trains on, augmented once before training: each step's batch of frames, in
    order, and what the augmentation did to them.

    ``digest`` is a SHA-256 of every sample's points, boxes and names in order: two runs with one
    digest, plan and detector train the same model, whatever code produced their samples.
    ``added`` counts, per transform and class, the objects the augmentation reports it added
    (drcpo's statistics); ``labels`` counts the labelled objects per class,
    ``labels_with_points`` those holding at least :data:`MIN_LABEL_POINTS` points and
    ``empty_labels`` those holding none; ``ranges`` lists their distances from the sensor
    (BEV, metres); ``points`` sums the samples' points; ``augment_seconds`` is each sample's
    augmentation time (CPU seconds; its median leaves out the first calls' kernel loading).
    """

    batches: list[list[Frame]]
    digest: str = ""
    added: dict[str, dict[str, int]] = field(default_factory=dict)
    labels: dict[str, int] = field(default_factory=dict)
    labels_with_points: dict[str, int] = field(default_factory=dict)
    empty_labels: dict[str, int] = field(default_factory=dict)
    ranges: dict[str, list[float]] = field(default_factory=dict)
    points: int = 0
    augment_seconds: list[float] = field(default_factory=list)

    @property
    def count(self) -> int:
        return sum(len(batch) for batch in self.batches)


@dataclass
class TrainResult:
    """A trained model and its loss per step; ``seconds`` is the CPU time of this process spent
    encoding (BEV features and targets) and in the optimiser steps (forward, backward, update):
    on a shared machine, what an idle core would take."""

    model: BevDetector
    losses: list[float]
    seconds: dict[str, float] = field(default_factory=dict)


MIN_LABEL_POINTS = 5  # a label with fewer points is hardly evidence of an object


def configure_torch(seed: int, device: str = "cpu") -> None:
    """One thread (the benchmark runs one process per core), deterministic kernels, the seed.
    On a GPU, the kernels without a deterministic version warn instead of failing."""
    torch.set_num_threads(1)
    if device != "cpu":
        os.environ.setdefault("CUBLAS_WORKSPACE_CONFIG", ":4096:8")
    torch.use_deterministic_algorithms(True, warn_only=device != "cpu")
    torch.manual_seed(seed)


def camera_view(frame: Frame) -> Frame:
    """The frame cut to the camera's field of view, as OpenPCDet trains KITTI (metadata
    ``fov_only`` tells DR.CPO to place objects where the camera sees them)."""
    calib = frame.metadata["calib"]
    keep = fov_mask(frame.points, calib, frame.metadata.get("image_shape", DEFAULT_IMAGE_SHAPE))
    return frame.replace(points=frame.points[keep], metadata={**frame.metadata, "fov_only": True})


def load_frames(root: str | Path, split: str) -> list[Frame]:
    """Frames of a KITTI split, cut to the camera's field of view."""
    return [camera_view(frame) for frame in KittiDataset(root, split)]


def sample_order(count: int, steps: int, batch_size: int, seed: int) -> np.ndarray:
    """``int64 (steps, batch_size, 2)``: (epoch, frame index) of each sample of each step."""
    needed = steps * batch_size
    epochs = -(-needed // count)
    order = [
        np.column_stack([np.full(count, e), np.random.default_rng([seed, e]).permutation(count)])
        for e in range(epochs)
    ]
    return np.concatenate(order)[:needed].reshape(steps, batch_size, 2)


def _tally_labels(result: Samples, frame: Frame) -> None:
    names = frame.names.astype(str)
    inside = np.zeros(len(names), dtype=np.int64)
    if len(names):
        _, box = box_members(frame.points[:, :3], frame.boxes)
        inside = np.bincount(box, minlength=len(names))
    distance = np.hypot(frame.boxes[:, 0], frame.boxes[:, 1])
    for name, count, far in zip(names.tolist(), inside.tolist(), distance.tolist(), strict=True):
        result.labels[name] = result.labels.get(name, 0) + 1
        result.ranges.setdefault(name, []).append(far)
        if count >= MIN_LABEL_POINTS:
            result.labels_with_points[name] = result.labels_with_points.get(name, 0) + 1
        if count == 0:
            result.empty_labels[name] = result.empty_labels.get(name, 0) + 1
    result.points += len(frame.points)


def _tally_added(added: dict[str, dict[str, int]], frame: Frame) -> None:
    for transform, per_class in frame.metadata.get(STATS_KEY, {}).get("objects", {}).items():
        row = added.setdefault(transform, {})
        for name, entry in per_class.items():
            row[name] = row.get(name, 0) + int(entry["added"])


def _batch(samples: Sequence[Frame], grid: Grid) -> tuple[torch.Tensor, ...]:
    features = np.stack([bev_features(f.points, grid) for f in samples])
    targets = [encode_targets(f.boxes, f.names, grid) for f in samples]
    heat, code, mask = (np.stack(parts) for parts in zip(*targets, strict=True))
    return tuple(torch.from_numpy(a) for a in (features, heat, code, mask))


def _digest_update(digest: Any, frame: Frame) -> None:
    for array in (frame.points, frame.boxes):
        array = np.ascontiguousarray(array)
        digest.update(f"{array.dtype.str}{array.shape}".encode() + array.tobytes())
    digest.update("\0".join(frame.names.astype(str).tolist()).encode() + b"\1")


def augment_samples(
    frames: Sequence[Frame], augment: Augment | None, config: TrainConfig | None = None
) -> Samples:
    """Every sample of a run, in training order, each passed through ``augment(frame, rng)``
    (``None``: no augmentation) with its own generator."""
    config = config or TrainConfig()
    if not frames:
        raise ValueError("train: no training frames")
    order = sample_order(len(frames), config.steps, config.batch_size, config.seed)
    digest = hashlib.sha256()
    samples = Samples([])
    for batch in order:
        samples.batches.append([])
        for epoch, index in batch:
            frame = frames[int(index)]
            if augment is not None:
                begun = time.process_time()
                frame = augment(frame, np.random.default_rng([config.seed, int(epoch), int(index)]))
                samples.augment_seconds.append(time.process_time() - begun)
                _tally_added(samples.added, frame)
            _tally_labels(samples, frame)
            _digest_update(digest, frame)
            samples.batches[-1].append(frame)
    samples.digest = digest.hexdigest()
    return samples


def train(
    samples: Samples,
    config: TrainConfig | None = None,
    grid: Grid | None = None,
    progress: Callable[[int, float, BevDetector], None] | None = None,
) -> TrainResult:
    """Train a fresh detector on ``samples`` (:func:`augment_samples`), one batch per step.

    ``progress(step, loss, model)`` is called after each step (a validation curve can
    evaluate the model there; it must leave it in training mode).
    """
    config = config or TrainConfig()
    grid = grid or Grid()
    if len(samples.batches) != config.steps:
        raise ValueError(f"train: {len(samples.batches)} batches for {config.steps} steps")
    configure_torch(config.seed, config.device)
    model = BevDetector(grid.channels).to(config.device)
    optimiser = torch.optim.AdamW(
        model.parameters(), lr=config.learning_rate, weight_decay=config.weight_decay
    )
    schedule = torch.optim.lr_scheduler.OneCycleLR(
        optimiser, max_lr=config.learning_rate, total_steps=config.steps, pct_start=0.3
    )
    result = TrainResult(model, [], seconds={"encode": 0.0, "step": 0.0})
    model.train()
    for step, batch in enumerate(samples.batches):
        start = time.process_time()
        features, heat, code, mask = _batch(batch, grid)
        stepping = time.process_time()
        features, heat, code, mask = (t.to(config.device) for t in (features, heat, code, mask))
        heat_logits, code_out = model(features)
        loss, _ = detection_loss(heat_logits, code_out, heat, code, mask, config.code_weight)
        optimiser.zero_grad(set_to_none=True)
        loss.backward()
        torch.nn.utils.clip_grad_norm_(model.parameters(), 10.0)
        optimiser.step()
        schedule.step()
        result.seconds["encode"] += stepping - start
        result.seconds["step"] += time.process_time() - stepping
        result.losses.append(float(loss.detach()))
        if progress is not None:
            progress(step + 1, result.losses[-1], model)
    return result


@torch.no_grad()
def predict(
    model: BevDetector,
    frames: Sequence[Frame],
    grid: Grid | None = None,
    batch_size: int = 8,
    device: str = "cpu",
    **decode_options: Any,
) -> list[Detections]:
    """Detections of ``model`` on each frame (options go to :func:`~.heads.decode`)."""
    grid = grid or Grid()
    model.eval()
    out: list[Detections] = []
    for start in range(0, len(frames), batch_size):
        chunk = frames[start : start + batch_size]
        features = torch.from_numpy(np.stack([bev_features(f.points, grid) for f in chunk]))
        heat_logits, code = model(features.to(device))
        heat, code = torch.sigmoid(heat_logits).cpu().numpy(), code.cpu().numpy()
        for k in range(len(chunk)):
            out.append(Detections(*decode(heat[k], code[k], grid, **decode_options)))
    return out
