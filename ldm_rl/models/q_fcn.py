"""The agent's Q network: a fully convolutional pick/place Q map over every pixel and rotation.

Architecture (the reference ``QValueModel``; channel counts at ``width`` = 1, every one scaled by
``width``; no BatchNorm, LeakyReLU 0.01, ``xavier_normal_`` on every conv weight, PyTorch defaults for
conv biases and linear layers):

* trunk on the rotated 128² scene: ``conv_1`` 3×3 1→16 (no bias) → ``layer_1..4`` basic blocks stride 2
  16→32→64→128→128 (128 → 8 px) → ``conv_2`` 3×3 128→128 (bias) → four up blocks (bilinear ×2 up,
  ``cat[skip, up]``, basic block) 256→128, 192→64, 96→32, 48→16 back to 16×128×128 features;
* pick head (hand empty): 3×3 16→8 (bias) → LReLU → 1×1 8→1 (bias);
* place head (holding): the in-hand image, zero-padded 24 → 64, goes through four 3×3 stride-2 convs
  1→32→64→128→256 (no bias) and an MLP 4096→1028→2304 that emits a per-sample 3×3 16→16 kernel; the
  trunk features are convolved with it (no bias) → LReLU → 3×3 16→8 → LReLU → 1×1 8→1.

Parameters: 8,417,110 at ``width=1`` (the hand encoder, convs and MLP, is 6,969,892 of them), exactly the
reference's. Differences from the reference's *execution* (not its weights): the hand kernel is computed
once per sample, not once per rotation; only the head of each sample's primitive runs; and the training
path :meth:`QFCN.action_values` runs the last up block and the head only on the 9 × 9 window around each
action's pixel (its whole receptive field there), not on the 128² map, for the same values and gradients
(the windowed layers were ≈ 40 % of a training pass's profiled time at ``stacking_lite``'s width).

Inputs are heights in metres, encoded as ``heights_to_classes(h) / (K − 1)`` (:func:`blocks.encode_heights`).

Rotations (``geometry`` conventions). Bin k is the gripper yaw ``θ_k = k·π/R``. The trunk of bin k sees
the scene rotated by ``+θ_k`` (``geometry.rotate``: ``out[p] = x[c + R(θ_k)(p − c)]``), so around a trunk
pixel ``p'`` it sees what ``geometry.crop(x, a, θ_k, d)`` samples around the action pixel
``a = c + R(θ_k)(p' − c)``: the gripper frame of action (a, k). The head's map is rotated back by ``−θ_k``,
so ``Q[b, k, row, col]`` is the value of action (row, col, k).

Both rotations sample ``nearest``, as the reference does: the rotated input stays on the depth-class
grid at every angle (what the net sees at bin 0), and every Q value is exactly one output pixel of the
head, so :meth:`QFCN.action_values` reads the number the map shows. Map pixels whose rotated position
falls outside the 128² frame (the corners at non-quarter bins) read 0. Being nearest-pixel, each
rotation is a fixed gather, tabulated once per model with ``geometry.rotate`` on an image of pixel ids
(:func:`_rotation_tables`): one ``index_select``/``gather`` per pass, no rotation stack of the source.
Each ``θ_k`` is tabulated as an exact quarter turn (``torch.rot90``) composed with a ``geometry.rotate``
by the residual ``φ ∈ [0, π/2)``, the scene quarter-turned first and the map last. That makes the Q maps
*bit-exactly* equivariant to quarter turns of the scene (rotate the scene by +90°, shift the bin by
R/2: the map rotates by +90°); tabulating ``geometry.rotate(x, θ_k)`` directly would not (for the even
128 px frame, ``rotate(rotate(x, π/2), φ)`` and ``rotate(x, π/2 + φ)`` differ in ≈0.5 % of the pixels).

Speed (CPU; other devices run the whole batch at once, NCHW). The trunk runs in chunks of
``CHUNK_IMAGES`` images (whole samples): the time per image grows ~2–3× from 8 to 256 images a pass.
The trunk's features are channels_last (forward 1.5–2×, forward + backward 2–4× faster for these narrow
convs; the strided shortcuts run as unstrided 1×1 convs on every second pixel, see ``BasicBlock``).
Without gradients the hand kernel is applied by one dense conv per sample, with gradients by one grouped
conv on NCHW features (its backward is ~3× faster than the per-sample loop's).
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import nn

from ldm_rl import geometry
from ldm_rl.models.blocks import LEAKY_SLOPE, BasicBlock, check_height_images, encode_heights, scaled_channels
from ldm_rl.models.compile import CompiledInference

__all__ = ["QFCN", "Q_PRESETS", "Q_ARCHITECTURES", "build_q_network", "check_q_arguments"]

Q_PRESETS = {"paper": 1.0, "lite": 0.5}
Q_ARCHITECTURES = ("fcn", "equivariant")  # build_q_network's choices (agent.q_architecture)

_HAND_PAD = 64  # the in-hand image is zero-padded to 64×64 before its encoder


class _UpBlock(nn.Module):
    """Bilinear up-sampling to the skip's size, ``cat[skip, up]``, basic block to ``out_channels``."""

    def __init__(self, in_channels: int, out_channels: int) -> None:
        super().__init__()
        self.block = BasicBlock(in_channels, out_channels)

    def forward(self, x: torch.Tensor, skip: torch.Tensor) -> torch.Tensor:
        up = F.interpolate(x, size=skip.shape[-2:], mode="bilinear", align_corners=False)
        return self.block(torch.cat((skip, up), dim=1))


