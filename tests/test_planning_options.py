"""Beyond the paper: the LDM's predictive entropy (metric, lookahead, planner and target penalties) and the
depth-d tree planner. Each option's defining behaviour, checked against a computation written out by hand."""

from __future__ import annotations

import math
from pathlib import Path

import pytest
import torch
from tensordict import TensorDict
from torch import nn
from torchrl.envs.utils import ExplorationType, set_exploration_type

from ldm_rl.objectives import LookaheadLoss
from ldm_rl.planning.lookahead import lookahead
from ldm_rl.planning.planner import LookaheadPlanner
from ldm_rl.planning.sampling import mask_actions, near_actions, sample_candidates, sweep_rotations
from ldm_rl.planning.tree_planner import TreePlanner
from ldm_rl.world_model import pixel_entropy
from ldm_rl.world_model.metrics import MetricSettings, auroc
from policy_helpers import MAX_HEIGHT, scenes, tiny_networks, transitions

pytestmark = pytest.mark.filterwarnings("ignore:No target network updater has been associated:UserWarning")
GREEDY = dict(num_candidates=5, tau=0.05, tau_value=0.1, proposal="argmax")


@pytest.fixture(scope="module")
def nets():
    return tiny_networks(0)


def batch(n=3, seed=0):
    return TensorDict(scenes(n, seed), batch_size=[n])


# ------------------------------------------------------------------------------------------- entropy


def test_pixel_entropy_is_zero_for_one_hot_and_log_k_for_uniform_predictions():
    k = 21
    one_hot = torch.full((2, k, 8, 8), -1e4)
    one_hot[:, 3] = 1e4
    torch.testing.assert_close(pixel_entropy(one_hot), torch.zeros(2))
    torch.testing.assert_close(pixel_entropy(torch.zeros(2, 3, k, 8, 8)), torch.full((2, 3), math.log(k)))
    # the mean over pixels: half the frame uniform, half certain -> log K / 2
    half = one_hot.clone()
    half[:, :, :4] = 0.0
    torch.testing.assert_close(pixel_entropy(half), torch.full((2,), math.log(k) / 2))
    with pytest.raises(ValueError, match="logits must be a"):
        pixel_entropy(torch.zeros(4, 4))


def test_auroc_equals_the_pairwise_count_with_ties_as_halves():
    g = torch.Generator().manual_seed(0)
    scores = torch.randint(0, 6, (40,), generator=g).float()  # many ties
    labels = torch.rand(40, generator=g) < 0.4
    pos, neg = scores[labels], scores[~labels]
    pairs = (pos[:, None] > neg[None, :]).float() + 0.5 * (pos[:, None] == neg[None, :]).float()
    assert auroc(scores, labels) == pytest.approx(pairs.mean().item())
    assert auroc(torch.arange(4.0), torch.tensor([False, False, True, True])) == 1.0
    assert math.isnan(auroc(torch.arange(3.0), torch.zeros(3, dtype=torch.bool)))
    with pytest.raises(ValueError, match="one label per score, got 3 scores and 2 labels"):
        auroc(torch.arange(3.0), torch.ones(2, dtype=torch.bool))


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
def test_auroc_on_cuda_matches_cpu():  # the Table 1 evaluation on a GPU once died here (a CPU tensor in the ranks)
    g = torch.Generator().manual_seed(1)
    scores = torch.randint(0, 5, (40,), generator=g).float()
    labels = torch.rand(40, generator=g) < 0.4
    assert auroc(scores.cuda(), labels.cuda()) == pytest.approx(auroc(scores, labels))


def test_lookahead_entropy_is_the_entropy_of_each_candidates_prediction(nets):
    q, dynamics, value = nets
    s = scenes(2)
    candidates = torch.tensor([[[60, 60, 0], [30, 90, 3]], [[64, 64, 5], [100, 20, 1]]])
    out = lookahead(dynamics, value, s["heightmap"], s["in_hand"], s["holding"], candidates, with_entropy=True, chunk_size=3)
    with torch.no_grad():
        pred = dynamics.eval().predict(s["heightmap"][:, None].expand(2, 2, 1, 128, 128),
                                       s["in_hand"][:, None].expand(2, 2, 1, 24, 24), s["holding"][:, None].expand(2, 2, 1),
                                       candidates)
    torch.testing.assert_close(out.entropy, pred.entropy())
    assert out.entropy.shape == (2, 2) and (out.entropy > 0).all() and (out.entropy <= math.log(21) + 1e-5).all()
    assert lookahead(dynamics, value, s["heightmap"], s["in_hand"], s["holding"], candidates).entropy is None


def test_held_out_metrics_report_how_well_entropy_flags_wrong_predictions(nets):
    from ldm_rl.world_model.training import evaluate

    _, dynamics, _ = nets
    metrics = evaluate(dynamics, transitions(12), MetricSettings(max_height=MAX_HEIGHT))
    assert 0.0 <= metrics["entropy_auroc"] <= 1.0  # random weights: right and wrong predictions both occur
    assert {"entropy_right", "entropy_wrong"} <= set(metrics)
    assert 0 < metrics["entropy_right"] <= math.log(21) + 1e-5


def test_undefined_entropy_scores_are_left_out_so_metrics_stay_json():
    import json

    from ldm_rl.world_model.metrics import summarize

    per = {"l1": torch.zeros(4), "l1_region": torch.zeros(4), "is_pick": torch.tensor([True, True, False, False]),
           "correct": torch.tensor([True, True, False, True]), "entropy": torch.tensor([0.1, 0.2, 0.5, 0.3])}
    out = summarize(per)
    assert out["entropy_auroc"] == 1.0 and out["entropy_auroc_place"] == 1.0
    assert "entropy_auroc_pick" not in out  # every pick right: undefined, not NaN
    json.dumps(out, allow_nan=False)


def test_the_uncertainty_penalty_scores_v_minus_lambda_entropy(nets):
    q, dynamics, value = nets
    plain = LookaheadPlanner(q, dynamics, value, **GREEDY)
    with set_exploration_type(ExplorationType.DETERMINISTIC):
        reference = plain(batch())
        for lam in (0.3, 1e6):
            out = LookaheadPlanner(q, dynamics, value, uncertainty_penalty=lam, **GREEDY)(batch())
            assert torch.equal(out["candidate_actions"], reference["candidate_actions"])
            torch.testing.assert_close(out["candidate_values"], reference["candidate_values"])
            best = (out["candidate_values"] - lam * out["candidate_entropy"]).argmax(-1)
            assert torch.equal(out["action"], out["candidate_actions"][torch.arange(3), best])
    # a huge λ: the most certain prediction wins whatever V says
    assert torch.equal(best, out["candidate_entropy"].argmin(-1))
    assert "candidate_entropy" not in reference.keys()
    with pytest.raises(ValueError, match="uncertainty_penalty must be a number >= 0"):
        LookaheadPlanner(q, dynamics, value, uncertainty_penalty=-0.1)


