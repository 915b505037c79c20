"""The agent's networks: Q FCN (rotation convention, exact quarter-turn equivariance, head routing,
the one-rotation training path) and V CNN (heads, batching); sizes of the paper presets; input checks."""

import math

import pytest
import torch

from ldm_rl import geometry as g
from ldm_rl.models.blocks import count_parameters, encode_heights
from ldm_rl.models.q_fcn import Q_PRESETS, QFCN, build_q_network, mask_empty_picks
from ldm_rl.models.v_cnn import V_PRESETS, VCNN, build_value_network
from policy_helpers import q_states, quarter_turn_maps

MAX_HEIGHT = 0.15
TINY = 0.125  # width of the networks in the tests that are not about the paper presets


@pytest.fixture(autouse=True)
def one_torch_thread():
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


def tiny_q(num_rotations: int = 8, seed: int = 0) -> QFCN:
    torch.manual_seed(seed)
    return build_q_network("lite", max_height=MAX_HEIGHT, num_rotations=num_rotations, width=TINY)


def tiny_v(seed: int = 0) -> VCNN:
    torch.manual_seed(seed)
    return build_value_network("lite", max_height=MAX_HEIGHT, width=TINY)


def states(n: int, seed: int = 0):
    return q_states(n, seed, max_layers=4)


# --------------------------------------------------------------------------------------------
# sizes and structure of the paper presets
# --------------------------------------------------------------------------------------------
def test_paper_presets_have_the_reference_parameter_counts_and_init():
    torch.manual_seed(0)
    q = build_q_network("paper", max_height=MAX_HEIGHT)
    assert count_parameters(q) == 8_417_110
    assert count_parameters(q.hand_encoder) == 6_969_892
    v = build_value_network("paper", max_height=MAX_HEIGHT)
    assert count_parameters(v) == 24_801_418
    assert (count_parameters(v.scene_trunk), count_parameters(v.hand_trunk)) == (1_213_760, 296_256)
    assert count_parameters(v.value_head) == count_parameters(v.reward_head) == 11_645_701
    for net in (q, v):
        assert not any(isinstance(m, torch.nn.modules.batchnorm._BatchNorm) for m in net.modules())
        slopes = {m.negative_slope for m in net.modules() if isinstance(m, torch.nn.LeakyReLU)}
        assert slopes == {0.01}
    # Q: xavier_normal_ (std √(2 / (fan_in + fan_out))); V: kaiming_normal_ fan_out (std gain / √fan_out)
    w = q.up_4.block.conv1.weight
    assert w.std().item() == pytest.approx(math.sqrt(2 / (256 * 9 + 128 * 9)), rel=0.05)
    w = v.value_head[0].weight
    assert w.std().item() == pytest.approx(math.sqrt(2 / (1 + 0.01**2)) / math.sqrt(256 * 9), rel=0.05)
    assert set(Q_PRESETS) == set(V_PRESETS) == {"paper", "lite"}
    assert count_parameters(build_q_network("lite", max_height=MAX_HEIGHT)) < count_parameters(q) / 3
    assert count_parameters(build_value_network("lite", max_height=MAX_HEIGHT)) < count_parameters(v) / 3


def test_unknown_preset_is_rejected():
    with pytest.raises(ValueError, match="preset 'huge'"):
        build_q_network("huge", max_height=MAX_HEIGHT)
    with pytest.raises(ValueError, match="preset 'huge'"):
        build_value_network("huge", max_height=MAX_HEIGHT)


