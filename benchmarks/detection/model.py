"""The CNN: a two-scale BEV backbone with a CenterPoint-style heatmap and box-code head."""

from __future__ import annotations

import torch
from torch import nn

from .heads import CLASSES, CODE_SIZE

HEATMAP_PRIOR = 0.1  # initial heatmap probability (bias), so the focal loss starts stable


def _block(inputs: int, outputs: int, stride: int = 1) -> list[nn.Module]:
    return [
        nn.Conv2d(inputs, outputs, 3, stride, 1, bias=False),
        nn.BatchNorm2d(outputs),
        nn.ReLU(inplace=True),
    ]


class BevDetector(nn.Module):
    """BEV features ``(B, C, H, W)`` to heatmap logits ``(B, len(CLASSES), H / 2, W / 2)`` and
    box codes ``(B, CODE_SIZE, H / 2, W / 2)`` (about 151k parameters for C = 10).

    Stride 2 (0.8 m) keeps a pedestrian's centre in a cell of its own; a stride-4 branch,
    upsampled and concatenated, widens the view for cars.
    """

    def __init__(self, channels: int = 10) -> None:
        super().__init__()
        self.stem = nn.Sequential(*_block(channels, 32))
        self.down = nn.Sequential(*_block(32, 48, 2), *_block(48, 48))
        self.deep = nn.Sequential(*_block(48, 64, 2), *_block(64, 64))
        self.up = nn.Sequential(
            nn.ConvTranspose2d(64, 64, 2, 2, bias=False), nn.BatchNorm2d(64), nn.ReLU(inplace=True)
        )
        self.shared = nn.Sequential(*_block(48 + 64, 32))
        self.heatmap = nn.Conv2d(32, len(CLASSES), 1)
        self.code = nn.Conv2d(32, CODE_SIZE, 1)
        nn.init.constant_(self.heatmap.bias, float(torch.logit(torch.tensor(HEATMAP_PRIOR))))

    def forward(self, features: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        half = self.down(self.stem(features))
        quarter = self.deep(half)
        x = self.shared(
            torch.cat([half, self.up(quarter)[..., : half.shape[2], : half.shape[3]]], 1)
        )
        return self.heatmap(x), self.code(x)


def focal_loss(logits: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """CenterNet's penalty-reduced focal loss (alpha 2, beta 4) per object."""
    prob = torch.sigmoid(logits).clamp(1e-4, 1 - 1e-4)
    positive = target.eq(1).float()
    pos = -torch.log(prob) * (1 - prob) ** 2 * positive
    neg = -torch.log(1 - prob) * prob**2 * (1 - target) ** 4 * (1 - positive)
    return (pos.sum() + neg.sum()) / positive.sum().clamp(min=1.0)


def detection_loss(
    heatmap_logits: torch.Tensor,
    code: torch.Tensor,
    heatmap: torch.Tensor,
    code_target: torch.Tensor,
    mask: torch.Tensor,
    code_weight: float = 1.0,
) -> tuple[torch.Tensor, dict[str, float]]:
    """Focal loss on the heatmap plus L1 on the box codes at the objects' centre cells."""
    heat = focal_loss(heatmap_logits, heatmap)
    weight = mask.unsqueeze(1)
    box = (torch.abs(code - code_target) * weight).sum() / weight.sum().clamp(min=1.0)
    total = heat + code_weight * box
    return total, {"heatmap": float(heat.detach()), "box": float(box.detach())}


def parameter_count(model: nn.Module) -> int:
    return sum(p.numel() for p in model.parameters())