def _acts_in_the_greedy_decisions_alone(nets, split_kwargs: dict, greedy_kwargs: dict):
    """A planner built with ``split_kwargs`` decides greedily as one built with ``greedy_kwargs`` (and not as the
    plain planner) and explores as the plain planner does (the same random stream); returns it and its greedy output."""
    q, dynamics, value = nets
    split = LookaheadPlanner(q, dynamics, value, **split_kwargs, **GREEDY)
    with set_exploration_type(ExplorationType.DETERMINISTIC):
        greedy = split(batch())
        alike = LookaheadPlanner(q, dynamics, value, **greedy_kwargs, **GREEDY)(batch())
        plain = LookaheadPlanner(q, dynamics, value, **GREEDY)(batch())
    assert torch.equal(greedy["action"], alike["action"])
    assert not torch.equal(greedy["action"], plain["action"])  # the greedy setting did change a decision
    with set_exploration_type(ExplorationType.RANDOM):
        torch.manual_seed(5)
        exploring = split(batch())
        torch.manual_seed(5)
        exploring_plain = LookaheadPlanner(q, dynamics, value, **GREEDY)(batch())
    assert torch.equal(exploring["action"], exploring_plain["action"])
    return split, greedy


def test_a_greedy_lambda_acts_in_the_greedy_decisions_alone(nets):
    """greedy_uncertainty_penalty: the greedy decisions are those of a planner with that λ, the exploring draws
    those of the exploring λ (the same random stream)."""
    q, dynamics, value = nets
    split, greedy = _acts_in_the_greedy_decisions_alone(
        nets, {"uncertainty_penalty": 0.0, "greedy_uncertainty_penalty": 1e6}, {"uncertainty_penalty": 1e6})
    assert torch.equal(greedy["action"], greedy["candidate_actions"][torch.arange(3),
                                                                   greedy["candidate_entropy"].argmin(-1)])
    assert split.penalty(greedy=False) == 0.0 and split.penalty(greedy=True) == 1e6
    assert LookaheadPlanner(q, dynamics, value, uncertainty_penalty=0.2).penalty(greedy=True) == 0.2  # None: the same
    with pytest.raises(ValueError, match="greedy_uncertainty_penalty must be a number >= 0 .* or None, got -1"):
        LookaheadPlanner(q, dynamics, value, greedy_uncertainty_penalty=-1)


def test_a_penalty_on_places_alone_leaves_the_picks_to_v(nets):
    """uncertainty_penalty_on="places": with a huge λ the place row (row 1 holds) takes the most certain prediction,
    the pick rows (0 and 2) decide as without λ; the written entropy is the LDM's at every candidate."""
    q, dynamics, value = nets
    with set_exploration_type(ExplorationType.DETERMINISTIC):
        plain = LookaheadPlanner(q, dynamics, value, **GREEDY)(batch())
        certain = LookaheadPlanner(q, dynamics, value, uncertainty_penalty=1e6, **GREEDY)(batch())
        places = LookaheadPlanner(q, dynamics, value, uncertainty_penalty=1e6, uncertainty_penalty_on="places",
                                  **GREEDY)(batch())
    picks, place = [0, 2], 1
    assert torch.equal(places["action"][picks], plain["action"][picks])
    assert not torch.equal(certain["action"][picks], plain["action"][picks])  # λ on picks would have moved them
    assert torch.equal(places["action"][place], certain["action"][place])
    torch.testing.assert_close(places["candidate_entropy"], certain["candidate_entropy"])
    with pytest.raises(ValueError, match="uncertainty_penalty_on must be one of .*'all', 'places'.*got 'picks'"):
        LookaheadPlanner(q, dynamics, value, uncertainty_penalty_on="picks")


def test_the_tree_charges_a_places_only_penalty_on_places_alone(nets):
    """A depth-2 tree from empty-handed states charging λ at the first step only (``penalty_depth=1``) decides, with
    the penalty on places alone, as the tree without λ: every first action is a pick; with it on every primitive,
    a huge λ moves a decision."""
    q, dynamics, value = nets
    td = batch(4)
    td["holding"] = torch.zeros(4, 1, dtype=torch.bool)
    td["in_hand"] = torch.zeros_like(td["in_hand"])
    tree = dict(depth=2, branching=2, gamma=0.5, penalty_depth=1, **GREEDY)
    with set_exploration_type(ExplorationType.DETERMINISTIC):
        plain = TreePlanner(q, dynamics, value, **tree)(td.clone())
        places = TreePlanner(q, dynamics, value, uncertainty_penalty=1e6, uncertainty_penalty_on="places", **tree)(td.clone())
        every = TreePlanner(q, dynamics, value, uncertainty_penalty=1e6, **tree)(td.clone())
    assert torch.equal(places["action"], plain["action"])
    torch.testing.assert_close(places["candidate_scores"], plain["candidate_scores"])
    assert not torch.equal(every["candidate_scores"], plain["candidate_scores"])


def test_q_blend_chooses_on_the_mix_of_v_and_q_of_each_candidate(nets):
    """q_blend w: the greedy choice is the argmax of (1 − w)·V(f(s, a)) + w·Q(s, a) over the same candidates, with Q
    read by the independent action_values path (and exp'd for a Q fitted on the log scale); w = 1 follows Q's ranking
    of its own proposals, which here is not V's."""
    q, dynamics, value = nets
    rows = torch.arange(3)
    with set_exploration_type(ExplorationType.DETERMINISTIC):
        plain = LookaheadPlanner(q, dynamics, value, **GREEDY)(batch())
        candidates = plain["candidate_actions"]
        s = scenes(3)
        with torch.no_grad():
            q_values = q.eval().action_values(s["heightmap"].repeat_interleave(5, 0), s["in_hand"].repeat_interleave(5, 0),
                                              s["holding"].repeat_interleave(5, 0), candidates.reshape(-1, 3)).reshape(3, 5)
        for w, floor in ((0.5, None), (1.0, None), (0.5, 0.01)):
            out = LookaheadPlanner(q, dynamics, value, q_blend=w, q_log_floor=floor, **GREEDY)(batch())
            assert torch.equal(out["candidate_actions"], candidates)
            torch.testing.assert_close(out["candidate_values"], plain["candidate_values"])
            read = q_values.exp() if floor else q_values
            best = ((1 - w) * plain["candidate_values"] + w * read).argmax(-1)
            assert torch.equal(out["action"], candidates[rows, best])
            if w == 1.0:
                assert torch.equal(best, q_values.argmax(-1))
                assert not torch.equal(out["action"], plain["action"])  # Q's vote changed a decision
    for bad in (-0.1, 1.5, True):
        with pytest.raises(ValueError, match=f"q_blend must be a number in \\[0, 1\\] .*, got {bad!r}"):
            LookaheadPlanner(q, dynamics, value, q_blend=bad)
    with pytest.raises(ValueError, match="q_log_floor must be None .* got 0"):
        LookaheadPlanner(q, dynamics, value, q_log_floor=0)