# --------------------------------------------------------------------------------------------
# Q: rotation convention and equivariance
# --------------------------------------------------------------------------------------------
@pytest.mark.parametrize("num_rotations, grad", [(8, False), (8, True), (6, False)])
def test_q_maps_are_bit_exactly_equivariant_to_quarter_turns(num_rotations, grad):
    """Scene +90° and bin + R/2 <=> map +90° (and −90° / bin − R/2), bit for bit, both heads."""
    half = num_rotations // 2
    maps, plus, minus = quarter_turn_maps(tiny_q(num_rotations), grad)
    # pixels no rotated frame covers read -inf; a finite sentinel lets geometry.rotate carry them exactly
    maps, plus, minus = (t.nan_to_num(neginf=-1e30) for t in (maps, plus, minus))
    assert torch.equal(plus[:, :half], g.rotate(maps[:, half:], math.pi / 2))
    assert torch.equal(minus[:, half:], g.rotate(maps[:, :half], -math.pi / 2))
    # not vacuous: the maps differ between bins, and a quarter turn with the wrong bin shift is not a match
    assert not torch.allclose(maps[:, 0], maps[:, 1])
    assert not torch.equal(plus[:, :half], g.rotate(maps[:, :half], math.pi / 2))


def test_pixels_no_rotated_frame_covers_are_never_proposable():
    """Near the border at non-quarter bins the trunk saw nothing: Q is -inf there (a max never picks
    them), finite everywhere at quarter-turn bins and in the image's centre."""
    q = tiny_q(8)
    scene, in_hand, holding = states(2, seed=3)
    with torch.no_grad():
        maps = q(scene, in_hand, holding)
    assert torch.isfinite(maps[:, 0]).all() and torch.isfinite(maps[:, 4]).all()
    assert torch.isneginf(maps[:, 1]).any() and torch.isfinite(maps[:, :, 40:88, 40:88]).all()
    best = maps.flatten(1).argmax(1)
    assert torch.isfinite(maps.flatten(1).gather(1, best[:, None])).all()


def test_a_frame_margin_masks_the_band_at_each_gripper_frames_edge_and_keeps_the_equivariance():
    """frame_margin=m: at quarter-turn bins the m-pixel image border is -inf, the rest finite; at other bins the
    band runs along the rotated frame's edge (inside the image); quarter turns still commute bit for bit;
    a different margin gives the same weights and the same values wherever both are finite."""
    torch.manual_seed(0)
    q = QFCN(MAX_HEIGHT, 21, 8, 0.125, frame_margin=6)
    plain = QFCN(MAX_HEIGHT, 21, 8, 0.125)
    plain.load_state_dict(q.state_dict())
    scene, in_hand, holding = states(3, seed=5)
    with torch.no_grad():
        maps, reference = q(scene, in_hand, holding), plain(scene, in_hand, holding)
        plus = q(g.rotate(scene, math.pi / 2), in_hand, holding)
    for k in (0, 4):
        assert torch.isneginf(maps[:, k, :6]).all() and torch.isneginf(maps[:, k, :, -6:]).all()
        assert torch.isfinite(maps[:, k, 6:-6, 6:-6]).all()
    band = torch.isneginf(maps[:, 1]) & torch.isfinite(reference[:, 1])
    assert band.any() and not band[:, 30:98, 30:98].any()  # a band along the rotated edge, not in the centre
    both = torch.isfinite(maps)
    assert torch.equal(maps[both], reference[both]) and (both <= torch.isfinite(reference)).all()
    maps_, plus_ = (t.nan_to_num(neginf=-1e30) for t in (maps, plus))
    assert torch.equal(plus_[:, :4], g.rotate(maps_[:, 4:], math.pi / 2))
    with pytest.raises(ValueError, match="frame_margin must be an int in"):
        QFCN(MAX_HEIGHT, frame_margin=-1)


