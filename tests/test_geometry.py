"""Property tests of the SE(2) pixel-geometry core (ldm_rl.geometry)."""

import math

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from ldm_rl import geometry as g

H = W = 48  # small scenes keep the property tests fast; nothing depends on 128
SETTINGS = settings(max_examples=40, deadline=None)

angles = st.floats(-2 * math.pi, 2 * math.pi, allow_nan=False)
sizes = st.sampled_from([1, 5, 8, 16, 17])
modes = st.sampled_from(["bilinear", "nearest"])
seeds = st.integers(0, 2**31 - 1)


def scene(seed, batch=(), channels=2, h=H, w=W):
    gen = torch.Generator().manual_seed(seed)
    return torch.rand(*batch, channels, h, w, generator=gen)


def rot_pixel(rc, h, k):
    """Where pixel (row, col) lands after torch.rot90(x, k, (-2, -1)) of a square h×h image."""
    r, c = rc[..., 0], rc[..., 1]
    for _ in range(k % 4):
        r, c = h - 1 - c, r
    return torch.stack((r, c), -1)


def square_coords(h, w, center, theta, d):
    """Patch coordinates R(−θ)(p − a) + d//2 of every scene pixel, float64 (independent of the module)."""
    rows = torch.arange(h, dtype=torch.float64)[:, None] - center[0]
    cols = torch.arange(w, dtype=torch.float64)[None, :] - center[1]
    su = math.cos(theta) * rows + math.sin(theta) * cols + d // 2
    sv = -math.sin(theta) * rows + math.cos(theta) * cols + d // 2
    return su, sv