def test_a_greedy_q_blend_acts_in_the_greedy_decisions_alone(nets):
    """greedy_q_blend: the greedy decisions are those of a planner with that w, the exploring draws those of the
    exploring w (the same random stream); None takes q_blend for both."""
    q, dynamics, value = nets
    split, _ = _acts_in_the_greedy_decisions_alone(nets, {"q_blend": 0.0, "greedy_q_blend": 1.0}, {"q_blend": 1.0})
    assert split.blend_weight(greedy=False) == 0.0 and split.blend_weight(greedy=True) == 1.0
    assert LookaheadPlanner(q, dynamics, value, q_blend=0.3).blend_weight(greedy=True) == 0.3  # None: the same
    for bad in (-0.5, 2, False):
        with pytest.raises(ValueError, match=f"greedy_q_blend must be a number in \\[0, 1\\] .* or None, got {bad!r}"):
            LookaheadPlanner(q, dynamics, value, greedy_q_blend=bad)


def test_q_blend_keeps_ranked_last_candidates_last_and_drops_those_off_q_s_frame(nets):
    q, dynamics, value = nets
    planner = LookaheadPlanner(q, dynamics, value, q_blend=1.0)
    q_map = torch.zeros(1, 8, 128, 128)
    q_map[0, 2, 10, 20], q_map[0, 0, 5, 6], q_map[0, 7, 0, 0] = 0.9, 0.3, float("-inf")
    candidates = torch.tensor([[[10, 20, 2], [5, 6, 0], [1, 1, 1], [0, 0, 7]]])
    scores = torch.tensor([[float("-inf"), 0.1, 0.2, 0.4]])
    blended = planner.blend_q(scores, q_map, candidates)
    torch.testing.assert_close(blended, torch.tensor([[float("-inf"), 0.3, 0.0, float("-inf")]]))  # w = 1: Q, marks kept
    planner.q_blend = 0.25
    torch.testing.assert_close(planner.blend_q(scores, q_map, candidates)[0, 1:3], torch.tensor([0.15, 0.15]))


def test_rank_empty_picks_last_sets_only_predicted_empty_picks_of_states_with_a_holding_alternative():
    from ldm_rl.planning.planner import rank_empty_picks_last

    scores = torch.tensor([[0.9, 0.5, 0.7], [0.9, 0.5, 0.7], [0.9, 0.5, 0.7], [0.9, 0.5, 0.7]])
    holding = torch.tensor([False, False, False, True])  # the last decision is a place
    next_holding = torch.tensor([[False, True, False], [False, False, False], [True, True, True], [False, False, False]])
    ranked = rank_empty_picks_last(scores, holding, next_holding)
    inf = float("-inf")
    assert torch.equal(ranked, torch.tensor([[inf, 0.5, inf], [0.9, 0.5, 0.7], [0.9, 0.5, 0.7], [0.9, 0.5, 0.7]]))
    assert ranked[0].argmax() == 1  # the pick predicted to hold wins though V rated the empty ones higher
    assert torch.equal(rank_empty_picks_last(scores, holding.view(4, 1).int(), next_holding), ranked)  # [B, 1] 0/1
    with pytest.raises(ValueError, match=r"must agree, got \(4, 3\), \(4, 2\) and \(4,\)"):
        rank_empty_picks_last(scores, holding, next_holding[:, :2])


class HoldingPattern(nn.Module):
    """The tiny LDM with its predicted hand state replaced: a pick holds iff its rotation bin is odd."""

    def __init__(self, dynamics):
        super().__init__()
        self.inner = dynamics

    def predict(self, heightmap, in_hand, holding, actions):
        pred = self.inner.predict(heightmap, in_hand, holding, actions)
        picked = (actions[:, 2] % 2 == 1).view(-1, 1) & ~holding.view(-1, 1).bool()
        return pred._replace(holding=picked)


def test_the_planner_with_empty_picks_last_never_chooses_a_predicted_empty_pick_beside_one_that_holds(nets):
    q, dynamics, value = nets
    model = HoldingPattern(dynamics)
    options = dict(GREEDY, num_candidates=8, sigma_rot=0.0)
    plain = LookaheadPlanner(q, model, value, **options)
    ranked = LookaheadPlanner(q, model, value, empty_picks_last=True, **options)
    data = batch(6)
    data["holding"] = torch.zeros_like(data["holding"])
    with set_exploration_type(ExplorationType.DETERMINISTIC):
        before, after = plain(data.clone()), ranked(data.clone())
    assert torch.equal(after["candidate_actions"], before["candidate_actions"])  # the same proposals and values
    torch.testing.assert_close(after["candidate_values"], before["candidate_values"])
    holds = after["candidate_actions"][..., 2] % 2 == 1
    assert holds.any(-1).all() and (~holds).any(-1).all()  # every state has both kinds of proposals
    best_holding = torch.where(holds, after["candidate_values"], float("-inf")).argmax(-1)
    assert torch.equal(after["action"], after["candidate_actions"][torch.arange(6), best_holding])
    chose_empty = before["action"][:, 2] % 2 == 0
    assert chose_empty.any()  # V alone chose an empty pick somewhere: the option changed that decision
    with pytest.raises(ValueError, match="empty_picks_last must be True or False, got 1"):
        LookaheadPlanner(q, dynamics, value, empty_picks_last=1)


# ------------------------------------------------------------------------------------------- pick rotations


def test_sweep_rotations_spreads_each_pick_proposal_over_pi_and_repeats_the_others():
    g = torch.Generator().manual_seed(0)
    r, k, n = 8, 4, 5
    rows = torch.arange(n).repeat(3, 1) * 20 + torch.randint(0, 10, (3, 1), generator=g)  # ≥ 10 px apart
    candidates = torch.stack([rows, torch.randint(0, 128, (3, n), generator=g), torch.randint(0, r, (3, n), generator=g)], -1)
    active = torch.tensor([True, False, True])
    swept = sweep_rotations(candidates, r, k, active=active).view(3, n, k, 3)
    assert torch.equal(swept[..., 0, :], candidates)  # each block starts with its proposal
    assert torch.equal(swept[..., :2], candidates[:, :, None, :2].expand(3, n, k, 2))  # the pixel never moves
    offsets = (swept[..., 2] - candidates[..., None, 2]).remainder(r)
    assert torch.equal(offsets[0], torch.tensor([0, 2, 4, 6]).expand(n, k)) and torch.equal(offsets[2], offsets[0])
    assert (offsets[1] == 0).all()  # an inactive row: every proposal K times, unchanged
    # a swept rotation near an action to avoid falls back to the proposal itself
    avoid = torch.full((3, 1, 3), -1)
    avoid[0, 0] = swept[0, 1, 2]  # the second proposal's third rotation
    again = sweep_rotations(candidates, r, k, active=active, avoid=avoid).view(3, n, k, 3)
    assert torch.equal(again[0, 1, 2], candidates[0, 1])
    assert torch.equal(again[0, 1], torch.cat((swept[0, 1, :2], candidates[0, 1:2], swept[0, 1, 3:])))  # 2 bins off: kept
    assert torch.equal(again[1:], swept[1:]) and torch.equal(again[0, ::2], swept[0, ::2])
    for bad in (3, 0, True):
        with pytest.raises(ValueError, match=f"sweep must be an int >= 1 dividing num_rotations=8, got {bad!r}"):
            sweep_rotations(candidates, r, bad, active=active)
    with pytest.raises(ValueError, match=r"candidates must be \[B, N, 3\] integer \(row, col, rot\) actions, got torch.float32"):
        sweep_rotations(candidates.float(), r, k, active=active)
    with pytest.raises(ValueError, match="must be .B, N, 3. and active .B. with the same B"):
        sweep_rotations(candidates, r, k, active=active[:2])


