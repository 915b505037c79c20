"""LookaheadLoss: batched targets equal per-sample ones, terminal rows, target networks, gradients."""

from __future__ import annotations

import pytest
import torch
from torchrl.objectives import HardUpdate

from ldm_rl import geometry
from ldm_rl.objectives import LookaheadLoss, draw_value_augmentation
from ldm_rl.models.v_cnn import build_value_network
from policy_helpers import MAX_HEIGHT, tiny_networks, transitions

# these tests build the loss alone; the agents pair it with TargetSync (tests/test_target_sync.py)
pytestmark = pytest.mark.filterwarnings("ignore:No target network updater has been associated:UserWarning")


def make_loss(seed=0, **kwargs):
    q, dynamics, value = tiny_networks(seed)
    return LookaheadLoss(q, dynamics, value, **{"gamma": 0.9, "num_target_candidates": 3, "chunk_size": 5, **kwargs})


def test_batched_targets_equal_per_sample_targets():
    loss = make_loss()
    batch = transitions(6, terminated=torch.tensor([[False], [True], [False], [False], [True], [False]]))
    q_all, v_all = loss.targets(batch)
    rows = [loss.targets(batch[i : i + 1]) for i in range(6)]
    torch.testing.assert_close(q_all, torch.cat([r[0] for r in rows]))
    torch.testing.assert_close(v_all, torch.cat([r[1] for r in rows]))


def test_terminal_targets_are_the_reward_and_live_ones_bootstrap():
    loss = make_loss()
    batch = transitions(4, terminated=torch.tensor([[True], [True], [False], [False]]))
    q_t, v_t = loss.targets(batch)
    reward = batch["next", "reward"]
    assert torch.equal(q_t[:2], reward[:2]) and torch.equal(v_t[:2], reward[:2])
    q, dynamics, value = loss.q_network, loss.dynamics, loss.value_network
    with torch.no_grad(), loss.target_networks():
        q_map = q.eval()(batch["next", "heightmap"][2:], batch["next", "in_hand"][2:], batch["next", "holding"][2:])
    torch.testing.assert_close(q_t[2:], reward[2:] + 0.9 * q_map.flatten(1).amax(1, keepdim=True))


def test_forward_trains_q_and_v_but_not_the_ldm_and_writes_priorities():
    loss = make_loss()
    batch = transitions(5)
    out = loss(batch)
    total = out["loss_q"] + out["loss_value"] + out["loss_reward"]
    total.backward()
    assert batch["td_error"].shape == (5,) and (batch["td_error"] >= 0).all()
    assert all(p.grad is not None for p in loss.q_network.parameters())
    assert any(p.grad is not None and p.grad.abs().sum() > 0 for p in loss.value_network.parameters())
    assert all(p.grad is None for p in loss.dynamics.parameters())


def test_target_networks_lag_until_the_hard_update():
    loss = make_loss()
    updater = HardUpdate(loss, value_network_update_interval=1)  # copies every 2nd step()
    batch = transitions(4, terminated=torch.zeros(4, 1, dtype=torch.bool))
    before = loss.targets(batch)[1]
    with torch.no_grad():
        for p in loss.value_network.parameters():
            p.add_(0.05)
    assert torch.equal(loss.targets(batch)[1], before)  # the target copy did not move
    updater.step()
    assert torch.equal(loss.targets(batch)[1], before)
    updater.step()
    assert not torch.equal(loss.targets(batch)[1], before)


def test_importance_weights_scale_the_losses():
    loss = make_loss()
    batch = transitions(4)
    plain = loss(batch.clone())["loss_q"]
    batch["priority_weight"] = torch.full((4,), 0.5)
    torch.testing.assert_close(loss(batch)["loss_q"], 0.5 * plain)


def test_bad_input():
    loss = make_loss()
    with pytest.raises(ValueError, match="missing keys"):
        loss(transitions(2).exclude(("next", "reward")))
    with pytest.raises(ValueError, match="gamma"):
        make_loss(gamma=1.5)