# ------------------------------------------------------------------------------------------
# crop / paste round trips
# ------------------------------------------------------------------------------------------
@SETTINGS
@given(seed=seeds, row=st.integers(0, H - 1), col=st.integers(0, W - 1), d=sizes, mode=modes)
def test_crop_then_paste_is_identity_at_zero_angle(seed, row, col, d, mode):
    x = scene(seed)
    c = torch.tensor([row, col])
    patch = g.crop(x, c, 0.0, d, mode)
    # the crop reads pixels exactly
    rr, cc = torch.meshgrid(torch.arange(d) - d // 2 + row, torch.arange(d) - d // 2 + col, indexing="ij")
    inside = (rr >= 0) & (rr < H) & (cc >= 0) & (cc < W)
    expected = torch.where(inside, x[:, rr.clamp(0, H - 1), cc.clamp(0, W - 1)], torch.zeros(()))
    assert torch.equal(patch, expected)
    # pasting it back changes nothing inside the image
    assert torch.equal(g.paste(x, patch, c, 0.0, mode), x)


@SETTINGS
@given(theta=angles, row=st.integers(20, 27), col=st.integers(20, 27), slope=st.floats(-1, 1))
def test_crop_then_paste_reproduces_affine_scenes_at_any_angle(theta, row, col, slope):
    """Bilinear interpolation is exact on affine images, so a round trip is exact up to float error
    everywhere the pasted coordinate lies between patch pixel centres (the border half-pixel clamps)."""
    d = 16
    r = torch.arange(H, dtype=torch.float32)[:, None]
    c = torch.arange(W, dtype=torch.float32)[None, :]
    x = (0.01 * r + 0.01 * slope * c + 0.5).expand(1, H, W).contiguous()
    centre = torch.tensor([row, col])
    y = g.paste(x, g.crop(x, centre, theta, d), centre, theta)
    su, sv = square_coords(H, W, (row, col), theta, d)
    interior = (su >= 1e-3) & (su <= d - 1 - 1e-3) & (sv >= 1e-3) & (sv <= d - 1 - 1e-3)
    assert interior.sum() > (d - 2) ** 2 // 2
    assert (y - x)[0][interior].abs().max() <= 1e-5


def test_round_trip_on_smooth_scene_within_bilinear_tolerance():
    """Double bilinear resampling of a smooth bump stays within bilinear error of it.

    Each pass errs by at most h²·|f''|/4 ≈ 0.007 here (σ = 6 px, unit peak); two passes plus the
    half-pixel border clamp stay under 0.03, while a half-pixel misalignment would err by ≈ 0.08."""
    r = torch.arange(H, dtype=torch.float32)[:, None] - 24
    c = torch.arange(W, dtype=torch.float32)[None, :] - 24
    x = torch.exp(-(r**2 + c**2) / (2 * 6.0**2))[None]
    for theta in (0.3, 1.0, 2.5):
        y = g.paste(x, g.crop(x, torch.tensor([24, 24]), theta, 24), torch.tensor([24, 24]), theta)
        assert (y - x).abs().max() < 0.03


@SETTINGS
@given(seed=seeds, theta=angles, row=st.integers(0, H - 1), col=st.integers(0, W - 1), d=sizes, mode=modes)
def test_paste_changes_nothing_outside_the_rotated_square(seed, theta, row, col, d, mode):
    x = scene(seed)
    patch = torch.full((2, d, d), 7.0)  # values no scene pixel has
    y = g.paste(x, patch, torch.tensor([row, col]), theta, mode)
    su, sv = square_coords(H, W, (row, col), theta, d)
    lo, hi, eps = -0.5, d - 0.5, 1e-6
    outside = (su < lo - eps) | (su > hi + eps) | (sv < lo - eps) | (sv > hi + eps)
    inside = (su > lo + eps) & (su < hi - eps) & (sv > lo + eps) & (sv < hi - eps)
    assert torch.equal(y[:, outside], x[:, outside])  # bit-exact
    assert torch.allclose(y[:, inside], torch.full_like(y[:, inside], 7.0))


def test_paste_covers_about_d_squared_pixels_at_any_angle():
    x = torch.zeros(1, 128, 128)
    for theta in np.linspace(0, math.pi, 9):
        y = g.paste(x, torch.ones(1, 64, 64), torch.tensor([64, 64]), float(theta))
        assert abs(int(y.sum()) - 64 * 64) <= 2 * 64  # the rotated square's area, up to its boundary


# ------------------------------------------------------------------------------------------
# equivariance
# ------------------------------------------------------------------------------------------
@SETTINGS
@given(seed=seeds, theta=angles, row=st.integers(0, H - 1), col=st.integers(0, W - 1), d=sizes, mode=modes, k=st.integers(1, 3))
def test_crop_is_exactly_invariant_to_quarter_turns_of_scene_and_action(seed, theta, row, col, d, mode, k):
    x = scene(seed)
    c = torch.tensor([row, col])
    xr = torch.rot90(x, k, (-2, -1))
    # torch.rot90(k) maps pixel offsets by R(k·π/2), so the action's angle turns by +k·π/2
    cr = rot_pixel(c, H, k)
    assert torch.equal(g.crop(x, c, theta, d, mode), g.crop(xr, cr, theta + k * math.pi / 2, d, mode))


@SETTINGS
@given(seed=seeds, theta=angles, row=st.integers(0, H - 1), col=st.integers(0, W - 1), k=st.integers(1, 3), mode=modes)
def test_paste_is_exactly_equivariant_to_quarter_turns(seed, theta, row, col, k, mode):
    x = scene(seed)
    patch = scene(seed + 1, channels=2, h=9, w=9)
    c = torch.tensor([row, col])
    y = g.paste(x, patch, c, theta, mode)
    yr = g.paste(torch.rot90(x, k, (-2, -1)), patch, rot_pixel(c, H, k), theta + k * math.pi / 2, mode)
    assert torch.equal(torch.rot90(y, k, (-2, -1)), yr)


@SETTINGS
@given(seed=seeds, theta=angles, row=st.integers(0, H - 1), col=st.integers(0, W - 1), dr=st.integers(-30, 30), dc=st.integers(-30, 30), mode=modes)
def test_crop_is_exactly_invariant_to_whole_pixel_translations(seed, theta, row, col, dr, dc, mode):
    x = scene(seed)
    big = torch.zeros(2, H + 60, W + 60)
    big[:, 30 + dr : 30 + dr + H, 30 + dc : 30 + dc + W] = x
    shifted = torch.tensor([row + 30 + dr, col + 30 + dc])
    assert torch.equal(g.crop(x, torch.tensor([row, col]), theta, 13, mode), g.crop(big, shifted, theta, 13, mode))


def test_discrete_bins_equivariance_with_the_paper_setting():
    """128² scene, 64 px crop, 8 bins: bin k at a quarter-turned scene is bin k + 4 (or k − 4)."""
    x = scene(3, h=128, w=128)
    for k_bin in range(8):
        c = torch.tensor([50, 90])
        theta = g.bin_to_angle(torch.tensor(k_bin), 8)
        turns = 1 if k_bin < 4 else -1  # keep the rotated action's angle inside [0, π)
        theta_r = g.bin_to_angle(torch.tensor(k_bin + 4 * turns), 8)
        cr = rot_pixel(c, 128, turns)
        assert torch.equal(g.crop(x, c, theta, 64), g.crop(torch.rot90(x, turns, (-2, -1)), cr, theta_r, 64))


# ------------------------------------------------------------------------------------------
# batching, broadcasting, centre crops, rotations
# ------------------------------------------------------------------------------------------
@settings(max_examples=15, deadline=None)
@given(seed=seeds, mode=modes)
def test_batched_equals_per_sample(seed, mode):
    gen = torch.Generator().manual_seed(seed)
    x = scene(seed, batch=(2, 3))
    centres = torch.randint(0, H, (2, 3, 2), generator=gen)
    thetas = torch.rand(2, 3, generator=gen) * 7 - 3.5
    patches = g.crop(x, centres, thetas, 11, mode)
    pasted = g.paste(x, patches * 2, centres, thetas, mode)
    for i in range(2):
        for j in range(3):
            assert torch.equal(patches[i, j], g.crop(x[i, j], centres[i, j], thetas[i, j], 11, mode))
            assert torch.equal(pasted[i, j], g.paste(x[i, j], patches[i, j] * 2, centres[i, j], thetas[i, j], mode))


def test_one_scene_broadcasts_against_many_actions_without_copies():
    x = scene(0, batch=(2,))
    centres = torch.randint(0, H, (2, 5, 2))
    thetas = torch.rand(2, 5)
    broadcast = g.crop(x.unsqueeze(1), centres, thetas, 9)
    expanded = g.crop(x.unsqueeze(1).expand(2, 5, 2, H, W).contiguous(), centres, thetas, 9)
    assert broadcast.shape == (2, 5, 2, 9, 9) and torch.equal(broadcast, expanded)


@pytest.mark.parametrize("mode", ["bilinear", "nearest"])
def test_center_crop_matches_a_smaller_crop(mode):
    x = scene(1, h=128, w=128)
    c, theta = torch.tensor([60, 70]), 0.77
    assert torch.equal(g.center_crop(g.crop(x, c, theta, 64, mode), 24), g.crop(x, c, theta, 24, mode))
    assert torch.equal(g.center_crop(g.crop(x, c, theta, 64, mode), 32), g.crop(x, c, theta, 32, mode))


def test_uint8_class_maps_crop_and_paste_in_nearest_mode():
    classes = torch.randint(0, 21, (1, H, W), dtype=torch.uint8)
    c = torch.tensor([20, 30])
    patch = g.crop(classes, c, math.pi / 2, 16, "nearest")
    assert patch.dtype == torch.uint8
    assert torch.equal(g.paste(classes, patch, c, math.pi / 2, "nearest"), classes)
    with pytest.raises(ValueError, match="bilinear"):
        g.crop(classes, c, 0.0, 16)


def test_rotate_quarter_turns_match_rot90_and_round_trip():
    x = scene(2, batch=(3,))
    assert torch.equal(g.rotate(x, math.pi / 2), torch.rot90(x, -1, (-2, -1)))
    assert torch.equal(g.rotate(x, -math.pi), torch.rot90(x, 2, (-2, -1)))
    stack = g.rotate_stack(x, 2)  # bins 0 and π/2
    assert stack.shape == (3, 2, 2, H, W)
    assert torch.equal(stack[:, 0], x) and torch.equal(stack[:, 1], torch.rot90(x, -1, (-2, -1)))
    assert torch.equal(g.unrotate_stack(stack, "nearest")[:, 1], x)


def test_rotate_matches_crop_about_the_centre_for_odd_images():
    x = scene(4, h=33, w=33)
    for theta in (0.2, 1.3, -2.0):
        assert torch.allclose(g.rotate(x, theta), g.crop(x, torch.tensor([16, 16]), theta, 33), atol=1e-6)


def test_rotate_stack_round_trip_keeps_the_inscribed_disc():
    r = torch.arange(64.0)[:, None] - 31.5
    c = torch.arange(64.0)[None, :] - 31.5
    x = torch.exp(-(r**2 + c**2) / (2 * 8.0**2))[None]  # smooth, zero near the border
    back = g.unrotate_stack(g.rotate_stack(x, 8))
    assert (back - x).abs().max() < 0.02


def test_crop_is_differentiable_in_the_image():
    x = scene(5, h=12, w=12).double().requires_grad_()
    torch.autograd.gradcheck(lambda t: g.crop(t, torch.tensor([5, 6]), 0.4, 5), (x,))
    patch = torch.rand(2, 5, 5, dtype=torch.float64, requires_grad=True)
    torch.autograd.gradcheck(lambda p: g.paste(x.detach(), p, torch.tensor([5, 6]), 0.4), (patch,))


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
def test_cuda_matches_cpu():
    x = scene(6, batch=(4,))
    c, t = torch.randint(0, H, (4, 2)), torch.rand(4) * 3
    assert torch.allclose(g.crop(x, c, t, 16).cpu(), g.crop(x.cuda(), c.cuda(), t.cuda(), 16).cpu(), atol=1e-6)


# ------------------------------------------------------------------------------------------
# depth classes, bins, workspace
# ------------------------------------------------------------------------------------------
@SETTINGS
@given(h=st.floats(0, 0.25), k=st.sampled_from([11, 21, 256]))
def test_height_class_round_trip_within_half_a_class(h, k):
    max_h = 0.2
    cls = g.heights_to_classes(torch.tensor([h]), max_h, k)
    assert cls.dtype == torch.uint8
    back = g.classes_to_heights(cls, max_h, k)
    assert abs(float(back) - min(h, max_h)) <= max_h / (k - 1) / 2 + 1e-7


def test_heights_clamp_and_have_no_dtype_skew():
    h = torch.tensor([-0.01, 0.0, 0.07, 0.14, 0.2, 0.35, 10.0], dtype=torch.float64)
    c64 = g.heights_to_classes(h, 0.2, 11)
    assert c64.tolist() == [0, 0, 4, 7, 10, 10, 10]
    # the reference snapped 0.7·max to class 8 in float64 but 7 in float32; we agree across dtypes
    grid = torch.linspace(0, 0.2, 2001, dtype=torch.float32)
    assert torch.equal(g.heights_to_classes(grid, 0.2, 21), g.heights_to_classes(grid.double(), 0.2, 21))
    with pytest.raises(ValueError, match="NaN"):
        g.heights_to_classes(torch.tensor([float("nan")]), 0.2, 21)
    with pytest.raises(ValueError, match="num_classes"):
        g.heights_to_classes(h, 0.2, 300)
    with pytest.raises(ValueError, match="classes must lie"):
        g.classes_to_heights(torch.tensor([21]), 0.2, 21)


def test_rotation_bins_are_circular_mod_pi():
    bins = torch.arange(8)
    assert torch.equal(g.angle_to_bin(g.bin_to_angle(bins, 8), 8), bins)
    assert torch.equal(g.angle_to_bin(torch.tensor([math.pi - 0.01, math.pi, -0.05, 2 * math.pi + 0.4]), 8), torch.tensor([0, 0, 0, 1]))
    d = g.circular_bin_distance(bins[:, None], bins[None, :], 8)
    assert torch.equal(d, d.T) and d.max() == 4 and int(d[0, 7]) == 1
    assert torch.allclose(g.rotation_angles(8), torch.arange(8) * math.pi / 8)


def test_action_to_pose():
    centres, angles_ = g.action_to_pose(torch.tensor([[3, 4, 2], [127, 0, 7]]), 8, image_size=(128, 128))
    assert centres.tolist() == [[3, 4], [127, 0]]
    assert torch.allclose(angles_, torch.tensor([math.pi / 4, 7 * math.pi / 8]))
    with pytest.raises(ValueError, match="rotation bins"):
        g.action_to_pose(torch.tensor([[3, 4, 8]]), 8)
    with pytest.raises(ValueError, match="action row"):
        g.action_to_pose(torch.tensor([[128, 4, 0]]), 8, image_size=(128, 128))


def test_workspace_pixel_metric_round_trip():
    ws = g.Workspace()
    assert ws.resolution == pytest.approx(0.003125)
    rc = torch.stack(torch.meshgrid(torch.arange(128), torch.arange(128), indexing="ij"), -1)
    assert torch.equal(ws.metric_to_pixel(ws.pixel_to_metric(rc)), rc)
    assert np.allclose(ws.pixel_to_metric([0, 127]), [0.2 + 0.0015625, 0.2 - 0.0015625])
    assert ws.metric_to_pixel(np.array([0.4, 0.0])).tolist() == [64, 64]  # numpy in, numpy out
    assert isinstance(ws.metric_to_pixel([0.4, 0.0]), np.ndarray)
    with pytest.raises(ValueError, match="outside the workspace"):
        ws.metric_to_pixel([0.61, 0.0])
    assert ws.metric_to_pixel([0.61, -0.3], clamp=True).tolist() == [127, 0]


# ------------------------------------------------------------------------------------------
# bad input
# ------------------------------------------------------------------------------------------
@pytest.mark.parametrize(
    "call, match",
    [
        (lambda x: g.crop(x[0, 0], torch.tensor([1, 1]), 0.0, 4), "images must be"),
        (lambda x: g.crop(x, torch.tensor([1.0, 1.0]), 0.0, 4), "centers must have an integer dtype"),
        (lambda x: g.crop(x, torch.tensor([1, 1, 1]), 0.0, 4), r"centers must be a \[\*B, 2\]"),
        (lambda x: g.crop(x, torch.tensor([H, 1]), 0.0, 4), r"centers row must lie in \[0, 48\)"),
        (lambda x: g.crop(x, torch.tensor([1, -1]), 0.0, 4), r"centers col must lie"),
        (lambda x: g.crop(x, torch.tensor([1, 1]), float("inf"), 4), "angles must be finite"),
        (lambda x: g.crop(x, torch.tensor([1, 1]), 0.0, 0), "size must be a positive int"),
        (lambda x: g.crop(x, torch.tensor([1, 1]), 0.0, 4, mode="cubic"), "mode must be one of"),
        (lambda x: g.crop(x, torch.zeros(3, 2, dtype=torch.long), torch.zeros(4), 4), "do not broadcast"),
        (lambda x: g.paste(x, torch.zeros(2, 4, 5), torch.tensor([1, 1]), 0.0), "patches must be square"),
        (lambda x: g.paste(x, torch.zeros(3, 4, 4), torch.tensor([1, 1]), 0.0), "channels"),
        (lambda x: g.paste(x, torch.zeros(2, 4, 4, dtype=torch.float64), torch.tensor([1, 1]), 0.0), "dtype"),
        (lambda x: g.center_crop(x, 100), "center_crop needs"),
    ],
)
def test_bad_input_raises_clear_value_errors(call, match):
    with pytest.raises(ValueError, match=match):
        call(scene(0, batch=(1,)))


def test_flat_index_and_action_are_inverse_in_the_q_map_order():
    from ldm_rl.geometry import action_to_flat, flat_to_action

    g = torch.Generator().manual_seed(0)
    r, h, w = 8, 16, 12
    index = torch.randint(0, r * h * w, (500,), generator=g)
    action = flat_to_action(index, h, w)
    assert action.dtype == torch.int64 and action.shape == (500, 3)
    assert torch.equal(action_to_flat(action, h, w), index)
    q = torch.randn(2, r, h, w, generator=g)
    row, col, rot = flat_to_action(q.flatten(1).argmax(1), h, w).unbind(-1)  # the order of a flattened map
    assert torch.equal(q[torch.arange(2), rot, row, col], q.flatten(1).amax(1))


def test_flat_index_conversions_refuse_floats_and_wrong_widths():
    from ldm_rl.geometry import action_to_flat, flat_to_action

    with pytest.raises(ValueError, match="integer tensor of flat indices"):
        flat_to_action(torch.tensor([1.0]), 4, 4)
    with pytest.raises(ValueError, match=r"\[\*B, 3\].*\(5, 2\)"):
        action_to_flat(torch.zeros(5, 2, dtype=torch.long), 4, 4)
    with pytest.raises(ValueError, match="integer tensor"):
        action_to_flat(torch.zeros(5, 3), 4, 4)


@pytest.mark.parametrize("seed", range(3))
def test_shift_moves_each_image_by_its_own_offset_and_fills_the_border_with_zeros(seed):
    gen = torch.Generator().manual_seed(seed)
    images = torch.rand(5, 2, 11, 9, generator=gen) + 0.5  # no zeros of its own
    offsets = torch.randint(-4, 5, (5, 2), generator=gen)
    offsets[0] = 0
    out = g.shift(images, offsets)
    assert torch.equal(out[0], images[0])  # a zero offset is the identity
    for row, (dr, dc) in enumerate(offsets.tolist()):
        for r in range(11):
            for c in range(9):
                sr, sc = r - dr, c - dc
                want = images[row, :, sr, sc] if 0 <= sr < 11 and 0 <= sc < 9 else torch.zeros(2)
                assert torch.equal(out[row, :, r, c], want), (row, r, c)
    # shifting back recovers the pixels that stayed inside, exactly
    back = g.shift(out, -offsets)
    kept = g.shift(g.shift(torch.ones_like(images), offsets), -offsets) > 0
    assert torch.equal(back[kept], images[kept]) and kept.float().mean() < 1
    with pytest.raises(ValueError, match=r"offsets must be \[5, 2\] int"):
        g.shift(images, offsets.float())
    with pytest.raises(ValueError, match=r"offsets must be \[5, 2\] int"):
        g.shift(images, offsets[:, :1])


@pytest.mark.parametrize("size", [24, 64])
def test_mirror_crops_is_an_involution_that_keeps_the_action_pixel_and_mirrors_about_it(size):
    gen = torch.Generator().manual_seed(size)
    crops = torch.rand(4, 2, size, size, generator=gen)
    rows, cols = torch.tensor([False, True, False, True]), torch.tensor([False, False, True, True])
    out = g.mirror_crops(crops, rows, cols)
    c = size // 2
    assert torch.equal(out[0], crops[0])
    assert torch.equal(out[:, :, c, c], crops[:, :, c, c])  # the action pixel stays
    for i, j in ((c - 5, c + 3), (1, size - 1), (c + 7, 2)):  # pixel (i, j) lies at offset (i − c, j − c)
        mi, mj = (size - i) % size, (size - j) % size  # the mirrored offset
        assert torch.equal(out[1, :, i, j], crops[1, :, mi, j])
        assert torch.equal(out[2, :, i, j], crops[2, :, i, mj])
        assert torch.equal(out[3, :, i, j], crops[3, :, mi, mj])
    assert torch.equal(g.mirror_crops(out, rows, cols), crops)  # its own inverse
    # the half turn of a crop is its 180° rotation about the action pixel (rot90 twice), but for row / column 0
    half = g.mirror_crops(crops, torch.ones(4, dtype=torch.bool), torch.ones(4, dtype=torch.bool))
    turned = torch.rot90(crops, 2, (-2, -1)).roll((1, 1), (-2, -1))
    assert torch.equal(half[..., 1:, 1:], turned[..., 1:, 1:])
    with pytest.raises(ValueError, match=r"even d, got \(4, 2, 5, 5\)"):
        g.mirror_crops(torch.zeros(4, 2, 5, 5), rows, cols)
    with pytest.raises(ValueError, match=r"rows must be a \[4\] bool tensor"):
        g.mirror_crops(crops, rows.long(), cols)


def _scene(*boxes, size=24):
    """[1, 1, size, size] heightmap of axis-aligned boxes (row0, col0, side, height m)."""
    image = torch.zeros(1, 1, size, size)
    for r, c, side, h in boxes:
        image[..., r:r + side, c:c + side] = h
    return image


def test_raise_tallest_lifts_the_whole_tallest_object_and_nothing_else():
    """A 2-stack whose lower cube sticks out (0.04 / 0.08 m), a loose cube apart: the stack's every pixel goes up by
    the row's lift, the loose cube and the table stay; a zero lift and an empty scene are the identity."""
    stack = _scene((3, 3, 6, 0.04), (4, 4, 4, 0.08), (15, 15, 5, 0.04))[0]  # the top cube's footprint inside the lower
    empty = torch.zeros(1, 24, 24)
    images = torch.stack([stack, stack, empty])
    out = g.raise_tallest(images, torch.tensor([0.08, 0.0, 0.04]), floor=0.02)
    tower = torch.zeros(1, 24, 24, dtype=torch.bool)
    tower[:, 3:9, 3:9] = True
    assert torch.equal(out[0][tower], stack[tower] + 0.08)
    assert torch.equal(out[0][~tower], stack[~tower])  # the loose cube and the table are untouched
    assert torch.equal(out[1], stack) and torch.equal(out[2], empty)


def test_raise_tallest_with_a_band_lifts_the_top_cube_and_leaves_what_leans_on_the_stack():
    """A 2-stack with a ledge and a cube leaning on its side: without a band the three are one region and all rise;
    with a band of half a cube only the top cube's footprint rises (as if cubes were slid in under it)."""
    image = _scene((3, 3, 6, 0.04), (4, 4, 4, 0.08), (3, 9, 5, 0.04))  # the leaning cube touches the lower one
    lift = torch.tensor([0.08])
    whole = g.raise_tallest(image, lift, floor=0.02)
    top = g.raise_tallest(image, lift, floor=0.02, band=0.02)
    assert torch.equal((whole - image).abs() > 1e-9, image > 0.02)
    footprint = _scene((4, 4, 4, 1.0)) > 0
    assert torch.equal((top - image).abs() > 1e-9, footprint)
    torch.testing.assert_close(top[footprint], image[footprint] + 0.08)
    with pytest.raises(ValueError, match="band must be a positive number of metres or None, got 0"):
        g.raise_tallest(image, lift, floor=0.02, band=0)


@pytest.mark.parametrize("seed", range(3))
def test_raise_tallest_follows_diagonal_contact_and_stops_at_the_floor(seed):
    """Property: on random scenes of separated cubes, exactly the cubes 8-connected to the highest pixel through
    pixels above the floor rise (a cube touching the tallest at a corner rises with it), and nothing else moves."""
    gen = torch.Generator().manual_seed(seed)
    heights = (torch.randint(1, 4, (4,), generator=gen) * 0.04).tolist()
    heights[0] = 0.2  # the tallest
    image = _scene((2, 2, 4, heights[0]), (6, 6, 4, heights[1]),  # touches the tallest at one corner pixel
                   (2, 14, 4, heights[2]), (14, 2, 4, heights[3]))  # apart (≥ 4 px of table between)
    out = g.raise_tallest(image, torch.tensor([0.04]), floor=0.02)
    rose = (out - image).abs() > 1e-9
    want = _scene((2, 2, 4, 1.0), (6, 6, 4, 1.0)) > 0
    assert torch.equal(rose, want)
    with pytest.raises(ValueError, match=r"lift must be a \[1\] tensor"):
        g.raise_tallest(image, torch.tensor([0.04, 0.04]), floor=0.02)
    with pytest.raises(ValueError, match="lift must be >= 0"):
        g.raise_tallest(image, torch.tensor([-0.04]), floor=0.02)
    with pytest.raises(ValueError, match=r"heightmaps must be \[B, 1, H, W\]"):
        g.raise_tallest(image.expand(1, 2, 24, 24), torch.tensor([0.04]), floor=0.02)
    with pytest.raises(ValueError, match=r"heightmaps must be \[B, 1, H, W\] float metres"):
        g.raise_tallest(image.long(), torch.tensor([0.04]), floor=0.02)


def test_quarter_turns_turn_each_image_by_its_own_count_exactly():
    images = torch.rand(6, 2, 9, 9, generator=torch.Generator().manual_seed(0))
    turns = torch.tensor([0, 1, 2, 3, 5, -1])
    out = g.quarter_turns(images, turns)
    for row, k in enumerate(turns.tolist()):
        assert torch.equal(out[row], images[row].rot90(k, (-2, -1)))
    assert not torch.equal(out[1], images[1])  # not vacuous: a turn moves pixels
    # four turns of a non-square image would change its shape: refused, as are float or misshaped counts
    with pytest.raises(ValueError, match="square"):
        g.quarter_turns(torch.rand(2, 1, 8, 9), torch.tensor([1, 2]))
    with pytest.raises(ValueError, match=r"turns must be \[6\] int"):
        g.quarter_turns(images, turns.float())
    with pytest.raises(ValueError, match=r"turns must be \[6\] int"):
        g.quarter_turns(images, turns[:3])