def test_near_actions_marks_exactly_the_entries_mask_actions_removes():
    g = torch.Generator().manual_seed(1)
    others = torch.stack([torch.randint(0, 32, (2, 4), generator=g), torch.randint(0, 32, (2, 4), generator=g),
                          torch.randint(0, 8, (2, 4), generator=g)], -1)
    others[1, 2:] = -1  # rows with -1 are ignored
    actions = torch.stack([torch.randint(0, 32, (2, 400), generator=g), torch.randint(0, 32, (2, 400), generator=g),
                           torch.randint(0, 8, (2, 400), generator=g)], -1)
    masked = torch.isinf(mask_actions(torch.zeros(2, 8, 32, 32), others))
    want = masked[torch.arange(2)[:, None], actions[..., 2], actions[..., 0], actions[..., 1]]
    got = near_actions(actions, others, 8)
    assert torch.equal(got, want) and want.any() and (~want).any()
    with pytest.raises(ValueError, match=r"others must be \[B, N, 3\] integer .* got torch.bool"):
        near_actions(actions, others > 0, 8)
    with pytest.raises(ValueError, match="the same batch size"):
        near_actions(actions, others[:1], 8)


class CountingModel(nn.Module):
    """The tiny LDM, counting the (state, action) pairs it predicts."""

    def __init__(self, dynamics):
        super().__init__()
        self.inner, self.pairs = dynamics, 0

    def predict(self, heightmap, in_hand, holding, actions):
        self.pairs += len(actions)
        return self.inner.predict(heightmap, in_hand, holding, actions)


def test_the_planner_with_pick_rotations_scores_every_swept_pick_and_each_place_proposal_once(nets):
    q, dynamics, value = nets
    options = dict(GREEDY, num_candidates=4)
    plain = LookaheadPlanner(q, dynamics, value, **options)
    counted = CountingModel(dynamics)
    swept = LookaheadPlanner(q, counted, value, pick_rotations=4, **options)
    data = batch(4)  # picks at rows 0 and 2, places at rows 1 and 3
    with set_exploration_type(ExplorationType.DETERMINISTIC):
        before, after = plain(data.clone()), swept(data.clone())
    assert counted.pairs == 2 * 16 + 2 * 4  # the places' copies are not predicted again
    actions, values = after["candidate_actions"], after["candidate_values"]
    assert actions.shape == (4, 16, 3) and values.shape == (4, 16)
    assert torch.equal(actions, sweep_rotations(before["candidate_actions"], q.num_rotations, 4,
                                                active=~data["holding"].view(-1)))
    # a place state's proposals: the plain planner's, each repeated (and predicted) once per copy
    torch.testing.assert_close(values[1::2], before["candidate_values"][1::2].repeat_interleave(4, dim=1))
    # a pick state's: every swept action scored as the lookahead scores it alone
    picks = data[0::2]
    alone = lookahead(dynamics, value, picks["heightmap"], picks["in_hand"], picks["holding"], actions[0::2])
    torch.testing.assert_close(values[0::2], alone.values)
    assert torch.equal(after["action"], actions[torch.arange(4), values.argmax(-1)])
    assert (after["action"][0::2] != before["action"][0::2]).any()  # the sweep changed a decision
    for bad in (3, 0, 16):
        with pytest.raises(ValueError, match=f"pick_rotations must be an int >= 1 dividing Q's num_rotations=8, got {bad}"):
            LookaheadPlanner(q, dynamics, value, pick_rotations=bad)


def test_the_target_uncertainty_penalty_lowers_each_bootstrap_by_lambda_entropy():
    q, dynamics, value = tiny_networks(0)
    lam = 0.5
    loss = LookaheadLoss(q, dynamics, value, gamma=0.9, num_target_candidates=3, chunk_size=5, target_range=None,
                         target_uncertainty_penalty=lam)
    data = transitions(4, terminated=torch.zeros(4, 1, dtype=torch.bool))
    _, v_target = loss.targets(data)
    nxt = [data["next", key] for key in ("heightmap", "in_hand", "holding")]
    with torch.no_grad(), loss.target_networks():
        q_map = loss.q_network.eval()(*nxt)
        candidates = sample_candidates(q_map, 3, **loss.target_proposal)
        out = lookahead(loss.dynamics, loss.value_network, *nxt, candidates, with_entropy=True)
    want = data["next", "reward"] + 0.9 * (out.values - lam * out.entropy).amax(1, keepdim=True)
    torch.testing.assert_close(v_target, want)
    cached = LookaheadLoss(*tiny_networks(0), gamma=0.9, num_target_candidates=3, chunk_size=5, target_range=None,
                           target_uncertainty_penalty=lam, bootstrap_cache=16, double_value=True)
    data["index"] = torch.arange(4)
    first, second = cached.targets(data), cached.targets(data)  # fresh, then from the cache (entropy kept)
    for a, b in zip(first, second):
        torch.testing.assert_close(a, b)
    with pytest.raises(ValueError, match="target_uncertainty_penalty must be a number >= 0"):
        LookaheadLoss(*tiny_networks(0), target_uncertainty_penalty=-1.0)


# ------------------------------------------------------------------------------------------- tree planner


class ConstantValue(nn.Module):
    """V ≡ ``value``, reward head ≡ ``reward``: every state alike."""

    def __init__(self, value: float = 0.3, reward: float = 0.0) -> None:
        super().__init__()
        self.value, self.reward = value, reward

    def forward(self, heightmap, in_hand):
        return torch.full((heightmap.shape[0], 1), self.value)

    def value_and_reward(self, heightmap, in_hand):
        return self(heightmap, in_hand), torch.full((heightmap.shape[0], 1), self.reward)