def test_a_padded_frame_keeps_every_pixel_proposable_at_every_rotation_and_the_equivariance():
    """frame_pad=p: the scene is rotated inside a (128 + 2p)-pixel frame. At 32 every pixel is finite at every bin
    (with an 8 px margin all but the 6 at each extreme corner); quarter turns still commute bit for bit; the
    training path reads the same values as the maps; frame_pad=0 builds the reference's tables."""
    from ldm_rl.models.q_fcn import _rotation_tables

    torch.manual_seed(0)
    q = build_q_network("lite", max_height=MAX_HEIGHT, width=TINY, frame_pad=32)
    margin = build_q_network("lite", max_height=MAX_HEIGHT, width=TINY, frame_pad=32, frame_margin=8)
    assert q.frame_size == 192 and tuple(q._scene_index.shape) == (8, 192 * 192)
    scene, in_hand, holding = states(2, seed=3)
    with torch.no_grad():
        maps, with_margin = q(scene, in_hand, holding), margin(scene, in_hand, holding)
    assert torch.isfinite(maps).all()
    corners = torch.isneginf(with_margin).any(1)  # [2, H, W]: -inf at some bin
    assert int(corners[0].sum()) == 4 * 6 and not corners[:, 4:-4].any() and not corners[:, :, 4:-4].any()
    maps, plus, minus = quarter_turn_maps(q)
    assert torch.equal(plus[:, :4], g.rotate(maps[:, 4:], math.pi / 2))
    assert torch.equal(minus[:, 4:], g.rotate(maps[:, :4], -math.pi / 2))
    n = 8
    gen = torch.Generator().manual_seed(1)
    action = torch.stack((torch.randint(0, 128, (n,), generator=gen), torch.randint(0, 128, (n,), generator=gen),
                          torch.arange(n)), -1)
    action[1] = torch.tensor([0, 127, 1])  # a corner outside bin 1's unpadded frame
    scene, in_hand, holding = states(n, seed=4)
    with torch.no_grad():
        maps = q(scene, in_hand, holding)
        values = q.action_values(scene, in_hand, holding, action)
    torch.testing.assert_close(values, maps[torch.arange(n), action[:, 2], action[:, 0], action[:, 1]], rtol=1e-5, atol=1e-6)
    for margin_px in (0, 8):
        plain, same = _rotation_tables(8, 128, margin_px), _rotation_tables(8, 128, margin_px, 128)
        assert all(torch.equal(a, b) for a, b in zip(plain, same))
    for bad in (-8, 12, 72, True):
        with pytest.raises(ValueError, match="frame_pad must be a multiple of 8 in \\[0, 64\\] pixels"):
            QFCN(MAX_HEIGHT, frame_pad=bad)
    with pytest.raises(ValueError, match="frame_pad=32 pads QFCN's rotated frames; architecture 'equivariant'"):
        build_q_network("lite", max_height=MAX_HEIGHT, frame_pad=32, architecture="equivariant")


def test_the_config_builds_the_padded_frame_and_refuses_it_where_there_is_none():
    from ldm_rl.config_schema import ConfigError, TrainPolicyConfig, validate_config
    from test_baselines import config, make_agent

    assert make_agent("fcdqn", "agent.q_frame_pad=16").policy.q_network.frame_size == 160
    for overrides, message in ((("agent.q_frame_pad=12",), "agent.q_frame_pad=12 must be a multiple of 8"),
                               (("agent.q_frame_pad=16", "agent.q_architecture=equivariant"),
                                "agent.q_frame_pad=16 pads QFCN's rotated frames")):
        with pytest.raises(ConfigError, match=message):
            validate_config(config("ldm", *overrides), TrainPolicyConfig)


