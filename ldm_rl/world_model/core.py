"""The dynamics core: s, a -> (logits of the frame after the action, predicted next state).

Plain ``nn.Module``; the TorchRL wrappers live next to it (``modules``, ``transform``, ``imagined_env``).

Frames. ``frame="local"`` (LDM): the frame is the crop B_a of side ``crop_size`` centred at the action
pixel and rotated by the action's bin angle (``geometry.crop``, nearest, on the depth-class map); the
predicted frame is pasted back inside B_a only (every other pixel is bit-identical). ``frame="global"``
(Naive baseline): the frame is the whole, unrotated heightmap and the action is given as 3 extra input
planes (a Gaussian blob at the action pixel, cos 2θ and sin 2θ); the prediction replaces the whole image.

Height anchor (``height_anchor``, metres; not in the paper, off by default). The local frame is also shifted in
height: with ``t`` the highest point in the central ``ANCHOR_WINDOW``² pixels (under the fingers) and ``A`` the
anchor, every height of the crop is lowered by ``b = t − A`` metres (0 unless that exceeds half a depth class;
heights clamped at 0) before it is quantised, the network predicts in that frame, and its prediction is raised back
by ``b`` (a pixel predicted at 0 keeps its height if that was ≤ b, else falls to b). Up to the anchor nothing
changes; above it a pick from or a place onto a taller stack is predicted as the same action on a stack of the
anchor's height: pick-and-place does not depend on how high the surface stands, while a classifier over absolute
classes cannot output a class it never saw as a target (docs/dynamics.md, "The height anchor").

Next state. heightmap' = pasted ``argmax`` classes converted to metres; holding' by
:class:`HandStateRule` on the depth classes around the action before vs after (and the hand before); in_hand' = the central
``hand_size`` crop of the pre-action heightmap at the action when holding' else zeros.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import torch
from torch import nn

from ldm_rl import geometry
from ldm_rl.models.dynamics_net import TwoHeadDynamicsNet

__all__ = ["HandStateRule", "RULE_KINDS", "DynamicsPrediction", "HeldOutcome", "DynamicsModel", "validate_state_action", "pixel_entropy",
           "HEIGHTMAP_SIZE", "HAND_SIZE"]

HEIGHTMAP_SIZE = geometry.HEIGHTMAP_SIZE
HAND_SIZE = geometry.HAND_SIZE
ANCHOR_WINDOW = 12  # px (3.75 cm, under the fingers): the central window whose highest point sets an anchored frame's shift


RULE_KINDS = ("occupancy", "removal")


@dataclass(frozen=True)
class HandStateRule:
    """Whether the hand holds an object after the action, read off depth classes around the action.

    ``kind="occupancy"`` (the reference's rule, the default): ``n(X)`` = number of pixels with class > 0 in
    the central ``center_size``² window of crop X (taken at the action, rotated by its angle). The hand
    holds something after the action iff ``n(before) > before_threshold`` and ``n(after) <= after_threshold``
    (an object was there and the window is empty now). Applied to picks and places alike (a place leaves
    the centre occupied, hence False). It misreads every pick that leaves something else in the window: a
    block taken from a stack's top, an object picked beside a neighbour or the bin's wall.

    ``kind="removal"`` (not in the paper): the hand holds something after a pick iff more than
    ``removal_fraction`` of the central ``removal_size``² pixels dropped by at least one depth class (the
    object under the fingers is gone, whatever stays around or below it); after a place never (the env's
    place always opens the hand). Measured on the true frames of noisy expert transitions (docs/dynamics.md,
    "The hand-state rule"): it misses 0–3 held picks per task where the occupancy rule misses 0–15.
    """

    center_size: int = 32
    before_threshold: int = 25
    after_threshold: int = 25
    kind: str = "occupancy"
    removal_size: int = 12
    removal_fraction: float = 0.5

    def __post_init__(self) -> None:
        if self.kind not in RULE_KINDS:
            raise ValueError(f"hand_rule.kind must be one of {RULE_KINDS}, got {self.kind!r}")
        if not 0.0 <= float(self.removal_fraction) < 1.0:
            raise ValueError(f"hand_rule.removal_fraction must be in [0, 1), got {self.removal_fraction!r}")
        if int(self.removal_size) < 1:
            raise ValueError(f"hand_rule.removal_size must be a positive number of pixels, got {self.removal_size!r}")

    @property
    def window(self) -> int:
        """Side (pixels) of the crop around the action the rule reads."""
        return self.center_size if self.kind == "occupancy" else self.removal_size

    def count(self, classes: torch.Tensor) -> torch.Tensor:
        """[N, 1, d, d] int classes (d >= center_size) -> [N] int64 occupied-pixel counts."""
        return (geometry.center_crop(classes, self.center_size) > 0).flatten(1).sum(1)

    def __call__(self, before: torch.Tensor, after: torch.Tensor, picking: torch.Tensor | None = None) -> torch.Tensor:
        """[N, 1, d, d] class crops centred at the action before/after (d >= :attr:`window`), optional [N]
        bool ``picking`` (the hand was empty; needed by ``removal``) -> [N] bool, holding after the action."""
        if self.kind == "occupancy":
            return (self.count(before) > self.before_threshold) & (self.count(after) <= self.after_threshold)
        if picking is None:
            raise ValueError("hand_rule.kind='removal' needs `picking` (the hand state before the action)")
        drop = geometry.center_crop(before, self.removal_size).long() - geometry.center_crop(after, self.removal_size).long()
        removed = (drop >= 1).flatten(1).float().mean(1) > self.removal_fraction
        return removed & picking.reshape(-1).bool()


def pixel_entropy(logits: torch.Tensor) -> torch.Tensor:
    """The model's predictive uncertainty: frame logits ``[*B, K, S, S]`` -> ``[*B]`` float32, nats.

    The mean over the S² pixels of the frame (the crop B_a for the LDM) of each pixel's categorical entropy
    ``−Σ_k p_k log p_k``, ``p = softmax(logits)`` over the K depth classes: 0 for a one-hot prediction,
    ``log K`` for a uniform one. Computed in float32 whatever the logits' dtype.
    """
    if not torch.is_tensor(logits) or logits.dim() < 3:
        raise _shape_error("logits", "a [*B, K, S, S] tensor of frame logits", logits)
    log_p = torch.log_softmax(logits.float(), dim=-3)
    return -(log_p.exp() * log_p).sum(-3).flatten(-2).mean(-1)


class DynamicsPrediction(NamedTuple):
    """Predicted next state; leading dims ``*B`` as the inputs."""

    heightmap: torch.Tensor  # [*B, 1, 128, 128] float32 metres
    in_hand: torch.Tensor  # [*B, 1, 24, 24] float32 metres
    holding: torch.Tensor  # [*B, 1] bool
    logits: torch.Tensor  # [*B, K, S, S] float32 frame logits

    def entropy(self) -> torch.Tensor:
        """``[*B]`` float32 nats: :func:`pixel_entropy` of the frame logits (mean pixel entropy inside B_a)."""
        return pixel_entropy(self.logits)


class HeldOutcome(NamedTuple):
    """A pick's held branch (:meth:`DynamicsModel.held_outcome`); leading dims ``*B`` as the inputs."""

    probability: torch.Tensor  # [*B] float32 in [0, 1]: the model's probability that the pick holds
    heightmap: torch.Tensor  # [*B, 1, 128, 128] float32 metres: the scene should it hold
    in_hand: torch.Tensor  # [*B, 1, 24, 24] float32 metres: the grasped crop


def channel_argmax(logits: torch.Tensor) -> torch.Tensor:
    """[N, K, *S] -> [N, *S] int64: ``logits.argmax(1)`` (first maximum), faster on CPU.

    On CPU reducing a contiguous last dim is ~2.4× faster than reducing dim 1 of [N, K, *S], even with
    the copy; other devices use ``argmax(1)`` directly.
    """
    if logits.device.type == "cpu":
        return logits.movedim(1, -1).contiguous().argmax(-1)
    return logits.argmax(1)


def _shape_error(name: str, expected: str, value) -> ValueError:
    got = tuple(value.shape) if torch.is_tensor(value) else type(value).__name__
    return ValueError(f"{name} must be {expected}, got {got}")


def validate_state_action(heightmap, in_hand, holding, action, num_rotations: int):
    """Check one state-action batch at the module boundary; returns (batch shape, holding as [*B] bool).

    heightmap [*B,1,128,128] float (finite), in_hand [*B,1,24,24] float (finite), holding [*B,1] or [*B]
    bool/integer in {0,1}, action [*B,3] integer (row, col in 0..127, rot in 0..R−1); ``*B`` may be () but
    not empty. Raises ValueError.
    """
    hw = HEIGHTMAP_SIZE
    if not torch.is_tensor(heightmap) or heightmap.dim() < 3 or tuple(heightmap.shape[-3:]) != (1, hw, hw):
        raise _shape_error("heightmap", f"a [*B, 1, {hw}, {hw}] float tensor (metres)", heightmap)
    batch = heightmap.shape[:-3]
    if 0 in tuple(batch):
        raise ValueError(f"empty batch: heightmap is {tuple(heightmap.shape)}; need at least one state-action pair")
    if not torch.is_tensor(in_hand) or tuple(in_hand.shape) != (*batch, 1, HAND_SIZE, HAND_SIZE):
        raise _shape_error("in_hand", f"[{', '.join(map(str, batch))}, 1, {HAND_SIZE}, {HAND_SIZE}] (batch of heightmap)", in_hand)
    if not torch.is_tensor(action) or tuple(action.shape) != (*batch, 3):
        raise _shape_error("action", f"[{', '.join(map(str, batch))}, 3] int64 (row, col, rot bin)", action)
    if not torch.is_tensor(holding) or tuple(holding.shape) not in ((*batch, 1), tuple(batch)):
        raise _shape_error("holding", f"[{', '.join(map(str, batch))}, 1] bool", holding)
    for name, t in (("heightmap", heightmap), ("in_hand", in_hand)):
        if not t.is_floating_point():
            raise ValueError(f"{name} must be a floating-point tensor in metres, got dtype {t.dtype}")
        if not torch.isfinite(t).all():
            raise ValueError(f"{name} contains NaN or inf")
    if action.is_floating_point() or action.dtype == torch.bool:
        raise ValueError(f"action must be an integer tensor (row, col, rot bin), got dtype {action.dtype}")
    limits = torch.tensor([hw, hw, num_rotations], device=action.device)
    if action.numel() and ((action < 0) | (action >= limits)).any():
        raise ValueError(f"action out of range: row, col must lie in [0, {hw}) and rot in [0, {num_rotations})")
    if holding.is_floating_point():
        raise ValueError(f"holding must be bool (or integer 0/1), got dtype {holding.dtype}")
    if holding.dtype != torch.bool and holding.numel() and ((holding < 0) | (holding > 1)).any():
        raise ValueError("holding must contain only 0/1")
    return batch, holding.reshape(batch).bool()


class DynamicsModel(nn.Module):
    """Local (LDM) or global (Naive) dynamics model around a :class:`TwoHeadDynamicsNet`.

    Args:
        net: the two-head network; ``net.extra_channels`` must be 0 (local) or 3 (global).
        frame: ``"local"`` (crop B_a, paste back) or ``"global"`` (whole image, action planes).
        crop_size: side of B_a in pixels (local frame; 64 = LDM(64), 128 = LDM(128)).
        max_height: metres mapped to the top depth class (per task).
        num_rotations: R rotation bins (angle k·π/R).
        hand_rule: the hand-state rule.
        hand_crop_mode: geometry.crop mode for the predicted in-hand image (as the env renders it).
        action_sigma: pixels, width of the Naive model's Gaussian action blob.
        height_anchor: metres, or None (the paper): the local frame lowered by how far the highest point under the
            fingers stands above it (see the module docstring).
    """

    def __init__(
        self,
        net: TwoHeadDynamicsNet,
        *,
        frame: str = "local",
        crop_size: int = 64,
        max_height: float,
        num_rotations: int = geometry.NUM_ROTATIONS,
        hand_rule: HandStateRule = HandStateRule(),
        hand_crop_mode: str = "bilinear",
        action_sigma: float = 2.0,
        height_anchor: float | None = None,
    ) -> None:
        super().__init__()
        if frame not in ("local", "global"):
            raise ValueError(f"frame must be 'local' or 'global', got {frame!r}")
        expected_extra = 0 if frame == "local" else 3
        if net.extra_channels != expected_extra:
            raise ValueError(f"frame={frame!r} needs a net with extra_channels={expected_extra}, got {net.extra_channels}")
        size = crop_size if frame == "local" else HEIGHTMAP_SIZE
        if size % 16 or not HAND_SIZE <= size <= HEIGHTMAP_SIZE or size < hand_rule.window:
            raise ValueError(f"crop_size must be a multiple of 16 in [{max(HAND_SIZE, hand_rule.window)}, {HEIGHTMAP_SIZE}], got {size}")
        self.net, self.frame, self.frame_size = net, frame, size
        self.max_height, self.num_rotations, self.num_classes = float(max_height), int(num_rotations), net.num_classes
        self.hand_rule, self.hand_crop_mode, self.action_sigma = hand_rule, hand_crop_mode, float(action_sigma)
        self.height_anchor = None
        if height_anchor is not None:
            if isinstance(height_anchor, bool) or not isinstance(height_anchor, (int, float)) \
                    or not 0 < height_anchor < max_height:
                raise ValueError(f"height_anchor must be None or metres in (0, max_height={max_height}), got {height_anchor!r}")
            if frame != "local":
                raise ValueError("height_anchor shifts the local frame (LDM); the Naive model's global frame has none")
            self.height_anchor = float(height_anchor)

    # ---------------------------------------------------------------- frames
    def classes(self, heights: torch.Tensor) -> torch.Tensor:
        """Heights (metres) -> uint8 depth classes, same shape."""
        return geometry.heights_to_classes(heights, self.max_height, self.num_classes)

    def heights(self, classes: torch.Tensor) -> torch.Tensor:
        """Depth classes -> float32 metres, same shape."""
        return geometry.classes_to_heights(classes, self.max_height, self.num_classes)

    def frame_classes(self, heightmap: torch.Tensor, action: torch.Tensor, shift: torch.Tensor | None = None) -> torch.Tensor:
        """[N,1,128,128] metres, [N,3] action -> [N,1,S,S] uint8 classes of the model's frame; ``shift`` ``[N, 1, 1, 1]``
        metres: the heights lowered by it first (clamped at 0; the height-anchored frame, :meth:`frame_shift`).

        Also the target of the loss when given the true next heightmap.
        """
        if shift is not None:
            heightmap = (heightmap - shift).clamp_min(0)
        classes = self.classes(heightmap)
        if self.frame == "global":
            return classes
        centers, angles = geometry.action_to_pose(action, self.num_rotations)
        return geometry.crop(classes, centers, angles, self.frame_size, mode="nearest")

    def frame_shift(self, heightmap: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        """``[N, 1, 1, 1]`` metres the height-anchored frame lowers each scene ``[N, 1, 128, 128]`` by at ``action``:
        how far the highest point under the fingers (the central ``ANCHOR_WINDOW``² pixels) stands above the anchor
        (0 without an anchor, below it, and within half a depth class above it: the env's heights carry
        sub-millimetre noise, and a frame must not move for it)."""
        if self.height_anchor is None:
            return heightmap.new_zeros(heightmap.shape[0], 1, 1, 1)
        centers, angles = geometry.action_to_pose(action, self.num_rotations)
        under = geometry.crop(heightmap, centers, angles, ANCHOR_WINDOW, mode="nearest")
        excess = under.flatten(1).amax(1) - self.height_anchor
        half_class = 0.5 * self.max_height / (self.num_classes - 1)
        return torch.where(excess > half_class, excess, torch.zeros_like(excess)).view(-1, 1, 1, 1)

    def from_model_frame(self, predicted: torch.Tensor, before: torch.Tensor, shift: torch.Tensor) -> torch.Tensor:
        """The network's predicted classes ``[N, 1, S, S]`` -> absolute ones (uint8), ``before`` the absolute classes of
        the crop and ``shift`` (metres, :meth:`frame_shift`): raised by ``shift``; a pixel predicted at 0 keeps its
        height where that was at most ``shift``, else falls to ``shift``."""
        if self.height_anchor is None:
            return predicted.to(torch.uint8)
        height = torch.where(predicted == 0, torch.minimum(self.heights(before), shift), self.heights(predicted) + shift)
        return self.classes(height)

    def frame_targets(self, heightmap: torch.Tensor, next_heightmap: torch.Tensor, action: torch.Tensor):
        """``(before, target)``: the crop classes ``[N, 1, S, S]`` of the state and of the true next state at
        ``action``, in the network's frame (what its logits are fitted to)."""
        shift = self.frame_shift(heightmap, action) if self.height_anchor is not None else None
        return self.frame_classes(heightmap, action, shift), self.frame_classes(next_heightmap, action, shift)

    def action_region(self, classes: torch.Tensor, action: torch.Tensor, size: int) -> torch.Tensor:
        """Rotated ``size``² class crop at the action (for the hand-state rule): [N,1,size,size] uint8."""
        centers, angles = geometry.action_to_pose(action, self.num_rotations)
        return geometry.crop(classes, centers, angles, size, mode="nearest")

    def action_planes(self, action: torch.Tensor) -> torch.Tensor:
        """[N,3] action -> [N,3,128,128] float32: Gaussian blob at (row, col), cos 2θ, sin 2θ (Naive input)."""
        n, hw = action.shape[0], HEIGHTMAP_SIZE
        grid = torch.arange(hw, device=action.device, dtype=torch.float32)
        dr = grid.view(1, hw, 1) - action[:, 0].float().view(n, 1, 1)
        dc = grid.view(1, 1, hw) - action[:, 1].float().view(n, 1, 1)
        blob = torch.exp(-(dr**2 + dc**2) / (2 * self.action_sigma**2))
        angle = geometry.bin_to_angle(action[:, 2], self.num_rotations).to(action.device)
        cos2, sin2 = torch.cos(2 * angle).view(n, 1, 1), torch.sin(2 * angle).view(n, 1, 1)
        return torch.stack((blob, cos2.expand(n, hw, hw), sin2.expand(n, hw, hw)), dim=1)

    # ---------------------------------------------------------------- model
    def net_inputs(self, heightmap, in_hand, action):
        """What the network reads for a flat batch (``[N,1,128,128]`` m, ``[N,1,24,24]`` m, ``[N,3]``): ``(seen, hand,
        extra, frame)``: the frame it sees ``[N,1,S,S]`` uint8 (height-anchored where set), the in-hand classes
        ``[N,1,24,24]`` uint8, the Naive model's action planes ``[N,3,128,128]`` (None for the LDM), and the crop's
        absolute classes ``[N,1,S,S]`` (what the prediction is pasted over)."""
        frame = self.frame_classes(heightmap, action)
        extra = self.action_planes(action) if self.frame == "global" else None
        seen = frame if self.height_anchor is None else self.frame_classes(heightmap, action, self.frame_shift(heightmap, action))
        return seen, self.classes(in_hand), extra, frame

    def _flat_logits(self, heightmap, in_hand, holding, action):
        seen, hand, extra, frame = self.net_inputs(heightmap, in_hand, action)
        return self.net(seen, hand, holding, extra), frame

    def forward(self, heightmap, in_hand, holding, action) -> torch.Tensor:
        """Frame logits ``[*B, K, S, S]`` for a state-action batch (see :func:`validate_state_action`)."""
        batch, holding = validate_state_action(heightmap, in_hand, holding, action, self.num_rotations)
        logits, _ = self._flat_logits(*self._flatten(batch, heightmap, in_hand, holding, action))
        return logits.reshape(*batch, *logits.shape[1:])

    def predict(self, heightmap, in_hand, holding, action) -> DynamicsPrediction:
        """Full next-state prediction (heightmap', in_hand', holding', logits); see the module docstring."""
        batch, holding = validate_state_action(heightmap, in_hand, holding, action, self.num_rotations)
        heightmap, in_hand, holding, action = self._flatten(batch, heightmap, in_hand, holding, action)
        logits, frame_before = self._flat_logits(heightmap, in_hand, holding, action)
        return self._next_state(batch, heightmap, holding, action, logits, frame_before)

    def next_state_from_logits(self, heightmap, in_hand, holding, action, logits) -> DynamicsPrediction:
        """The next state implied by frame ``logits`` ``[*B, K, S, S]`` already computed for this batch
        (e.g. by the training loss' forward pass): no second network pass. Gradients are not tracked."""
        batch, holding = validate_state_action(heightmap, in_hand, holding, action, self.num_rotations)
        if not torch.is_tensor(logits) or tuple(logits.shape) != (*batch, self.num_classes, self.frame_size, self.frame_size):
            raise _shape_error("logits", f"[*B, {self.num_classes}, {self.frame_size}, {self.frame_size}]", logits)
        heightmap, _, holding, action = self._flatten(batch, heightmap, in_hand, holding, action)
        with torch.no_grad():
            return self._next_state(batch, heightmap, holding, action, logits.detach().reshape(-1, *logits.shape[len(batch):]))

    def held_outcome(self, heightmap, action, logits) -> HeldOutcome:
        """A pick's outcome should it hold, from the frame ``logits`` ``[*B, K, S, S]`` already computed for the
        picks ``action`` ``[*B, 3]`` in ``heightmap`` ``[*B, 1, 128, 128]`` (metres); no network pass.

        The per-pixel distribution mixes a pick's two outcomes, and its mode (:meth:`predict`) keeps the likelier
        one only: a pick that holds one time in three is predicted to change nothing. Here ``probability`` is the
        mean, over the central ``hand_rule.removal_size``² pixels at the action, of the model's probability that
        a pixel's depth class drops (the object under the fingers leaves); the held scene lowers every pixel
        whose drop probability reaches half of it (the pixels that go with the object) to its likeliest lower
        class, the other pixels keep the mode; the in-hand image is the grasped crop, as :meth:`predict` gives it.
        """
        batch = heightmap.shape[:-3] if torch.is_tensor(heightmap) else ()
        device = heightmap.device if torch.is_tensor(heightmap) else None
        blank = torch.zeros(*batch, 1, HAND_SIZE, HAND_SIZE, device=device)  # checked as a pick: an empty hand
        validate_state_action(heightmap, blank, torch.zeros(*batch, 1, dtype=torch.bool, device=device), action, self.num_rotations)
        k, s = self.num_classes, self.frame_size
        if not torch.is_tensor(logits) or tuple(logits.shape) != (*batch, k, s, s):
            raise _shape_error("logits", f"[{', '.join(map(str, (*batch, k, s, s)))}] (the frame logits of these picks)", logits)
        heightmap, action = heightmap.reshape(-1, *heightmap.shape[-3:]), action.reshape(-1, 3).long()
        logits = logits.reshape(-1, k, s, s).float()
        absolute = self.frame_classes(heightmap, action)  # [N, 1, S, S]
        shift = self.frame_shift(heightmap, action)
        before = self.frame_classes(heightmap, action, shift).long()  # in the network's frame, as the logits
        below = torch.arange(k, device=logits.device).view(1, k, 1, 1) < before  # classes under each pixel's
        p_drop = torch.where(below, torch.softmax(logits, 1), 0.0).sum(1, keepdim=True)  # [N, 1, S, S]
        size = self.hand_rule.removal_size
        if self.frame == "local":
            under_fingers = geometry.center_crop(p_drop, size)
        else:
            under_fingers = self.action_region(p_drop, action, size)
        probability = under_fingers.flatten(1).mean(1).clamp(0.0, 1.0)
        leaves = (p_drop > 0) & (p_drop >= 0.5 * probability.view(-1, 1, 1, 1))
        lower = channel_argmax(logits.masked_fill(~below, float("-inf"))).unsqueeze(1)
        frame = self.from_model_frame(torch.where(leaves, lower, channel_argmax(logits).unsqueeze(1)), absolute, shift)
        centers, angles = geometry.action_to_pose(action, self.num_rotations)
        if self.frame == "local":
            held = geometry.paste(heightmap, self.heights(frame).to(heightmap.dtype), centers, angles, mode="nearest")
        else:
            held = self.heights(frame).to(heightmap.dtype)
        in_hand = geometry.crop(heightmap, centers, angles, HAND_SIZE, mode=self.hand_crop_mode)
        return HeldOutcome(probability.reshape(batch), held.reshape(*batch, *held.shape[1:]),
                           in_hand.reshape(*batch, *in_hand.shape[1:]))

    def _next_state(self, batch, heightmap, holding, action, logits, frame_before=None) -> DynamicsPrediction:
        """Flat [N] heightmap/holding (before)/action and [N, K, S, S] logits -> the prediction reshaped to ``batch``."""
        if frame_before is None:
            frame_before = self.frame_classes(heightmap, action)
        frame_after = self.from_model_frame(channel_argmax(logits).unsqueeze(1), frame_before, self.frame_shift(heightmap, action))
        centers, angles = geometry.action_to_pose(action, self.num_rotations)
        size, picking = self.hand_rule.window, ~holding
        if self.frame == "local":
            patch = self.heights(frame_after).to(heightmap.dtype)
            next_heightmap = geometry.paste(heightmap, patch, centers, angles, mode="nearest")
            next_holding = self.hand_rule(geometry.center_crop(frame_before, size), geometry.center_crop(frame_after, size), picking)
        else:
            next_heightmap = self.heights(frame_after).to(heightmap.dtype)
            next_holding = self.hand_rule(
                self.action_region(frame_before, action, size), self.action_region(frame_after, action, size), picking
            )
        grasped = geometry.crop(heightmap, centers, angles, HAND_SIZE, mode=self.hand_crop_mode)
        next_in_hand = torch.where(next_holding.view(-1, 1, 1, 1), grasped, torch.zeros_like(grasped))
        return DynamicsPrediction(
            next_heightmap.reshape(*batch, *next_heightmap.shape[1:]),
            next_in_hand.reshape(*batch, *next_in_hand.shape[1:]),
            next_holding.reshape(*batch, 1),
            logits.reshape(*batch, *logits.shape[1:]),
        )

    @staticmethod
    def _flatten(batch, heightmap, in_hand, holding, action):
        return (
            heightmap.reshape(-1, *heightmap.shape[len(batch):]),
            in_hand.reshape(-1, *in_hand.shape[len(batch):]),
            holding.reshape(-1),
            action.reshape(-1, 3).long(),
        )