def test_targets_are_clamped_into_the_return_range():
    loss = make_loss(target_range=(0.0, 0.05))
    batch = transitions(6)
    q_t, v_t = loss.targets(batch)
    assert (q_t <= 0.05).all() and (v_t <= 0.05).all() and (q_t >= 0).all()
    free = make_loss()
    assert (free.targets(batch)[1] > 0.05).any()  # the clamp is what bounded them
    with pytest.raises(ValueError, match="target_range"):
        make_loss(target_range=(1.0, 0.0))


def test_out_keys_name_what_forward_returns():
    loss = make_loss()
    assert set(loss(transitions(3)).keys()) == set(loss.out_keys)
    assert "LookaheadLoss" in repr(loss)


def _per_candidate_scores(loss, batch):
    """Target-LDM predictions of the target proposals, scored by the (target V, online V): [B, N] each."""
    from ldm_rl.planning.sampling import sample_candidates
    from ldm_rl.planning.lookahead import lookahead

    state = [batch["next", key] for key in ("heightmap", "in_hand", "holding")]
    with torch.no_grad():
        with loss.target_networks():
            q_map = loss.q_network.eval()(*state)
            cands = sample_candidates(q_map, loss.num_target_candidates, **loss.target_proposal)
            result = lookahead(loss.dynamics, loss.value_network, *state, cands, with_states=True)
        online = loss.value_network.eval()(result.next_heightmap.flatten(0, 1), result.next_in_hand.flatten(0, 1))
    return result.values, online.reshape(result.values.shape)


def test_double_value_scores_the_online_choice_with_the_target_network():
    loss = make_loss(double_value=True)
    plain = make_loss(double_value=False)
    batch = transitions(6, terminated=torch.zeros(6, 1, dtype=torch.bool))
    # online == target weights: choosing with one and scoring with the other is the plain max
    torch.testing.assert_close(loss.targets(batch)[1], plain.targets(batch)[1])
    with torch.no_grad():  # the online V drifts away from its target copy
        for p in loss.value_network.parameters():
            p.mul_(-1.5)
    target_v, online_v = _per_candidate_scores(loss, batch)
    chosen = target_v.gather(1, online_v.argmax(1, keepdim=True))
    torch.testing.assert_close(loss.targets(batch)[1], batch["next", "reward"] + 0.9 * chosen)
    assert (chosen <= target_v.amax(1, keepdim=True)).all() and (chosen < target_v.amax(1, keepdim=True)).any()


def test_lookahead_q_target_is_the_value_target():
    loss = make_loss(q_target="lookahead")
    batch = transitions(5, terminated=torch.tensor([[True], [False], [False], [True], [False]]))
    y_q, y_v = loss.targets(batch)
    assert torch.equal(y_q, y_v)
    with pytest.raises(ValueError, match="q_target"):
        make_loss(q_target="double")


def test_bf16_autocast_gives_float32_targets_close_to_float32_and_trainable_losses():
    loss = make_loss(double_value=True)
    batch = transitions(4, terminated=torch.tensor([[False], [True], [False], [False]]))
    q_ref, v_ref = loss.targets(batch)
    with torch.autocast("cpu", dtype=torch.bfloat16):
        q_t, v_t = loss.targets(batch)
        out = loss(batch.clone())
    assert q_t.dtype == v_t.dtype == torch.float32
    torch.testing.assert_close(v_t, v_ref, atol=0.05, rtol=0.05)  # bf16 keeps ~3 significant digits
    total = out["loss_q"] + out["loss_value"] + out["loss_reward"]
    assert torch.isfinite(total) and total.requires_grad
    total.backward()
    assert all(p.grad is not None for p in loss.q_network.parameters() if p.requires_grad)