def _bilinear_window(
    x: torch.Tensor, rows: torch.Tensor, cols: torch.Tensor, size: tuple[int, int], batch: torch.Tensor
) -> torch.Tensor:
    """``F.interpolate(x, size, mode="bilinear", align_corners=False)`` read only at the pixels
    ``rows [n, a] × cols [n, b]`` (long, inside ``size``) of each sample: ``x`` [n, C, h, w] -> [n, a, b, C]."""

    def taps(out: torch.Tensor, n_in: int, n_out: int):
        src = ((out.to(x.dtype) + 0.5) * (n_in / n_out) - 0.5).clamp(min=0)
        lo = src.floor().long().clamp(max=n_in - 1)
        return lo, (lo + 1).clamp(max=n_in - 1), src - lo.to(x.dtype)

    r0, r1, wr = taps(rows, x.shape[-2], size[0])
    c0, c1, wc = taps(cols, x.shape[-1], size[1])
    r0, r1, wr = r0.unsqueeze(2), r1.unsqueeze(2), wr[:, :, None, None]
    c0, c1, wc = c0.unsqueeze(1), c1.unsqueeze(1), wc[:, None, :, None]
    top = x[batch, :, r0, c0] * (1 - wc) + x[batch, :, r0, c1] * wc
    bottom = x[batch, :, r1, c0] * (1 - wc) + x[batch, :, r1, c1] * wc
    return top * (1 - wr) + bottom * wr


def _map_head(channels: int, hidden: int) -> nn.Sequential:
    return nn.Sequential(nn.Conv2d(channels, hidden, 3, padding=1), nn.LeakyReLU(LEAKY_SLOPE), nn.Conv2d(hidden, 1, 1))


def _rotation_tables(num_rotations: int, size: int, margin: int = 0, frame: int | None = None
                     ) -> tuple[torch.Tensor, torch.Tensor]:
    """Nearest-pixel gather tables: ``scene [R, frame²]`` and ``maps [R, size²]`` (int64, flat index + 1; 0 = outside).

    ``scene[k][p]``: the scene pixel that the trunk of bin k sees at frame pixel p, i.e. ``rotate(x, θ_k)`` of the
    scene centred in a ``frame``-pixel square of zeros; ``maps[k][p]``: the gripper-frame pixel of bin k that
    ``Q[k]`` shows at scene pixel p, i.e. ``rotate(m, −θ_k)`` cropped back to the scene. ``frame`` (default
    ``size``, the reference) larger than the scene by ⌈(√2 − 1)·size⌉ keeps every scene pixel inside every bin's
    frame; at ``size`` the corners leave the frames of the non-quarter bins.
    Each ``θ_k = q·π/2 + φ`` (q ∈ {0, 1}, φ ∈ [0, π/2), exact rational split) is applied as an exact
    quarter turn (``torch.rot90``; ``rot90(x, −1) == geometry.rotate(x, π/2)``) and a
    ``geometry.rotate`` by φ: the scene is quarter-turned first, the map last. So bin k + R/2 of a
    scene and bin k of the same scene quarter-turned read identical trunk inputs, and their maps come
    back quarter-turned exactly. Built by rotating an image of pixel ids (exact in ``nearest`` mode).
    ``margin`` > 0 also marks as outside every map pixel that falls within ``margin`` pixels of its
    gripper frame's edge (the band where the trunk's convolutions read their zero padding).
    """
    frame = size if frame is None else frame
    pad = (frame - size) // 2
    if frame < size or frame - size != 2 * pad:
        raise ValueError(f"frame must be the scene's size {size} plus an even number of pixels, got {frame!r}")
    ids = F.pad(torch.arange(1, size * size + 1, dtype=torch.int64).view(1, size, size), (pad, pad, pad, pad))
    frame_ids = torch.arange(1, frame * frame + 1, dtype=torch.int64).view(1, frame, frame)
    scene, maps = [], []
    for k in range(num_rotations):
        q = (2 * k) // num_rotations
        phi = (2 * k - q * num_rotations) * math.pi / (2 * num_rotations)
        scene.append(geometry.rotate(torch.rot90(ids, -q, (-2, -1)), phi, mode="nearest"))
        back = torch.rot90(geometry.rotate(frame_ids, -phi, mode="nearest"), q, (-2, -1))
        maps.append(back[..., pad : pad + size, pad : pad + size])
    maps = torch.stack(maps).reshape(num_rotations, -1)
    if margin > 0:
        row, col = (maps - 1).div(frame, rounding_mode="floor"), (maps - 1).remainder(frame)
        band = (row < margin) | (row >= frame - margin) | (col < margin) | (col >= frame - margin)
        maps = maps.masked_fill(band & (maps > 0), 0)
    return torch.stack(scene).view(num_rotations, -1), maps


