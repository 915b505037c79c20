"""A rotation-equivariant Q network (``agent.q_architecture=equivariant``): :class:`QFCN`'s interface, built on e2cnn.

Group. Bin k is the gripper yaw ``θ_k = k·π/R`` (``geometry`` conventions); the parallel-jaw gripper is
symmetric, so yaws are taken mod π and the R bins span π, not 2π. Turning the scene by ``θ_j`` (one group
step) must turn the Q maps and shift every bin by j. The network is therefore equivariant under
``C_2R`` = rotations by multiples of ``π/R`` (``e2cnn.gspaces.Rot2dOnR2(N=2R)``: C₁₆ for R = 8), and its
output is one field of the *quotient* representation ``C_2R / C_2`` (``gspace.quotient_repr(2)``): R channels
that a group step ``θ_j`` cyclically shifts by j, the half turn (which leaves a yaw mod π unchanged) fixing
them. Channel k is bin k (``Q[b, k, row, col]`` = Q of action (row, col, k), as :class:`QFCN`'s maps):
``forward(rotate(x, θ_j))[:, k] = rotate(forward(x)[:, (k + j) mod R], θ_j)``. C_R with its regular
representation would not do: its step 2π/R is two bins. The hidden features are regular fields of C_2R
(2R channels each: one value per orientation mod 2π), which do not force the half-turn symmetry on the
intermediate features; only the last 1×1 layer folds them onto the R yaws.

Exactness. Quarter turns (R even) are symmetries of the square pixel grid: every op here (zero-padded 3×3
convs on even sizes, 2×2 max pooling, bilinear ×2 up-sampling, pointwise LeakyReLU) commutes with
``torch.rot90``, and e2cnn's kernels are exactly quarter-turn symmetric up to float rounding, so the maps
commute with quarter turns to float tolerance (~1e-6; :class:`QFCN`: bit for bit). Other group steps (π/R)
hold only up to the interpolation error of rotating a pixel image (tests/test_equivariant_q.py measures it).

Architecture (fields f_l = max(1, round(c_l / R)), c_l = QFCN's channels at ``width``: 1, 2, 4, 8, 8
regular fields = 16…128 channels at ``lite`` and R = 8; LeakyReLU 0.01, no BatchNorm):

* trunk, once per scene (QFCN: once per bin): lift 3×3 (scene, a trivial field) → f₀ at 128² → four
  levels of [2×2 max-pool, 3×3, 3×3] to f₁…f₄ at 64² … 8² → four up levels [bilinear ×2, ``cat[skip, up]``,
  3×3] back to f₀ at 128²;
* pick head: 3×3 f₀ → f₀, LReLU, 1×1 f₀ → the quotient field (R channels, the R bins);
* place head: the in-hand conditioning is a per-sample equivariant 3×3 kernel (QFCN's dynamic kernel,
  lifted): its coefficients in the e2cnn steerable basis of a f₀ → f₀ ``R2Conv`` are a learned base
  plus an MLP of the in-hand image (a plain CNN: the held object is in the gripper frame, which does not
  turn with the scene), so every per-sample kernel is equivariant by construction; then LReLU, 3×3,
  LReLU, 1×1 to the quotient field, as the pick head.

Masks: the maps are ``-inf`` exactly where :class:`QFCN`'s are (``_rotation_tables``: pixels whose gripper
frame of bin k leaves the image or comes within ``frame_margin`` of its edge), so both architectures
propose from the same action set; ``action_values`` reads 0 there.

Cost: one trunk pass per sample gives all R bins (QFCN: R passes for a map, one for ``action_values``).
Measured at ``lite``, batch 32, one CPU thread (this 2-core machine, shared): the map without gradients
0.56 s (QFCN 2.03 s), ``action_values`` forward + backward 1.77 s (QFCN 0.84 s); 147,581 parameters
(QFCN 1,808,620). e2cnn expands each kernel from its basis coefficients on every call (never cached:
e2cnn's eval-mode cache would go stale under the target networks' parameter swap). Not compiled by
``compile_inference``. e2cnn is an optional extra: ``pip install -e ".[equivariant]"``.
"""

from __future__ import annotations

