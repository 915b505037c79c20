"""ldm_rl's pieces in a plain TorchRL pipeline, end to end on CPU (docs/api.md walks through it).

    collector (scripted expert) -> replay buffer -> LDMLoss -> Adam step -> foresight on replay samples
    -> imagined rollouts driven by TorchRL's RandomPolicy -> the lookahead planner acting in the env

    python docs/examples/compose_pipeline.py                       # about 15 s on one CPU core
    python docs/examples/compose_pipeline.py --frames 64 --updates 20 --num-candidates 8

Nothing here is specific to ldm_rl except the pieces it imports: the env is a TorchRL ``TransformedEnv``,
the world model a ``torch.nn.Module``, the loss a TorchRL ``LossModule``, the transform a TorchRL
``Transform``, the imagined env a ``ModelBasedEnvBase`` and the planner a TensorDict policy.
tests/test_api_composition.py runs ``main`` with tiny sizes.
"""

from __future__ import annotations

import argparse

import torch
from torchrl.collectors import Collector
from torchrl.data import LazyTensorStorage, TensorDictReplayBuffer
from torchrl.envs import StepCounter
from torchrl.envs.utils import ExplorationType, RandomPolicy, set_exploration_type

import ldm_rl
from ldm_rl import keys
from ldm_rl.models.q_fcn import build_q_network
from ldm_rl.models.v_cnn import build_value_network
from ldm_rl.objectives import LDMLoss
from ldm_rl.planning.planner import LookaheadPlanner
from ldm_rl.world_model import ForesightTransform, LDMImaginedEnv


def main(
    *,
    frames: int = 48,
    batch_size: int = 8,
    updates: int = 10,
    imagined_steps: int = 3,
    planner_steps: int = 4,
    num_candidates: int = 6,
    ldm_width: float = 0.25,
    net_width: float = 0.5,
    seed: int = 0,
) -> dict:
    """Run the pipeline once; returns what each stage produced (for a look, or for a test)."""
    torch.manual_seed(seed)

    # 1. A task and a dynamics model for it, by name: max_height / rotations come from conf/env/block_stacking.yaml.
    dynamics = ldm_rl.make_dynamics_model("ldm64", task="block_stacking", preset="lite",
                                          overrides=[f"model.width={ldm_width}"])

    def make_env(env_seed: int):  # our env + your transforms, in one TransformedEnv (no nesting)
        env = ldm_rl.make_env("ldm_rl/BlockStacking-v0", transforms=[StepCounter()])
        env.set_seed(env_seed)
        return env

    # 2. Collect expert transitions with a TorchRL collector into a TorchRL replay buffer. A collector closes the
    #    env it is given when it reaches total_frames, so each collector gets its own env.
    demo_env = make_env(seed)
    collector = Collector(demo_env, ldm_rl.expert_policy(demo_env), frames_per_batch=frames, total_frames=frames)
    replay = TensorDictReplayBuffer(storage=LazyTensorStorage(4 * frames), batch_size=batch_size)
    for data in collector:
        replay.extend(data)
    collector.shutdown()

    # 3. Train the LDM: LDMLoss reads heightmap, in_hand, holding, action and ("next", "heightmap").
    loss_module = LDMLoss(dynamics, class_weights="auto")  # "auto": the recipes' (and the paper's) class weights
    optimizer = torch.optim.Adam(loss_module.parameters(), lr=1e-3)
    losses = []
    for _ in range(updates):
        loss = loss_module(replay.sample())
        optimizer.zero_grad()
        loss["loss_dynamics"].backward()
        optimizer.step()
        losses.append(loss["loss_dynamics"].detach().item())

    # 4. Foresight: every replay sample gains ("next", "pred_*") beside the real ("next", ...) data.
    replay.append_transform(ForesightTransform(dynamics))
    sample = replay.sample()
    predicted, real = sample[keys.FORESIGHT_KEYS[0]], sample[keys.NEXT, keys.HEIGHTMAP]
    foresight_l1_mm = 1000 * float((predicted - real).abs().mean())

    # 5. Imagination: an env over the sampled states that TorchRL's RandomPolicy (or a Collector) drives.
    imagined = LDMImaginedEnv(dynamics, start_states=sample.select(*keys.STATE_KEYS))
    dream = imagined.rollout(imagined_steps, RandomPolicy(imagined.action_spec))

    # 6. The planner: Q proposes candidates, the LDM predicts each outcome, V scores them.
    q_network = build_q_network("lite", max_height=dynamics.max_height, num_classes=dynamics.num_classes,
                                num_rotations=dynamics.num_rotations, width=net_width)
    value_network = build_value_network("lite", max_height=dynamics.max_height, num_classes=dynamics.num_classes,
                                        width=net_width)
    planner = LookaheadPlanner(q_network, dynamics, value_network, num_candidates=num_candidates)
    # (the planner keeps no recurrent state: it needs no InitTracker, which TorchRL 0.14 would ask about)
    explore = Collector(lambda: make_env(seed + 1), planner, frames_per_batch=planner_steps, total_frames=planner_steps,
                        auto_register_policy_transforms=False)
    for data in explore:  # exploring (softmax over the candidates' values): fresh data for the buffer
        replay.extend(data.exclude(keys.ACTION_VALUE))
    explore.shutdown()
    eval_env = make_env(seed + 2)
    with set_exploration_type(ExplorationType.DETERMINISTIC):  # greedy: the best-scored candidate
        episode = eval_env.rollout(planner_steps, planner)
    eval_env.close()
    return {"losses": losses, "foresight_l1_mm": foresight_l1_mm, "sample": sample, "dream": dream,
            "episode": episode, "replay_size": len(replay)}


def _parse() -> dict:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--frames", type=int, default=48, help="expert transitions to collect")
    parser.add_argument("--batch-size", type=int, default=8, help="replay samples per update")
    parser.add_argument("--updates", type=int, default=10, help="LDMLoss / Adam steps")
    parser.add_argument("--imagined-steps", type=int, default=3, help="steps of the imagined rollout")
    parser.add_argument("--planner-steps", type=int, default=4, help="planner steps in the real env")
    parser.add_argument("--num-candidates", type=int, default=6, help="candidate actions per decision")
    parser.add_argument("--ldm-width", type=float, default=0.25, help="channel multiplier of the lite LDM")
    parser.add_argument("--net-width", type=float, default=0.5, help="channel multiplier of the lite Q and V")
    parser.add_argument("--seed", type=int, default=0)
    return vars(parser.parse_args())


if __name__ == "__main__":
    out = main(**_parse())
    print(f"LDM loss {out['losses'][0]:.3f} -> {out['losses'][-1]:.3f} over {len(out['losses'])} updates; "
          f"foresight L1 {out['foresight_l1_mm']:.2f} mm on a replay sample")
    print(f"imagined rollout {list(out['dream'].batch_size)} (states x steps); planner actions "
          f"{out['episode'][keys.ACTION].tolist()}; replay holds {out['replay_size']} transitions")