def _channels_last(x: torch.Tensor) -> bool:
    return x.dim() >= 4 and x.shape[-3] > 1 and x.is_contiguous(memory_format=torch.channels_last) and not x.is_contiguous()


def check_q_arguments(max_height, num_classes, num_rotations, width, frame_margin, pick_min_height=0.0,
                      head_channels=None) -> None:
    """The constructor arguments every Q map network takes; one ValueError naming the bad one."""
    if head_channels is not None and (not isinstance(head_channels, int) or isinstance(head_channels, bool) or head_channels < 1):
        raise ValueError(f"head_channels must be a positive int or None (the reference's 8 scaled by width), got {head_channels!r}")
    encode_heights(torch.zeros(1), max_height, num_classes)  # validates max_height and num_classes
    if not isinstance(num_rotations, int) or isinstance(num_rotations, bool) or num_rotations < 1:
        raise ValueError(f"num_rotations must be a positive int, got {num_rotations!r}")
    if not isinstance(width, (int, float)) or isinstance(width, bool) or not (width > 0 and math.isfinite(width)):
        raise ValueError(f"width must be a positive number, got {width!r}")
    if not isinstance(frame_margin, int) or isinstance(frame_margin, bool) or not 0 <= frame_margin < geometry.HEIGHTMAP_SIZE // 4:
        raise ValueError(f"frame_margin must be an int in [0, {geometry.HEIGHTMAP_SIZE // 4}) pixels, got {frame_margin!r}")
    real = isinstance(pick_min_height, (int, float)) and not isinstance(pick_min_height, bool)
    if not real or not 0 <= pick_min_height < max_height:
        raise ValueError(f"pick_min_height must be a number of metres in [0, max_height = {max_height}), got {pick_min_height!r}")


def check_frame_pad(frame_pad) -> None:
    """``frame_pad``: an int in [0, 64], a multiple of 8 (the trunk halves its input four times); one ValueError."""
    if not isinstance(frame_pad, int) or isinstance(frame_pad, bool) or not 0 <= frame_pad <= 64 or frame_pad % 8:
        raise ValueError(f"frame_pad must be a multiple of 8 in [0, 64] pixels, got {frame_pad!r}")


MIN_PICK_ENTRIES = 64  # a pick map the mask would leave with fewer finite entries keeps its unmasked ones


def mask_empty_picks(maps: torch.Tensor, heightmap: torch.Tensor, holding: torch.Tensor, min_height: float) -> torch.Tensor:
    """Pick maps with ``-inf`` wherever the fingers would close on nothing.

    ``maps`` ``[N, R, H, W]``, ``heightmap`` ``[N, 1, H, W]`` metres, ``holding`` ``[N]`` bool. In each pick
    map (``holding`` False) every pixel whose height is not above ``min_height`` (the table, a tray's floor)
    reads ``-inf`` at every rotation. Place maps, and pick maps that would keep fewer than
    :data:`MIN_PICK_ENTRIES` finite entries (a nearly empty scene: the proposals need entries to draw), are
    returned as they are. Returns a new tensor.
    """
    n, _, h, w = maps.shape if maps.dim() == 4 else (None, None, None, None)
    if n is None or tuple(heightmap.shape) != (n, 1, h, w) or holding.dtype != torch.bool or tuple(holding.shape) != (n,):
        raise ValueError(f"mask_empty_picks needs maps [N, R, H, W], heightmap [N, 1, H, W] and holding bool [N], got "
                         f"{tuple(maps.shape)}, {tuple(heightmap.shape)} and {holding.dtype} {tuple(holding.shape)}")
    masked = maps.masked_fill((heightmap <= min_height) & ~holding.view(-1, 1, 1, 1), float("-inf"))
    enough = torch.isfinite(masked).flatten(1).sum(1) >= MIN_PICK_ENTRIES
    return torch.where(enough.view(-1, 1, 1, 1), masked, maps)