@pytest.mark.parametrize("q_target", ["max", "lookahead"])
def test_return_lower_bound_raises_both_targets_to_the_collected_return(q_target):
    plain, bounded = make_loss(q_target=q_target), make_loss(q_target=q_target, return_lower_bound=True)
    batch = transitions(4, terminated=torch.tensor([[False], [False], [True], [False]]))
    q_plain, v_plain = plain.targets(batch)
    # one bound far above, one far below, one -inf (truncated episode), one on a terminal row
    batch.set("return_to_go", torch.tensor([[0.97], [-0.5], [float("-inf")], [0.99]]))
    q_bound, v_bound = bounded.targets(batch)
    expected_v = torch.maximum(v_plain, batch["return_to_go"])
    torch.testing.assert_close(v_bound, expected_v)
    torch.testing.assert_close(q_bound, torch.maximum(q_plain, batch["return_to_go"]))
    assert v_bound[0] > v_plain[0] and torch.equal(v_bound[1:3], v_plain[1:3])
    with pytest.raises(KeyError, match="needs 'return_to_go' in the batch: sample from FrameReplay"):
        bounded.targets(transitions(2))


def _cached_and_plain(**kwargs):
    return make_loss(bootstrap_cache=64, **kwargs), make_loss(**kwargs)


@pytest.mark.parametrize("double_value", [False, True])
def test_cached_targets_equal_fresh_ones_until_and_after_a_target_copy(double_value):
    from ldm_rl.objectives import TargetSync

    cached, plain = _cached_and_plain(double_value=double_value, q_target="max")
    first = transitions(6, seed=0, terminated=torch.zeros(6, 1, dtype=torch.bool))
    first["index"] = torch.arange(6)
    second = transitions(6, seed=5, terminated=torch.zeros(6, 1, dtype=torch.bool))
    second["index"] = torch.tensor([4, 5, 6, 7, 8, 9])  # rows 4, 5: same index, another next state (slot reused)
    for batch in (first, second, first, second):
        for got, want in zip(cached.targets(batch), plain.targets(batch)):
            torch.testing.assert_close(got, want, rtol=1e-5, atol=1e-6)
    assert cached.bootstrap_cache.hits > 0
    updaters = [TargetSync(loss, interval=1) for loss in (cached, plain)]
    for loss in (cached, plain):  # the online networks move on; V's online choice changes at once
        with torch.no_grad():
            for p in loss.value_network.parameters():
                p.mul_(-1.5)
            for p in loss.q_network.parameters():
                p.mul_(0.5)
    for got, want in zip(cached.targets(first), plain.targets(first)):
        torch.testing.assert_close(got, want, rtol=1e-5, atol=1e-6)
    for updater in updaters:  # the copy clears the cache: the new target networks are used
        updater.sync()
    assert len(cached.bootstrap_cache) == 0
    for got, want in zip(cached.targets(first), plain.targets(first)):
        torch.testing.assert_close(got, want, rtol=1e-5, atol=1e-6)


def test_cached_rows_skip_the_target_networks():
    cached = make_loss(bootstrap_cache=64)
    batch = transitions(4, terminated=torch.zeros(4, 1, dtype=torch.bool))
    batch["index"] = torch.arange(4)
    cached.targets(batch)
    calls = []
    hook = cached.q_network.register_forward_hook(lambda *args: calls.append(1))
    cached.targets(batch)
    assert not calls and cached.bootstrap_cache.hit_rate == 0.5  # 4 misses, then 4 hits
    del batch["index"]  # no replay index: nothing to key on, computed afresh
    cached.targets(batch)
    hook.remove()
    assert calls


def test_bootstrap_cache_needs_deterministic_target_proposals():
    with pytest.raises(ValueError, match="bootstrap_cache=8 needs deterministic target proposals"):
        make_loss(bootstrap_cache=8, target_proposal={"mode": "softmax"})
    with pytest.raises(ValueError, match="bootstrap_cache must be an int >= 0"):
        make_loss(bootstrap_cache=-1)


def v_inputs(loss, batch, seed=None) -> list[torch.Tensor]:
    """The heightmaps ``loss``'s V is fitted on in one call on ``batch`` (real next states, then predicted ones)."""
    seen = []
    original = loss.value_network.value_and_reward
    loss.value_network.value_and_reward = lambda heightmap, in_hand: (seen.append(heightmap.detach()), original(heightmap, in_hand))[1]
    if seed is not None:
        torch.manual_seed(seed)
    with torch.no_grad():
        loss(batch)
    loss.value_network.value_and_reward = original
    return seen


