"""LDM training-step benchmark: ours beside the authors' released architecture, measured in the same run.

    python benchmarks/bench_ldm.py --threads 2                     # paper preset + reference, fp32 / bf16
    python benchmarks/bench_ldm.py --threads 2 --repeats 10 --models ours-paper ref-1head
    python benchmarks/bench_ldm.py --models ours-lite --modes fp32 bf16 fp32+cl

One step = forward + backward + Adam on ``--batch`` transitions with random block scenes (first half
picks, second half places), built once from one seed and shared by every row:

* ``ours-paper`` / ``ours-lite``: ``LDMLoss`` (crop, depth classes, **one head per sample**, focal loss,
  γ = 2, auto class weights) and Adam with its fused kernel (``ldm_rl.torch_utils.make_adam``) as the training
  recipe uses it (``--plain-adam``: torch's default for-loop Adam).
* ``ref-1head`` / ``ref-2heads``: the released network rebuilt layer by layer in
  ``benchmarks/reference_ldm.py`` (24,893,963 parameters per head, K = 11 classes) and its released
  update on the same scenes: bilinear crops of the one-hot scene, both heads on every sample
  (``ref-2heads``, the released code) or one head on the whole batch (``ref-1head``), paste-back,
  γ = 0 "focal" loss, Adam (weight decay 1e-5).

Each (model, mode) runs in its own child process of this run (a crash, e.g. the channels_last abort
torch 2.13 CPU can hit, is reported as ``crashed``). The first step (allocator and kernel warm-up) is
reported separately; best and median are over ``--repeats`` further steps, wall clock
(``time.perf_counter``). Modes: ``fp32``, ``bf16`` (CPU autocast), ``+cl`` = channels_last weights.
"""

from __future__ import annotations

import argparse
import statistics
import subprocess
import sys
import time
from pathlib import Path

import torch
from tensordict import TensorDict
from torch.utils.flop_counter import FlopCounterMode

sys.path.insert(0, str(Path(__file__).resolve().parent))  # benchmarks/reference_ldm.py

from reference_ldm import REFERENCE_HEAD_PARAMS, ReferenceHead, ReferenceLDMStep, make_reference_batch  # noqa: E402

from ldm_rl.geometry import heights_to_classes  # noqa: E402
from ldm_rl.objectives import LDMLoss  # noqa: E402
from ldm_rl.torch_utils import make_adam  # noqa: E402
from ldm_rl.world_model import build_dynamics_model, count_parameters  # noqa: E402
from ldm_rl.world_model.training import dynamics_update  # noqa: E402

MAX_HEIGHT = 0.15
REFERENCE_CLASSES = 11  # the released configs
MODELS = ("ours-paper", "ours-lite", "ref-1head", "ref-2heads")
MODES = ("fp32", "bf16", "fp32+cl", "bf16+cl")


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


def reference_batch(batch: TensorDict) -> dict:
    """The same transitions in the released update's input format (K = 11 one-hot scenes)."""
    def classes(h):
        return heights_to_classes(h, MAX_HEIGHT, REFERENCE_CLASSES)

    return make_reference_batch(classes(batch["heightmap"]), classes(batch["next", "heightmap"]), classes(batch["in_hand"]),
                                batch["action"], batch["holding"], REFERENCE_CLASSES)


def build_ours(preset: str, width: float):
    return build_dynamics_model({"name": "ldm", "preset": preset, "width": width, "crop_size": 64}, MAX_HEIGHT)


def describe(model_name: str, width: float) -> tuple[int, float]:
    """(parameters of one head, forward GFLOPs (2·MAC) of one head on one 64 px crop)."""
    if model_name.startswith("ours"):
        model = build_ours(model_name.split("-")[1], width)
        head, channels = model.net.pick, 2 * model.num_classes
    else:
        head, channels = ReferenceHead(REFERENCE_CLASSES), 2 * REFERENCE_CLASSES
        assert count_parameters(head) == REFERENCE_HEAD_PARAMS
    with FlopCounterMode(display=False) as counter, torch.no_grad():
        head.eval()(torch.zeros(1, channels, 64, 64))
    return count_parameters(head), counter.get_total_flops() / 1e9


