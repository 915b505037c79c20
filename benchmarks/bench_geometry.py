"""Speed of the SE(2) geometry core on this machine (CPU by default; --device cuda where available).

Prints one row per operation: median and best wall time over repeats, for the batch sizes the method
uses (a training minibatch of 32 actions, and planning 32 states × 10 candidates). For reference the
row `grid_sample crop` times torch's own affine_grid + grid_sample crop (what the authors' code does),
which is not exactly equivariant.

    python benchmarks/bench_geometry.py [--threads 2] [--device cpu] [--repeats 20]
"""

from __future__ import annotations

import argparse
import statistics
import time

import torch
import torch.nn.functional as F

from ldm_rl import geometry as g


def timeit(fn, repeats: int, device: torch.device) -> tuple[float, float]:
    fn()  # warm-up
    times = []
    for _ in range(repeats):
        if device.type == "cuda":
            torch.cuda.synchronize()
        t0 = time.perf_counter()
        fn()
        if device.type == "cuda":
            torch.cuda.synchronize()
        times.append(time.perf_counter() - t0)
    return statistics.median(times), min(times)


def grid_sample_crop(images, centers, angles, size):
    """Reference-style crop: affine_grid + grid_sample (bilinear, zeros)."""
    n, _, h, w = images.shape
    cos, sin = torch.cos(angles), torch.sin(angles)
    theta = torch.zeros(n, 2, 3, device=images.device)
    # grid x ↔ column, y ↔ row; R(θ) in (row, col) becomes this matrix in (col, row)
    theta[:, 0, 0], theta[:, 0, 1] = cos * size / w, sin * size / w
    theta[:, 1, 0], theta[:, 1, 1] = -sin * size / h, cos * size / h
    theta[:, 0, 2] = (centers[:, 1].float() - (w - 1) / 2) * 2 / w
    theta[:, 1, 2] = (centers[:, 0].float() - (h - 1) / 2) * 2 / h
    grid = F.affine_grid(theta, (n, images.shape[1], size, size), align_corners=False)
    return F.grid_sample(images, grid, mode="bilinear", padding_mode="zeros", align_corners=False)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--repeats", type=int, default=20)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    device = torch.device(args.device)
    gen = torch.Generator().manual_seed(0)

    rows = []
    for label, b, n in (("train batch", 32, 1), ("planning", 32, 10)):
        scenes = torch.rand(b, 1, 1, 128, 128, generator=gen).to(device)
        centers = torch.randint(0, 128, (b, n, 2), generator=gen).to(device)
        angles = g.bin_to_angle(torch.randint(0, 8, (b, n), generator=gen), 8).to(device)
        patches = torch.rand(b, n, 1, 64, 64, generator=gen).to(device)
        classes = torch.randint(0, 21, (b, 1, 1, 128, 128), generator=gen, dtype=torch.uint8).to(device)
        tag = f"{label} ({b}x{n})"
        rows.append((f"crop 64 bilinear, {tag}", timeit(lambda: g.crop(scenes, centers, angles, 64), args.repeats, device)))
        rows.append((f"crop 64 nearest uint8, {tag}", timeit(lambda: g.crop(classes, centers, angles, 64, "nearest"), args.repeats, device)))
        rows.append((f"paste 64 bilinear, {tag}", timeit(lambda: g.paste(scenes, patches, centers, angles), args.repeats, device)))
        class_patches = torch.randint(0, 21, (b, n, 1, 64, 64), generator=gen, dtype=torch.uint8).to(device)
        rows.append((f"paste 64 nearest uint8, {tag}", timeit(lambda: g.paste(classes, class_patches, centers, angles, "nearest"), args.repeats, device)))
        flat = scenes.expand(b, n, 1, 128, 128).reshape(b * n, 1, 128, 128)
        rows.append(
            (f"grid_sample crop (reference), {tag}", timeit(lambda: grid_sample_crop(flat, centers.reshape(-1, 2), angles.reshape(-1), 64), args.repeats, device))
        )
    q_in = torch.rand(1, 1, 128, 128, generator=gen).to(device)
    rows.append(("rotate_stack 8 bins, 1x128²", timeit(lambda: g.rotate_stack(q_in, 8), args.repeats, device)))
    rows.append(("rotate_stack 8 bins, 32x128²", timeit(lambda: g.rotate_stack(q_in.expand(32, 1, 128, 128), 8), args.repeats, device)))

    print(f"device={device}  threads={torch.get_num_threads()}  repeats={args.repeats}")
    print(f"| {'operation':<48} | median ms | best ms |")
    print(f"|{'-' * 50}|-----------|---------|")
    for name, (med, best) in rows:
        print(f"| {name:<48} | {med * 1e3:9.2f} | {best * 1e3:7.2f} |")


if __name__ == "__main__":
    main()