def augmented_and_plain(loss, batch, seed=3):
    """On ``batch``: ``loss``'s outputs, V's real and predicted inputs under ``loss``'s augmentation (drawn from
    ``seed``), and the plain loss's predicted inputs and value target."""
    torch.manual_seed(seed)
    out = loss(batch.clone())
    real, predicted = v_inputs(loss, batch, seed=seed)
    plain = make_loss()
    return out, real, predicted, v_inputs(plain, batch.clone())[1], plain(batch.clone())["value_target"]


def test_quarter_turn_augmentation_fits_v_on_turned_copies_of_the_next_states():
    """Each row's V input (real and predicted next state) is its stored heightmap turned by one whole quarter-turn
    count, the same for both; over a seeded batch all four counts occur; the targets do not move."""
    loss = make_loss(value_augmentation="quarter_turns")
    batch = transitions(24, terminated=torch.zeros(24, 1, dtype=torch.bool))
    out, real, predicted, predicted_plain, plain_target = augmented_and_plain(loss, batch)
    stored = batch["next", "heightmap"]
    turns = []
    for row in range(24):
        matches = [k for k in range(4) if torch.equal(real[row], stored[row].rot90(k, (-2, -1)))]
        assert len(matches) == 1, f"row {row}: V saw no whole quarter turn of its next state"
        turns.append(matches[0])
    assert set(turns) == {0, 1, 2, 3}
    for row, k in enumerate(turns):  # the prediction is turned by the same count as the real state
        assert torch.equal(predicted[row], predicted_plain[row].rot90(k, (-2, -1)))
    torch.testing.assert_close(out["value_target"], plain_target)
    with pytest.raises(ValueError, match="value_augmentation must be one of"):
        make_loss(value_augmentation="flips")


def test_shift_augmentation_fits_v_on_shifted_copies_of_the_next_states():
    """Each row's V input (real and predicted next state) is its stored heightmap moved by one offset of at most
    ``value_shift`` pixels per axis, the same for both; over a seeded batch the offsets vary; the targets do not
    move."""
    loss = make_loss(value_augmentation="shifts", value_shift=2)
    batch = transitions(24, terminated=torch.zeros(24, 1, dtype=torch.bool))
    batch["next", "heightmap"] = batch["next", "heightmap"] + 0.01  # no zero pixels: a shift shows at the border
    out, real, predicted, predicted_plain, plain_target = augmented_and_plain(loss, batch)
    stored = batch["next", "heightmap"]
    found = []
    for row in range(24):
        matches = [(dr, dc) for dr in range(-2, 3) for dc in range(-2, 3)
                   if torch.equal(real[row], geometry.shift(stored[row:row + 1], torch.tensor([[dr, dc]]))[0])]
        assert len(matches) == 1, f"row {row}: V saw no shift within 2 px of its next state"
        found.append(matches[0])
        shifted_prediction = geometry.shift(predicted_plain[row:row + 1], torch.tensor([matches[0]]))[0]
        assert torch.equal(predicted[row], shifted_prediction)  # the prediction moved by the same offset
    assert len(set(found)) > 5  # the rows drew different offsets
    torch.testing.assert_close(out["value_target"], plain_target)
    with pytest.raises(ValueError, match="value_shift must be an int >= 1"):
        make_loss(value_augmentation="shifts", value_shift=0)
    with pytest.raises(ValueError, match="value_shift must be an int >= 1"):
        draw_value_augmentation("symmetries", 4, shift=2.5)
    with pytest.raises(ValueError, match="value_augmentation must be one of"):
        draw_value_augmentation("flips", 4)


