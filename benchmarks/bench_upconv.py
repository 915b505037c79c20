"""Fewer-FLOP or fewer-call alternatives to the LDM decoder's convolutions, timed against the ones we use.

    python benchmarks/bench_upconv.py --threads 1          # per-layer table, paper preset shapes
    python benchmarks/bench_upconv.py --threads 2 --heads  # the two heads: one after the other vs side by side

The up-projections hold 84 % of the LDM's forward FLOPs and run near this CPU's peak, so the update only
gets faster with fewer multiplications or better-shaped calls. Each alternative below computes exactly
the same function (checked in float64 before timing, printed as ``max |diff|``):

* ``3x3 conv``: the up-projection's 3×3 conv at 2H×2W (``F.conv2d``) vs **Winograd F(2×2, 3×3)** written in
  torch ops (input/output tile transforms + 16 batched GEMMs: 2.25× fewer multiplications).
* ``up-conv``: :class:`~ldm_rl.models.blocks.UnpoolAsConv` (four convs, 25 taps, interleaved) vs **one
  transposed conv** (5×5 kernel, stride 2, the four kernels on its even/odd taps) vs **one 3×3 conv** with
  the four kernels zero-padded to 3×3 (36 taps, 4·C_out channels) + ``pixel_shuffle``.
* ``--heads``: the two paper-preset heads (16 crops each) one after the other on ``--threads`` intra-op
  threads vs side by side, each on its own Python thread with one intra-op thread.

Times are forward + backward (gradients of input and weights), batch 16, best of ``--repeats`` after one
warm-up call, milliseconds, fp32 and bf16 autocast.
"""

from __future__ import annotations

import argparse
import threading
import time

import torch
import torch.nn.functional as F

from ldm_rl.models.blocks import UnpoolAsConv
from ldm_rl.models.unet import DepthUNet

LEVELS = ((512, 4), (256, 8), (128, 16), (64, 32))  # paper preset decoder: (channels, input side) of each up-projection
WINOGRAD_G = torch.tensor([[1.0, 0.0, 0.0], [0.5, 0.5, 0.5], [0.5, -0.5, 0.5], [0.0, 0.0, 1.0]])


