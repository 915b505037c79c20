"""Where bin packing's pile height comes from: how the blocks come to rest, what the world model predicted, what V chose.

    python benchmarks/place_outcomes.py <run>/checkpoint.pt [--episodes 30] [--planner uncertainty_penalty=0.25 ...]

Plays a bin-packing checkpoint's greedy policy on the held-out scenes of ``recipes/evaluate.py`` (``--seed``), then
the scripted expert on the same scenes. Per place that leaves its block in the bin: whether the block rests *tilted*
(its axis nearest the vertical more than ``--tilt`` degrees off it) or *raised* (its AABB more than 6 mm taller than
the block lying on its widest face), whether it was tilted in the hand before the place, and how far the place raised
the pile (the highest point over the bin's floor, read from the heightmap). For the agent's places (an LDM agent) also
the world model's prediction for the place taken: the pile top it predicted against the real one (*missed rises*: the
real top more than 1 cm above the predicted), and among the N candidates the planner scored, those the model predicts
to put the block into the bin (more than ``--min-volume`` m³ added inside it): the rank correlation of V with their
predicted pile tops (negative: V prefers the lower piles) and how often the chosen one's predicted top is more than
2 mm above the lowest of them. A measurement of decisions, not of time; run by hand (docs/policy.md, "Bin packing").

Two diagnostics change the place decisions (not planners to train with; the picks stay with the planner):
``--choose lowest-top`` takes, among the candidates the world model predicts to enter the bin, the one with the lowest
predicted pile top instead of V's best (V still decides where none enters): how low a V that read the pile off the
predicted heightmap could keep it with these candidates and this world model; with ``--top-quantile Q`` each
candidate's pile is read with every pixel of the LDM's crop at the Q-quantile of its predicted depth classes instead
of their mode (whether the model's distribution, not its mode, knows which places tip). ``--choose q-first`` takes Q's first
proposal (its argmax under the greedy ``argmax`` proposal): the place Q alone would choose; ``nearest-expert`` the
candidate nearest the noiseless scripted expert's place for the same state (pixels plus ``ROTATION_PX`` per rotation
bin apart), and reports how near the nearest was: whether the candidates hold the expert's place. ``--expert-does places``
(or ``picks``) splits the work: the scripted expert takes those primitives, the checkpoint's policy the others, which
tells the part the pick order plays from the part the places play. ``--place-weights CHECKPOINT`` hands the places to
another checkpoint's greedy planner (``pick_outcomes.py --places --margin-steps K --save-weights``: the same weights with
Q's place map fitted), the picks staying with the first: what a sharper place map alone does to the pile (``--choose``
then acts on that planner's places). ``--place-planner KEY=VALUE ...`` gives the places' planner its own settings
over ``--planner``'s (alone: the checkpoint's own weights under them), e.g. ``--planner q_blend=1.0 --place-planner
q_blend=0.0``: Q picks, V places, which splits a pile between the two choices on the same weights.
"""

from __future__ import annotations

import argparse
import math
import sys

import numpy as np
import torch

RAISED_SLACK = 0.006  # m
MISSED_RISE = 0.01  # m
HIGHER_CHOICE = 0.002  # m
ROTATION_PX = 10.0  # pixels a rotation bin apart counts for in --choose nearest-expert


def tilt_degrees(rotation: np.ndarray) -> np.ndarray:
    """Angle (degrees) between the world's z axis and the body axis nearest to it, for rotation matrices
    ``[..., 3, 3]`` (columns: the body's axes in world coordinates); 0 for a block resting on any face."""
    cos = np.abs(rotation[..., 2, :]).max(-1)
    return np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))


def yaw_off_axes(rotation: np.ndarray, frame_yaw: float) -> np.ndarray:
    """Degrees in [0, 45] between a resting block's sides and a frame's axes (yaw ``frame_yaw`` rad), for rotation
    matrices ``[..., 3, 3]``: the body axis nearest the horizontal plane, its heading modulo a quarter turn."""
    horizontal = np.take_along_axis(rotation, np.abs(rotation[..., 2:3, :]).argmin(-1)[..., None, :], -1)[..., 0]
    heading = np.degrees(np.arctan2(horizontal[..., 1], horizontal[..., 0]) - frame_yaw) % 90.0
    return np.minimum(heading, 90.0 - heading)