def test_symmetry_augmentation_turns_mirrors_and_shifts_each_next_state():
    """Each row's V input is its stored next state under one element of the square's symmetries (quarter turn,
    then a mirror or not) followed by one shift of at most ``value_shift`` px; over a seeded batch both mirrored
    and plain rows, several turns and several shifts occur."""
    loss = make_loss(value_augmentation="symmetries", value_shift=1)
    batch = transitions(24, terminated=torch.zeros(24, 1, dtype=torch.bool))
    batch["next", "heightmap"] = batch["next", "heightmap"] + 0.01
    real = v_inputs(loss, batch, seed=5)[0]
    stored = batch["next", "heightmap"]
    found = []
    for row in range(24):
        matches = []
        for k in range(4):
            turned = stored[row:row + 1].rot90(k, (-2, -1))
            for mirrored in (False, True):
                image = turned.transpose(-2, -1) if mirrored else turned
                for dr in (-1, 0, 1):
                    for dc in (-1, 0, 1):
                        if torch.equal(real[row], geometry.shift(image, torch.tensor([[dr, dc]]))[0]):
                            matches.append((k, mirrored, dr, dc))
        assert len(matches) == 1, f"row {row}: V saw {len(matches)} symmetries of its next state, not one"
        found.append(matches[0])
    assert {m[1] for m in found} == {False, True}
    assert len({m[0] for m in found}) >= 3 and len({m[2:] for m in found}) >= 4


@pytest.mark.parametrize("region, band", [("object", None), ("top", 0.02)])
def test_raise_augmentation_fits_v_on_next_states_with_the_tallest_object_raised_by_whole_levels(region, band):
    """``value_raise_levels=2``: each row's V input (real and predicted next state) is its stored heightmap with the
    tallest object (``value_raise_region=object``) or its top level (``top``: a band of half a level) raised by 0, 1
    or 2 levels of ``value_raise_height`` — the same count for both images; over a seeded batch all three counts
    occur, and the two regions differ; the targets do not move; the option is off (no draw) by default."""
    loss = make_loss(value_raise_levels=2, value_raise_height=0.04, value_raise_region=region)
    batch = transitions(24, terminated=torch.zeros(24, 1, dtype=torch.bool))
    out, real, predicted, predicted_plain, plain_target = augmented_and_plain(loss, batch)
    stored = batch["next", "heightmap"]
    levels, other_region_differs = [], False
    for row in range(24):
        matches = [n for n in range(3) if torch.equal(real[row], geometry.raise_tallest(
            stored[row:row + 1], torch.tensor([n * 0.04]), floor=0.02, band=band)[0])]
        assert len(matches) == 1, f"row {row}: V saw no whole-level raise of its next state"
        levels.append(matches[0])
        raised = geometry.raise_tallest(predicted_plain[row:row + 1], torch.tensor([matches[0] * 0.04]), floor=0.02,
                                        band=band)
        assert torch.equal(predicted[row], raised[0])  # the prediction raised by the same count
        other = geometry.raise_tallest(predicted_plain[row:row + 1], torch.tensor([matches[0] * 0.04]), floor=0.02,
                                       band=0.02 if band is None else None)
        other_region_differs |= not torch.equal(predicted[row], other[0])  # the model's blurred edges: not one level
    assert set(levels) == {0, 1, 2}
    assert other_region_differs, "the two raise regions gave the same images on every row"
    torch.testing.assert_close(out["value_target"], plain_target)
    state, images = torch.get_rng_state(), stored[:4]
    assert draw_value_augmentation(None, 4)(images) is images
    assert torch.equal(torch.get_rng_state(), state)  # off: no random draw, so earlier runs replay exactly
    with pytest.raises(ValueError, match="value_raise_height must be metres in"):
        make_loss(value_raise_levels=1)
    with pytest.raises(ValueError, match="value_raise_levels must be an int >= 0"):
        draw_value_augmentation(None, 4, raise_levels=-1, raise_height=0.04)
    with pytest.raises(ValueError, match=r"value_raise_region must be one of \('object', 'top'\), got 'tower'"):
        draw_value_augmentation(None, 4, raise_levels=1, raise_height=0.04, raise_region="tower")


