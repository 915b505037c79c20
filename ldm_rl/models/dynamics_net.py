"""Pick/place two-head dynamics network with per-sample head routing.

Input encoding (one place for it): the frame's depth classes and the current in-hand image's depth
classes, each one-hot over K classes; the in-hand one-hot is padded into the frame centre (class 0
elsewhere), as the reference's ``padHandObs``. Optional ``extra`` float planes (the Naive baseline's
action encoding) are appended. Each sample runs **only** the head of its primitive: the batch is split
by ``holding`` (False → pick head, True → place head) and the two outputs are scattered back.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from ldm_rl.models.unet import DepthUNet

__all__ = ["TwoHeadDynamicsNet", "encode_depth_inputs"]


def encode_depth_inputs(frame_classes: torch.Tensor, hand_classes: torch.Tensor, num_classes: int) -> torch.Tensor:
    """One-hot planes of the frame and of the centre-padded hand.

    Args:
        frame_classes: [B, 1, S, S] integer depth classes of the crop (or full image).
        hand_classes: [B, 1, h, h] integer depth classes of the in-hand image (h <= S).
    Returns:
        [B, 2·K, S, S] float32.
    """
    size, hand = frame_classes.shape[-1], hand_classes.shape[-1]
    lo = size // 2 - hand // 2
    pad = (lo, size - hand - lo, lo, size - hand - lo)
    padded_hand = F.pad(hand_classes.long(), pad, value=0)
    planes = torch.cat((frame_classes.long(), padded_hand), dim=1)  # [B, 2, S, S]
    one_hot = F.one_hot(planes, num_classes)  # [B, 2, S, S, K]
    return one_hot.permute(0, 1, 4, 2, 3).flatten(1, 2).float()


class TwoHeadDynamicsNet(nn.Module):
    """Routes each sample to the pick or the place :class:`DepthUNet`.

    Args:
        num_classes: K depth classes (input one-hot size and output logits).
        width: channel multiplier (1.0 = reference widths).
        extra_channels: float planes appended to the 2·K one-hot planes (0 for the LDM).
    """

    def __init__(self, num_classes: int, width: float = 1.0, extra_channels: int = 0) -> None:
        super().__init__()
        in_channels = 2 * num_classes + extra_channels
        self.pick = DepthUNet(in_channels, num_classes, width)
        self.place = DepthUNet(in_channels, num_classes, width)
        self.num_classes, self.extra_channels = num_classes, extra_channels

    def forward(
        self,
        frame_classes: torch.Tensor,
        hand_classes: torch.Tensor,
        holding: torch.Tensor,
        extra: torch.Tensor | None = None,
    ) -> torch.Tensor:
        """[B,1,S,S] int, [B,1,h,h] int, [B] bool, optional [B,E,S,S] float -> [B, K, S, S] logits."""
        x = encode_depth_inputs(frame_classes, hand_classes, self.num_classes)
        if self.extra_channels:
            if extra is None or extra.shape[1] != self.extra_channels:
                raise ValueError(f"extra must be [B, {self.extra_channels}, S, S], got {None if extra is None else tuple(extra.shape)}")
            x = torch.cat((x, extra.to(x.dtype)), dim=1)
        holding = holding.reshape(-1).bool()
        out = None
        for head, rows in ((self.pick, (~holding).nonzero().squeeze(1)), (self.place, holding.nonzero().squeeze(1))):
            if rows.numel() == 0:
                continue
            logits = head(x.index_select(0, rows))
            if out is None:
                out = logits.new_zeros((x.shape[0], *logits.shape[1:]))
            out = out.index_copy(0, rows, logits)
        return out