def winograd_conv3x3(x: torch.Tensor, weight: torch.Tensor) -> torch.Tensor:
    """3×3 conv, padding 1, no bias, by Winograd F(2×2, 3×3): [B, C, H, W] (H, W even) -> [B, C_out, H, W]."""
    b, _, h, w = x.shape
    xp = F.pad(x, (1, 1, 1, 1))

    def transform(s):  # B^T d of the four strided taps s[k] = d[2i + k] of every tile
        return (s[0] - s[2], s[1] + s[2], s[2] - s[1], s[1] - s[3])

    rows = transform([xp[:, :, k:k + h:2] for k in range(4)])
    tiles = [c for r in rows for c in transform([r[..., k:k + w:2] for k in range(4)])]  # 16 × [B, C, H/2, W/2]
    v = torch.stack(tiles).permute(0, 1, 3, 4, 2).flatten(1, 3)  # [16, B·T, C]
    g = WINOGRAD_G.to(weight.dtype)
    u = torch.einsum("ak,oikl,bl->abio", g, weight, g).flatten(0, 1)  # [16, C, C_out]
    m = torch.bmm(v, u.to(v.dtype)).unflatten(0, (4, 4)).unflatten(2, (b, h // 2, w // 2))  # [4, 4, B, h, w, C_out]

    def inverse(t):  # A^T m along the first dim
        return torch.stack((t[0] + t[1] + t[2], t[1] - t[2] - t[3]))

    y = inverse(inverse(m).transpose(0, 1)).transpose(0, 1)  # [2 (row), 2 (col), B, h, w, C_out]
    return y.permute(2, 5, 3, 0, 4, 1).reshape(b, -1, h, w)


def phase_bias(m: UnpoolAsConv) -> torch.Tensor:
    """[C_out, 4] biases of the output phases (row, col) = (0, 0), (0, 1), (1, 0), (1, 1): A, C, B, D."""
    return torch.stack((m.conv_a.bias, m.conv_c.bias, m.conv_b.bias, m.conv_d.bias), -1)


def upconv_transposed(m: UnpoolAsConv, x: torch.Tensor) -> torch.Tensor:
    """UnpoolAsConv as one 5×5 transposed conv (stride 2) + a per-phase bias."""
    kernels = [c.weight.flip(-1, -2).transpose(0, 1) for c in (m.conv_a, m.conv_b, m.conv_c, m.conv_d)]
    weight = kernels[0].new_zeros(*kernels[0].shape[:2], 5, 5)
    for k, (r, c) in zip(kernels, ((0, 0), (1, 0), (0, 1), (1, 1))):
        weight[:, :, r::2, c::2] = k
    b, _, h, w = x.shape
    y = F.conv_transpose2d(x, weight, stride=2, padding=2, output_padding=1)
    bias = phase_bias(m).view(1, -1, 1, 2, 1, 2)
    return (y.view(b, -1, h, 2, w, 2) + bias.to(y.dtype)).view(b, -1, 2 * h, 2 * w)


def upconv_shuffle(m: UnpoolAsConv, x: torch.Tensor) -> torch.Tensor:
    """UnpoolAsConv as one 3×3 conv with the four kernels zero-padded to 3×3 + pixel_shuffle."""
    weight = torch.stack((m.conv_a.weight, F.pad(m.conv_c.weight, (1, 0, 0, 0)), F.pad(m.conv_b.weight, (0, 0, 1, 0)),
                          F.pad(m.conv_d.weight, (1, 0, 1, 0))), 1).flatten(0, 1)
    return F.pixel_shuffle(F.conv2d(x, weight, phase_bias(m).flatten(), padding=1), 2)


def best_ms(fn, bf16: bool, repeats: int) -> float:
    """Best wall time (ms) of ``fn()`` forward + backward after one warm-up call."""
    times = []
    for _ in range(repeats + 1):
        start = time.perf_counter()
        with torch.autocast("cpu", dtype=torch.bfloat16, enabled=bf16):
            out = fn()
        out.float().sum().backward()
        times.append(time.perf_counter() - start)
    return 1e3 * min(times[1:])


def check_exact() -> dict[str, float]:
    """max |alternative − ours| in float64 on random inputs."""
    torch.manual_seed(0)
    m = UnpoolAsConv(6, 5).double()
    x = torch.randn(2, 6, 4, 6, dtype=torch.float64)
    w = torch.randn(5, 6, 3, 3, dtype=torch.float64)
    return {
        "winograd": (winograd_conv3x3(x, w) - F.conv2d(x, w, padding=1)).abs().max().item(),
        "transposed": (upconv_transposed(m, x) - m(x)).abs().max().item(),
        "3x3+shuffle": (upconv_shuffle(m, x) - m(x)).abs().max().item(),
    }


def layer_table(repeats: int) -> None:
    print("| layer | C | input side | variant | fp32 ms | bf16 ms |")
    print("|---|---|---|---|---|---|")
    for channels, side in LEVELS:
        torch.manual_seed(0)
        conv_in = torch.randn(16, channels, 2 * side, 2 * side, requires_grad=True)
        weight = torch.randn(channels, channels, 3, 3, requires_grad=True)
        up = UnpoolAsConv(channels, channels)
        up_in = torch.randn(16, channels, side, side, requires_grad=True)
        rows = [("3x3 conv", 2 * side, "conv2d (ours)", lambda: F.conv2d(conv_in, weight, padding=1)),
                ("3x3 conv", 2 * side, "Winograd F(2x2,3x3)", lambda: winograd_conv3x3(conv_in, weight)),
                ("up-conv", side, "4 convs (ours)", lambda: up(up_in)),
                ("up-conv", side, "transposed 5x5", lambda: upconv_transposed(up, up_in)),
                ("up-conv", side, "3x3 + pixel_shuffle", lambda: upconv_shuffle(up, up_in))]
        for layer, s, name, fn in rows:
            print(f"| {layer} | {channels} | {s} | {name} | {best_ms(fn, False, repeats):.1f} | {best_ms(fn, True, repeats):.1f} |",
                  flush=True)


def heads_table(threads: int, repeats: int, num_classes: int = 21) -> None:
    torch.manual_seed(0)
    heads = [DepthUNet(2 * num_classes, num_classes, 1.0) for _ in range(2)]
    inputs = [torch.zeros(16, 2 * num_classes, 64, 64).bernoulli_(0.05) for _ in range(2)]

    def one(head, x, bf16):
        with torch.autocast("cpu", dtype=torch.bfloat16, enabled=bf16):
            out = head(x)
        out.float().square().mean().backward()

    def sequential(bf16):
        torch.set_num_threads(threads)
        for head, x in zip(heads, inputs):
            one(head, x, bf16)

    def side_by_side(bf16):
        torch.set_num_threads(1)
        workers = [threading.Thread(target=one, args=(h, x, bf16)) for h, x in zip(heads, inputs)]
        for t in workers:
            t.start()
        for t in workers:
            t.join()

    print("| both paper heads, 16 crops each, fwd + bwd | fp32 s | bf16 s |\n|---|---|---|")
    for name, fn in ((f"one after the other, {threads} intra-op threads", sequential),
                     ("side by side, a Python thread + 1 intra-op thread each", side_by_side)):
        cells = []
        for bf16 in (False, True):
            times = []
            for _ in range(repeats + 1):
                start = time.perf_counter()
                fn(bf16)
                times.append(time.perf_counter() - start)
            cells.append(f"{min(times[1:]):.3f}")
        print(f"| {name} | {cells[0]} | {cells[1]} |", flush=True)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--repeats", type=int, default=3, help="timed calls after the warm-up call")
    parser.add_argument("--heads", action="store_true", help="time the two heads one after the other vs side by side "
                        "(instead of the layer table)")
    args = parser.parse_args()
    if args.threads < 1 or args.repeats < 1:
        parser.error(f"need --threads >= 1 and --repeats >= 1, got {args.threads}, {args.repeats}")
    torch.set_num_threads(args.threads)
    print(f"torch {torch.__version__}, {args.threads} thread(s), batch 16, fwd + bwd, best of {args.repeats} after a warm-up call")
    print("max |diff| vs ours in float64: " + ", ".join(f"{k} {v:.1e}" for k, v in check_exact().items()))
    if args.heads:
        heads_table(args.threads, args.repeats)
    else:
        layer_table(args.repeats)


if __name__ == "__main__":
    main()