def test_depth_one_is_the_one_step_planner(nets):
    q, dynamics, value = nets
    with set_exploration_type(ExplorationType.DETERMINISTIC):
        one_step = LookaheadPlanner(q, dynamics, value, **GREEDY)(batch())
        tree = TreePlanner(q, dynamics, value, depth=1, gamma=0.9, **GREEDY)(batch())
    for key in ("action", "candidate_actions", "candidate_values"):
        assert torch.equal(tree[key], one_step[key])
    torch.testing.assert_close(tree["candidate_scores"], one_step["candidate_values"])


def test_branching_one_with_a_constant_value_picks_the_first_proposal(nets):
    q, dynamics, _ = nets
    with set_exploration_type(ExplorationType.DETERMINISTIC):
        out = TreePlanner(q, dynamics, ConstantValue(), depth=2, branching=1, gamma=0.9, **GREEDY)(batch())
    assert torch.equal(out["action"], out["candidate_actions"][:, 0])  # Q's argmax proposal
    assert torch.isfinite(out["candidate_scores"]).sum(-1).tolist() == [1, 1, 1]
    torch.testing.assert_close(out["candidate_scores"][:, 0], torch.full((3,), 0.9 * 0.3))


def test_depth_two_scores_are_the_backup_of_the_expanded_candidates_written_out(nets):
    q, dynamics, value = nets
    gamma, k = 0.8, 2
    planner = TreePlanner(q, dynamics, value, depth=2, branching=k, gamma=gamma, terminal_reward=0.1, **GREEDY)
    s = scenes(2, seed=3)
    with set_exploration_type(ExplorationType.DETERMINISTIC):
        out = planner(TensorDict(s, batch_size=[2]))
    first = lookahead(dynamics, value, s["heightmap"], s["in_hand"], s["holding"], out["candidate_actions"],
                      with_states=True, with_reward=True)
    hp = planner.hyperparameters(greedy=True)
    for row in range(2):  # one state and one expanded candidate at a time
        expanded = first.values[row].sort(descending=True, stable=True).indices[:k]
        assert set(torch.isfinite(out["candidate_scores"][row]).nonzero().view(-1).tolist()) == set(expanded.tolist())
        for i in expanded.tolist():
            state = (first.next_heightmap[row, i][None], first.next_in_hand[row, i][None],
                     first.next_holding[row, i].view(1, 1))
            with torch.no_grad():
                q_map = q.eval()(*state)
            proposals = sample_candidates(q_map, 5, beta=hp["beta"], sigma=hp["sigma"], sigma_rot=hp["sigma_rot"],
                                          mode="argmax")
            leaves = lookahead(dynamics, value, *state, proposals).values
            reward = first.rewards[row, i]
            want = reward + gamma * float(reward <= 0.1) * leaves.amax()
            torch.testing.assert_close(out["candidate_scores"][row, i], want, rtol=1e-5, atol=1e-6)
    best = out["candidate_scores"].argmax(-1)
    assert torch.equal(out["action"], out["candidate_actions"][torch.arange(2), best])


def test_penalty_depth_one_charges_the_entropy_of_the_first_action_alone(nets):
    """penalty_depth=1: every expanded first action's backed-up score is the unpenalised tree's less λ·H of its own
    prediction (all candidates expanded, so the penalty cannot change which are); the default charges the deeper
    predictions too, which differs."""
    q, dynamics, value = nets
    lam, common = 0.5, dict(depth=2, branching=5, gamma=0.8, terminal_reward=0.1, **GREEDY)
    with set_exploration_type(ExplorationType.DETERMINISTIC):
        plain = TreePlanner(q, dynamics, value, **common)(batch())
        first = TreePlanner(q, dynamics, value, uncertainty_penalty=lam, penalty_depth=1, **common)(batch())
        every = TreePlanner(q, dynamics, value, uncertainty_penalty=lam, **common)(batch())
    assert torch.equal(first["candidate_actions"], plain["candidate_actions"])
    want = plain["candidate_scores"] - lam * first["candidate_entropy"]
    torch.testing.assert_close(first["candidate_scores"], want)
    assert not torch.allclose(every["candidate_scores"], want)  # every depth: the leaves' entropies charged too
    assert torch.equal(first["action"], first["candidate_actions"][torch.arange(3), want.argmax(-1)])
    with pytest.raises(ValueError, match=r"penalty_depth must be None \(every depth\) or an int in \[1, depth=2\], got 3"):
        TreePlanner(q, dynamics, value, penalty_depth=3, **common)


def test_a_predicted_success_ends_its_branch(nets):
    q, dynamics, _ = nets
    with set_exploration_type(ExplorationType.DETERMINISTIC):
        out = TreePlanner(q, dynamics, ConstantValue(value=0.9, reward=0.6), depth=3, branching=2, gamma=0.9,
                          terminal_reward=0.1, **GREEDY)(batch())
    finite = out["candidate_scores"][torch.isfinite(out["candidate_scores"])]
    torch.testing.assert_close(finite, torch.full_like(finite, 0.6))  # the reward, no continuation


def test_exploring_draws_only_among_the_expanded_candidates(nets):
    q, dynamics, value = nets
    torch.manual_seed(0)
    planner = TreePlanner(q, dynamics, value, depth=2, branching=2, gamma=0.9, **{**GREEDY, "tau_value": 1e6})
    td = batch(1)
    chosen = set()
    for _ in range(12):
        out = planner(td.clone())
        index = (out["candidate_actions"][0] == out["action"][0]).all(-1).nonzero().view(-1)[0]
        assert torch.isfinite(out["candidate_scores"][0, index])
        chosen.add(int(index))
    assert len(chosen) == 2  # both expanded candidates, nothing else


def test_tree_planner_bad_arguments_are_one_clear_error(nets):
    q, dynamics, value = nets
    for kwargs, message in (({"depth": 0}, "depth must be an int >= 1"),
                            ({"branching": 6}, r"branching must be an int in \[1, num_candidates=5\]"),
                            ({"gamma": 1.5}, r"gamma must be a number in \[0, 1\]"),
                            ({"terminal_reward": 0}, "terminal_reward must be a number > 0")):
        with pytest.raises(ValueError, match=message):
            TreePlanner(q, dynamics, value, **{"gamma": 0.9, **GREEDY, **kwargs})
    with pytest.raises(ValueError, match="has no value_and_reward"):
        TreePlanner(q, dynamics, lambda h, i: h.new_zeros(h.shape[0], 1), gamma=0.9, **GREEDY)


def test_env_rollout_with_the_tree_planner(nets):
    from ldm_rl.envs import make_env

    q, dynamics, value = nets
    env = make_env("ldm_rl/BlockStacking-v0", num_objects=2, max_steps=2)
    planner = TreePlanner(q, dynamics, value, depth=2, branching=2, gamma=0.9, uncertainty_penalty=0.1, **GREEDY)
    with set_exploration_type(ExplorationType.DETERMINISTIC):
        rollout = env.rollout(2, planner)
    assert rollout["candidate_scores"].shape == (rollout.shape[0], 5)
    assert rollout["candidate_entropy"].shape == (rollout.shape[0], 5)
    env.close()


