"""LDM training-step benchmark: params, FLOPs, fwd+bwd+Adam time on a batch of crops.

    python benchmarks/bench_ldm.py                      # paper + lite, fp32 / bf16 / channels_last
    python benchmarks/bench_ldm.py --presets lite --repeats 5 --threads 2

One step = LDMLoss forward (crop, classify, run only the needed head per sample: half picks, half
places), backward and an Adam step, on ``--batch`` transitions with random block scenes. Prints the
best (and median) of ``--repeats`` timed steps after one warm-up step. Each measurement runs in its own
process: with torch 2.13 CPU, channels_last training of the lite network can abort the process
("double free or corruption"), which is then reported as ``crashed``. The reference measured 4.3 s for
the paper network on this kind of 2-core CPU, running both heads on every sample.
"""

from __future__ import annotations

import argparse
import statistics
import subprocess
import sys
import time

import torch
from tensordict import TensorDict
from torch.utils.flop_counter import FlopCounterMode

from ldm_rl.world_model import build_dynamics_model, count_parameters
from ldm_rl.objectives import LDMLoss

MAX_HEIGHT = 0.15


def make_batch(n: int, seed: int = 0) -> TensorDict:
    """n transitions (first half picks, second half places) with random 4 cm blocks."""
    g = torch.Generator().manual_seed(seed)
    scene = torch.zeros(n, 1, 128, 128)
    for i in range(n):
        for _ in range(4):
            r, c = torch.randint(4, 112, (2,), generator=g).tolist()
            scene[i, 0, r : r + 13, c : c + 13] += 0.04
    nxt = scene.roll(3, dims=-1)
    holding = (torch.arange(n) >= n // 2).unsqueeze(-1)
    action = torch.stack([torch.randint(0, 128, (n,), generator=g), torch.randint(0, 128, (n,), generator=g),
                          torch.randint(0, 8, (n,), generator=g)], -1)
    return TensorDict({"heightmap": scene, "in_hand": torch.zeros(n, 1, 24, 24), "holding": holding, "action": action,
                       "next": {"heightmap": nxt}}, batch_size=[n])


def head_gflops(model, crop_size: int) -> float:
    """Forward GFLOPs (2·MAC) of one head on one crop."""
    k = model.num_classes
    x = torch.zeros(1, 2 * k + model.net.extra_channels, crop_size, crop_size)
    head = model.net.pick.eval()
    with FlopCounterMode(display=False) as counter, torch.no_grad():
        head(x)
    head.train()
    return counter.get_total_flops() / 1e9


def time_steps(preset: str, width: float, batch: TensorDict, *, bf16: bool, channels_last: bool, repeats: int) -> list[float]:
    torch.manual_seed(0)
    model = build_dynamics_model({"name": "ldm", "preset": preset, "width": width, "crop_size": 64}, MAX_HEIGHT)
    if channels_last:
        model = model.to(memory_format=torch.channels_last)
    loss = LDMLoss(model, gamma=2.0, class_weights="auto").train()
    opt = torch.optim.Adam(loss.parameters(), lr=1e-3)
    times = []
    for step in range(repeats + 1):
        start = time.perf_counter()
        with torch.autocast("cpu", dtype=torch.bfloat16, enabled=bf16):
            value = loss(batch)["loss_dynamics"]
        opt.zero_grad(set_to_none=True)
        value.backward()
        opt.step()
        if step:  # the first step warms up allocators and kernels
            times.append(time.perf_counter() - start)
    return times


def measure_in_subprocess(args, preset: str, mode: str) -> str:
    """Run one (preset, mode) measurement in a child process; returns 'best median' or 'crashed'."""
    cmd = [sys.executable, __file__, "--single", preset, mode, "--width", str(args.width), "--batch", str(args.batch),
           "--repeats", str(args.repeats)] + (["--threads", str(args.threads)] if args.threads else [])
    result = subprocess.run(cmd, capture_output=True, text=True)
    lines = result.stdout.strip().splitlines()
    return lines[-1] if result.returncode == 0 and lines else "crashed"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--presets", nargs="+", default=["paper", "lite"], choices=["paper", "lite"])
    parser.add_argument("--width", type=float, default=0.25, help="lite width multiplier")
    parser.add_argument("--batch", type=int, default=32)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--threads", type=int, default=None, help="torch threads (default: torch's)")
    parser.add_argument("--modes", nargs="+", default=["fp32", "bf16", "fp32+cl", "bf16+cl"])
    parser.add_argument("--single", nargs=2, metavar=("PRESET", "MODE"), help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.threads:
        torch.set_num_threads(args.threads)
    if args.single:
        preset, mode = args.single
        times = time_steps(preset, args.width, make_batch(args.batch), bf16="bf16" in mode, channels_last="cl" in mode,
                           repeats=args.repeats)
        print(f"{min(times):.3f} {statistics.median(times):.3f}")
        return
    print(f"torch {torch.__version__}, {torch.get_num_threads()} threads, batch {args.batch} (half pick / half place)")
    print(f"{'preset':<7} {'params/head':>12} {'GFLOP/crop/head':>16} {'mode':<8} {'best s':>7} {'median s':>9}")
    for preset in args.presets:
        model = build_dynamics_model({"name": "ldm", "preset": preset, "width": args.width}, MAX_HEIGHT)
        params, gflops = count_parameters(model.net.pick), head_gflops(model, 64)
        for mode in args.modes:
            result = measure_in_subprocess(args, preset, mode).split()
            best, median = (result + ["", ""])[:2] if result != ["crashed"] else ("crashed", "")
            print(f"{preset:<7} {params:>12,} {gflops:>16.3f} {mode:<8} {best:>7} {median:>9}", flush=True)


if __name__ == "__main__":
    main()