def lying_height(half_extents) -> float:
    """A box-like block's height lying on its widest face, m: twice its smallest half extent."""
    return 2.0 * float(min(half_extents))


def rank_correlation(x: np.ndarray, y: np.ndarray) -> float:
    """Spearman's rank correlation of ``x`` and ``y`` ``[N]`` (average ranks for ties); nan when either is constant."""
    def ranks(v):
        order = np.argsort(v, kind="stable")
        r = np.empty(len(v))
        r[order] = np.arange(len(v), dtype=float)
        for value in np.unique(v):  # average the ranks of ties
            tied = v == value
            r[tied] = r[tied].mean()
        return r

    x, y = np.asarray(x, float), np.asarray(y, float)
    if len(x) < 2 or np.ptp(x) == 0 or np.ptp(y) == 0:
        return float("nan")
    return float(np.corrcoef(ranks(x), ranks(y))[0, 1])


def bin_interior(task, inset: float = 0.004) -> np.ndarray:
    """``[H, W]`` bool: heightmap pixels whose centre lies inside the bin's inner walls less ``inset`` m."""
    from ldm_rl.envs.tasks.bin_packing import BIN

    ws = task.workspace
    centres = (np.arange(ws.pixels) + 0.5) * ws.resolution
    xy = np.stack(np.meshgrid(ws.x_min + centres, ws.y_min + centres, indexing="ij"), -1)
    uv = task.bin.to_local(xy.reshape(-1, 2)).reshape(ws.pixels, ws.pixels, 2)
    return (np.abs(uv[..., 0]) < BIN.inner_x / 2 - inset) & (np.abs(uv[..., 1]) < BIN.inner_y / 2 - inset)


def block_states(task) -> dict[int, dict]:
    """Every block's state now: in the bin (centre seen from above), tilt (degrees), AABB height (m), lying height."""
    import pybullet as pb

    states = {}
    for obj in task.sim.objects:
        low, high = task.sim.aabb(obj.body)
        position, quaternion = task.sim.pose(obj.body)
        rotation = np.array(pb.getMatrixFromQuaternion(list(quaternion))).reshape(3, 3)
        states[obj.body] = {"in_bin": bool(task.bin.contains(position)), "tilt": float(tilt_degrees(rotation)),
                            "yaw_off": float(yaw_off_axes(rotation, task.bin.yaw)),
                            "height": float(high[2] - low[2]), "lying": lying_height(obj.half_extents),
                            "volume": float(8 * np.prod(obj.half_extents))}
    return states


def place_rows(snapshots: list[dict], tilt: float, yaw: float = 10.0) -> list[dict]:
    """One row per place into the bin from the per-decision ``snapshots`` (``held``: the held body or None,
    ``blocks``: :func:`block_states`, plus the one after the last decision); ``turned``: the block rests level
    (not ``tilt``-ed) with its sides more than ``yaw`` degrees off the bin's walls; ``largest``: the block was the
    largest (by volume) of those not yet in the bin when it was placed (the scripted expert packs largest first)."""
    rows = []
    for before, after in zip(snapshots[:-1], snapshots[1:]):
        body = before["held"]
        if body is None or after["held"] is not None or not after["blocks"][body]["in_bin"]:
            continue
        rest = after["blocks"][body]
        left = [b["volume"] for key, b in before["blocks"].items() if key != body and not b["in_bin"]]
        rows.append({"tilted": rest["tilt"] > tilt, "raised": rest["height"] > rest["lying"] + RAISED_SLACK,
                     "tilted_in_hand": before["blocks"][body]["tilt"] > tilt, "step": before["step"],
                     "turned": rest["tilt"] <= tilt and rest["yaw_off"] > yaw,
                     "largest": rest["volume"] >= max(left, default=0.0) - 1e-12})
    return rows


def recorder(policy, take):
    """``policy`` wrapped as the TensorDict module ``env.rollout`` calls, appending ``take(step)`` (a snapshot of
    the scene, ``step`` the decision's index) to its ``snapshots`` before each decision (the caller clears them per
    episode)."""
    from tensordict.nn import TensorDictModuleBase

    class Recorder(TensorDictModuleBase):
        in_keys, out_keys = [], []

        def __init__(self):
            super().__init__()
            self.snapshots = []

        def forward(self, tensordict):
            self.snapshots.append(take(len(self.snapshots)))
            return policy(tensordict)

    return Recorder()