# ------------------------------------------------------------------------------------------- config


def _composed(*overrides):
    from hydra import compose, initialize_config_dir
    from omegaconf import OmegaConf

    conf = Path(__file__).resolve().parents[1] / "conf"
    with initialize_config_dir(version_base="1.3", config_dir=str(conf)):
        composed = compose(config_name="train_policy", overrides=["experiment=smoke", *overrides])
    composed.logger.exp_name = "run"
    return composed, OmegaConf.to_container(composed, resolve=True)


def test_planner_tree_is_chosen_by_config_with_the_agents_gamma():
    from ldm_rl.agents import build_agent
    from ldm_rl.config_schema import SCHEMAS, validate_config

    composed, cfg = _composed("planner=tree", "planner.uncertainty_penalty=0.2", "agent.target_uncertainty_penalty=0.1")
    validate_config(composed, SCHEMAS["train_policy"])
    agent = build_agent(cfg, 0.25)
    assert type(agent.planner) is TreePlanner
    assert agent.planner.gamma == cfg["agent"]["gamma"] and agent.planner.uncertainty_penalty == 0.2
    assert agent.loss.target_uncertainty_penalty == 0.1


def test_the_schemas_null_tree_keys_do_not_reach_the_one_step_planner():
    """The recipes compose over the schema, which gives every planner config the tree's keys as null."""
    from ldm_rl.agents import build_agent

    _, cfg = _composed()
    cfg["planner"].update(depth=None, branching=None, gamma=None, terminal_reward=None)
    assert type(build_agent(cfg, 0.25).planner) is LookaheadPlanner


def test_a_one_step_runs_config_planned_with_the_tree_takes_the_trees_defaults():
    """recipes/evaluate.py planner.name=tree on a checkpoint trained with planner=diverse: the stored config holds
    the tree's keys as null, which must become TreePlanner's defaults and the agent's gamma, not an error."""
    from ldm_rl.agents import build_agent

    _, cfg = _composed("agent.gamma=0.8")
    cfg["planner"].update(name="tree", depth=None, branching=None, gamma=None, terminal_reward=None)
    agent = build_agent(cfg, 0.25)
    planner = agent.planner
    assert type(planner) is TreePlanner
    assert (planner.depth, planner.branching, planner.gamma, planner.terminal_reward) == (2, 3, 0.8, 0.1)
    # and evaluation.json's record of what played names the depth and branching that no config holds
    import sys

    recipes = str(Path(__file__).resolve().parents[1] / "recipes")
    sys.path.insert(0, recipes)
    try:
        from evaluate import played_with
    finally:
        sys.path.remove(recipes)
    assert played_with(agent, cfg)["planner"] == {"name": "tree", "num_candidates": cfg["planner"]["num_candidates"],
                                                  "uncertainty_penalty": 0.0, "empty_picks_last": False,
                                                  "pick_outcome": "mode", "pick_rotations": 1, "revisits_last": False,
                                                  "q_blend": 0.0, "uncertainty_penalty_on": "all", "depth": 2, "branching": 3,
                                                  "penalty_depth": 2}


@pytest.mark.parametrize("overrides, message", [
    (("planner.depth=2",), r"planner.depth=2 is read by planner=tree only \(got planner=diverse\)"),
    (("planner=tree", "planner.branching=11"), r"planner.branching=11 is out of range: must be <= planner.num_candidates"),
    (("planner.uncertainty_penalty=-1",), "planner.uncertainty_penalty=-1"),
    (("agent=fcdqn", "agent.target_uncertainty_penalty=0.1"), "only agent=ldm uses it"),
    (("agent=rs", "planner.empty_picks_last=true"), "planner.empty_picks_last=true is set but agent=rs .* only agent=ldm"),
    (("agent=fcdqn", "planner.pick_outcome=expected"), "planner.pick_outcome=expected is set but agent=fcdqn .* only agent=ldm"),
    (("planner.pick_outcome=mean",), "planner.pick_outcome"),
    (("agent=dynaq", "planner.uncertainty_penalty=0.25"),
     "planner.uncertainty_penalty=0.25 is set but agent=dynaq .* only agent=ldm"),
    (("agent=fcdqn", "planner.greedy_uncertainty_penalty=1.0"),
     "planner.greedy_uncertainty_penalty=1.0 is set but agent=fcdqn .* only agent=ldm"),
    (("planner.greedy_uncertainty_penalty=-2",), "planner.greedy_uncertainty_penalty=-2"),
    (("planner.pick_rotations=3",), r"planner.pick_rotations=3 must divide env.num_rotations=8"),
    (("agent=fcdqn", "planner.pick_rotations=2"), "planner.pick_rotations=2 is set but agent=fcdqn .* only agent=ldm"),
    (("agent=dynaq", "planner.q_blend=0.5"), "planner.q_blend=0.5 is set but agent=dynaq .* only agent=ldm"),
    (("agent=fcdqn", "planner.greedy_q_blend=0.5"), "planner.greedy_q_blend=0.5 is set but agent=fcdqn .* only agent=ldm"),
    (("planner.greedy_q_blend=-1",), "planner.greedy_q_blend=-1"),
    (("planner.q_blend=1.5",), "planner.q_blend=1.5"),
    (("planner=tree", "planner.penalty_depth=3"), r"planner.penalty_depth=3 is out of range: must be <= planner.depth \(2\)"),
    (("planner.penalty_depth=1",), r"planner.penalty_depth=1 is read by planner=tree only"),
])
def test_option_misuse_is_one_clear_config_error(overrides, message):
    from ldm_rl.config_schema import SCHEMAS, ConfigError, validate_config

    composed, _ = _composed(*overrides)
    with pytest.raises(ConfigError, match=message):
        validate_config(composed, SCHEMAS["train_policy"])


