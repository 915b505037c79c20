"""How well V carries what it fitted to scenes it never saw, per augmentation (not timed; prints a table).

A fresh V (the agent's ``VCNN``) is fitted to the Monte-Carlo returns of one run's replay — every transition of its
terminated episodes, ``V(s')`` toward the transition's discounted return, the convention of the agent's V — and
scored on another run's replay (other scenes, another policy). Each augmentation is the one training uses
(``ldm_rl.objectives.draw_value_augmentation``). Columns: mean |V − return| held out and in sample; mean V of the
held-out terminal failures (true 0); P(a held-out non-terminal state is scored above a held-out terminal failure).
With ``--termination`` each augmentation is fitted a second time with V's termination head (the agent's
``agent.termination_head``: ``V = T·R + (1 − T)·W``, T fitted by binary cross-entropy on "the episode ended here",
R on the reward received there, the return's Huber reaching W alone), and a column gives the AUROC of T for a
held-out terminal failure against a held-out non-terminal state.

    python benchmarks/value_generalization.py <run A>/replay-<n> <run B>/replay-<m> --gamma 0.5
    python benchmarks/value_generalization.py A B --augment none symmetries --steps 3000 --width 0.25
    python benchmarks/value_generalization.py A B --augment shifts --termination
"""

from __future__ import annotations

import argparse
import time

import torch
import torch.nn.functional as F
from tensordict import TensorDict

from ldm_rl import geometry
from ldm_rl.models.v_cnn import VCNN
from ldm_rl.objectives import draw_value_augmentation


def load_returns(replay_dir: str, gamma: float, max_height: float, num_classes: int):
    """``(heightmap, in_hand, return, kind)`` of the next states of a replay's terminated episodes; kind 0 = a
    terminal failure, 1 = not terminal, 2 = a terminal success. Returns are recomputed with ``gamma``."""
    frames = TensorDict.load_memmap(f"{replay_dir}/frames").to_tensordict()
    reward, terminated = frames["reward"].reshape(-1), frames["terminated"].reshape(-1)
    is_last = frames["is_last"].reshape(-1)
    returns, keep, running, finished = torch.zeros_like(reward), torch.zeros_like(terminated), 0.0, False
    for i in range(len(reward) - 1, -1, -1):  # backwards: a terminal step starts an episode's return
        if is_last[i]:
            running, finished = 0.0, False
            continue
        if terminated[i]:
            running, finished = 0.0, True
        running = float(reward[i]) + gamma * running
        returns[i], keep[i] = running, finished
    index = keep.nonzero().squeeze(1)
    kind = torch.where(terminated[index] & (reward[index] == 0), 0, torch.where(terminated[index], 2, 1))
    decode = lambda classes: geometry.classes_to_heights(classes.long(), max_height, num_classes)  # noqa: E731
    return decode(frames["heightmap"][index + 1]), decode(frames["in_hand"][index + 1]), returns[index], kind


def fit(data, augment: str | None, steps: int, width: float, max_height: float, seed: int,
        termination: bool = False) -> VCNN:
    torch.manual_seed(seed)
    value = VCNN(max_height, width=width, termination_head=termination)
    optimiser = torch.optim.Adam(value.parameters(), lr=1e-3)
    heightmap, in_hand, target, kind = data
    ended = (kind != 1).float()
    reward = target * ended  # every task here rewards only on termination: a terminal state's return is its reward
    for _ in range(steps):
        rows = torch.randint(len(target), (32,))
        moved = draw_value_augmentation(augment, 32)(heightmap[rows])
        if termination:  # as LookaheadLoss: V's Huber reaches W alone, T and R are fitted on their own labels
            going_on, r, logit = (x.reshape(-1) for x in value.heads(moved, in_hand[rows]))
            composed = value.compose(going_on, r.detach(), logit.detach())
            loss = (F.smooth_l1_loss(composed, target[rows]) + F.smooth_l1_loss(r, reward[rows])
                    + F.binary_cross_entropy_with_logits(logit, ended[rows]))
        else:
            loss = F.smooth_l1_loss(value(moved, in_hand[rows]).reshape(-1), target[rows])
        optimiser.zero_grad()
        loss.backward()
        optimiser.step()
    return value.eval()


@torch.no_grad()
def score(value: VCNN, data) -> dict[str, float]:
    heightmap, in_hand, target, kind = data
    chunks = range(0, len(target), 64)
    pred = torch.cat([value(heightmap[i : i + 64], in_hand[i : i + 64]).reshape(-1) for i in chunks])
    fail, alive = pred[kind == 0], pred[kind == 1]
    out = {"error": float((pred - target).abs().mean()), "fail": float(fail.mean()),
           "ranked": float((alive[:, None] > fail[None, :]).float().mean()), "auroc": float("nan")}
    if value.termination_head is not None:  # P(T of a failure > T of a state still going)
        logit = torch.cat([value.heads(heightmap[i : i + 64], in_hand[i : i + 64])[2].reshape(-1) for i in chunks])
        out["auroc"] = float((logit[kind == 0][:, None] > logit[kind == 1][None, :]).float().mean())
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("fit_replay")
    parser.add_argument("score_replay")
    parser.add_argument("--augment", nargs="+", default=["none", "shifts", "quarter_turns", "symmetries"])
    parser.add_argument("--gamma", type=float, default=0.5, help="the runs' discount")
    parser.add_argument("--steps", type=int, default=3000)
    parser.add_argument("--width", type=float, default=0.25)
    parser.add_argument("--max-height", type=float, default=0.15, help="the task's max_height, metres")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--termination", action="store_true", help="also fit each with V's termination head")
    args = parser.parse_args()
    torch.set_num_threads(1)
    train = load_returns(args.fit_replay, args.gamma, args.max_height, 21)
    test = load_returns(args.score_replay, args.gamma, args.max_height, 21)
    print(f"fit on {len(train[2])} states, scored on {len(test[2])} ({int((test[3] == 0).sum())} terminal failures)")
    print("| augmentation | termination head | held-out error | in-sample error | V of held-out failures | "
          "P(alive > failure) | AUROC of T | fit s |")
    print("|---|---|---|---|---|---|---|---|")
    for name in args.augment:
        for termination in (False, True) if args.termination else (False,):
            start = time.perf_counter()
            value = fit(train, None if name == "none" else name, args.steps, args.width, args.max_height, args.seed,
                        termination)
            held, seen = score(value, test), score(value, train)
            print(f"| {name} | {'yes' if termination else 'no'} | {held['error']:.3f} | {seen['error']:.3f} | "
                  f"{held['fail']:.3f} | {held['ranked']:.3f} | {held['auroc']:.3f} | "
                  f"{time.perf_counter() - start:.0f} |", flush=True)


if __name__ == "__main__":
    main()
