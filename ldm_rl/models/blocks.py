"""Building blocks of the depth UNets: bottleneck residual blocks and Laina up-projections.

All blocks keep the reference's structure (LeakyReLU slope 0.01, BatchNorm after every conv of the
encoder, biased convs in the up-projections); only the channel counts are free. Their LeakyReLUs act in
place (always on a fresh BatchNorm output or residual sum, which nothing else reads): same values, one
allocation less per activation.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

__all__ = ["LEAKY_SLOPE", "conv_bn_act", "Bottleneck", "bottleneck_stage", "UnpoolAsConv", "UpProjection", "CatConv"]

LEAKY_SLOPE = 0.01


def conv_bn_act(in_channels: int, out_channels: int, *, bias: bool = False) -> nn.Sequential:
    """3×3 conv (padding 1) + BatchNorm + LeakyReLU; keeps H and W."""
    return nn.Sequential(
        nn.Conv2d(in_channels, out_channels, 3, padding=1, bias=bias),
        nn.BatchNorm2d(out_channels),
        nn.LeakyReLU(LEAKY_SLOPE, inplace=True),
    )


class Bottleneck(nn.Module):
    """ResNet bottleneck with expansion 2: 1×1 → 3×3 (stride s) → 1×1 to ``2·width`` channels, + shortcut.

    [B, in_channels, H, W] -> [B, 2·width, H/s, W/s]. The shortcut is a strided 1×1 conv + BN whenever
    the stride or the channel count changes, else the identity.
    """

    expansion = 2

    def __init__(self, in_channels: int, width: int, stride: int = 1) -> None:
        super().__init__()
        out_channels = width * self.expansion
        self.body = nn.Sequential(
            nn.Conv2d(in_channels, width, 1, bias=False),
            nn.BatchNorm2d(width),
            nn.LeakyReLU(LEAKY_SLOPE, inplace=True),
            nn.Conv2d(width, width, 3, stride=stride, padding=1, bias=False),
            nn.BatchNorm2d(width),
            nn.LeakyReLU(LEAKY_SLOPE, inplace=True),
            nn.Conv2d(width, out_channels, 1, bias=False),
            nn.BatchNorm2d(out_channels),
        )
        if stride != 1 or in_channels != out_channels:
            self.shortcut = nn.Sequential(
                nn.Conv2d(in_channels, out_channels, 1, stride=stride, bias=False),
                nn.BatchNorm2d(out_channels),
            )
        else:
            self.shortcut = nn.Identity()
        self.act = nn.LeakyReLU(LEAKY_SLOPE, inplace=True)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.act(self.body(x) + self.shortcut(x))


def bottleneck_stage(in_channels: int, width: int, blocks: int, stride: int) -> nn.Sequential:
    """``blocks`` bottlenecks; the first one strides. Output channels ``2·width``."""
    layers = [Bottleneck(in_channels, width, stride)]
    layers += [Bottleneck(width * Bottleneck.expansion, width) for _ in range(blocks - 1)]
    return nn.Sequential(*layers)


class UnpoolAsConv(nn.Module):
    """Laina et al.'s fast 2× up-convolution: four biased convs (3×3, 2×3, 3×2, 2×2) interleaved.

    [B, C_in, H, W] -> [B, C_out, 2H, 2W] with ``out[2i,2j]=A, out[2i+1,2j]=B, out[2i,2j+1]=C,
    out[2i+1,2j+1]=D`` (B pads right/bottom, C and D likewise, as the reference).
    """

    def __init__(self, in_channels: int, out_channels: int) -> None:
        super().__init__()
        self.conv_a = nn.Conv2d(in_channels, out_channels, (3, 3), padding=1)
        self.conv_b = nn.Conv2d(in_channels, out_channels, (2, 3))
        self.conv_c = nn.Conv2d(in_channels, out_channels, (3, 2))
        self.conv_d = nn.Conv2d(in_channels, out_channels, (2, 2))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        a = self.conv_a(x)
        b = self.conv_b(F.pad(x, (1, 1, 0, 1)))
        c = self.conv_c(F.pad(x, (0, 1, 1, 1)))
        d = self.conv_d(F.pad(x, (0, 1, 0, 1)))
        top = torch.stack((a, c), dim=-1).flatten(-2)  # rows 2i:   A C A C ...
        bottom = torch.stack((b, d), dim=-1).flatten(-2)  # rows 2i+1: B D B D ...
        return torch.stack((top, bottom), dim=-2).flatten(-3, -2)


class UpProjection(nn.Module):
    """Laina up-projection: [B, C_in, H, W] -> [B, C_out, 2H, 2W], a residual pair of up-convolutions."""

    def __init__(self, in_channels: int, out_channels: int) -> None:
        super().__init__()
        self.main = nn.Sequential(
            UnpoolAsConv(in_channels, out_channels),
            nn.BatchNorm2d(out_channels),
            nn.LeakyReLU(LEAKY_SLOPE, inplace=True),
            nn.Conv2d(out_channels, out_channels, 3, padding=1),
            nn.BatchNorm2d(out_channels),
        )
        self.residual = nn.Sequential(UnpoolAsConv(in_channels, out_channels), nn.BatchNorm2d(out_channels))
        self.act = nn.LeakyReLU(LEAKY_SLOPE, inplace=True)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.act(self.main(x) + self.residual(x))


class CatConv(nn.Module):
    """Skip fusion: 1×1 biased conv of ``cat([skip, up], dim=1)``; no nonlinearity (as the reference)."""

    def __init__(self, skip_channels: int, up_channels: int, out_channels: int) -> None:
        super().__init__()
        self.conv = nn.Conv2d(skip_channels + up_channels, out_channels, 1)

    def forward(self, skip: torch.Tensor, up: torch.Tensor) -> torch.Tensor:
        return self.conv(torch.cat((skip, up), dim=1))


def count_parameters(module: nn.Module) -> int:
    """Number of trainable parameters."""
    return sum(p.numel() for p in module.parameters() if p.requires_grad)


# --------------------------------------------------------------------------------------------
# Agent networks (Q FCN, V CNN): BatchNorm-free basic blocks and the shared height encoding
# --------------------------------------------------------------------------------------------
from ldm_rl import geometry as _geometry  # noqa: E402  (appended section)


class BasicBlock(nn.Module):
    """ResNet basic block without BatchNorm: 3×3 (stride s) → LReLU → 3×3, + shortcut, → LReLU.

    [B, in_channels, H, W] -> [B, out_channels, H/s, W/s]. Convs carry no bias. The shortcut is a bare
    strided 1×1 conv (no bias) whenever the stride or the channel count changes, else the identity; it
    runs as a 1×1 conv on every s-th pixel (the same sums): on torch 2.13 CPU (oneDNN 3.12) the backward
    of a *strided* 1×1 conv on channels_last input with fewer than 16 channels segfaults, the unstrided
    one does not, and channels_last makes the training pass of these narrow convs 2–4× faster.
    """

    def __init__(self, in_channels: int, out_channels: int, stride: int = 1) -> None:
        super().__init__()
        self.conv1 = nn.Conv2d(in_channels, out_channels, 3, stride=stride, padding=1, bias=False)
        self.conv2 = nn.Conv2d(out_channels, out_channels, 3, padding=1, bias=False)
        self.act = nn.LeakyReLU(LEAKY_SLOPE)
        self.stride = stride
        if stride != 1 or in_channels != out_channels:
            self.shortcut = nn.Conv2d(in_channels, out_channels, 1, bias=False)
        else:
            self.shortcut = nn.Identity()

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        skip = x if self.stride == 1 else x[:, :, :: self.stride, :: self.stride]
        return self.act(self.conv2(self.act(self.conv1(x))) + self.shortcut(skip))


def scaled_channels(channels: int, width: float) -> int:
    """``round(channels · width)``, at least 1: the channel count of a reference layer at ``width``."""
    return max(1, int(round(channels * width)))


def encode_heights(heights: torch.Tensor, max_height: float, num_classes: int, dtype: torch.dtype = torch.float32) -> torch.Tensor:
    """Heights (metres) -> the agent networks' input ``class / (K − 1)`` in [0, 1], same shape.

    ``class = geometry.heights_to_classes(heights, max_height, K)``: raw env heights and heights decoded
    from uint8 replay storage give bit-identical inputs.
    """
    classes = _geometry.heights_to_classes(heights, max_height, num_classes)
    return classes.to(dtype).div_(num_classes - 1)


def check_height_images(value, name: str, size: int, batch_shape: torch.Size | None = None) -> torch.Size:
    """Validate a ``[*B, 1, size, size]`` finite floating-point image in metres; return ``*B``.

    With ``batch_shape`` the leading dims must equal it. One-line ValueError naming ``name`` otherwise.
    """
    expected = f"[*B, 1, {size}, {size}] floating-point metres"
    if not torch.is_tensor(value):
        raise ValueError(f"{name} must be a {expected} tensor, got {type(value).__name__}")
    if value.dim() < 4 or tuple(value.shape[-3:]) != (1, size, size):
        raise ValueError(f"{name} must be {expected}, got shape {tuple(value.shape)}")
    if not value.is_floating_point():
        raise ValueError(f"{name} must be {expected}, got dtype {value.dtype}")
    if batch_shape is not None and value.shape[:-3] != batch_shape:
        raise ValueError(f"{name} must have batch shape {tuple(batch_shape)}, got shape {tuple(value.shape)}")
    if not bool(torch.isfinite(value).all()):
        raise ValueError(f"{name} must be finite (no NaN or inf)")
    return value.shape[:-3]


__all__ += ["BasicBlock", "scaled_channels", "encode_heights", "check_height_images"]  # noqa: PLE0605