@pytest.mark.slow
def test_smoke_run_with_every_option_then_evaluate_its_weights_with_the_tree_planner(tmp_path):
    """CI smoke: a tiny training run with the tree planner, both entropy penalties, swept pick rotations, the failed-pick memory,
    the revisit rule with its scene memory, the LDM's height anchor, 2- or 3-block training scenes, Q fitted on its
    proposals and the expert margin, V on the log scale, then recipes/evaluate.py
    planning its weights with planner overrides (written into evaluation.json)."""
    import json
    import os
    import subprocess
    import sys

    root = Path(__file__).resolve().parents[1]
    env = {**os.environ, "OMP_NUM_THREADS": "1", "MPLBACKEND": "Agg"}

    def run(script, *overrides):
        proc = subprocess.run([sys.executable, str(root / "recipes" / script), *overrides], capture_output=True,
                              text=True, env=env, cwd=tmp_path, timeout=900)
        assert proc.returncode == 0, proc.stderr[-3000:]
        return proc

    train = tmp_path / "train"
    run("train_policy.py", "experiment=smoke", "planner=tree", "planner.depth=2", "planner.branching=2",
        "planner.uncertainty_penalty=0.1", "planner.greedy_uncertainty_penalty=0.3", "planner.empty_picks_last=true",
        "planner.pick_rotations=2", "agent.target_uncertainty_penalty=0.1", "env.failed_pick_memory=4",
        "planner.revisits_last=true", "env.scene_memory=4", "env.train_object_counts=[2,3]", "agent.q_proposal_fit=1",
        "model.height_anchor=0.08", "agent.expert_margin_weight=0.1", "agent.value_log_floor=0.01",
        "agent.value_margin_weight=0.5", "planner.greedy_q_blend=0.25",
        f"hydra.run.dir={train}")
    final = json.loads((train / "final_metrics.json").read_text())
    assert final["agent"] == "ldm" and final["episodes"] >= 2
    from ldm_rl.agents import load_agent

    agent, _ = load_agent(train / "checkpoint.pt")  # the log-scale V is rebuilt from the checkpoint's config
    assert agent.loss.value_network.value_log_floor == 0.01
    run("evaluate.py", f"checkpoint={train / 'checkpoint.pt'}", "episodes=1", "progress=false", "planner.name=diverse",
        "planner.num_candidates=1", "planner.uncertainty_penalty=0.0", "planner.empty_picks_last=true",
        "planner.pick_outcome=expected", "planner.pick_rotations=4", "planner.q_blend=0.5",
        "planner.uncertainty_penalty_on=places", "failed_pick_memory=0",
        "q_pick_min_height=0.015", "hand_rule=removal",
        f"hydra.run.dir={tmp_path / 'eval'}")
    result = json.loads((tmp_path / "eval" / "evaluation.json").read_text())
    assert result["planner"] == {"name": "diverse", "num_candidates": 1, "uncertainty_penalty": 0.0, "empty_picks_last": True,
                                 "pick_outcome": "expected", "pick_rotations": 4, "q_blend": 0.5,
                                 "uncertainty_penalty_on": "places"}
    assert result["episodes"] == 1
    assert result["failed_pick_memory"] == 0 and result["q_pick_min_height"] == 0.015 and result["hand_rule"] == "removal"
    # what played: the overrides over the checkpoint's own settings (trained with the tree, λ = 0.1, greedy 0.3, Q's
    # greedy vote 0.25): an overridden λ or w is these greedy decisions' λ or w
    assert result["played_with"] == {"q_pick_min_height": 0.015, "hand_rule": "removal", "height_anchor": 0.08, "planner": {
        "name": "diverse", "num_candidates": 1, "uncertainty_penalty": 0.0, "empty_picks_last": True, "pick_outcome": "expected",
        "pick_rotations": 4, "revisits_last": True, "q_blend": 0.5, "uncertainty_penalty_on": "places"}}
    run("evaluate.py", f"checkpoint={train / 'checkpoint.pt'}", "episodes=1", "progress=false",
        f"hydra.run.dir={tmp_path / 'eval_own'}")
    own = json.loads((tmp_path / "eval_own" / "evaluation.json").read_text())
    assert "planner" not in own and "hand_rule" not in own and own["played_with"]["hand_rule"] == "occupancy"
    assert own["played_with"]["planner"] == {  # the checkpoint's greedy λ and w
        "name": "tree", "num_candidates": 3, "uncertainty_penalty": 0.3, "empty_picks_last": True, "pick_outcome": "mode",
        "pick_rotations": 2, "revisits_last": True, "q_blend": 0.25, "uncertainty_penalty_on": "all", "depth": 2,
        "branching": 2, "penalty_depth": 2}


def test_planner_overrides_on_a_checkpoint_of_another_agent_are_one_clear_error(tmp_path):
    from ldm_rl.agents import load_agent
    from ldm_rl.run.checkpoint import CheckpointError, save_checkpoint

    path = save_checkpoint(tmp_path / "checkpoint.pt", {"agent": {}},
                           meta={"kind": "agent", "preset": "lite", "task": "ldm_rl/BlockStacking-v0",
                                 "config": {"agent": {"name": "fcdqn"}, "planner": {"tau": 0.1}}})
    with pytest.raises(CheckpointError, match="apply to the ldm agent's planner; .* holds agent 'fcdqn'"):
        load_agent(path, planner={"name": "tree"})
    with pytest.raises(CheckpointError, match="hand_rule='removal' is the world model's; .* holds agent 'fcdqn'"):
        load_agent(path, hand_rule="removal")


def test_a_checkpoint_plays_with_the_empty_pick_mask_set_at_load_and_bad_values_are_refused(tmp_path):
    """load_agent(q_pick_min_height=h) builds the checkpoint's Q with the mask (the weights unchanged), so a run
    trained without it is played with it; RS (no Q) and heights outside [0, max_height) are one clear error."""
    from hydra import compose, initialize_config_dir
    from omegaconf import OmegaConf

    from ldm_rl.agents import build_agent, load_agent
    from ldm_rl.run.checkpoint import CheckpointError, save_checkpoint

    root = Path(__file__).resolve().parents[1]
    with initialize_config_dir(version_base="1.3", config_dir=str(root / "conf")):
        cfg = compose(config_name="train_policy", overrides=["experiment=smoke"])
    trained = build_agent(cfg, float(cfg.env.max_height))
    stored = {key: value for key, value in OmegaConf.to_container(cfg).items() if key != "logger"}  # names Hydra's run
    meta = {"kind": "agent", "agent": "ldm", "preset": "lite", "task": cfg.env.id,
            "config": OmegaConf.to_container(OmegaConf.create(stored), resolve=True)}
    path = save_checkpoint(tmp_path / "checkpoint.pt", {"agent": trained.policy_state_dict()}, meta=meta)

    plain, plain_cfg = load_agent(path)
    masked, masked_cfg = load_agent(path, q_pick_min_height=0.02)
    assert plain.greedy_policy.q_network.pick_min_height == 0.0 and plain_cfg["agent"].get("q_pick_min_height", 0) == 0
    assert masked.greedy_policy.q_network.pick_min_height == 0.02 and masked_cfg["agent"]["q_pick_min_height"] == 0.02
    assert masked.evaluation_policy().q_network.pick_min_height == 0.02  # what recipes/evaluate.py plays
    for key, value in plain.greedy_policy.q_network.state_dict().items():
        assert torch.equal(value, masked.greedy_policy.q_network.state_dict()[key]), key

    too_high = float(cfg.env.max_height)
    with pytest.raises(CheckpointError, match=rf"q_pick_min_height must be in \[0, max_height = {too_high}\) .* got {too_high}"):
        load_agent(path, q_pick_min_height=too_high)
    rs = save_checkpoint(tmp_path / "rs.pt", {"agent": {}},
                         meta={**meta, "agent": "rs", "config": {**meta["config"], "agent": {"name": "rs"}}})
    with pytest.raises(CheckpointError, match="q_pick_min_height=0.02 masks a Q network's picks; .* holds agent 'rs'"):
        load_agent(rs, q_pick_min_height=0.02)


