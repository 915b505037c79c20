"""The depth-class UNet of the Local Dynamics Model (the reference's ``ActionPrimativeModel``).

Encoder: 3×3 stem + four bottleneck-ResNet stages (1, 2, 3, 1 blocks, stride 2 each), channels
``32·m → 64·m → 128·m → 256·m → 512·m`` for a width multiplier ``m`` (``m = 1`` is the reference).
Decoder: four Laina up-projections, each fused with the matching encoder feature by a 1×1 ``CatConv``,
then a 3×3 conv to ``num_classes`` per-pixel logits. The input side must be divisible by 16.
"""

from __future__ import annotations

import torch
from torch import nn

from ldm_rl.models.blocks import LEAKY_SLOPE, CatConv, UpProjection, bottleneck_stage, conv_bn_act
from ldm_rl.models.compile import CompiledInference

__all__ = ["DepthUNet", "REFERENCE_BASE_CHANNELS", "STAGE_BLOCKS"]

REFERENCE_BASE_CHANNELS = 32
STAGE_BLOCKS = (1, 2, 3, 1)


class DepthUNet(CompiledInference, nn.Module):
    """[B, in_channels, S, S] float -> [B, num_classes, S, S] logits (S divisible by 16).

    Args:
        in_channels: input planes (2·K one-hot planes for the LDM, + action planes for Naive).
        num_classes: K depth classes predicted per pixel.
        width: channel multiplier of the reference widths (1.0 = the paper/reference network).
    """

    def __init__(self, in_channels: int, num_classes: int, width: float = 1.0) -> None:
        super().__init__()
        if in_channels < 1 or num_classes < 2:
            raise ValueError(f"need in_channels >= 1 and num_classes >= 2, got {in_channels}, {num_classes}")
        if not width > 0:
            raise ValueError(f"width must be > 0, got {width}")
        base = max(1, round(REFERENCE_BASE_CHANNELS * width))
        c = [base * 2**i for i in range(5)]  # stem, stage1..4 outputs: 32, 64, 128, 256, 512 at width 1
        self.stem = conv_bn_act(in_channels, c[0])
        self.stages = nn.ModuleList(
            bottleneck_stage(c[i], c[i], blocks, stride=2) for i, blocks in enumerate(STAGE_BLOCKS)
        )
        self.bridge = conv_bn_act(c[4], c[4], bias=True)
        self.ups = nn.ModuleList(UpProjection(c[i + 1], c[i + 1]) for i in reversed(range(4)))
        self.fuses = nn.ModuleList(CatConv(c[i], c[i + 1], c[i]) for i in reversed(range(4)))
        self.head = nn.Conv2d(c[0], num_classes, 3, padding=1)
        self.in_channels, self.num_classes, self.width = in_channels, num_classes, width
        self._init_weights()

    def _init_weights(self) -> None:
        for m in self.modules():
            if isinstance(m, nn.Conv2d):
                nn.init.kaiming_normal_(m.weight, a=LEAKY_SLOPE, mode="fan_out", nonlinearity="leaky_relu")
            elif isinstance(m, nn.BatchNorm2d):
                nn.init.ones_(m.weight)
                nn.init.zeros_(m.bias)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self._inference(self._forward, x, dynamic_batch=True)

    def _forward(self, x: torch.Tensor) -> torch.Tensor:
        skips = [self.stem(x)]
        for stage in self.stages:
            skips.append(stage(skips[-1]))
        y = self.bridge(skips.pop())
        for up, fuse in zip(self.ups, self.fuses):
            y = fuse(skips.pop(), up(y))
        return self.head(y)
