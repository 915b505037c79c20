"""The authors' released LDM network and its training step, rebuilt for side-by-side timing only.

Used by ``benchmarks/bench_ldm.py``; the ``ldm_rl`` package never imports this module. The network is the
released ``ActionPrimativeModel`` (one head = 24,893,963 parameters for K = 11 depth classes): a 3×3 stem,
four bottleneck-ResNet stages (expansion 2; 1, 2, 3, 1 blocks; stride 2), a 3×3 bridge, four Laina
up-projections fused with the encoder features by biased 1×1 convs of the concatenation, and a 3×3 output
conv followed by a channel softmax. LeakyReLU slope 0.01, BatchNorm after every encoder conv.

The training step mirrors the released update of the dynamics model: rotated bilinear crops of the
C-channel one-hot scene (``affine_grid``/``grid_sample``, empty pixels set to class 0), the in-hand
one-hot padded into the crop centre, the head(s) on the whole batch, the predicted crop pasted back into
the scene (detached; as the released forward does), the target classes = argmax of the crop of the true
next scene, the released "focal" loss with γ = 0 (class-weighted, smoothed cross-entropy on the softmax
probabilities) and an Adam step. With ``heads=2`` both heads run on every sample (the released code) and
each sample's loss uses the head of its hand state; with ``heads=1`` a single head runs on the batch.
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import nn

__all__ = ["ReferenceHead", "ReferenceLDMStep", "REFERENCE_HEAD_PARAMS", "one_hot_classes", "make_reference_batch", "focal_loss_gamma0"]

REFERENCE_HEAD_PARAMS = 24_893_963  # one head, K = 11 (the released configs)
SLOPE = 0.01
CROP, HAND, SCENE = 64, 24, 128


def _lrelu() -> nn.Module:
    return nn.LeakyReLU(SLOPE)


class _Bottleneck(nn.Module):
    """1×1 in→k, 3×3 k→k (stride s), 1×1 k→2k, each + BN (LReLU after the first two); + shortcut; LReLU."""

    def __init__(self, cin: int, k: int, stride: int = 1) -> None:
        super().__init__()
        self.c1, self.b1 = nn.Conv2d(cin, k, 1, bias=False), nn.BatchNorm2d(k)
        self.c2, self.b2 = nn.Conv2d(k, k, 3, stride, 1, bias=False), nn.BatchNorm2d(k)
        self.c3, self.b3 = nn.Conv2d(k, 2 * k, 1, bias=False), nn.BatchNorm2d(2 * k)
        self.down = None
        if stride != 1 or cin != 2 * k:
            self.down = nn.Sequential(nn.Conv2d(cin, 2 * k, 1, stride, bias=False), nn.BatchNorm2d(2 * k))
        self.act = _lrelu()

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        y = self.act(self.b1(self.c1(x)))
        y = self.act(self.b2(self.c2(y)))
        y = self.b3(self.c3(y))
        return self.act(y + (x if self.down is None else self.down(x)))


def _layer(cin: int, k: int, blocks: int, stride: int) -> nn.Sequential:
    return nn.Sequential(_Bottleneck(cin, k, stride), *[_Bottleneck(2 * k, k) for _ in range(blocks - 1)])


class _Unpool(nn.Module):
    """Up-convolution as four convs (3×3, 2×3, 3×2, 2×2, biased) interleaved into a 2× larger map."""

    def __init__(self, cin: int, k: int) -> None:
        super().__init__()
        self.a, self.b = nn.Conv2d(cin, k, 3, padding=1), nn.Conv2d(cin, k, (2, 3))
        self.c, self.d = nn.Conv2d(cin, k, (3, 2)), nn.Conv2d(cin, k, 2)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        a = self.a(x)
        b = self.b(F.pad(x, [1, 1, 0, 1]))
        c = self.c(F.pad(x, [0, 1, 1, 1]))
        d = self.d(F.pad(x, [0, 1, 0, 1]))
        n, k, h, w = a.shape
        even = torch.stack([a, c], 4).view(n, k, h, 2 * w)  # row 2i
        odd = torch.stack([b, d], 4).view(n, k, h, 2 * w)  # row 2i+1
        return torch.stack([even, odd], 3).view(n, k, 2 * h, 2 * w)


class _UpBlock(nn.Module):
    """Laina up-projection: (unpool+BN+LReLU+3×3 conv+BN) + (unpool+BN), then LReLU."""

    def __init__(self, cin: int, k: int) -> None:
        super().__init__()
        self.u1, self.n1 = _Unpool(cin, k), nn.BatchNorm2d(k)
        self.conv, self.n2 = nn.Conv2d(k, k, 3, padding=1), nn.BatchNorm2d(k)
        self.u2, self.n3 = _Unpool(cin, k), nn.BatchNorm2d(k)
        self.act = _lrelu()

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        main = self.n2(self.conv(self.act(self.n1(self.u1(x)))))
        return self.act(main + self.n3(self.u2(x)))


class ReferenceHead(nn.Module):
    """One released head: ``[B, 2K, 64, 64]`` one-hot planes -> ``[B, K, 64, 64]`` class probabilities."""

    def __init__(self, num_classes: int = 11) -> None:
        super().__init__()
        k = num_classes
        self.inp = nn.Sequential(nn.Conv2d(2 * k, 32, 3, padding=1, bias=False), nn.BatchNorm2d(32), _lrelu())
        self.layer1, self.layer2 = _layer(32, 32, 1, 2), _layer(64, 64, 2, 2)
        self.layer3, self.layer4 = _layer(128, 128, 3, 2), _layer(256, 256, 1, 2)
        self.forward_layer = nn.Sequential(nn.Conv2d(512, 512, 3, padding=1), nn.BatchNorm2d(512), _lrelu())
        self.up4, self.cat4 = _UpBlock(512, 512), nn.Conv2d(256 + 512, 256, 1)
        self.up3, self.cat3 = _UpBlock(256, 256), nn.Conv2d(128 + 256, 128, 1)
        self.up2, self.cat2 = _UpBlock(128, 128), nn.Conv2d(64 + 128, 64, 1)
        self.up1, self.cat1 = _UpBlock(64, 64), nn.Conv2d(32 + 64, 32, 1)
        self.out = nn.Conv2d(32, k, 3, padding=1)
        for m in self.modules():
            if isinstance(m, nn.Conv2d):
                nn.init.kaiming_normal_(m.weight, a=SLOPE, mode="fan_out", nonlinearity="leaky_relu")
            elif isinstance(m, nn.BatchNorm2d):
                nn.init.constant_(m.weight, 1.0)
                nn.init.constant_(m.bias, 0.0)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        f0 = self.inp(x)
        f1 = self.layer1(f0)
        f2 = self.layer2(f1)
        f3 = self.layer3(f2)
        f4 = self.forward_layer(self.layer4(f3))
        y = self.cat4(torch.cat([f3, self.up4(f4)], 1))
        y = self.cat3(torch.cat([f2, self.up3(y)], 1))
        y = self.cat2(torch.cat([f1, self.up2(y)], 1))
        y = self.cat1(torch.cat([f0, self.up1(y)], 1))
        return torch.softmax(self.out(y), dim=1)


def one_hot_classes(classes: torch.Tensor, num_classes: int) -> torch.Tensor:
    """[B, 1, H, W] integer classes -> [B, K, H, W] float one-hot (the released replay-sample format)."""
    return torch.zeros(classes.shape[0], num_classes, *classes.shape[-2:]).scatter_(1, classes.long(), 1.0)


def _crop(scene: torch.Tensor, rows: torch.Tensor, cols: torch.Tensor, theta: torch.Tensor) -> torch.Tensor:
    """Rotated 64×64 bilinear crops of a [B, C, 128, 128] one-hot scene; empty pixels -> class 0."""
    scale = CROP / SCENE
    cos, sin = torch.cos(theta) * scale, torch.sin(theta) * scale
    tx, ty = (cols.float() - SCENE / 2) / (SCENE / 2), (rows.float() - SCENE / 2) / (SCENE / 2)
    affine = torch.stack([torch.stack([cos, sin, tx], -1), torch.stack([-sin, cos, ty], -1)], 1)  # T·S·R(−θ)
    grid = F.affine_grid(affine, [scene.shape[0], 1, CROP, CROP], align_corners=False)
    crop = F.grid_sample(scene, grid, mode="bilinear", padding_mode="zeros", align_corners=False)
    if crop.shape[1] > 1:
        empty = crop.sum(1) == 0
        crop[:, 0] = torch.where(empty, torch.ones_like(crop[:, 0]), crop[:, 0])
    return crop


def _pad_hand(hand: torch.Tensor) -> torch.Tensor:
    """[B, K, 24, 24] one-hot hand -> [B, K, 64, 64], class 0 outside the central 24×24 window."""
    out = torch.zeros(hand.shape[0], hand.shape[1], CROP, CROP, dtype=hand.dtype)
    out[:, 0] = 1.0
    lo = (CROP - HAND) // 2
    out[:, :, lo : lo + HAND, lo : lo + HAND] = hand
    return out


def _paste(scene: torch.Tensor, crop: torch.Tensor, rows: torch.Tensor, cols: torch.Tensor, theta: torch.Tensor) -> torch.Tensor:
    """Rotate predicted crops back (R(+θ)) and overwrite the axis-aligned 64×64 window of each scene."""
    cos, sin = torch.cos(theta), torch.sin(theta)
    zero = torch.zeros_like(cos)
    affine = torch.stack([torch.stack([cos, -sin, zero], -1), torch.stack([sin, cos, zero], -1)], 1)
    grid = F.affine_grid(affine, list(crop.shape), align_corners=True)
    rotated = F.grid_sample(crop, grid, mode="bilinear", padding_mode="zeros", align_corners=False)
    half = CROP // 2
    padded = F.pad(scene, [half] * 4)
    for i, (r, c) in enumerate(zip(rows.tolist(), cols.tolist())):
        padded[i, :, r : r + CROP, c : c + CROP] = rotated[i]
    return padded[:, :, half:-half, half:-half]


def focal_loss_gamma0(probs: torch.Tensor, target: torch.Tensor, alpha: torch.Tensor, smooth: float = 1e-5) -> torch.Tensor:
    """The released loss at γ = 0: per-sample mean over pixels of ``−α[t]·log(Σ q·p + smooth)``.

    probs [B, K, H, W] softmax outputs, target [B, H, W] int64, alpha [K]; ``q`` = one-hot(t) clamped to
    ``[smooth/(K−1), 1 − smooth]``. Returns [B].
    """
    k = probs.shape[1]
    q = torch.zeros_like(probs).scatter_(1, target.unsqueeze(1), 1.0).clamp(smooth / (k - 1), 1.0 - smooth)
    pt = (q * probs).sum(1) + smooth
    return (-alpha[target] * pt.log()).flatten(1).mean(1)


class ReferenceLDMStep:
    """The released dynamics update, ``heads`` ∈ {1, 2}: ``step(batch)`` = forward + backward + Adam.

    ``batch`` is a dict of ``scene``/``next_scene`` [B, K, 128, 128] and ``hand`` [B, K, 24, 24] one-hot
    floats, ``rows``/``cols`` [B] int64 action pixels, ``theta`` [B] radians and ``holding`` [B] bool
    (prepared once, outside the timed step, as the released samplers do). Adam: lr 1e-3, weight decay
    1e-5 (the block-stacking config).
    """

    def __init__(self, heads: int = 2, num_classes: int = 11, bf16: bool = False) -> None:
        if heads not in (1, 2):
            raise ValueError(f"heads must be 1 or 2, got {heads}")
        self.heads = nn.ModuleList(ReferenceHead(num_classes) for _ in range(heads)).train()
        self.optimizer = torch.optim.Adam(self.heads.parameters(), lr=1e-3, weight_decay=1e-5)
        self.alpha = torch.linspace(1.0, 3.0, num_classes)
        self.bf16 = bf16

    def step(self, batch: dict) -> float:
        rows, cols, theta = batch["rows"], batch["cols"], batch["theta"]
        with torch.autocast("cpu", dtype=torch.bfloat16, enabled=self.bf16):
            crop = _crop(batch["scene"], rows, cols, theta)
            x = torch.cat([crop, _pad_hand(batch["hand"])], 1)
            outs = torch.stack([head(x) for head in self.heads], 1)  # [B, heads, K, 64, 64]
            with torch.no_grad():  # the released forward also pastes every head's crop into the scene
                for h in range(outs.shape[1]):
                    _paste(batch["scene"], outs[:, h].detach().float(), rows, cols, theta)
            index = batch["holding"].long() if len(self.heads) == 2 else torch.zeros_like(rows)
            pred = outs[torch.arange(outs.shape[0]), index]
            target = _crop(batch["next_scene"], rows, cols, theta).argmax(1)
            loss = focal_loss_gamma0(pred.float(), target, self.alpha).mean()  # IS weights all 1
        self.optimizer.zero_grad()
        loss.backward()
        self.optimizer.step()
        return float(loss.detach())


def make_reference_batch(scene_classes: torch.Tensor, next_classes: torch.Tensor, hand_classes: torch.Tensor,
                         action: torch.Tensor, holding: torch.Tensor, num_classes: int = 11, num_rotations: int = 8) -> dict:
    """Our batch (classes, action (row, col, rot bin), holding) -> the released step's input dict."""
    return {
        "scene": one_hot_classes(scene_classes, num_classes),
        "next_scene": one_hot_classes(next_classes, num_classes),
        "hand": one_hot_classes(hand_classes, num_classes),
        "rows": action[:, 0].long(),
        "cols": action[:, 1].long(),
        "theta": action[:, 2].float() * (math.pi / num_rotations),
        "holding": holding.reshape(-1).bool(),
    }