import copy
import warnings

import torch
import torch.nn.functional as F
from torch import nn

from ldm_rl import geometry
from ldm_rl.extras import MissingExtraError, require_equivariant_q
from ldm_rl.models.blocks import LEAKY_SLOPE, scaled_channels

require_equivariant_q()  # one line naming the extra, not a traceback
try:
    from e2cnn import gspaces
    from e2cnn import nn as enn
except ImportError as err:  # installed without its dependencies (scipy, sympy)
    raise MissingExtraError(f"agent.q_architecture=equivariant: e2cnn does not import ({err}): "
                            "pip install 'ldm_rl[equivariant]' (from a clone: pip install -e '.[equivariant]')") from None

__all__ = ["EquivariantQFCN"]

_UINT8_MASK_WARNING = "indexing with dtype torch.uint8 is now deprecated"  # e2cnn 0.2.3's basis sampling


_BY_IDENTITY: dict[type, type] = {}


def _compare_by_identity(module: nn.Module) -> None:
    """Make ``module`` (an e2cnn basis expansion) equal and hash by identity, as every ``nn.Module``: e2cnn's
    compare by content, so torch's and TensorDict's module walks (``named_modules``' memo set, the ``to_module``
    memo of TorchRL's multi-process collectors) took two layers with equal bases for one."""
    cls = type(module)
    if cls.__eq__ is object.__eq__ and cls.__hash__ is object.__hash__:
        return
    if cls not in _BY_IDENTITY:
        _BY_IDENTITY[cls] = type(cls.__name__, (cls,), {"__eq__": object.__eq__, "__hash__": object.__hash__,
                                                         "__module__": __name__})
    module.__class__ = _BY_IDENTITY[cls]