def test_pick_min_height_masks_picks_on_nothing_and_nothing_else():
    """pick_min_height=h: each pick map is -inf at every rotation exactly on the pixels not above h (the table, a
    tray's floor) and equal to the plain map elsewhere; place maps, a scene with almost nothing above h and the
    training path (action_values) are untouched; a value outside [0, max_height) is refused by name."""
    torch.manual_seed(0)
    q = QFCN(MAX_HEIGHT, 21, 8, TINY, pick_min_height=0.015)
    plain = QFCN(MAX_HEIGHT, 21, 8, TINY)
    plain.load_state_dict(q.state_dict())
    scene = torch.zeros(3, 1, 128, 128)
    scene[:, :, 20:44, 30:60] = 0.04  # a block
    scene[:, :, 80:100, 80:100] = 0.01  # a tray floor: not above 1.5 cm
    scene[2] = 0.0
    scene[2, :, 60:62, 60:63] = 0.04  # 6 pixels above h, at most 48 entries: too few to mask
    in_hand, holding = torch.zeros(3, 1, 24, 24), torch.tensor([False, True, False])
    with torch.no_grad():
        maps, reference = q(scene, in_hand, holding), plain(scene, in_hand, holding)
    empty = (scene[0, 0] <= 0.015).expand(8, -1, -1)
    assert torch.isneginf(maps[0][empty]).all()
    assert torch.equal(maps[0][~empty], reference[0][~empty]) and torch.isfinite(maps[0][~empty]).any()
    assert torch.equal(maps[1:], reference[1:])  # the place map, and the scene with 6 pixels above h
    action = torch.tensor([[90, 90, 0], [90, 90, 0], [90, 90, 0]])
    with torch.no_grad():
        assert torch.isfinite(q.action_values(scene, in_hand, holding, action)).all()
    for bad in (-0.01, MAX_HEIGHT, True):
        with pytest.raises(ValueError, match="pick_min_height must be a number of metres in"):
            QFCN(MAX_HEIGHT, pick_min_height=bad)
    assert build_q_network("lite", max_height=MAX_HEIGHT, width=TINY, pick_min_height=0.02).pick_min_height == 0.02
    with pytest.raises(ValueError, match=r"mask_empty_picks needs maps \[N, R, H, W\], heightmap \[N, 1, H, W\]"):
        mask_empty_picks(maps[:2], scene, holding[:2], 0.015)


def _capture(q: QFCN):
    """Hooks recording the trunk inputs and the pick head's outputs (gripper frames), in batch order."""
    seen = {"inputs": [], "maps": []}
    hooks = [
        q.conv_1.register_forward_pre_hook(lambda _m, args: seen["inputs"].append(args[0].detach())),
        q.pick_head.register_forward_hook(lambda _m, _a, out: seen["maps"].append(out.detach())),
    ]
    return seen, hooks