def test_a_termination_head_is_fitted_on_the_terminated_flag_and_v_only_trains_the_value_head():
    q, dynamics, _ = tiny_networks(0)
    torch.manual_seed(5)
    value = build_value_network("lite", max_height=MAX_HEIGHT, width=0.125, termination_head=True)
    loss = LookaheadLoss(q, dynamics, value, gamma=0.9, num_target_candidates=3, chunk_size=5)
    plain = make_loss()
    assert loss.termination and not plain.termination
    assert "loss_termination" in loss.out_keys and "loss_termination" not in plain.out_keys
    terminated = torch.tensor([[True], [False], [True], [False]])
    batch = transitions(4, terminated=terminated)
    out = loss(batch)
    assert set(out.keys()) == set(loss.out_keys)
    # the termination loss: binary cross-entropy of T's logit toward the flag, on real and predicted next states
    with torch.no_grad():
        logit = value.heads(batch["next", "heightmap"], batch["next", "in_hand"])[2]
    bce_real = torch.nn.functional.binary_cross_entropy_with_logits(logit, terminated.float())
    assert out["loss_termination"] > bce_real  # the predicted states' term comes on top
    loss_no_pred = LookaheadLoss(q, dynamics, value, gamma=0.9, num_target_candidates=3, chunk_size=5,
                                 value_on_prediction=False)
    torch.testing.assert_close(loss_no_pred(transitions(4, terminated=terminated))["loss_termination"], bce_real)
    # V's loss reaches the value head only; the termination loss reaches the termination head
    out["loss_value"].backward(retain_graph=True)
    assert all(p.grad is None for p in loss.value_network.termination_head.parameters())
    assert all(p.grad is None for p in loss.value_network.reward_head.parameters())
    assert any(p.grad is not None and p.grad.abs().sum() > 0 for p in loss.value_network.value_head.parameters())
    loss.value_network.zero_grad(set_to_none=True)
    out["loss_termination"].backward()
    assert any(p.grad is not None and p.grad.abs().sum() > 0 for p in loss.value_network.termination_head.parameters())
    assert all(p.grad is None for p in loss.value_network.value_head.parameters())


def test_a_log_scale_v_is_fitted_on_log_targets_while_the_targets_stay_linear():
    from ldm_rl.planning.lookahead import lookahead
    from ldm_rl.planning.sampling import sample_candidates

    q, dynamics, _ = tiny_networks(0)
    torch.manual_seed(5)
    value = build_value_network("lite", max_height=MAX_HEIGHT, width=0.125, value_log_floor=0.01)
    loss = LookaheadLoss(q, dynamics, value, gamma=0.9, num_target_candidates=3, chunk_size=5, value_on_prediction=False,
                         target_range=(0.0, 1.0))
    terminated = torch.tensor([[True], [False], [False], [True]])
    batch = transitions(4, terminated=terminated)
    batch["next", "reward"] = torch.tensor([[0.5], [0.0], [0.0], [0.0]])  # a terminal row below the floor: log(ε)
    _, y_v = loss.targets(batch)
    # the bootstrap reads V on the linear scale: exp of the head, maximised over the target proposals
    live = torch.tensor([1, 2])
    state = [batch["next", key][live] for key in ("heightmap", "in_hand", "holding")]
    with torch.no_grad(), loss.target_networks():
        q_map = loss.q_network.eval()(*state)
        candidates = sample_candidates(q_map, 3, mode="argmax", tau=1.0, beta=1.0, sigma=2.0, sigma_rot=1.0)
        values = lookahead(loss.dynamics.eval(), loss.value_network.eval(), *state, candidates, chunk_size=5).values
    torch.testing.assert_close(y_v[live], 0.9 * values.amax(1, keepdim=True))
    assert (values > 0).all() and y_v[0] == 0.5 and y_v[3] == 0.0
    # V's Huber and the priorities compare log V with log(max(y_V, ε))
    out = loss(batch)
    with torch.no_grad():
        v_now = loss.value_network.train()(batch["next", "heightmap"], batch["next", "in_hand"])
    fitted = y_v.clamp_min(0.01).log()
    torch.testing.assert_close(out["loss_value"], torch.nn.functional.smooth_l1_loss(v_now.log(), fitted))
    torch.testing.assert_close(batch["td_error"], (v_now.log() - fitted).abs().reshape(-1))
    out["loss_value"].backward()
    assert any(p.grad is not None and p.grad.abs().sum() > 0 for p in loss.value_network.value_head.parameters())
    # the same network on the linear scale is fitted on y_V itself
    linear = LookaheadLoss(q, dynamics, build_value_network("lite", max_height=MAX_HEIGHT, width=0.125), gamma=0.9,
                           num_target_candidates=3, chunk_size=5, value_on_prediction=False)
    assert linear.value_scale.log_floor is None and loss.value_scale.log_floor == 0.01