def check_q_action(action, batch: tuple, num_rotations: int) -> torch.Tensor:
    """``action`` ``[*B, 3]`` integer (row, col, rot) checked against the batch ``*B`` and the map's ranges;
    returns it as ``[N, 3]`` int64 (one ValueError naming what is wrong)."""
    size = geometry.HEIGHTMAP_SIZE
    integer = torch.is_tensor(action) and not action.is_floating_point() and action.dtype != torch.bool
    if not integer or action.shape != tuple(batch) + (3,):
        got = f"{action.dtype} {tuple(action.shape)}" if torch.is_tensor(action) else type(action).__name__
        raise ValueError(f"action must be an integer [*B, 3] (row, col, rot) tensor with *B = {tuple(batch)}, got {got}")
    action = action.reshape(-1, 3).long()
    pixel_ok = (action[:, :2] >= 0) & (action[:, :2] < size)
    if action.numel() and not bool(pixel_ok.all() & ((action[:, 2] >= 0) & (action[:, 2] < num_rotations)).all()):
        lo, hi = int(action.min()), int(action.max())
        raise ValueError(f"action must have row, col in [0, {size}) and rot in [0, {num_rotations}); "
                         f"got values in [{lo}, {hi}]")
    return action


def encode_q_inputs(heightmap, in_hand, holding, max_height: float, num_classes: int, dtype: torch.dtype):
    """A Q network's inputs checked and encoded: ``heightmap`` ``[*B, 1, 128, 128]``, ``in_hand``
    ``[*B, 1, h, h]`` (metres), ``holding`` bool ``[*B]`` or ``[*B, 1]`` -> (``*B``, ``[N, 1, 128, 128]``,
    ``[N, 1, h, h]`` encoded heights in ``dtype`` (:func:`blocks.encode_heights`), ``[N]`` bool),
    N = prod(*B); one ValueError naming what is wrong."""
    size, hand_size = geometry.HEIGHTMAP_SIZE, geometry.HAND_SIZE
    batch = check_height_images(heightmap, "heightmap", size)
    check_height_images(in_hand, "in_hand", hand_size, batch)
    expected = f"bool [*B] or [*B, 1] with *B = {tuple(batch)}"
    if not torch.is_tensor(holding) or holding.dtype != torch.bool:
        raise ValueError(f"holding must be {expected}, got {getattr(holding, 'dtype', type(holding).__name__)}")
    if holding.shape not in (batch, batch + (1,)):
        raise ValueError(f"holding must be {expected}, got shape {tuple(holding.shape)}")
    x = encode_heights(heightmap.reshape(-1, 1, size, size), max_height, num_classes, dtype)
    hand = encode_heights(in_hand.reshape(-1, 1, hand_size, hand_size), max_height, num_classes, dtype)
    return batch, x, hand, holding.reshape(-1)