class _R2Conv(enn.R2Conv):
    """e2cnn's ``R2Conv`` (zero padding ``kernel // 2``) that expands its filter from the current weights on
    every call: ``R2Conv.eval()`` caches the filter as a buffer, which a later weight change (an optimiser step
    in eval mode, the target networks' ``to_module`` swap) would leave stale, and which changes the state dict.
    Its state dict holds only the basis coefficients ``weights`` and ``bias``; the sampled basis is rebuilt."""

    def __init__(self, in_type: enn.FieldType, out_type: enn.FieldType, kernel_size: int, bias: bool = True) -> None:
        with warnings.catch_warnings():
            warnings.filterwarnings("ignore", message=_UINT8_MASK_WARNING, category=UserWarning)
            super().__init__(in_type, out_type, kernel_size, padding=kernel_size // 2, bias=bias)
        del self.filter  # R2Conv's zero placeholders of the eval-mode cache, never used here
        if bias:
            del self.expanded_bias
        for _, module in self.named_modules(remove_duplicate=False):
            _compare_by_identity(module)
            for name, buffer in list(module.named_buffers(recurse=False)):  # the sampled bases: constants of the
                module.register_buffer(name, buffer, persistent=False)  # constructor's arguments (~13 MB at lite)

    def train(self, mode: bool = True) -> "_R2Conv":
        return nn.Module.train(self, mode)

    def forward(self, x: enn.GeometricTensor) -> enn.GeometricTensor:
        weight, bias = self.expand_parameters()
        return enn.GeometricTensor(F.conv2d(x.tensor, weight, bias, padding=self.padding), self.out_type)


def _act(x: enn.GeometricTensor) -> enn.GeometricTensor:
    """Pointwise LeakyReLU: equivariant on regular fields (their group action permutes channels)."""
    return enn.GeometricTensor(F.leaky_relu(x.tensor, LEAKY_SLOPE), x.type)


class _Down(nn.Module):
    """2×2 max-pool (exactly quarter-turn equivariant on even sizes, unlike a stride-2 conv), 3×3, 3×3."""

    def __init__(self, in_type: enn.FieldType, out_type: enn.FieldType) -> None:
        super().__init__()
        self.pool = enn.PointwiseMaxPool(in_type, 2)
        self.conv1 = _R2Conv(in_type, out_type, 3)
        self.conv2 = _R2Conv(out_type, out_type, 3)

    def forward(self, x: enn.GeometricTensor) -> enn.GeometricTensor:
        return _act(self.conv2(_act(self.conv1(self.pool(x)))))


class _Up(nn.Module):
    """Bilinear ×2 up-sampling (``align_corners=False``: symmetric), ``cat[skip, up]``, 3×3."""

    def __init__(self, in_type: enn.FieldType, skip_type: enn.FieldType, out_type: enn.FieldType) -> None:
        super().__init__()
        self.up = enn.R2Upsampling(in_type, scale_factor=2, mode="bilinear", align_corners=False)
        self.conv = _R2Conv(skip_type + in_type, out_type, 3)

    def forward(self, x: enn.GeometricTensor, skip: enn.GeometricTensor) -> enn.GeometricTensor:
        return _act(self.conv(enn.tensor_directsum([skip, self.up(x)])))


class EquivariantQFCN(nn.Module):
    """Pick/place Q maps over all pixels and R rotation bins, equivariant under C_2R. See the module docstring.

    Args: as :class:`~ldm_rl.models.q_fcn.QFCN` (``max_height`` metres of the top depth class, ``num_classes``
    K, ``num_rotations`` R, ``width`` channel multiplier, ``frame_margin`` pixels, ``pick_min_height`` metres).
    """

    CHUNK_SAMPLES = 8  # samples per pass on CPU (measured flat from 4 to 16, slower at 32)

    def __init__(
        self, max_height: float, num_classes: int = 21, num_rotations: int = geometry.NUM_ROTATIONS, width: float = 1.0,
        frame_margin: int = 0, pick_min_height: float = 0.0,
    ) -> None:
        super().__init__()
        from ldm_rl.models.q_fcn import _rotation_tables, check_q_arguments

        check_q_arguments(max_height, num_classes, num_rotations, width, frame_margin, pick_min_height)
        self._init_args = (float(max_height), num_classes, num_rotations, float(width), frame_margin, float(pick_min_height))
        self.pick_min_height = float(pick_min_height)
        self.max_height, self.num_classes = float(max_height), num_classes
        self.num_rotations, self.width, self.frame_margin = num_rotations, float(width), frame_margin

        r = num_rotations
        self.gspace = gspaces.Rot2dOnR2(N=2 * r)  # rotations by multiples of π/R: one bin per group step
        fields = [max(1, round(scaled_channels(c, width) / r)) for c in (16, 32, 64, 128, 128)]
        types = [enn.FieldType(self.gspace, n * [self.gspace.regular_repr]) for n in fields]
        self.scene_type = enn.FieldType(self.gspace, [self.gspace.trivial_repr])
        q_type = enn.FieldType(self.gspace, [self.gspace.quotient_repr(2)])  # R channels: channel k = bin k
        self.feature_channels = types[0].size

        self.lift = _R2Conv(self.scene_type, types[0], 3, bias=False)
        self.down = nn.ModuleList(_Down(types[i], types[i + 1]) for i in range(4))
        self.up = nn.ModuleList(_Up(types[i + 1], types[i], types[i]) for i in reversed(range(4)))
        self.pick_head = nn.ModuleList([_R2Conv(types[0], types[0], 3), _R2Conv(types[0], q_type, 1)])
        self.place_conv = _R2Conv(types[0], types[0], 3, bias=False)  # the dynamic kernel's base and basis
        self.place_head = nn.ModuleList([_R2Conv(types[0], types[0], 3), _R2Conv(types[0], q_type, 1)])

        c16, c32, c64 = (scaled_channels(c, width) for c in (16, 32, 64))
        hand_convs: list[nn.Module] = []
        for cin, cout in ((1, c16), (c16, c32), (c32, c64)):  # 24 -> 12 -> 6 -> 3
            hand_convs += [nn.Conv2d(cin, cout, 3, stride=2, padding=1, bias=False), nn.LeakyReLU(LEAKY_SLOPE)]
        side = -(-geometry.HAND_SIZE // 8)
        self.hand_encoder = nn.Sequential(
            *hand_convs, nn.Flatten(), nn.Linear(c64 * side * side, scaled_channels(512, width)), nn.LeakyReLU(LEAKY_SLOPE),
            nn.Linear(scaled_channels(512, width), self.place_conv.weights.numel()),
        )
        for m in self.hand_encoder.modules():
            if isinstance(m, nn.Conv2d):
                nn.init.xavier_normal_(m.weight)

        with torch.no_grad():  # the steerable basis as a matrix: filter = basis @ coefficients (expansion is linear)
            unit = torch.eye(self.place_conv.weights.numel())
            basis = torch.stack([self.place_conv.basisexpansion(e).reshape(-1) for e in unit], dim=1)
        self.register_buffer("_place_basis", basis, persistent=False)  # [C·C·9, D]

        _, map_index = _rotation_tables(num_rotations, geometry.HEIGHTMAP_SIZE, frame_margin)
        self.register_buffer("_outside", (map_index == 0).view(r, geometry.HEIGHTMAP_SIZE, geometry.HEIGHTMAP_SIZE),
                             persistent=False)

    def __reduce__(self):
        """Pickle as constructor arguments + state (e2cnn's groups hold lambdas, which pickle cannot)."""
        return _rebuild, (self._init_args, self.state_dict(), self.training)

    def __deepcopy__(self, memo: dict) -> "EquivariantQFCN":
        """A plain deep copy of every attribute (``__reduce__`` is for pickling only)."""
        other = self.__class__.__new__(self.__class__)
        memo[id(self)] = other
        other.__dict__.update(copy.deepcopy(self.__dict__, memo))
        return other

    # ------------------------------------------------------------------------------------------
    # network pieces
    # ------------------------------------------------------------------------------------------
    def _trunk(self, x: torch.Tensor) -> enn.GeometricTensor:
        """[n, 1, H, W] encoded scenes -> features (f₀ regular fields) [n, C, H, W]."""
        lifted = self.lift(enn.GeometricTensor(x, self.scene_type)).tensor
        if x.device.type == "cpu":  # channels_last: forward ~20 %, forward + backward ~7 % faster (measured)
            lifted = lifted.contiguous(memory_format=torch.channels_last)
        skips = [_act(enn.GeometricTensor(lifted, self.lift.out_type))]
        for down in self.down:
            skips.append(down(skips[-1]))
        y = skips.pop()
        for up in self.up:
            y = up(y, skips.pop())
        return y

    def _head(self, head: nn.ModuleList, feat: enn.GeometricTensor) -> torch.Tensor:
        return head[1](_act(head[0](feat))).tensor

    def _place(self, feat: enn.GeometricTensor, in_hand: torch.Tensor) -> torch.Tensor:
        """Features [n, C, H, W], encoded hands [n, 1, 24, 24] -> [n, R, H, W] place maps."""
        n, c, h, w = feat.shape
        coefficients = self.place_conv.weights + self.hand_encoder(in_hand)  # [n, D]
        kernels = (coefficients @ self._place_basis.t()).view(n * c, c, 3, 3)  # equivariant, one per sample
        y = F.conv2d(feat.tensor.reshape(1, n * c, h, w), kernels, padding=1, groups=n).view(n, c, h, w)
        return self._head(self.place_head, _act(enn.GeometricTensor(y, feat.type)))

    def _maps(self, x: torch.Tensor, in_hand: torch.Tensor, holding: torch.Tensor) -> torch.Tensor:
        """Encoded scenes [n, 1, H, W], hands [n, 1, 24, 24], holding [n] bool -> [n, R, H, W] raw maps."""
        n = x.shape[0]
        place_rows = holding.nonzero().squeeze(1)
        n_place = place_rows.numel()
        feat = self._trunk(x)
        if n_place == 0:
            return self._head(self.pick_head, feat)
        if n_place == n:
            return self._place(feat, in_hand)
        pick_rows = (~holding).nonzero().squeeze(1)
        pick = self._head(self.pick_head, enn.GeometricTensor(feat.tensor.index_select(0, pick_rows), feat.type))
        place = self._place(enn.GeometricTensor(feat.tensor.index_select(0, place_rows), feat.type),
                            in_hand.index_select(0, place_rows))
        return torch.cat((pick, place)).index_select(0, torch.cat((pick_rows, place_rows)).argsort())

    # ------------------------------------------------------------------------------------------
    # public API (QFCN's)
    # ------------------------------------------------------------------------------------------
    def _inputs(self, heightmap, in_hand, holding):
        """Validate and encode; -> batch shape, [N, 1, H, W], [N, 1, h, h] (encoded), [N] bool."""
        from ldm_rl.models.q_fcn import encode_q_inputs

        return encode_q_inputs(heightmap, in_hand, holding, self.max_height, self.num_classes, self.lift.weights.dtype)

    def _chunks(self, n: int, device: torch.device) -> list[slice]:
        step = self.CHUNK_SAMPLES if device.type == "cpu" else max(1, n)
        return [slice(i, i + step) for i in range(0, n, step)]

    def _all_maps(self, x: torch.Tensor, hand: torch.Tensor, holding: torch.Tensor) -> torch.Tensor:
        parts = [self._maps(x[sl], hand[sl], holding[sl]) for sl in self._chunks(x.shape[0], x.device)]
        return parts[0] if len(parts) == 1 else torch.cat(parts)

    def forward(self, heightmap: torch.Tensor, in_hand: torch.Tensor, holding: torch.Tensor) -> torch.Tensor:
        """Q maps of each sample's current primitive over all rotations.

        Args:
            heightmap: ``[*B, 1, 128, 128]`` float metres.
            in_hand: ``[*B, 1, 24, 24]`` float metres (read only where holding).
            holding: ``[*B]`` or ``[*B, 1]`` bool; False → pick map, True → place map.
        Returns:
            ``[*B, R, 128, 128]`` float32; entry ``[..., k, row, col]`` is Q of action (row, col, k);
            ``-inf`` where :class:`QFCN`'s maps are (outside bin k's gripper frame or within its margin; with
            ``pick_min_height``, picks on nothing).
        """
        batch, x, hand, holding = self._inputs(heightmap, in_hand, holding)
        size, r = geometry.HEIGHTMAP_SIZE, self.num_rotations
        if x.shape[0] == 0:
            return x.new_zeros(*batch, r, size, size)
        maps = self._all_maps(x, hand, holding).masked_fill(self._outside, float("-inf"))
        if self.pick_min_height:
            from ldm_rl.models.q_fcn import mask_empty_picks

            maps = mask_empty_picks(maps, heightmap.reshape(-1, 1, size, size), holding, self.pick_min_height)
        return maps.reshape(*batch, r, size, size)

    def action_values(
        self, heightmap: torch.Tensor, in_hand: torch.Tensor, holding: torch.Tensor, action: torch.Tensor
    ) -> torch.Tensor:
        """Q of the given actions (the training path; one trunk pass gives every bin, so it costs a map).

        Args: as :meth:`forward`, plus ``action`` ``[*B, 3]`` integer (row, col, rotation bin).
        Returns: ``[*B]`` float32, ``forward(...)[..., k, row, col]`` up to float summation order; an action
        whose map entry is ``-inf`` reads 0, a finite training output.
        """
        batch, x, hand, holding = self._inputs(heightmap, in_hand, holding)
        from ldm_rl.models.q_fcn import check_q_action

        size = geometry.HEIGHTMAP_SIZE
        action = check_q_action(action, batch, self.num_rotations)
        if x.shape[0] == 0:
            return x.new_zeros(batch)
        flat = (action[:, 2] * size + action[:, 0]) * size + action[:, 1]  # [N] index into one [R, H, W] map
        values = self._all_maps(x, hand, holding).flatten(1).gather(1, flat.unsqueeze(1)).squeeze(1)
        return values.masked_fill(self._outside.view(-1)[flat], 0.0).reshape(batch)


def _rebuild(args: tuple, state: dict, training: bool) -> EquivariantQFCN:
    """Unpickle: build (without drawing from the global RNG: the weights come from ``state``) and take the
    pickled tensors themselves (``assign``: meta tensors stay meta, as TorchRL's worker copies of a policy are)."""
    with torch.random.fork_rng(devices=[]):
        net = EquivariantQFCN(*args)
    net.load_state_dict(state, assign=True)
    return net.train(training)