def test_q_bin_k_is_the_gripper_frame_that_crop_sees_at_yaw_k_pi_over_r():
    """Trunk input of bin k = the scene as ``geometry.rotate(·, θ_k)`` / ``geometry.crop(·, a, θ_k)`` see it;
    ``Q[k, a]`` = the head's value at the gripper-frame pixel of a."""
    q, r = tiny_q(), 8
    scene, in_hand, _ = states(2, seed=2)
    holding = torch.zeros(2, dtype=torch.bool)
    seen, hooks = _capture(q)
    with torch.no_grad():
        maps = q(scene, in_hand, holding)
    for h in hooks:
        h.remove()
    x = encode_heights(scene, MAX_HEIGHT, 21)
    maps = maps.masked_fill(maps.isneginf(), 0.0)  # uncovered pixels (-inf) are where geometry.rotate reads 0
    inputs = torch.cat(seen["inputs"]).view(2, r, 128, 128)
    heads = torch.cat(seen["maps"]).view(2, r, 128, 128)
    thetas = g.rotation_angles(r, dtype=torch.float64)
    for k in range(r):
        expected_in = g.rotate(x, thetas[k].item(), mode="nearest")[:, 0]
        expected_q = g.rotate(heads[:, k : k + 1], -thetas[k].item(), mode="nearest")[:, 0]
        if k < r // 2:  # no quarter turn: the same samples as geometry.rotate
            assert torch.equal(inputs[:, k], expected_in) and torch.equal(maps[:, k], expected_q)
        else:  # quarter turn + residual: the same rotation, up to last-bit ties of the nearest pixel
            assert (inputs[:, k] == expected_in).float().mean() > 0.99
            assert (maps[:, k] == expected_q).float().mean() > 0.99
    # exact at yaw π/2: the trunk pixel p' = (col, 127 − row) of action a = (row, col) sees crop(x, a, π/2)
    k, d = r // 2, 9
    for row, col in [(40, 90), (64, 17), (100, 100)]:
        window = inputs[:, k, col - d // 2 : col + d // 2 + 1, 127 - row - d // 2 : 127 - row + d // 2 + 1]
        crop = g.crop(x, torch.tensor([row, col]), math.pi / 2, d, mode="nearest")[:, 0]
        assert torch.equal(window, crop)
        assert not torch.equal(window, torch.rot90(crop, 2, (-2, -1)))  # the opposite yaw differs
        assert torch.equal(maps[:, k, row, col], heads[:, k, col, 127 - row])


# --------------------------------------------------------------------------------------------
# Q: routing and the training path
# --------------------------------------------------------------------------------------------
def test_q_place_rows_use_the_hand_and_pick_rows_ignore_it():
    q = tiny_q()
    scene, in_hand, holding = states(4, seed=3)
    other_hand = torch.flip(in_hand, (-1,)) + 0.03
    with torch.no_grad():
        maps = q(scene, in_hand, holding)
        maps_other = q(scene, other_hand, holding)
        as_pick = q(scene, in_hand, torch.zeros_like(holding))
        alone = torch.cat([q(scene[i : i + 1], in_hand[i : i + 1], holding[i : i + 1]) for i in range(4)])
    pick, place = ~holding[:, 0], holding[:, 0]
    assert torch.equal(maps[pick], maps_other[pick])  # pick head: no dependence on the hand image
    assert not torch.allclose(maps[place], maps_other[place])  # place head: conditioned on the hand
    assert torch.equal(maps[pick], as_pick[pick])
    assert not torch.allclose(maps[place], as_pick[place])  # holding rows are routed to the other head
    torch.testing.assert_close(maps, alone, rtol=1e-5, atol=1e-6)  # routing keeps each sample in its row


def test_q_action_values_equal_the_maps_and_run_one_rotation_per_sample():
    q, n = tiny_q(), 10
    scene, in_hand, holding = states(n, seed=4)
    gen = torch.Generator().manual_seed(5)
    action = torch.stack(
        (torch.randint(0, 128, (n,), generator=gen), torch.randint(0, 128, (n,), generator=gen), torch.arange(n) % 8), -1
    )
    action[0] = torch.tensor([0, 0, 2])  # a corner outside the rotated frame: the map reads -inf, action_values 0
    with torch.no_grad():
        maps = q(scene, in_hand, holding)
    images = []
    hook = q.conv_1.register_forward_pre_hook(lambda _m, args: images.append(args[0].shape[0]))
    values = q.action_values(scene, in_hand, holding, action)
    hook.remove()
    assert sum(images) == n  # one trunk image per sample, not R
    expected = maps[torch.arange(n), action[:, 2], action[:, 0], action[:, 1]]
    assert torch.isneginf(expected[0])
    expected = expected.masked_fill(expected.isneginf(), 0.0)
    assert values.shape == (n,) and values.dtype == torch.float32
    torch.testing.assert_close(values.detach(), expected, rtol=1e-5, atol=1e-6)
    assert values[0].item() == 0.0 and expected[0].item() == 0.0
    with torch.no_grad():  # the inference path (channels_last, one dense hand conv per sample) agrees too
        torch.testing.assert_close(q.action_values(scene, in_hand, holding, action), expected, rtol=1e-5, atol=1e-6)
    assert not torch.allclose(expected, expected[1])  # different actions, different values
    values.sum().backward()
    for part in (q.pick_head, q.place_head, q.hand_encoder, q.conv_1):
        assert any(p.grad is not None and p.grad.abs().sum() > 0 for p in part.parameters())


@pytest.mark.parametrize("radius, exact", [(QFCN.WINDOW_RADIUS, True), (QFCN.WINDOW_RADIUS - 1, False)])
def test_q_action_values_window_is_the_whole_receptive_field_at_the_frame_border(radius, exact):
    """action_values runs up_1 and the heads on a window around each action: its values and parameter
    gradients equal the full maps' at the frame's corners and edges (where the window leaves the frame),
    for pick and place rows; one pixel less of window is no longer exact."""
    q, n = tiny_q(seed=3), 12
    q.WINDOW_RADIUS = radius
    scene, in_hand, _ = states(n, seed=11)
    holding = torch.arange(n) % 2 == 1  # pick and place rows
    pixels = torch.tensor([[0, 0], [0, 127], [127, 0], [127, 127], [1, 64], [126, 64], [64, 2], [64, 125],
                           [3, 3], [124, 125], [64, 64], [40, 90]])
    bins = torch.tensor([0, 4] * (n // 2))  # quarter turns: the rotated frame covers every pixel
    action = torch.cat((pixels, bins.unsqueeze(1)), 1)
    values = q.action_values(scene, in_hand, holding, action)
    values.sum().backward()
    window_grads = [p.grad.clone() for p in q.parameters()]
    q.zero_grad()
    maps = q(scene, in_hand, holding)
    expected = maps[torch.arange(n), bins, pixels[:, 0], pixels[:, 1]]
    expected.sum().backward()
    close = torch.allclose(values, expected, rtol=1e-5, atol=1e-6)
    assert close == exact
    if exact:
        for window_grad, p in zip(window_grads, q.parameters()):
            torch.testing.assert_close(window_grad, p.grad, rtol=1e-4, atol=1e-7)


def test_raw_and_replay_decoded_heights_give_identical_outputs():
    q, v = tiny_q(), tiny_v()
    scene, in_hand, holding = states(2, seed=6)
    scene[0, 0, :5, :5] = 1.0  # above max_height: clamps to the top class
    decoded = [g.classes_to_heights(g.heights_to_classes(t, MAX_HEIGHT, 21), MAX_HEIGHT, 21) for t in (scene, in_hand)]
    assert not torch.equal(decoded[0], scene)
    with torch.no_grad():
        assert torch.equal(q(scene, in_hand, holding), q(*decoded, holding))
        assert torch.equal(v(scene, in_hand), v(*decoded))


def test_q_keeps_leading_batch_dims_and_empty_batches():
    q = tiny_q()
    scene, in_hand, holding = states(4, seed=7)
    with torch.no_grad():
        flat = q(scene, in_hand, holding[:, 0])
        nested = q(scene.view(2, 2, 1, 128, 128), in_hand.view(2, 2, 1, 24, 24), holding.view(2, 2, 1))
        empty = q(scene[:0], in_hand[:0], holding[:0])
    assert flat.shape == (4, 8, 128, 128) and nested.shape == (2, 2, 8, 128, 128) and empty.shape == (0, 8, 128, 128)
    torch.testing.assert_close(nested.reshape(4, 8, 128, 128), flat, rtol=1e-5, atol=1e-6)
    action = torch.tensor([[[3, 4, 5], [6, 7, 1]]])
    assert q.action_values(scene[:2].unsqueeze(0), in_hand[:2].unsqueeze(0), holding[:2].unsqueeze(0), action).shape == (1, 2)


# --------------------------------------------------------------------------------------------
# V
# --------------------------------------------------------------------------------------------
def test_v_value_and_reward_heads_share_the_trunk_and_batch_any_way():
    v = tiny_v()
    scene, in_hand, _ = states(6, seed=8)
    with torch.no_grad():
        value = v(scene, in_hand)
        value2, reward = v.value_and_reward(scene, in_hand)
        nested = v(scene.view(2, 3, 1, 128, 128), in_hand.view(2, 3, 1, 24, 24))
        other_hand = v(scene, in_hand.flip(-2) + 0.03)
        v.CHUNK = 4  # chunked inference gives the same values as one pass
        chunked = v(scene, in_hand)
    assert value.shape == reward.shape == (6, 1) and nested.shape == (2, 3, 1)
    assert torch.equal(value, value2)
    assert not torch.allclose(value, reward)  # separate heads
    assert not torch.allclose(value, other_hand)  # the in-hand image matters
    torch.testing.assert_close(nested.reshape(6, 1), value, rtol=1e-5, atol=1e-6)
    torch.testing.assert_close(chunked, value, rtol=1e-5, atol=1e-6)
    value, reward = v.value_and_reward(scene, in_hand)
    (value.sum() + reward.sum()).backward()
    assert all(p.grad is not None for p in v.parameters())


def test_a_termination_head_composes_v_from_the_reward_where_the_episode_ends():
    torch.manual_seed(3)
    v = build_value_network("lite", max_height=MAX_HEIGHT, width=TINY, termination_head=True)
    plain = tiny_v()
    assert sum(p.numel() for p in v.parameters()) > sum(p.numel() for p in plain.parameters())
    scene, in_hand, _ = states(5, seed=2)
    with torch.no_grad():
        going_on, reward, logit = v.heads(scene, in_hand)
        value = v(scene, in_hand)
        value2, reward2 = v.value_and_reward(scene, in_hand)
        # a sure end is worth the reward received, a sure continuation the value of going on
        for bias, expected in ((40.0, reward), (-40.0, going_on)):
            v.termination_head[-1].bias.fill_(bias)
            torch.testing.assert_close(v(scene, in_hand), expected)
    t = torch.sigmoid(logit)
    torch.testing.assert_close(value, t * reward + (1 - t) * going_on)
    assert torch.equal(value, value2) and torch.equal(reward, reward2)
    assert not torch.allclose(value, going_on)  # the composition is not the value head alone
    assert len(plain.heads(scene, in_hand)) == 2 and plain.termination_head is None
    with pytest.raises(ValueError, match="termination_head must be a bool, got 'yes'"):
        VCNN(MAX_HEIGHT, termination_head="yes")


def test_a_log_scale_v_is_the_exponential_of_its_head_and_starts_near_its_floor():
    torch.manual_seed(3)
    v = build_value_network("lite", max_height=MAX_HEIGHT, width=TINY, value_log_floor=0.01)
    scene, in_hand, _ = states(5, seed=2)
    with torch.no_grad():
        value = v(scene, in_hand)
        value2, reward = v.value_and_reward(scene, in_hand)
        heads = v.heads(scene, in_hand)
        raw = v.value_head(v._features(*(encode_heights(x, v.max_height, v.num_classes) for x in (scene, in_hand))))
    torch.testing.assert_close(value, raw.exp())  # V is the exponential of the value head, so it is positive
    assert torch.equal(value, value2) and torch.equal(value, heads[0]) and torch.equal(reward, heads[1])
    assert (value > 0).all() and (value.log() - math.log(0.01)).abs().max() < 1.0  # starts near the floor
    assert tiny_v().value_log_floor is None
    for bad in (0.0, 1.0, True, "0.01"):
        with pytest.raises(ValueError, match=rf"value_log_floor must be null .* got {bad!r}"):
            VCNN(MAX_HEIGHT, value_log_floor=bad)
    with pytest.raises(ValueError, match="value_log_floor=0.01 cannot be combined with termination_head=True"):
        VCNN(MAX_HEIGHT, termination_head=True, value_log_floor=0.01)


# --------------------------------------------------------------------------------------------
# input validation
# --------------------------------------------------------------------------------------------
GOOD = {
    "heightmap": torch.zeros(2, 1, 128, 128),
    "in_hand": torch.zeros(2, 1, 24, 24),
    "holding": torch.zeros(2, 1, dtype=torch.bool),
    "action": torch.tensor([[1, 2, 0], [3, 4, 7]]),
}


@pytest.mark.parametrize(
    "field, value, message",
    [
        ("heightmap", torch.zeros(2, 1, 64, 64), r"heightmap must be \[\*B, 1, 128, 128\]"),
        ("heightmap", torch.zeros(2, 1, 128, 128, dtype=torch.uint8), "heightmap.*dtype torch.uint8"),
        ("heightmap", torch.full((2, 1, 128, 128), float("nan")), "heightmap must be finite"),
        ("in_hand", torch.zeros(3, 1, 24, 24), "in_hand must have batch shape"),
        ("in_hand", torch.full((2, 1, 24, 24), float("inf")), "in_hand must be finite"),
        ("holding", torch.zeros(2, 1), "holding must be bool"),
        ("holding", torch.zeros(2, 2, dtype=torch.bool), "holding must be bool.*shape"),
        ("action", torch.tensor([[1.0, 2.0, 0.0], [1.0, 2.0, 0.0]]), "action must be an integer"),
        ("action", torch.tensor([1, 2, 0]), "action must be an integer"),
        ("action", torch.tensor([[1, 2, 8], [1, 2, 0]]), r"rot in \[0, 8\)"),
        ("action", torch.tensor([[1, 128, 0], [1, 2, 0]]), r"row, col in \[0, 128\)"),
    ],
)
def test_q_rejects_bad_inputs_with_one_line_messages(field, value, message):
    q = tiny_q()
    inputs = {**GOOD, field: value}
    with pytest.raises(ValueError, match=message) as info:
        q.action_values(**inputs)
    assert "\n" not in str(info.value)
    if field != "action":
        with pytest.raises(ValueError, match=message):
            q(inputs["heightmap"], inputs["in_hand"], inputs["holding"])


@pytest.mark.parametrize(
    "field, value, message",
    [
        ("heightmap", torch.zeros(2, 128, 128), "heightmap must be"),
        ("in_hand", torch.zeros(2, 1, 24, 24, dtype=torch.int64), "in_hand.*dtype"),
        ("in_hand", torch.zeros(1, 1, 24, 24), "in_hand must have batch shape"),
    ],
)
def test_v_rejects_bad_inputs(field, value, message):
    v = tiny_v()
    inputs = {"heightmap": GOOD["heightmap"], "in_hand": GOOD["in_hand"], field: value}
    with pytest.raises(ValueError, match=message):
        v(**inputs)
    with pytest.raises(ValueError, match=message):
        v.value_and_reward(**inputs)


def test_constructor_arguments_are_checked():
    with pytest.raises(ValueError, match="max_height"):
        QFCN(max_height=0.0)
    with pytest.raises(ValueError, match="num_classes"):
        VCNN(MAX_HEIGHT, num_classes=1)
    with pytest.raises(ValueError, match="num_rotations"):
        QFCN(MAX_HEIGHT, num_rotations=0)
    with pytest.raises(ValueError, match="width"):
        VCNN(MAX_HEIGHT, width=-1.0)


def test_head_channels_set_the_heads_hidden_units_and_default_to_eight_scaled_by_the_width():
    assert build_q_network("lite", max_height=MAX_HEIGHT, width=0.25).head_channels == 2  # runs before the key
    q = build_q_network("lite", max_height=MAX_HEIGHT, width=0.25, head_channels=8)
    assert q.pick_head[0].weight.shape[0] == q.place_head[0].weight.shape[0] == 8 == q.place_head[2].weight.shape[1]
    assert build_q_network("paper", max_height=MAX_HEIGHT).head_channels == 8  # the reference's at width 1
    for bad in (0, 2.0, True):
        with pytest.raises(ValueError, match=f"head_channels must be a positive int or None .*got {bad!r}"):
            QFCN(MAX_HEIGHT, width=0.25, head_channels=bad)



def test_q_heads_benchmark_tells_a_flat_head_from_one_running_on_the_leaky_slope():
    """benchmarks/q_heads.py: per hidden unit the share of pixels where it is positive, and the map's spread over
    object pixels: units far below 0 still give a map that varies (slope 0.01), units held at 0 give a flat one."""
    from benchmark_loader import load_benchmark

    bench = load_benchmark("q_heads")
    heightmap, in_hand, _ = q_states(2, seed=3)
    picking = (heightmap, in_hand, torch.zeros(2, 1, dtype=torch.bool))
    torch.manual_seed(0)
    q = build_q_network("lite", max_height=MAX_HEIGHT, width=0.25, head_channels=2).eval()
    hidden = q.pick_head[0]
    with torch.no_grad():
        hidden.bias.fill_(-50.0)  # both units off everywhere, their inputs still weighted
        shares, spread = bench.head_report(q, picking, 0.015)
        assert shares == [0.0, 0.0] and spread > 1e-3
        hidden.weight.zero_()  # off and constant: the map is the output bias plus a constant
        shares, spread = bench.head_report(q, picking, 0.015)
        assert shares == [0.0, 0.0] and spread < 1e-5
        hidden.bias.fill_(1.0)
        shares, _ = bench.head_report(q, picking, 0.015)
        assert shares == [1.0, 1.0]