def snapshot(task, step: int) -> dict:
    """The held body (or None) and :func:`block_states` at decision ``step``."""
    held = task.gripper.held
    return {"held": None if held is None else held.body, "blocks": block_states(task), "step": step}


def decision_rows(rollout, planner, interior: torch.Tensor, min_volume: float, resolution: float) -> list[dict]:
    """Per place decision of an LDM agent's ``rollout``: the world model's predicted pile top for the place taken
    against the real one, and V against the predicted pile tops of the candidates predicted to enter the bin."""
    from ldm_rl.planning.lookahead import lookahead

    rows = []
    for t in range(rollout.shape[0]):
        step = rollout[t]
        if not bool(step["holding"].reshape(-1)[0]):
            continue
        heightmap, candidates = step["heightmap"][None], step["candidate_actions"][None]
        result = lookahead(planner.dynamics, planner.value_network, heightmap, step["in_hand"][None],
                           step["holding"].reshape(1, 1), candidates, with_states=True)
        predicted = result.next_heightmap[0, :, 0][:, interior]  # [N, P] m
        before = heightmap[0, 0][interior]
        tops = predicted.amax(-1).numpy()
        added = ((predicted - before).clamp(min=0).sum(-1) * resolution ** 2).numpy()  # m^3 inside the bin
        chosen = int((candidates[0] == step["action"].reshape(1, -1)).all(-1).float().argmax())
        entering = added > min_volume
        values = result.values[0].reshape(len(tops)).numpy()
        rows.append({"real_top": float(step["next", "heightmap"][0][interior].max()), "predicted_top": float(tops[chosen]),
                     "chosen_enters": bool(entering[chosen]), "entering": int(entering.sum()),
                     "rho": rank_correlation(tops[entering], values[entering]) if entering.sum() >= 3 else float("nan"),
                     "above_lowest": float(tops[chosen] - tops[entering].min()) if entering[chosen] else float("nan")})
    return rows


def quantile_heightmaps(dynamics, heightmap, in_hand, holding, candidates, quantile: float) -> torch.Tensor:
    """``[B, N, 1, H, W]`` m: the next heightmaps of ``candidates`` ``[B, N, 3]`` with each pixel of the LDM's crop at
    the ``quantile`` of its predicted depth-class distribution (the smallest class whose cumulative probability reaches
    it) instead of its mode: a rise the model gives a chance below one half (a block that may tip) shows once that
    chance exceeds ``1 − quantile`` (the LDM in eval mode)."""
    from ldm_rl.torch_utils import eval_mode

    b, n = candidates.shape[:2]
    rows = torch.arange(b).repeat_interleave(n)
    state = (heightmap[rows], in_hand[rows], holding.reshape(b, 1)[rows], candidates.reshape(b * n, 3))
    with eval_mode(dynamics):
        logits = dynamics(*state)  # [B·N, K, S, S]
    cumulative = torch.softmax(logits.float(), 1).cumsum(1)
    classes = (cumulative < quantile).sum(1, keepdim=True).clamp(max=logits.shape[1] - 1)  # [B·N, 1, S, S]
    one_hot = torch.zeros_like(logits).scatter_(1, classes, 1.0)  # its argmax is the quantile's class
    return dynamics.next_state_from_logits(*state, one_hot).heightmap.reshape(b, n, *heightmap.shape[1:])


