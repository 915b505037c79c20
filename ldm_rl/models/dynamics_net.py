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
    planes = torch.cat((frame_classes.long(), padded_hand + num_classes), dim=1)  # [B, 2, S, S] plane index
    # scatter the ones straight into the float planes (no int64 one-hot, no permuted copy)
    out = torch.zeros(planes.shape[0], 2 * num_classes, size, size, device=planes.device)
    return out.scatter_(1, planes, 1.0)


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
        if self.extra_channels and (extra is None or extra.shape[1] != self.extra_channels):
            raise ValueError(f"extra must be [B, {self.extra_channels}, S, S], got {None if extra is None else tuple(extra.shape)}")
        holding = holding.reshape(-1).bool()
        n = frame_classes.shape[0]
        routes = [(head, rows) for head, rows in ((self.pick, (~holding).nonzero().squeeze(1)), (self.place, holding.nonzero().squeeze(1)))
                  if rows.numel()]
        if not routes:  # empty batch
            size = frame_classes.shape[-1]
            return torch.zeros(0, self.num_classes, size, size, device=frame_classes.device)
        if len(routes) == 1:  # one head for the whole batch: no gathers, no reordering
            x = encode_depth_inputs(frame_classes, hand_classes, self.num_classes)
            return routes[0][0](torch.cat((x, extra.to(x.dtype)), dim=1) if self.extra_channels else x)
        outputs = []
        for head, rows in routes:  # encode each head's samples from their (uint8) classes: no float-plane gathers
            x = encode_depth_inputs(frame_classes.index_select(0, rows), hand_classes.index_select(0, rows), self.num_classes)
            if self.extra_channels:
                x = torch.cat((x, extra.index_select(0, rows).to(x.dtype)), dim=1)
            outputs.append(head(x))
        order = torch.cat([rows for _, rows in routes])  # input sample of each row of cat(outputs)
        inverse = torch.empty_like(order).scatter_(0, order, torch.arange(n, device=order.device))
        return torch.cat(outputs).index_select(0, inverse)
