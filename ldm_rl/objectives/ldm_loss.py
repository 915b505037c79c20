"""``LDMLoss``: the focal loss of the Local Dynamics Model as a TorchRL ``LossModule``."""

from __future__ import annotations

from dataclasses import dataclass

import torch
from tensordict import TensorDict, TensorDictBase
from tensordict.utils import NestedKey
from torchrl.objectives import LossModule

from ldm_rl import geometry
from ldm_rl.keys import ACTION, HEIGHTMAP, HOLDING, IN_HAND, NEXT_LOGITS, next_key, require_keys
from ldm_rl.objectives.focal import depth_class_weights, focal_loss
from ldm_rl.world_model.core import DynamicsModel, channel_argmax, validate_state_action

__all__ = ["LDMLoss"]


class LDMLoss(LossModule):
    """Focal loss between the model's frame logits and the depth classes of the true next frame.

    The target is ``dynamics.frame_targets(heightmap, next_heightmap, action)[1]``: the crop of the true next heightmap
    at the same action and angle (LDM; in its height-anchored frame with ``height_anchor``) or the whole next heightmap
    (Naive).

    Args:
        dynamics: the :class:`DynamicsModel` to train (a child module: ``loss.parameters()`` are its
            parameters).
        gamma: focal exponent, default 2 (0 = weighted cross-entropy, the released code's choice).
        class_weights: default ``None`` = uniform (every class weighs 1); or a [K] tensor; or ``"auto"``:
            the reference's rule ``w_c = max(1, ln(0.05·N/n_c))`` from the target class counts
            accumulated over every batch seen in training mode (buffer ``class_counts``; fixed in eval
            mode). The recipes pass ``"auto"`` (``conf/loss/focal.yaml``), as the paper did; pass it too
            to train as they do.
        label_smoothing: ε of the smoothed target distribution, default 0.
        write_logits: also write the detached frame logits ``[*B, K, S, S]`` into the input under
            ``next_logits`` (the agent derives the predicted next state from them: no second LDM pass).
        gripper_symmetries: in training mode, show the network each transition under one of the four symmetries of
            a parallel-jaw gripper, drawn per sample (identity, the mirror across either axis of its frame, the half
            turn: :func:`ldm_rl.geometry.mirror_crops`), applied alike to the crop it sees, the in-hand image and the
            target crop; the written logits are mirrored back, so they predict the untouched transition. Mirrored
            physics is physics, so each transition counts up to four times (not in the paper). The LDM's
            gripper-aligned frame only: a Naive model raises.

    Input: a batch ``[*B]`` (not empty) of transitions with the keys of :attr:`in_keys` (heightmap,
    in_hand, holding, action, ``("next", "heightmap")``), e.g. a replay-buffer sample; a missing key or an
    empty batch raises one ``ValueError`` before any work. Returns a TensorDict with ``loss_dynamics``
    (scalar) and diagnostics ``pixel_accuracy`` (argmax == target over the frame) and
    ``changed_pixel_accuracy`` (the same over pixels whose class changes).
    """

    @dataclass
    class _AcceptedKeys:
        """Input keys; change them with ``loss.set_keys(heightmap=..., next_heightmap=...)``."""

        heightmap: NestedKey = HEIGHTMAP
        in_hand: NestedKey = IN_HAND
        holding: NestedKey = HOLDING
        action: NestedKey = ACTION
        next_heightmap: NestedKey = next_key(HEIGHTMAP)
        next_logits: NestedKey = NEXT_LOGITS

    default_keys = _AcceptedKeys
    tensor_keys: _AcceptedKeys

    def __init__(self, dynamics: DynamicsModel, *, gamma: float = 2.0, class_weights=None, label_smoothing: float = 0.0,
                 write_logits: bool = False, gripper_symmetries: bool = False) -> None:
        super().__init__()
        if gamma < 0 or not 0.0 <= label_smoothing < 1.0:
            raise ValueError(f"need gamma >= 0 and label_smoothing in [0, 1), got {gamma}, {label_smoothing}")
        if gripper_symmetries and dynamics.frame != "local":
            raise ValueError(f"gripper_symmetries needs the LDM's gripper-aligned local frame, got frame={dynamics.frame!r}")
        self.dynamics = dynamics
        self.gripper_symmetries = bool(gripper_symmetries)
        self.gamma, self.label_smoothing = float(gamma), float(label_smoothing)
        self.write_logits = bool(write_logits)
        k = dynamics.num_classes
        self.auto_weights = isinstance(class_weights, str)
        if self.auto_weights and class_weights != "auto":
            raise ValueError(f"class_weights must be None, a [K] tensor or 'auto', got {class_weights!r}")
        if class_weights is not None and not self.auto_weights:
            class_weights = torch.as_tensor(class_weights, dtype=torch.float32)
            if class_weights.shape != (k,) or not torch.isfinite(class_weights).all() or (class_weights < 0).any():
                raise ValueError(f"class_weights must be a finite non-negative [{k}] tensor, got {tuple(class_weights.shape)}")
        self.register_buffer("class_counts", torch.zeros(k, dtype=torch.float64))
        self.register_buffer("fixed_weights", None if class_weights is None or self.auto_weights else class_weights)

    def _forward_value_estimator_keys(self, **kwargs) -> None:
        pass

    @property
    def in_keys(self) -> list[NestedKey]:
        k = self.tensor_keys
        return [k.heightmap, k.in_hand, k.holding, k.action, k.next_heightmap]

    def class_weights(self) -> torch.Tensor | None:
        """The [K] weights in use (None = uniform)."""
        if self.auto_weights:
            return depth_class_weights(self.class_counts) if self.class_counts.sum() > 0 else None
        return self.fixed_weights

    def forward(self, tensordict: TensorDictBase) -> TensorDict:
        k = self.tensor_keys
        require_keys(tensordict, self.in_keys, "LDMLoss")
        heightmap, action = tensordict.get(k.heightmap), tensordict.get(k.action)
        next_heightmap = tensordict.get(k.next_heightmap)
        if not torch.is_tensor(next_heightmap) or next_heightmap.shape != heightmap.shape or not torch.isfinite(next_heightmap).all():
            raise ValueError(f"{k.next_heightmap} must be a finite tensor shaped like {k.heightmap} {tuple(heightmap.shape)}")
        batch, holding = validate_state_action(
            heightmap, tensordict.get(k.in_hand), tensordict.get(k.holding), action, self.dynamics.num_rotations
        )
        if not batch:
            raise ValueError("LDMLoss needs a batched tensordict (non-empty batch_size)")
        in_hand, flat_action = tensordict.get(k.in_hand), action.reshape(-1, 3).long()
        before, target = self.dynamics.frame_targets(heightmap.reshape(-1, *heightmap.shape[-3:]),
                                                     next_heightmap.reshape(-1, *next_heightmap.shape[-3:]), flat_action)
        if self.gripper_symmetries and self.training:
            seen, hand, extra, _ = self.dynamics.net_inputs(heightmap.reshape(-1, *heightmap.shape[-3:]),
                                                            in_hand.reshape(-1, *in_hand.shape[-3:]), flat_action)
            rows, cols = torch.randint(0, 2, (2, seen.shape[0]), device=seen.device).bool()
            mirror = lambda x: geometry.mirror_crops(x, rows, cols)  # noqa: E731  (its own inverse)
            logits = self.dynamics.net(mirror(seen), mirror(hand), holding.reshape(-1), extra)  # [N, K, S, S]
            before, target = mirror(before), mirror(target)
            if self.write_logits:
                tensordict.set(k.next_logits, mirror(logits.detach()).reshape(*batch, *logits.shape[1:]))
        else:
            logits = self.dynamics(heightmap, in_hand, holding, action)
            if self.write_logits:
                tensordict.set(k.next_logits, logits.detach())
            logits = logits.reshape(-1, *logits.shape[-3:])  # [N, K, S, S]
        before, target = before[:, 0], target[:, 0]
        if self.auto_weights and self.training:
            self.class_counts += torch.bincount(target.flatten().long(), minlength=self.dynamics.num_classes).to(self.class_counts)
        per_sample = focal_loss(
            logits, target, gamma=self.gamma, weight=self.class_weights(), label_smoothing=self.label_smoothing
        )
        with torch.no_grad():
            correct = channel_argmax(logits) == target
            changed = target != before
            changed_acc = (correct & changed).sum() / changed.sum().clamp_min(1)
        return TensorDict(
            {
                "loss_dynamics": per_sample.mean(),
                "pixel_accuracy": correct.float().mean(),
                "changed_pixel_accuracy": changed_acc.float(),
            },
            batch_size=[],
        )