def choose_lowest_top(planner, task, min_volume: float, quantile: float | None = None) -> None:
    """Make ``planner``'s place decisions by the lowest predicted pile top among the candidates predicted to enter
    ``task``'s bin (more than ``min_volume`` m^3 added inside it); picks, and places where none enters, keep its own
    scores. ``quantile``: the pile read from :func:`quantile_heightmaps` instead of the prediction's mode. Replaces
    the instance's ``score`` (the diagnostic of ``--choose lowest-top``)."""
    score, resolution = planner.score, task.workspace.resolution

    def lowest_top(heightmap, in_hand, holding, candidates, penalty, **options):
        scores, result = score(heightmap, in_hand, holding, candidates, penalty, **{**options, "with_states": True})
        interior = torch.as_tensor(bin_interior(task))  # the bin moves with each scene
        states = result.next_heightmap if quantile is None else quantile_heightmaps(
            planner.dynamics, heightmap, in_hand, holding, candidates, quantile)
        predicted = states[:, :, 0][..., interior]  # [B, N, P] m
        added = (predicted - heightmap[:, 0][:, interior][:, None]).clamp(min=0).sum(-1) * resolution ** 2
        entering = added > min_volume  # [B, N]
        tops = torch.where(entering, -predicted.amax(-1), torch.full_like(scores, -math.inf))
        use = holding.reshape(-1, 1).bool() & entering.any(-1, keepdim=True)
        return torch.where(use, tops, scores), result

    planner.score = lowest_top


def choose_q_first(planner) -> None:
    """Make ``planner``'s place decisions take its first candidate (Q's argmax under the ``argmax`` proposal); picks
    keep its own scores. Replaces the instance's ``score`` (the diagnostic of ``--choose q-first``)."""
    score = planner.score

    def q_first(heightmap, in_hand, holding, candidates, penalty, **options):
        scores, result = score(heightmap, in_hand, holding, candidates, penalty, **options)
        first = torch.full_like(scores, -math.inf)
        first[:, 0] = 0.0
        return torch.where(holding.reshape(-1, 1).bool(), first, scores), result

    planner.score = q_first


def choose_nearest_expert(planner, task) -> list[tuple[float, int]]:
    """Make ``planner``'s place decisions take the candidate nearest ``task``'s noiseless expert place (pixel distance
    plus ``ROTATION_PX`` per rotation bin apart); picks keep its own scores. Replaces the instance's ``score`` (the
    diagnostic of ``--choose nearest-expert``); returns the list it fills per place decision with the nearest
    candidate's (pixel distance, rotation bins apart) and the fraction of Q's map entries above the expert's place."""
    from ldm_rl.envs.base import ExpertNoise
    from ldm_rl.geometry import circular_bin_distance

    score, nearest, noiseless = planner.score, [], ExpertNoise()

    def nearest_expert(heightmap, in_hand, holding, candidates, penalty, **options):
        scores, result = score(heightmap, in_hand, holding, candidates, penalty, **options)
        if candidates.shape[0] != 1:  # the expert reads the one env's state
            raise ValueError(f"--choose nearest-expert plays one env: a batch of 1 state, got {candidates.shape[0]}")
        if not bool(holding.reshape(-1)[0]):
            return scores, result
        expert = torch.as_tensor(task.expert_action(noiseless))
        pixels = (candidates[0, :, :2] - expert[:2]).float().norm(dim=-1)  # [N]
        turns = circular_bin_distance(candidates[0, :, 2], expert[2], task.num_rotations)
        distance = pixels + ROTATION_PX * turns
        best = int(distance.argmin())
        q_map = planner.q_network(heightmap, in_hand, holding)[0]  # [R, H, W], eval mode (inside decide)
        above = float((q_map > q_map[expert[2], expert[0], expert[1]]).float().mean())
        nearest.append((float(pixels[best]), int(turns[best]), above))
        chosen = torch.full_like(scores, -math.inf)
        chosen[0, best] = 0.0
        return chosen, result

    planner.score = nearest_expert
    return nearest


def split_policy(agent_policy, expert, expert_does: str):
    """A policy writing only ``"action"``: ``expert``'s at its primitives (``expert_does``: ``"places"``, the
    decisions with a block in the hand, or ``"picks"``), ``agent_policy``'s at the others."""
    def policy(tensordict):
        holding = bool(tensordict.get("holding").reshape(-1)[0])
        chooser = expert if holding == (expert_does == "places") else agent_policy
        tensordict.set("action", chooser(tensordict.clone()).get("action"))
        return tensordict

    return policy


def route_places(pick_policy, place_policy):
    """A policy handing the decisions with a block in the hand to ``place_policy`` and the others to ``pick_policy``,
    each writing its whole output (two planners of one kind: the same keys at every step)."""
    def policy(tensordict):
        holding = bool(tensordict.get("holding").reshape(-1)[0])
        return (place_policy if holding else pick_policy)(tensordict)

    return policy


