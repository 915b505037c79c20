"""How a trained agent's world model predicts scenes with more objects than it trained on (not timed; prints a table).

    python benchmarks/ldm_zero_shot.py <run>/checkpoint.pt --objects 3 4 5 --episodes 20

For each object count the task's scripted expert plays ``--episodes`` scenes (block stacking and house building: the
paper's build-deconstruct-replay, so a 5-block episode places a cube on stacks of 0 … 4); the checkpoint's world
model — the one its greedy policy plans with (the averaged one under ``agent.greedy_ema_decay``), or the online one
with ``--online`` — predicts every transition, scored by the dynamics metrics of Table 1 (``ldm_rl.world_model.metrics``:
a pick is right when the predicted hand state is, a place when the changed footprint's IoU ≥ 0.75 and its classes
agree within one). Rows split the transitions by primitive and by level: for a place, the number of objects stacked
at the action's pixel after it (1 = on the table), for a pick, before it (the top of a stack of that many), read off
the true heightmaps as the highest pixel within ±2 px of the action over ``--object-height``. A trained-on level
beside an unseen one says whether the model carries its local dynamics up a taller stack (docs/policy.md,
"Table 2 (blocks)"). With ``--value`` the agent's value network (the greedy policy's) also scores each transition's
true next state: mean V and reward head R per row, so whether V still rises as a taller stack grows, and where R calls
a scene the goal. With ``--noise p`` the expert takes a random action with probability ``p`` (failed picks, misplaced
cubes). A measurement, run by hand; ``--json`` keeps the rows.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import torch


def world_model(checkpoint: Path, online: bool, height_anchor: float | None = None):
    """``(dynamics model, value network or None, config)`` the greedy policy of ``checkpoint`` plans with
    (``online``: the model its loss trains and the online planner's V)."""
    from ldm_rl.agents import load_agent
    from ldm_rl.world_model import DynamicsModel

    agent, cfg = load_agent(checkpoint, height_anchor=height_anchor)
    policy = agent.policy if online else agent.greedy_policy
    owners = (getattr(agent, "dynamics_loss", None),) if online else (policy, getattr(agent, "dynamics_loss", None))
    for owner in owners:
        model = getattr(owner, "dynamics", None)
        if isinstance(model, DynamicsModel):
            return model, getattr(policy, "value_network", None), cfg
    raise SystemExit(f"{checkpoint} holds agent {cfg['agent']['name']!r}, which has no world model")


def levels(data, object_height: float) -> torch.Tensor:
    """``[N]`` int64: objects stacked at each action's pixel, after a place and before a pick (0 = bare table)."""
    is_pick = ~data["holding"].reshape(-1).bool()
    frame = torch.where(is_pick.view(-1, 1, 1, 1), data["heightmap"], data["next", "heightmap"])
    padded = torch.nn.functional.max_pool2d(frame, 5, stride=1, padding=2)  # highest pixel within ±2 px
    rows, cols = data["action"][:, 0].long(), data["action"][:, 1].long()
    top = padded[torch.arange(len(rows)), 0, rows, cols]
    return torch.round(top / object_height).long()


def rows_of(model, data, object_height: float, objects: int, value=None) -> list[dict]:
    """One row per (primitive, level) of ``data``: transitions, share right, region L1 (mm), mean entropy (nats) and,
    with a ``value`` network, mean V and R of the true next states."""
    from ldm_rl.world_model.metrics import MetricSettings, transition_metrics

    settings = MetricSettings(max_height=model.max_height, num_classes=model.num_classes,
                              num_rotations=model.num_rotations)
    parts: dict[str, list[torch.Tensor]] = {}
    model.eval()
    with torch.inference_mode():
        for start in range(0, data.shape[0], 64):
            batch = data[start:start + 64]
            pred = model.predict(batch["heightmap"], batch["in_hand"], batch["holding"], batch["action"])
            for key, part in transition_metrics(pred.heightmap, pred.holding, batch, settings, pred.entropy()).items():
                parts.setdefault(key, []).append(part)
            if value is not None:
                v, r = value.eval().value_and_reward(batch["next", "heightmap"], batch["next", "in_hand"])
                parts.setdefault("v", []).append(v.reshape(-1))
                parts.setdefault("r", []).append(r.reshape(-1))
    m = {key: torch.cat(part) for key, part in parts.items()}
    level = levels(data, object_height)
    out = []
    for kind, mask in (("pick", m["is_pick"]), ("place", ~m["is_pick"])):
        for lv in sorted(set(level[mask].tolist())):
            sel = mask & (level == lv)
            out.append({"objects": objects, "primitive": kind, "level": lv, "n": int(sel.sum()),
                        "right": float(m["correct"][sel].float().mean()),
                        "l1_region_mm": 1000 * float(m["l1_region"][sel].mean()),
                        "entropy": float(m["entropy"][sel].mean()),
                        **({"v": float(m["v"][sel].mean()), "r": float(m["r"][sel].mean())} if "v" in m else {})})
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("checkpoint", type=Path, help="a train_policy run's checkpoint.pt (an agent with a world model)")
    parser.add_argument("--objects", type=int, nargs="+", default=[3, 4, 5], help="object counts, one expert set each")
    parser.add_argument("--episodes", type=int, default=20, help="expert episodes per object count")
    parser.add_argument("--seed", type=int, default=0, help="the expert scenes' seed")
    parser.add_argument("--noise", type=float, default=0.0, help="probability of a random expert action")
    parser.add_argument("--object-height", type=float, default=0.04, help="m: one object's height (4 cm cubes)")
    parser.add_argument("--online", action="store_true", help="the online world model, not the greedy policy's")
    parser.add_argument("--value", action="store_true", help="also V and R of the true next states")
    parser.add_argument("--height-anchor", type=float, help="m: the world model's frame anchored at this height "
                        "(model.height_anchor over the checkpoint's; 0 = none)")
    parser.add_argument("--json", type=Path, help="also write the rows here")
    args = parser.parse_args()
    if args.episodes < 1 or not 0.0 <= args.noise < 1.0 or args.object_height <= 0:
        raise SystemExit(f"--episodes must be >= 1, --noise in [0, 1), --object-height > 0 m; got {args.episodes}, "
                         f"{args.noise}, {args.object_height}")
    from ldm_rl.data.demos import collect_demos

    torch.set_num_threads(1)
    model, value, cfg = world_model(args.checkpoint, args.online, args.height_anchor)
    if args.value and value is None:
        raise SystemExit(f"--value: {args.checkpoint} holds agent {cfg['agent']['name']!r}, whose policy has no value network")
    env_cfg = dict(cfg["env"])
    procedure = env_cfg.get("demo_procedure", "direct")
    rows = []
    for objects in args.objects:
        env_cfg.update(num_objects=objects, max_steps=None, train_object_counts=None)
        data = collect_demos(env_cfg, num_episodes=args.episodes, seed=args.seed, procedure=procedure,
                             noise={"random_action_prob": args.noise} if args.noise else None, progress=False)
        rows += rows_of(model, data, args.object_height, objects, value if args.value else None)
    anchor = f", height anchor {model.height_anchor} m" if model.height_anchor is not None else ""
    print(f"{args.checkpoint} ({'online' if args.online else 'greedy'} world model{anchor}), expert ({procedure}, noise "
          f"{args.noise}), {args.episodes} episodes per count, seed {args.seed}")
    extra = " V(next) | R(next) |" if args.value else ""
    print("| objects | primitive | level | transitions | right | region L1 (mm) | entropy (nats) |" + extra)
    print("|---|---|---|---|---|---|---|" + "---|" * (2 if args.value else 0))
    for r in rows:
        print(f"| {r['objects']} | {r['primitive']} | {r['level']} | {r['n']} | {r['right']:.2f} | "
              f"{r['l1_region_mm']:.2f} | {r['entropy']:.3f} |" + (f" {r['v']:.3f} | {r['r']:.3f} |" if args.value else ""))
    if args.json:
        args.json.write_text(json.dumps({"checkpoint": str(args.checkpoint), "online": args.online, "noise": args.noise,
                                         "height_anchor": model.height_anchor,
                                         "episodes": args.episodes, "seed": args.seed, "rows": rows}, indent=1) + "\n")


if __name__ == "__main__":
    main()
