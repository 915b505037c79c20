"""The agent's state-value network: V(s) and the reward of being in s, from the scene and the in-hand image.

Architecture (the reference ``StateValueModel``; channel and hidden sizes at ``width`` = 1, every one
scaled by ``width``; no BatchNorm, LeakyReLU 0.01, ``kaiming_normal_(fan_out, leaky_relu 0.01)`` on every
conv weight, PyTorch defaults for conv biases and linear layers):

* scene trunk: four basic blocks stride 2, 1→32→64→128→256 (128² → 256×8×8);
* hand trunk: the in-hand image zero-padded 24 → 64, three basic blocks stride 2, 1→32→64→128 (→ 128×8×8);
* ``cat`` → 384×8×8, then two separate, identical heads (``value`` and ``reward``): 3×3 conv stride 2
  384→256 (bias) → LReLU → flatten 4096 → 2048 → 1028 → 256 → 1 (LReLU between, no output activation).

Option ``termination_head`` (not in the reference): a third identical head gives the logit of ``T(s)``, the
probability that the episode ends on arriving in ``s``, and V is composed as
``V(s) = T(s)·R(s) + (1 − T(s))·W(s)``, ``R`` the reward head and ``W`` the value head (the value of going on):
a state the model predicts terminal is worth the reward received there, whatever ``W`` says. A model-based
agent's planner scores predicted states, and a terminal one it cannot recognise (a roof tipped over, a bottle
fallen) is scored as if the episode went on; the termination model is what world-model agents learn beside the
reward for that reason (Dreamer's continue predictor). :meth:`heads` gives ``(W, R, T logit)`` for fitting.

Option ``value_log_floor`` ε in (0, 1) (not in the reference): the value head predicts ``log V`` and V is its
exponential, positive; the head's last bias starts at ``log ε`` so that V starts near ε, as the plain head starts
near 0. Every reader of V (planners, targets, clamps) sees it on the linear scale as before; only the fit changes:
the loss regresses ``log V`` on ``log(max(y, ε))`` (:class:`~ldm_rl.objectives.LookaheadLoss`), so an error counts
by its ratio to the return, not by its size. A terminal-reward task's states far from the end are worth ``≈ γᵏ·R``:
on the linear scale their differences (the pile a place leaves, worth 0.05 at the end of a bin-packing episode, is
0.05·γᵏ before it) are orders of magnitude below the fit's error on the states near the end; on the log scale
every state's differences are ratios alike (the reasoning of ``q_log_floor`` for Q). Not combined with
``termination_head`` (a composed V has no log head).

Parameters: 24,801,418 at ``width=1`` (scene 1,213,760; hand 296,256; each head 11,645,701), exactly the
reference's. Inputs are heights in metres, encoded as ``heights_to_classes(h) / (K − 1)``
(:func:`blocks.encode_heights`). On CPU without gradients, large batches run in chunks of ``CHUNK`` states
(measured on CPU: 16 a pass is ~2× faster per state than 64 or more; channels_last gains nothing here).
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import nn

from ldm_rl import geometry
from ldm_rl.models.blocks import LEAKY_SLOPE, BasicBlock, check_height_images, encode_heights, scaled_channels

__all__ = ["VCNN", "V_PRESETS", "build_value_network"]

V_PRESETS = {"paper": 1.0, "lite": 0.5}

_HAND_PAD = 64  # the in-hand image is zero-padded to 64×64 before its trunk


def _stages(channels: list[int]) -> nn.Sequential:
    return nn.Sequential(*(BasicBlock(cin, cout, stride=2) for cin, cout in zip(channels[:-1], channels[1:])))


class VCNN(nn.Module):
    """State value and state reward of (scene, in-hand image). See the module docstring.

    Args:
        max_height: metres mapped to the top depth class (per task).
        num_classes: K depth classes of the input quantisation.
        width: channel multiplier (1.0 = the reference).
        termination_head: add the termination head and compose V from it (see the module docstring).
        value_log_floor: None (the value head is V) or ε in (0, 1): the value head is ``log V`` (see the module
            docstring); the floor is the smallest return the fit tells apart.
    """

    CHUNK = 16  # states per pass without gradients (measured: 64 a pass is ~2x slower per state)

    def __init__(self, max_height: float, num_classes: int = 21, width: float = 1.0,
                 termination_head: bool = False, value_log_floor: float | None = None) -> None:
        super().__init__()
        if value_log_floor is not None and (isinstance(value_log_floor, bool) or not isinstance(value_log_floor, (int, float))
                                            or not 0 < value_log_floor < 1):
            raise ValueError(f"value_log_floor must be null (V on the linear scale) or a number in (0, 1) (the smallest "
                             f"return the log scale tells apart), got {value_log_floor!r}")
        if value_log_floor is not None and termination_head:
            raise ValueError(f"value_log_floor={value_log_floor} cannot be combined with termination_head=True "
                             "(a composed V = T·R + (1 − T)·W has no log head); set one of them off")
        self.value_log_floor = None if value_log_floor is None else float(value_log_floor)
        encode_heights(torch.zeros(1), max_height, num_classes)  # validates max_height and num_classes
        if not isinstance(width, (int, float)) or isinstance(width, bool) or not (width > 0 and math.isfinite(width)):
            raise ValueError(f"width must be a positive number, got {width!r}")
        self.max_height, self.num_classes, self.width = float(max_height), num_classes, float(width)

        def ch(n: int) -> int:
            return scaled_channels(n, width)

        self.scene_trunk = _stages([1, ch(32), ch(64), ch(128), ch(256)])
        self.hand_trunk = _stages([1, ch(32), ch(64), ch(128)])
        self.value_head = self._head(ch(256) + ch(128), ch)
        self.reward_head = self._head(ch(256) + ch(128), ch)
        if not isinstance(termination_head, bool):
            raise ValueError(f"termination_head must be a bool, got {termination_head!r}")
        self.termination_head = self._head(ch(256) + ch(128), ch) if termination_head else None
        for m in self.modules():
            if isinstance(m, nn.Conv2d):
                nn.init.kaiming_normal_(m.weight, a=LEAKY_SLOPE, mode="fan_out", nonlinearity="leaky_relu")
        if self.value_log_floor is not None:  # V starts near the floor, as the linear head starts near 0
            nn.init.constant_(self.value_head[-1].bias, math.log(self.value_log_floor))

    @staticmethod
    def _head(in_channels: int, ch) -> nn.Sequential:
        side = geometry.HEIGHTMAP_SIZE // 32  # 128 → 8 (trunk) → 4 (head conv)
        sizes = [ch(256) * side * side, ch(2048), ch(1028), ch(256)]
        layers: list[nn.Module] = [
            nn.Conv2d(in_channels, ch(256), 3, stride=2, padding=1),
            nn.LeakyReLU(LEAKY_SLOPE),
            nn.Flatten(),
        ]
        for fan_in, fan_out in zip(sizes[:-1], sizes[1:]):
            layers += [nn.Linear(fan_in, fan_out), nn.LeakyReLU(LEAKY_SLOPE)]
        layers.append(nn.Linear(sizes[-1], 1))
        return nn.Sequential(*layers)

    def _features(self, scene: torch.Tensor, hand: torch.Tensor) -> torch.Tensor:
        """Encoded [n, 1, 128, 128], [n, 1, 24, 24] -> [n, 384·w, 8, 8]."""
        lo = (_HAND_PAD - hand.shape[-1]) // 2
        hi = _HAND_PAD - hand.shape[-1] - lo
        hand = F.pad(hand, (lo, hi, lo, hi))
        return torch.cat((self.scene_trunk(scene), self.hand_trunk(hand)), dim=1)

    def _run(self, heightmap: torch.Tensor, in_hand: torch.Tensor, heads: tuple[nn.Module, ...]) -> list[torch.Tensor]:
        size, hand_size = geometry.HEIGHTMAP_SIZE, geometry.HAND_SIZE
        batch = check_height_images(heightmap, "heightmap", size)
        check_height_images(in_hand, "in_hand", hand_size, batch)
        dtype = self.value_head[0].weight.dtype
        scene = encode_heights(heightmap.reshape(-1, 1, size, size), self.max_height, self.num_classes, dtype)
        hand = encode_heights(in_hand.reshape(-1, 1, hand_size, hand_size), self.max_height, self.num_classes, dtype)
        n = scene.shape[0]
        step = self.CHUNK if scene.device.type == "cpu" and not torch.is_grad_enabled() else n
        outs: list[list[torch.Tensor]] = [[] for _ in heads]
        for i in range(0, n, max(1, step)):
            feat = self._features(scene[i : i + step], hand[i : i + step])
            for out, head in zip(outs, heads):
                out.append(head(feat))
        return [(o[0] if len(o) == 1 else torch.cat(o)).reshape(*batch, 1) if o else scene.new_zeros(*batch, 1) for o in outs]

    @staticmethod
    def compose(going_on: torch.Tensor, reward: torch.Tensor, termination_logit: torch.Tensor) -> torch.Tensor:
        """``V = T·R + (1 − T)·W`` with ``T = sigmoid(termination_logit)``; all ``[*B, 1]``."""
        ends = torch.sigmoid(termination_logit)
        return ends * reward + (1.0 - ends) * going_on

    def heads(self, heightmap: torch.Tensor, in_hand: torch.Tensor) -> tuple[torch.Tensor, ...]:
        """The heads in one trunk pass: ``(value head, reward head)``, and with ``termination_head`` the
        termination logit third; each ``[*B, 1]``. The value head is V itself without the termination head, the
        value of going on ``W`` with it; with ``value_log_floor`` it is the exponential of the head's output."""
        heads = (self.value_head, self.reward_head)
        out = self._run(heightmap, in_hand, heads if self.termination_head is None else heads + (self.termination_head,))
        if self.value_log_floor is not None:
            out[0] = out[0].exp()
        return tuple(out)

    def forward(self, heightmap: torch.Tensor, in_hand: torch.Tensor) -> torch.Tensor:
        """``heightmap [*B, 1, 128, 128]``, ``in_hand [*B, 1, 24, 24]`` float metres -> V ``[*B, 1]`` float32."""
        if self.termination_head is not None:
            return self.compose(*self.heads(heightmap, in_hand))
        value = self._run(heightmap, in_hand, (self.value_head,))[0]
        return value if self.value_log_floor is None else value.exp()

    def value_and_reward(self, heightmap: torch.Tensor, in_hand: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """As :meth:`forward`, -> (V ``[*B, 1]``, reward of being in the state ``[*B, 1]``); one shared trunk pass."""
        out = self.heads(heightmap, in_hand)
        return (out[0] if self.termination_head is None else self.compose(*out)), out[1]


def build_value_network(preset: str, *, max_height: float, num_classes: int = 21, width: float | None = None,
                        termination_head: bool = False, value_log_floor: float | None = None) -> VCNN:
    """A :class:`VCNN` at a preset width (``V_PRESETS``); ``width`` overrides the preset's."""
    if preset not in V_PRESETS:
        raise ValueError(f"unknown value network preset {preset!r}; expected one of {sorted(V_PRESETS)}")
    return VCNN(max_height, num_classes, V_PRESETS[preset] if width is None else width, termination_head,
                value_log_floor)