def play(env, task, policy, episodes: int, seed: int, tilt: float, on_episode=None) -> tuple[list[dict], list[float]]:
    """Greedy episodes on the held-out scenes of ``seed``: the place rows and each packed episode's pile top (m)."""
    from ldm_rl.envs.tasks.bin_packing import pile_top_from_reward
    from ldm_rl.evaluation import evaluate_policy
    from ldm_rl.seeds import held_out_scenes

    module, places, tops = recorder(policy, lambda step: snapshot(task, step)), [], []

    def record(index, rollout):
        places.extend(place_rows(module.snapshots + [snapshot(task, len(module.snapshots))], tilt))
        module.snapshots = []
        if task.pack_reward > 0:
            tops.append(pile_top_from_reward(task.pack_reward))
        if on_episode is not None:
            on_episode(index, rollout)

    evaluate_policy(env, module, episodes, seed=held_out_scenes(seed), on_episode=record)
    return places, tops


def summary(name: str, places: list[dict], tops: list[float], episodes: int) -> str:
    tilted = np.mean([p["tilted"] for p in places]) if places else float("nan")
    raised = np.mean([p["raised"] for p in places]) if places else float("nan")
    in_hand = np.mean([p["tilted_in_hand"] for p in places]) if places else float("nan")
    turned = np.mean([p["turned"] for p in places]) if places else float("nan")
    largest = np.mean([p["largest"] for p in places]) if places else float("nan")
    top = f"{100 * np.mean(tops):.1f} cm" if tops else "-"
    return (f"| {name} | {len(tops)} / {episodes} | {top} | {len(places)} | {100 * tilted:.0f} % | {100 * raised:.0f} % "
            f"| {100 * in_hand:.0f} % | {100 * turned:.0f} % | {100 * largest:.0f} % |")