def _expert_batch(n=5, expert=(True, False, True, True, False)):
    batch = transitions(n)
    batch["is_expert"] = torch.tensor(expert)
    return batch


def _lookahead_scores(loss, batch, rows, actions):
    """V (train mode, as the loss runs it) of the online LDM's eval-mode predictions of ``actions`` [n, m, 3]."""
    state = [batch[key][rows] for key in ("heightmap", "in_hand", "holding")]
    m = actions.shape[1]
    with torch.no_grad():
        predicted = loss.dynamics.eval().predict(*(x.repeat_interleave(m, 0) for x in state), actions.reshape(-1, 3))
        loss.dynamics.train()
        return loss.value_network.train()(predicted.heightmap, predicted.in_hand).reshape(-1, m)


def _proposals(loss, batch, rows):
    from ldm_rl.planning.sampling import sample_candidates

    state = [batch[key][rows] for key in ("heightmap", "in_hand", "holding")]
    with torch.no_grad():
        q_map = loss.q_network.eval()(*state)
        loss.q_network.train()
    return sample_candidates(q_map, loss.num_target_candidates, **loss.target_proposal)


def test_the_value_margin_ranks_the_experts_predicted_outcome_above_qs_proposals():
    loss = make_loss(value_margin_weight=0.5, value_margin=0.05, expert_margin_rows=2)
    plain = make_loss()
    batch = _expert_batch()
    rows = torch.tensor([0, 2])  # the first expert_margin_rows = 2 expert rows
    proposals = _proposals(loss, batch, rows)
    # in row 0 the expert's action is the proposal V rates best (no lead is asked of it), in row 2 another pose
    best = int(_lookahead_scores(loss, batch, rows[:1], proposals[:1]).argmax())
    batch["action"][0] = proposals[0, best]
    actions = torch.cat((batch["action"][rows].unsqueeze(1).long(), proposals), 1)
    scores = _lookahead_scores(loss, batch, rows, actions)  # [2, 1 + N]: the expert's outcome first
    lead = torch.full_like(scores[:, 1:], 0.05)
    lead[0, best] = 0.0
    expected = ((scores[:, 1:] + lead).amax(1) - scores[:, 0]).clamp_min(0).mean()
    asked_of_all = ((scores[:, 1:] + 0.05).amax(1) - scores[:, 0]).clamp_min(0).mean()
    assert not torch.isclose(expected, asked_of_all)  # the expert's own pose among the proposals changes the term
    out = loss(batch.clone())
    torch.testing.assert_close(out["value_margin"], expected)
    torch.testing.assert_close(out["loss_value"], plain(batch.clone())["loss_value"] + 0.5 * expected)
    assert "value_margin" in loss.out_keys and "value_margin" not in plain.out_keys
    # the margin trains V alone: Q, which proposed, and the LDM, which predicted, get no gradient from it
    loss.zero_grad()
    loss.value_margin_loss(batch.clone()).backward()
    assert any(p.grad is not None and p.grad.abs().sum() > 0 for p in loss.value_network.parameters())
    assert all(p.grad is None for p in [*loss.q_network.parameters(), *loss.dynamics.parameters()])


def test_the_value_margin_is_zero_without_expert_rows_and_needs_the_flag():
    loss = make_loss(value_margin_weight=1.0)
    assert loss.value_margin_loss(_expert_batch(expert=(False,) * 5)) == 0
    with pytest.raises(KeyError, match="value_margin_weight > 0 needs 'is_expert' in the batch"):
        loss(transitions(3))
    assert make_loss().value_margin_loss(transitions(3)) is None  # off: no flag needed, nothing computed
    for kwargs, message in (({"value_margin_weight": -1}, "value_margin_weight must be a number >= 0 .* got -1"),
                            ({"value_margin_weight": True}, "value_margin_weight must be a number >= 0 .* got True"),
                            ({"value_margin": 0}, r"value_margin must be a number > 0 \(V's fitted units\), got 0")):
        with pytest.raises(ValueError, match=message):
            make_loss(**kwargs)