class QFCN(CompiledInference, nn.Module):
    """Pick/place Q maps over all pixels and R rotation bins. See the module docstring.

    Args:
        max_height: metres mapped to the top depth class (per task).
        num_classes: K depth classes of the input quantisation.
        num_rotations: R rotation bins k·π/R.
        width: channel multiplier (1.0 = the reference).
        frame_margin: pixels at each gripper frame's edge whose Q is ``-inf`` (never proposed; 0 = none,
            the reference). The trunk's zero padding makes that band's values arbitrary, and an object
            there would lie partly outside the workspace; untrained, the band's Q outranked every object
            and put the greedy proposals on the image border (docs/policy.md).
        pick_min_height: metres; > 0: a pick whose pixel is not above it (nothing to grasp) is ``-inf``
            (:func:`mask_empty_picks`; 0 = none, the reference). Only :meth:`forward` masks: the maps that
            propose actions and take target maxima; :meth:`action_values` (the loss) does not.
        head_channels: hidden units of the pick and place heads; None: the reference's 8 scaled by ``width``
            (2 at 0.25). A head's units see non-negative features, so each starts active everywhere or nowhere,
            and the first updates, raising Q towards the returns, switch off those with a negative output weight:
            at 2 units a house run's pick head kept none, its pre-activations near 0, and its map went flat
            (docs/policy.md, "Q heads that go flat"); 8 keeps the reference's count at every width.
        frame_pad: pixels of zeros around the scene on each side before it is rotated into each bin's frame (0 =
            the reference: the frames are the 128 px image, so near its corners a pixel falls outside the frames of
            the non-quarter bins and its Q there is ``-inf``). 32 keeps every pixel inside every frame (with an
            8 px ``frame_margin``, all but 6 at each corner), at (192/128)² ≈ 2.25× the trunk's pixels (measured 2.6–3× a pick
            decision's Q time at one thread; docs/policy.md, "Where Q cannot grasp").
    """

    CHUNK_IMAGES = 8  # trunk images per pass (measured: per-image time grows ~2x from 8 to 64 images)
    # px: one map pixel's receptive field in up_1's input (up_1's two 3×3 convs, the place path's hand-kernel
    # conv, the head's 3×3); action_values runs up_1 and the heads only on this window around each action
    WINDOW_RADIUS = 4

    def __init__(
        self, max_height: float, num_classes: int = 21, num_rotations: int = geometry.NUM_ROTATIONS, width: float = 1.0,
        frame_margin: int = 0, pick_min_height: float = 0.0, head_channels: int | None = None, frame_pad: int = 0,
    ) -> None:
        super().__init__()
        check_q_arguments(max_height, num_classes, num_rotations, width, frame_margin, pick_min_height, head_channels)
        check_frame_pad(frame_pad)
        self.frame_margin, self.pick_min_height = frame_margin, float(pick_min_height)
        self.frame_pad, self.frame_size = frame_pad, geometry.HEIGHTMAP_SIZE + 2 * frame_pad
        self.max_height, self.num_classes = float(max_height), num_classes
        self.num_rotations, self.width = num_rotations, float(width)

        def ch(n: int) -> int:
            return scaled_channels(n, width)

        c16, c32, c64, c128, c256 = ch(16), ch(32), ch(64), ch(128), ch(256)
        self.feature_channels = c16
        self.conv_1 = nn.Sequential(nn.Conv2d(1, c16, 3, padding=1, bias=False), nn.LeakyReLU(LEAKY_SLOPE))
        self.layer_1 = BasicBlock(c16, c32, stride=2)
        self.layer_2 = BasicBlock(c32, c64, stride=2)
        self.layer_3 = BasicBlock(c64, c128, stride=2)
        self.layer_4 = BasicBlock(c128, c128, stride=2)
        self.conv_2 = nn.Sequential(nn.Conv2d(c128, c128, 3, padding=1), nn.LeakyReLU(LEAKY_SLOPE))
        self.up_4 = _UpBlock(c128 + c128, c128)
        self.up_3 = _UpBlock(c64 + c128, c64)
        self.up_2 = _UpBlock(c32 + c64, c32)
        self.up_1 = _UpBlock(c16 + c32, c16)
        self.head_channels = scaled_channels(8, width) if head_channels is None else head_channels
        self.pick_head = _map_head(c16, self.head_channels)

        hand_convs: list[nn.Module] = []
        for cin, cout in ((1, c32), (c32, c64), (c64, c128), (c128, c256)):
            hand_convs += [nn.Conv2d(cin, cout, 3, stride=2, padding=1, bias=False), nn.LeakyReLU(LEAKY_SLOPE)]
        side = _HAND_PAD // 16
        self.hand_encoder = nn.Sequential(
            *hand_convs,
            nn.Flatten(),
            nn.Linear(c256 * side * side, ch(1028)),
            nn.LeakyReLU(LEAKY_SLOPE),
            nn.Linear(ch(1028), c16 * c16 * 9),
        )
        self.place_head = _map_head(c16, self.head_channels)
        self.act = nn.LeakyReLU(LEAKY_SLOPE)

        for m in self.modules():
            if isinstance(m, nn.Conv2d):
                nn.init.xavier_normal_(m.weight)

        scene_index, map_index = _rotation_tables(num_rotations, geometry.HEIGHTMAP_SIZE, frame_margin, self.frame_size)
        self.register_buffer("_scene_index", scene_index, persistent=False)
        self.register_buffer("_map_index", map_index, persistent=False)

    # ------------------------------------------------------------------------------------------
    # rotations: one gather each, through the tables of _rotation_tables
    # ------------------------------------------------------------------------------------------
    def _rotate_scene(self, x: torch.Tensor, bins: torch.Tensor | None = None) -> torch.Tensor:
        """``[N, 1, H, W]`` -> ``[N, R, S, S]`` (all bins) or, with ``bins [N]``, ``[N, 1, S, S]``: the
        scene in the gripper frame of each bin, S = :attr:`frame_size` (pixels from outside the scene read 0)."""
        n, _, h, w = x.shape
        f = self.frame_size
        flat = F.pad(x.reshape(n, h * w), (1, 0))  # index 0 reads the zero outside the frame
        if bins is None:
            return flat.index_select(1, self._scene_index.reshape(-1)).view(n, -1, f, f)
        return flat.gather(1, self._scene_index.index_select(0, bins)).view(n, 1, f, f)

    def _unrotate_maps(self, maps: torch.Tensor) -> torch.Tensor:
        """``[N, R, S, S]`` maps in the gripper frames -> ``[N, R, H, W]`` in the scene: ``Q[n, k, row, col]``.

        Pixels that bin k's rotated frame does not cover (near the image border at non-quarter bins) read
        ``-inf``: the trunk never saw them, so they are never proposed and never win a max (read as 0 they
        beat every negative learned value and drew every greedy action to the border)."""
        n, r, f, _ = maps.shape
        size = geometry.HEIGHTMAP_SIZE
        flat = F.pad(maps.reshape(n, r, f * f), (1, 0), value=float("-inf"))
        return flat.gather(2, self._map_index.unsqueeze(0).expand(n, r, size * size)).view(n, r, size, size)

    # ------------------------------------------------------------------------------------------
    # network pieces
    # ------------------------------------------------------------------------------------------
    def _trunk(self, x: torch.Tensor) -> torch.Tensor:
        """[M, 1, H, W] encoded scenes -> [M, C, H, W] features (compiled for inference where switched on:
        :mod:`ldm_rl.models.compile`; on CPU M is always one chunk of whole samples)."""
        return self._inference(self._trunk_eager, x, dynamic_batch=x.device.type != "cpu")

    def _trunk_eager(self, x: torch.Tensor) -> torch.Tensor:
        return self.up_1(*self._trunk_to_up_2(x))

    def _trunk_to_up_2(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """[M, 1, H, W] encoded scenes -> (``up_2``'s output [M, C32, H/2, W/2], ``conv_1``'s [M, C16, H, W]):
        the two inputs of ``up_1``, the last up block."""
        inp = self.conv_1(x)
        if x.device.type == "cpu":  # see the module docstring (channels_last)
            inp = inp.contiguous(memory_format=torch.channels_last)  # the later layers keep the format
        d1 = self.layer_1(inp)
        d2 = self.layer_2(d1)
        d3 = self.layer_3(d2)
        y = self.conv_2(self.layer_4(d3))
        return self.up_2(self.up_3(self.up_4(y, d3), d2), d1), inp

    def _window_values(
        self, up: torch.Tensor, skip: torch.Tensor, hand: torch.Tensor, holding: torch.Tensor, centre: torch.Tensor
    ) -> torch.Tensor:
        """The map value at one pixel per sample, running ``up_1`` and the head only on the
        ``(2·WINDOW_RADIUS + 1)²`` window around it (the pixel's whole receptive field from ``up_1``'s input).

        Args: ``up`` [n, C32, H/2, W/2] and ``skip`` [n, C16, H, W] (:meth:`_trunk_to_up_2`), ``hand``
        [n, 1, 24, 24] encoded, ``holding`` [n] bool, ``centre`` [n, 2] long (row, col) in the gripper frame.
        Returns [n]: the value ``_maps`` shows there, up to float summation order. Window pixels outside the
        frame are zeroed before every 3×3 conv, which is what the full map's zero padding does there.
        """
        n, _, h, w = skip.shape
        r = self.WINDOW_RADIUS
        offsets = torch.arange(-r, r + 1, device=skip.device)
        rows, cols = centre[:, :1] + offsets, centre[:, 1:] + offsets  # [n, 2r + 1] full-resolution pixels
        inside = (((rows >= 0) & (rows < h)).unsqueeze(2) & ((cols >= 0) & (cols < w)).unsqueeze(1)).unsqueeze(1)
        mask = inside.to(skip.dtype)  # [n, 1, 2r + 1, 2r + 1]
        batch = torch.arange(n, device=skip.device).view(n, 1, 1)
        rows, cols = rows.clamp(0, h - 1), cols.clamp(0, w - 1)  # the mask zeroes what the clamp repeats
        skip_window = skip[batch, :, rows.unsqueeze(2), cols.unsqueeze(1)]
        up_window = _bilinear_window(up, rows, cols, (h, w), batch)
        x = torch.cat((skip_window, up_window), dim=-1).permute(0, 3, 1, 2) * mask  # channels_last [n, C, 2r+1, 2r+1]
        block = self.up_1.block
        feat = block.act(block.conv2(block.act(block.conv1(x)) * mask) + block.shortcut(x)) * mask
        place_rows = holding.nonzero().squeeze(1)
        if place_rows.numel() == 0:
            return self.pick_head(feat)[:, 0, r, r]
        values = feat.new_empty(n)
        pick_rows = (~holding).nonzero().squeeze(1)
        if pick_rows.numel():
            values = values.index_put((pick_rows,), self.pick_head(feat[pick_rows])[:, 0, r, r])
        c, side = feat.shape[1], 2 * r + 1
        kernels = self._hand_kernels(hand[place_rows]).reshape(-1, c, 3, 3)
        y = F.conv2d(feat[place_rows].reshape(1, -1, side, side), kernels, padding=1, groups=place_rows.numel())
        y = self.act(y.view(-1, c, side, side)) * mask[place_rows]
        return values.index_put((place_rows,), self.place_head(y)[:, 0, r, r])

    def _hand_kernels(self, in_hand: torch.Tensor) -> torch.Tensor:
        """[n, 1, 24, 24] encoded hands -> [n, C, C, 3, 3] per-sample kernels."""
        lo = (_HAND_PAD - in_hand.shape[-1]) // 2
        hi = _HAND_PAD - in_hand.shape[-1] - lo
        c = self.feature_channels
        return self.hand_encoder(F.pad(in_hand, (lo, hi, lo, hi))).view(-1, c, c, 3, 3)

    def _place(self, feat: torch.Tensor, in_hand: torch.Tensor) -> torch.Tensor:
        """[n, r, C, H, W] features, [n, 1, 24, 24] encoded hands -> [n, r, H, W] place maps."""
        n, r, c, h, w = feat.shape
        kernels = self._hand_kernels(in_hand)  # [n, C, C, 3, 3]
        if _channels_last(feat[0]) and not torch.is_grad_enabled():  # a dense conv per sample: ~3x faster than grouped
            y = torch.cat([F.conv2d(feat[i], kernels[i], padding=1) for i in range(n)])
        else:  # one grouped conv (its backward is ~3x faster than the per-sample loop's)
            kernels = kernels.unsqueeze(1).expand(n, r, c, c, 3, 3).reshape(n * r * c, c, 3, 3)
            y = F.conv2d(feat.reshape(1, n * r * c, h, w), kernels, padding=1, groups=n * r).view(n * r, c, h, w)
        return self.place_head(self.act(y)).reshape(n, r, h, w)

    def _maps(self, scenes: torch.Tensor, in_hand: torch.Tensor, holding: torch.Tensor) -> torch.Tensor:
        """Rotated scenes [N, r, H, W] (encoded), hands [N, 1, 24, 24] (encoded), holding [N] bool
        -> [N, r, H, W] maps of each sample's head, in the gripper frames."""
        n, r, h, w = scenes.shape
        place_rows = holding.nonzero().squeeze(1)
        n_place = place_rows.numel()
        if 0 < n_place < n:  # pick rows first, then place rows: each head reads a contiguous slice
            order = torch.cat(((~holding).nonzero().squeeze(1), place_rows))
            scenes = scenes.index_select(0, order)
        feat = self._trunk(scenes.reshape(n * r, 1, h, w)).view(n, r, -1, h, w)
        n_pick = n - n_place
        parts = []
        if n_pick:
            pick = feat[:n_pick].flatten(0, 1)
            if _channels_last(feat[0]):  # the flattened view lost the format flag: 4-5x slower head convs
                pick = pick.contiguous(memory_format=torch.channels_last)
            parts.append(self.pick_head(pick).view(n_pick, r, h, w))
        if n_place:
            parts.append(self._place(feat[n_pick:], in_hand.index_select(0, place_rows) if n_pick else in_hand))
        if len(parts) == 1:
            return parts[0]
        maps = torch.cat(parts)
        return torch.empty_like(maps).index_copy_(0, order, maps)

    # ------------------------------------------------------------------------------------------
    # public API
    # ------------------------------------------------------------------------------------------
    def _inputs(self, heightmap, in_hand, holding):
        """Validate and encode; -> batch shape, [N, 1, H, W], [N, 1, h, h] (encoded), [N] bool."""
        return encode_q_inputs(heightmap, in_hand, holding, self.max_height, self.num_classes, self.conv_1[0].weight.dtype)

    def _chunks(self, x: torch.Tensor, images_per_sample: int) -> list[slice]:
        """On CPU, slices of at most ``CHUNK_IMAGES`` trunk images (whole samples; big batches thrash
        the cache); elsewhere the whole batch at once."""
        n = x.shape[0]
        step = max(1, self.CHUNK_IMAGES // images_per_sample) if x.device.type == "cpu" else max(1, n)
        return [slice(i, i + step) for i in range(0, n, step)]

    def forward(self, heightmap: torch.Tensor, in_hand: torch.Tensor, holding: torch.Tensor) -> torch.Tensor:
        """Q maps of each sample's current primitive over all rotations.

        Args:
            heightmap: ``[*B, 1, 128, 128]`` float metres.
            in_hand: ``[*B, 1, 24, 24]`` float metres (read only where holding).
            holding: ``[*B]`` or ``[*B, 1]`` bool; False → pick map, True → place map.
        Returns:
            ``[*B, R, 128, 128]`` float32; entry ``[..., k, row, col]`` is Q of action (row, col, k);
            ``-inf`` where bin k's rotated frame does not cover the pixel (never proposed, never a max) and,
            with ``pick_min_height``, on pick maps where there is nothing to grasp.
        """
        batch, x, hand, holding = self._inputs(heightmap, in_hand, holding)
        size, r = geometry.HEIGHTMAP_SIZE, self.num_rotations
        parts = [
            self._unrotate_maps(self._maps(self._rotate_scene(x[sl]), hand[sl], holding[sl]))
            for sl in self._chunks(x, r)
        ]
        if not parts:
            return x.new_zeros(*batch, r, size, size)
        maps = parts[0] if len(parts) == 1 else torch.cat(parts)
        if self.pick_min_height:
            maps = mask_empty_picks(maps, heightmap.reshape(-1, 1, size, size), holding, self.pick_min_height)
        return maps.reshape(*batch, r, size, size)

    def action_values(
        self, heightmap: torch.Tensor, in_hand: torch.Tensor, holding: torch.Tensor, action: torch.Tensor
    ) -> torch.Tensor:
        """Q of the given actions, running only each action's rotation (the training path).

        Args: as :meth:`forward`, plus ``action`` ``[*B, 3]`` integer (row, col, rotation bin).
        Returns: ``[*B]`` float32, ``forward(...)[..., k, row, col]`` up to float summation order
        (the trunk runs on other batch sizes, and without channels_last when gradients are on); an
        action the rotated frame does not cover (``-inf`` in the map) reads 0, a finite training output.
        """
        batch, x, hand, holding = self._inputs(heightmap, in_hand, holding)
        action = check_q_action(action, batch, self.num_rotations)
        parts = [self._action_chunk(x[sl], hand[sl], holding[sl], action[sl]) for sl in self._chunks(x, 1)]
        if not parts:
            return x.new_zeros(batch)
        return (parts[0] if len(parts) == 1 else torch.cat(parts)).reshape(batch)

    def _action_chunk(self, x: torch.Tensor, hand: torch.Tensor, holding: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        """Encoded [n, 1, H, W], [n, 1, 24, 24], [n] bool, [n, 3] long -> [n] Q of the actions."""
        size, f = x.shape[-1], self.frame_size
        bins = action[:, 2]
        pixel = self._map_index[bins, action[:, 0] * size + action[:, 1]]  # [n], 0 = outside the frame
        frame_pixel = (pixel - 1).clamp(min=0)
        centre = torch.stack((frame_pixel.div(f, rounding_mode="floor"), frame_pixel.remainder(f)), dim=1)
        up, skip = self._trunk_to_up_2(self._rotate_scene(x, bins))
        values = self._window_values(up, skip, hand, holding, centre)
        return torch.where(pixel > 0, values, torch.zeros_like(values))


def build_q_network(
    preset: str,
    *,
    max_height: float,
    num_classes: int = 21,
    num_rotations: int = geometry.NUM_ROTATIONS,
    width: float | None = None,
    frame_margin: int = 0,
    architecture: str = "fcn",
    pick_min_height: float = 0.0,
    head_channels: int | None = None,
    frame_pad: int = 0,
) -> nn.Module:
    """A Q network at a preset width (``Q_PRESETS``); ``width`` overrides the preset's. ``architecture``
    (``Q_ARCHITECTURES``, ``agent.q_architecture``): ``"fcn"`` a :class:`QFCN`, ``"equivariant"`` an
    :class:`~ldm_rl.models.equivariant_q.EquivariantQFCN` (the same interface; needs the ``equivariant`` extra).
    ``head_channels``: the QFCN heads' hidden units (None: scaled with the width); the equivariant heads keep their
    feature fields and ignore it. ``frame_pad``: :class:`QFCN`'s padded frames (the equivariant net has none)."""
    if preset not in Q_PRESETS:
        raise ValueError(f"unknown Q network preset {preset!r}; expected one of {sorted(Q_PRESETS)}")
    if architecture not in Q_ARCHITECTURES:
        raise ValueError(f"unknown Q architecture {architecture!r}; expected one of {list(Q_ARCHITECTURES)}")
    args = (max_height, num_classes, num_rotations, Q_PRESETS[preset] if width is None else width, frame_margin,
            pick_min_height)
    if architecture == "equivariant":
        if frame_pad:
            raise ValueError(f"frame_pad={frame_pad!r} pads QFCN's rotated frames; architecture 'equivariant' has none "
                             "(set it to 0)")
        from ldm_rl.models.equivariant_q import EquivariantQFCN  # raises MissingExtraError without e2cnn

        return EquivariantQFCN(*args)
    return QFCN(*args, head_channels=head_channels, frame_pad=frame_pad)