def parse_args(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("checkpoint", help="a bin-packing run's checkpoint.pt (or best_policy.pt)")
    parser.add_argument("--episodes", type=int, default=30)
    parser.add_argument("--seed", type=int, default=0, help="the held-out scenes of recipes/evaluate.py seed=...")
    parser.add_argument("--planner", nargs="*", default=[], metavar="KEY=VALUE",
                        help="planner settings over the checkpoint's (as recipes/evaluate.py planner.KEY=VALUE)")
    parser.add_argument("--tilt", type=float, default=10.0, help="degrees off the nearest face-down pose: tilted")
    parser.add_argument("--min-volume", type=float, default=1.5e-5,
                        help="m^3 a candidate must add inside the bin to count as entering it (half a half cube)")
    parser.add_argument("--choose", choices=("value", "lowest-top", "q-first", "nearest-expert"), default="value",
                        help="how the places are chosen: by the planner (value) or, diagnostics, by the lowest "
                             "predicted pile top among the candidates predicted to enter the bin, Q's argmax, or the "
                             "candidate nearest the scripted expert's place")
    parser.add_argument("--top-quantile", type=float, default=None, metavar="Q",
                        help="with --choose lowest-top: read each candidate's pile at the Q-quantile of the LDM's "
                             "per-pixel depth classes instead of their mode (in (0, 1))")
    parser.add_argument("--expert-does", choices=("places", "picks"), default=None,
                        help="the scripted expert takes these primitives, the checkpoint's policy the others")
    parser.add_argument("--place-weights", default=None, metavar="CHECKPOINT",
                        help="another checkpoint of the same run's kind whose greedy planner makes the places (e.g. "
                             "pick_outcomes.py --save-weights' fit), the checkpoint's the picks")
    parser.add_argument("--place-planner", nargs="*", default=[], metavar="KEY=VALUE",
                        help="planner settings of the places' planner over --planner's (with --place-weights, or alone: "
                             "the checkpoint's own weights make the places under these settings, e.g. q_blend=0)")
    args = parser.parse_args(argv)
    if args.place_weights and args.expert_does:
        parser.error(f"--place-weights {args.place_weights} makes the places: leave out --expert-does")
    if args.expert_does and args.choose != "value":
        parser.error(f"--expert-does {args.expert_does} leaves no place decision to --choose {args.choose}: give one")
    if args.top_quantile is not None and (args.choose != "lowest-top" or not 0 < args.top_quantile < 1):
        parser.error(f"--top-quantile must be in (0, 1) and go with --choose lowest-top, got {args.top_quantile} "
                     f"with --choose {args.choose}")
    if args.episodes < 1:
        parser.error(f"--episodes must be >= 1, got {args.episodes}")
    if not 0 < args.tilt < 90:
        parser.error(f"--tilt must be in (0, 90) degrees, got {args.tilt}")
    for name in ("planner", "place_planner"):
        setattr(args, name, key_values(parser, f"--{name.replace('_', '-')}", getattr(args, name)))
    if args.place_planner and args.expert_does:
        parser.error(f"--place-planner {args.place_planner} sets the places' planner: leave out --expert-does")
    return args


def key_values(parser, option: str, items: list[str]) -> dict:
    """``KEY=VALUE`` items as a dict, each value read as an int, a float, true / false or else a string; an item
    without ``=`` stops the parser in one line naming ``option`` and the item."""
    settings = {}
    for item in items:
        key, sep, value = item.partition("=")
        if not sep or not key:
            parser.error(f"{option} takes KEY=VALUE items, got {item!r}")
        settings[key] = _number(value)
    return settings


def _number(text: str):
    for cast in (int, float):
        try:
            return cast(text)
        except ValueError:
            pass
    return {"true": True, "false": False}.get(text.lower(), text)


def main(argv=None) -> None:
    args = parse_args(argv)
    from ldm_rl.agents import load_agent
    from ldm_rl.envs import expert_policy, make_env_from_config
    from ldm_rl.envs.torchrl_env import unwrap
    from ldm_rl.evaluation import is_bin_packing
    from ldm_rl.run.checkpoint import CheckpointError
    from ldm_rl.torch_utils import seed_everything, set_threads

    set_threads(1)
    seed_everything(args.seed)
    try:
        agent, cfg = load_agent(args.checkpoint, planner=args.planner or None)
    except (CheckpointError, ValueError) as err:
        sys.exit(f"error: {err}")
    env = make_env_from_config(dict(cfg["env"]))
    if not is_bin_packing(env):
        sys.exit(f"error: {args.checkpoint} plays {cfg['env']['id']}, not bin packing")
    task = unwrap(env)
    planner = agent.greedy_policy if agent.name == "ldm" else None
    if args.place_weights or args.place_planner:  # the places' planner: the one --choose acts on and the readings read
        try:
            placer, place_cfg = load_agent(args.place_weights or args.checkpoint,
                                           planner={**args.planner, **args.place_planner} or None)
        except (CheckpointError, ValueError) as err:
            sys.exit(f"error: {err}")
        if placer.name != "ldm" or planner is None or place_cfg["env"]["id"] != cfg["env"]["id"]:
            sys.exit(f"error: --place-weights / --place-planner need LDM checkpoints of one task; {args.place_weights} "
                     f"holds {placer.name!r} on {place_cfg['env']['id']}, {args.checkpoint} {agent.name!r} on {cfg['env']['id']}")
        planner = placer.greedy_policy
    if args.choose != "value" and planner is None:
        sys.exit(f"error: --choose {args.choose} needs an LDM agent's checkpoint, {args.checkpoint} is {agent.name}'s")
    if args.choose == "lowest-top":
        choose_lowest_top(planner, task, args.min_volume, args.top_quantile)
    elif args.choose == "q-first":
        if planner.greedy_proposal != "argmax":
            sys.exit(f"error: --choose q-first needs the greedy proposal 'argmax' (Q's argmax first), "
                     f"the checkpoint's planner has {planner.greedy_proposal!r}")
        choose_q_first(planner)
    nearest = choose_nearest_expert(planner, task) if args.choose == "nearest-expert" else []
    decisions: list[dict] = []

    def read_decisions(index, rollout):
        interior = torch.as_tensor(bin_interior(task))
        decisions.extend(decision_rows(rollout, planner, interior, args.min_volume, task.workspace.resolution))

    policy = agent.evaluation_policy()
    if args.place_weights or args.place_planner:
        policy = route_places(policy, placer.evaluation_policy())
    if args.expert_does:
        policy, planner = split_policy(policy, expert_policy(env), args.expert_does), None
    with torch.no_grad():
        agent_places, agent_tops = play(env, task, policy, args.episodes, args.seed, args.tilt,
                                        read_decisions if planner is not None else None)
        expert_places, expert_tops = play(env, task, expert_policy(env), args.episodes, args.seed, args.tilt)
    print(f"{args.checkpoint}, {args.episodes} held-out scenes (seed {args.seed})"
          + (f", planner {args.planner}" if args.planner else "")
          + {"value": "", "lowest-top": ", places chosen by the lowest predicted pile top"
                 + (f" (each pixel at the {args.top_quantile:g}-quantile of its depth classes)" if args.top_quantile else ""),
             "q-first": ", places at Q's argmax", "nearest-expert": ", places at the candidate nearest the expert's"}[args.choose]
          + (f", the scripted expert's {args.expert_does}" if args.expert_does else "")
          + (f", places by {args.place_weights}" if args.place_weights else "")
          + (f", the places' planner {args.place_planner}" if args.place_planner else ""))
    print("| who | packed | mean pile top of the packs | places into the bin | resting tilted | raised | tilted in the hand "
          "| level but turned > 10° off the walls | the largest block left |")
    print("|---|---|---|---|---|---|---|---|---|")
    who = f"{agent.name} agent" + (f", the expert's {args.expert_does}" if args.expert_does else "")
    print(summary(who, agent_places, agent_tops, args.episodes))
    print(summary("scripted expert", expert_places, expert_tops, args.episodes))
    if nearest:
        pixels, turns, above = np.array(nearest).T
        print(f"\nthe candidate nearest the expert's place, over {len(nearest)} place decisions: {np.median(pixels):.1f} px "
              f"away (median; {np.mean(pixels <= 2):.0%} within 2 px, {np.mean(pixels <= 5):.0%} within 5 px), "
              f"at the expert's rotation in {np.mean(turns == 0):.0%}, within 2 px and at its rotation in "
              f"{np.mean((pixels <= 2) & (turns == 0)):.0%}")
        print(f"Q's map at the expert's place: {np.median(above):.2%} of the map's entries above it (median; "
              f"{np.percentile(above, 25):.2%} / {np.percentile(above, 75):.2%} at the quartiles; Q's argmax there in "
              f"{np.mean(above == 0):.0%})")
    if decisions:
        real = np.array([d["real_top"] for d in decisions])
        predicted = np.array([d["predicted_top"] for d in decisions])
        rho = np.array([d["rho"] for d in decisions])
        above = np.array([d["above_lowest"] for d in decisions])
        rho, above = rho[np.isfinite(rho)], above[np.isfinite(above)]
        print(f"\nplace decisions: {len(decisions)}; candidates predicted to enter the bin "
              f"{np.mean([d['entering'] for d in decisions]):.1f} of {planner.num_candidates} per decision, the chosen one among "
              f"them in {100 * np.mean([d['chosen_enters'] for d in decisions]):.0f} %")
        print(f"world model, the place taken: real pile top - predicted {100 * np.mean(real - predicted):+.2f} cm on "
              f"average, |.| {100 * np.mean(np.abs(real - predicted)):.2f} cm; missed rises (real > predicted + 1 cm) "
              f"{100 * np.mean(real - predicted > MISSED_RISE):.0f} %")
        if len(rho):
            print(f"V against the predicted pile top among the entering candidates (>= 3): rank correlation "
                  f"{np.mean(rho):+.2f} on average over {len(rho)} decisions (negative in {100 * np.mean(rho < 0):.0f} %, "
                  f"positive in {100 * np.mean(rho > 0):.0f} %: V prefers lower piles where negative)")
        if len(above):
            print(f"chosen predicted top above the lowest entering candidate's: {100 * np.mean(above):.2f} cm on average, "
                  f"> {1000 * HIGHER_CHOICE:.0f} mm in {100 * np.mean(above > HIGHER_CHOICE):.0f} % of "
                  f"{len(above)} decisions")


if __name__ == "__main__":
    main()