# ------------------------------------------------------------------------------------- expected pick outcome


def _block_and_logits(dynamics, hold: float, action):
    """A 0.05 m block of 16×16 px centred at (64, 64) and frame logits at ``action`` that drop the block's pixels
    to the floor with probability ``hold`` and leave every pixel as it was otherwise (all classes' log-probabilities)."""
    heightmap = torch.zeros(1, 1, 128, 128)
    heightmap[..., 56:72, 56:72] = 0.05
    before = dynamics.frame_classes(heightmap, action).long()  # [1, 1, 64, 64]
    k = dynamics.num_classes
    probs = torch.full((1, k, 64, 64), 1e-6)
    probs.scatter_(1, before, 1.0 - hold)
    on_block = (before > 0).expand(1, k, 64, 64) & (torch.arange(k).view(1, k, 1, 1) == 0)
    probs = torch.where(on_block, torch.full_like(probs, hold), probs)
    return heightmap, probs.log()


@pytest.mark.parametrize("hold", [0.0, 0.3, 0.8])
def test_held_outcome_reads_the_pick_probability_and_removes_the_object_the_mode_keeps(nets, hold):
    _, dynamics, _ = nets
    action = torch.tensor([[64, 64, 0]])
    heightmap, logits = _block_and_logits(dynamics, hold, action)
    held = dynamics.held_outcome(heightmap, action, logits)
    assert held.probability.shape == (1,) and held.probability.item() == pytest.approx(hold, abs=1e-3)
    mode = dynamics.next_state_from_logits(heightmap, torch.zeros(1, 1, 24, 24), torch.zeros(1, 1, dtype=torch.bool),
                                           action, logits)
    if hold > 0:  # the block's pixels go, every other pixel as it was (at 0 the branch weighs nothing)
        torch.testing.assert_close(held.heightmap, torch.zeros_like(heightmap))
    # the mode keeps the likelier outcome only: the block stays below one chance in two
    torch.testing.assert_close(mode.heightmap, heightmap if hold < 0.5 else torch.zeros_like(heightmap))
    from ldm_rl import geometry
    torch.testing.assert_close(held.in_hand, geometry.crop(heightmap, action[:, :2], torch.zeros(1), 24, mode="bilinear"))


def test_held_outcome_of_an_off_centre_pick_weighs_the_pixels_under_the_fingers(nets):
    _, dynamics, _ = nets
    action = torch.tensor([[64, 72, 0]])  # the 12-px window under the fingers: columns 66..77, half on the block
    heightmap, logits = _block_and_logits(dynamics, 0.6, action)
    assert dynamics.held_outcome(heightmap, action, logits).probability.item() == pytest.approx(0.6 * 6 / 12, abs=1e-3)
    with pytest.raises(ValueError, match=r"logits must be \[1, 21, 64, 64\]"):
        dynamics.held_outcome(heightmap, action, logits[..., :32])
    with pytest.raises(ValueError, match="action must be"):
        dynamics.held_outcome(heightmap, action[:, :2], logits)
    with pytest.raises(ValueError, match="heightmap must be"):
        dynamics.held_outcome(heightmap[..., :64], action, logits)
    with pytest.raises(ValueError, match="action out of range"):
        dynamics.held_outcome(heightmap, torch.tensor([[64, 200, 0]]), logits)


def test_expected_pick_outcome_scores_picks_by_both_branches_and_leaves_places_as_the_mode_scores_them(nets):
    q, dynamics, value = nets
    data = scenes(4, seed=3)  # states 0, 2 pick (empty hand), 1, 3 place
    g = torch.Generator().manual_seed(5)
    candidates = torch.stack([torch.randint(20, 108, (4, 6), generator=g), torch.randint(20, 108, (4, 6), generator=g),
                              torch.randint(0, 8, (4, 6), generator=g)], -1)
    args = (dynamics, value, data["heightmap"], data["in_hand"], data["holding"], candidates)
    mode = lookahead(*args, chunk_size=5)
    expected = lookahead(*args, chunk_size=7, pick_outcome="expected", with_states=True)
    placing = data["holding"].view(4).bool()
    torch.testing.assert_close(expected.values[placing], mode.values[placing])
    assert torch.equal(expected.next_holding, mode.next_holding) and (expected.hold_probability[placing] == 0).all()
    # by hand, one pick state: p·V(held) + (1 − p)·V(s)
    with torch.no_grad():
        dynamics.eval(), value.eval()
        s = {key: data[key][:1].expand(6, *data[key].shape[1:]) for key in ("heightmap", "in_hand", "holding")}
        logits = dynamics(s["heightmap"], s["in_hand"], s["holding"], candidates[0])
        held = dynamics.held_outcome(s["heightmap"], candidates[0], logits)
        want = held.probability * value(held.heightmap, held.in_hand).view(6) + \
            (1 - held.probability) * value(data["heightmap"][:1], data["in_hand"][:1]).view(1)
    torch.testing.assert_close(expected.values[0], want)
    torch.testing.assert_close(expected.hold_probability[0], held.probability)
    torch.testing.assert_close(expected.next_heightmap[0], held.heightmap)  # the states V scored: the held branch
    assert not torch.allclose(expected.values[~placing], mode.values[~placing])
    with pytest.raises(ValueError, match="pick_outcome must be one of .*'mode', 'expected'.*, got 'mean'"):
        lookahead(*args, pick_outcome="mean")
    with pytest.raises(ValueError, match="pick_outcome='expected' scores V alone: with_reward"):
        lookahead(*args, pick_outcome="expected", with_reward=True)


def test_the_planner_with_expected_pick_outcomes_chooses_by_them_and_the_tree_refuses_them(nets):
    q, dynamics, value = nets
    data = batch(4)
    planner = LookaheadPlanner(q, dynamics, value, pick_outcome="expected", **GREEDY)
    with set_exploration_type(ExplorationType.DETERMINISTIC):
        out = planner(data.clone())
    with torch.no_grad():
        again = lookahead(dynamics, value, data["heightmap"], data["in_hand"], data["holding"], out["candidate_actions"],
                          pick_outcome="expected")
    torch.testing.assert_close(out["candidate_values"], again.values)
    best = out["candidate_actions"][torch.arange(4), again.values.argmax(-1)]
    assert torch.equal(out["action"], best)
    with pytest.raises(ValueError, match="pick_outcome must be one of"):
        LookaheadPlanner(q, dynamics, value, pick_outcome="expectation")
    with pytest.raises(ValueError, match="pick_outcome='expected' is the one-step planner's .*got depth=2"):
        TreePlanner(q, dynamics, value, gamma=0.9, depth=2, pick_outcome="expected")
    assert TreePlanner(q, dynamics, value, gamma=0.9, depth=1, pick_outcome="expected").pick_outcome == "expected"