def time_steps(model_name: str, mode: str, args) -> list[float]:
    """Seconds of 1 + ``args.repeats`` steps (the first is the warm-up)."""
    bf16, channels_last = "bf16" in mode, "cl" in mode
    batch = make_batch(args.batch)
    torch.manual_seed(0)
    if model_name.startswith("ours"):
        model = build_ours(model_name.split("-")[1], args.width)
        if channels_last:
            model = model.to(memory_format=torch.channels_last)
        loss = LDMLoss(model, gamma=2.0, class_weights="auto").train()
        opt = (torch.optim.Adam(loss.parameters(), lr=1e-3) if args.plain_adam else make_adam(loss.parameters(), lr=1e-3))

        def step() -> None:
            dynamics_update(loss, opt, batch, autocast="bf16" if bf16 else None)  # the recipe's step
    else:
        ref = ReferenceLDMStep(heads=2 if model_name == "ref-2heads" else 1, num_classes=REFERENCE_CLASSES, bf16=bf16)
        if channels_last:
            ref.heads.to(memory_format=torch.channels_last)
        ref_batch = reference_batch(batch)

        def step() -> None:
            ref.step(ref_batch)

    times = []
    for _ in range(args.repeats + 1):
        start = time.perf_counter()
        step()
        times.append(time.perf_counter() - start)
    return times


def measure_in_subprocess(args, model_name: str, mode: str) -> list[str]:
    """Run one (model, mode) in a child process; returns [warm-up, best, median] or ['crashed']."""
    cmd = [sys.executable, __file__, "--single", model_name, mode, "--width", str(args.width), "--batch",
           str(args.batch), "--repeats", str(args.repeats)]
    cmd += (["--threads", str(args.threads)] if args.threads else []) + (["--plain-adam"] if args.plain_adam else [])
    result = subprocess.run(cmd, capture_output=True, text=True)
    lines = result.stdout.strip().splitlines()
    return lines[-1].split() if result.returncode == 0 and lines else ["crashed"]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--models", nargs="+", default=["ours-paper", "ref-1head", "ref-2heads"], choices=MODELS)
    parser.add_argument("--modes", nargs="+", default=["fp32", "bf16"], choices=MODES)
    parser.add_argument("--width", type=float, default=0.25, help="ours-lite width multiplier")
    parser.add_argument("--batch", type=int, default=32)
    parser.add_argument("--repeats", type=int, default=5, help="timed steps after the warm-up step")
    parser.add_argument("--threads", type=int, default=None, help="torch threads (default: torch's)")
    parser.add_argument("--plain-adam", action="store_true", help="ours: torch's default Adam (a for-loop on CPU) instead of "
                        "the recipe's fused kernel (ldm_rl.torch_utils.make_adam)")
    parser.add_argument("--single", nargs=2, metavar=("MODEL", "MODE"), help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.batch < 2 or args.repeats < 1:
        parser.error(f"need --batch >= 2 and --repeats >= 1, got {args.batch}, {args.repeats}")
    if args.threads:
        torch.set_num_threads(args.threads)
    if args.single:
        times = time_steps(*args.single, args)
        print(f"{times[0]:.3f} {min(times[1:]):.3f} {statistics.median(times[1:]):.3f}")
        return
    adam = "Adam (default for-loop)" if args.plain_adam else "fused Adam (as the recipe)"
    print(f"torch {torch.__version__}, {torch.get_num_threads()} threads, batch {args.batch} (half pick / half place), "
          f"{args.repeats} timed steps after 1 warm-up step, wall seconds; ours: {adam}")
    print(f"| {'model':<10} | {'params/head':>11} | {'GFLOP/crop/head':>15} | {'mode':<7} | {'warm-up s':>9} "
          f"| {'best s':>7} | {'median s':>8} |")
    print("|---|---|---|---|---|---|---|")
    for model_name in args.models:
        params, gflops = describe(model_name, args.width)
        for mode in args.modes:
            result = measure_in_subprocess(args, model_name, mode)
            warm, best, median = (result + ["", ""])[:3]
            print(f"| {model_name:<10} | {params:>11,} | {gflops:>15.3f} | {mode:<7} | {warm:>9} | {best:>7} | {median:>8} |",
                  flush=True)
    picks = args.batch - args.batch // 2
    print(f"ours: one head per sample ({picks} + {args.batch - picks} crops); ref-1head: one released head on all "
          f"{args.batch} crops; ref-2heads: both released heads on all {args.batch} crops (the released update). "
          f"K: ours 21, ref {REFERENCE_CLASSES} classes.")


if __name__ == "__main__":
    main()
