"""Where a run's picks land and which of them held, read from the run's replay (no env, no network).

    python benchmarks/pick_outcomes.py <run> [<run> ...]          # a training run's folder (its replay-* inside)

Every pick in the replay (a transition from an empty hand) is split by who acted (the expert's demonstrations,
the agent's own episodes: exploration included) and by its outcome (holding after it or not). Per group: how
many landed on bare surface (the heightmap at the pick pixel not above ``--surface`` m: nothing the fingers can
close on), and, for the picks on an object, the distance in pixels from the pick to the centroid of the object
under it (a connected region of pixels above ``--surface``; regions larger than ``--max-region`` px, a
container's walls, are left out). Then the agent's on-object picks: the share that held per distance band, and
per band of the object's span along the fingers' closing direction (the extent of its region projected on
``(cos θ, sin θ)``, θ the pick's yaw: docs/conventions.md), in cm beside ``--opening``, the open fingers' gap.
With ``--model``, the run's own world model (its ``checkpoint.pt``) is scored on the same picks on objects: how
many it predicts to hold under its hand-state rule, and ``p_drop``, its probability that the pixels under the
fingers drop (the mean over the central 12×12 of the predicted frame of P(class after < class before)), with the
AUROC of ``p_drop`` against the true outcome on the agent's picks: what the model knows beyond its per-pixel mode.
With ``--rotations`` too, the model is also read at every rotation of each agent pick's pixel: how often the
object's span along the closing direction fits the open fingers at the rotation taken, at the rotation of the
highest ``p_drop`` among the taken one's K evenly spaced (what ``planner.pick_rotations=K`` chooses from), and at
the best rotation there is.
Last, the agent's on-object picks in ``--parts`` consecutive parts of equal size, in the order they were taken: the
share that held and the share whose object's span fits the open fingers, part by part, so whether the agent's picks
improve over training.
With ``--proposals`` (an LDM agent's run): its greedy planner's N pick proposals on the last 100 expert pick states
and the last 100 of the agent's, read with the run's ``checkpoint.pt`` (the final weights; ``--weights best_policy.pt``:
the selected ones, on the same states; either way the greedy planner's: the averaged weights of a run trained with
``agent.greedy_ema_decay``): how many are a fitting,
centred grasp (on an object, its span along the closing direction under ``--opening``, within 4 px of its centroid),
whether Q's first one is, and whether the one V(f(s, a)) chooses is. ``--margin-steps K`` first fits the run's Q
with the expert margin term alone (``agent.expert_margin_weight``; Adam, 4 expert picks per step, ``--margin-lr``)
on its other expert picks for K steps, then reads the proposals again: what the demonstrations can teach Q about
the grasp's pose beyond its TD targets (``--margin-temperature τ``: the soft max of
``agent.expert_margin_temperature``). It also ranks the expert's pick in Q's whole map on the last 100 expert pick
states: first, in the top 10, the median count of entries above it and its median gap to the best. ``--frame-pad P`` reads the same weights in frames padded by P px
(``agent.q_frame_pad``: every pixel proposable at every rotation).
``--places`` reads the expert's *places* instead (an LDM agent's run, nothing else): the expert's place in Q's whole
map on the last 100 expert place states (each with its in-hand image), before and after ``--margin-steps`` on the
other expert places: whether Q has learnt, or can learn from the demonstrations, where the expert sets a block.
``--save-weights FILE`` writes the weights so fitted as a checkpoint to play (``place_outcomes.py FILE``): what the
pile does when Q's place map is nearer the expert's. ``--value-margin-steps K`` (with ``--places``) reads V instead of Q's map:
on the same 100 states, the expert's place and Q's proposals (the targets' proposal, N of them) predicted by the LDM,
how often V ranks the expert's outcome first and by how much the best proposal leads it; then fits V with its expert
margin alone (``agent.value_margin_weight``, lead ``--value-margin``) on the other expert places for K steps and reads
again: whether the demonstrations can teach V to prefer the expert's lower pile (``--save-weights``: play it).
A measurement of the data a run collected, not of time; run by hand (docs/policy.md, "Bin packing").
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import cv2
import numpy as np
import torch
from tensordict import TensorDict

from ldm_rl import geometry

BANDS = ((0, 2), (2, 4), (4, 7), (7, 12), (12, 10_000))
SPAN_BANDS = ((0.0, 5.0), (5.0, 6.0), (6.0, 7.0), (7.0, 8.5), (8.5, 100.0))  # cm


def _replay_frames(run: Path) -> tuple[dict, TensorDict, torch.Tensor, torch.Tensor]:
    """``run``'s newest replay: its meta, its frames, and ``[n]`` bool masks of the frames that start a pick and a
    place (a transition from an empty or a holding hand)."""
    replays = sorted(run.glob("replay-*"))
    if not replays:
        raise SystemExit(f"no replay-* folder in {run}: pass a training run's folder (hydra.run.dir)")
    meta = json.loads((replays[-1] / "frame_replay.json").read_text())
    frames = TensorDict.load_memmap(replays[-1] / "frames")
    n = int(meta["num_frames"])
    holding = frames["holding"][:n].reshape(-1).bool()
    starts = ~frames["is_last"][:n].reshape(-1).bool()
    starts[-1] = False  # the newest frame has no transition yet
    return meta, frames, starts & ~holding, starts & holding


def _heights(meta: dict, frames: TensorDict, key: str, rows: torch.Tensor) -> np.ndarray:
    """Frames ``key`` (``heightmap`` or ``in_hand``, stored as classes) at ``rows`` -> ``[P, h, w]`` float32 m."""
    maps = geometry.classes_to_heights(frames[key][rows], meta["max_height"], meta["num_classes"])
    return maps.reshape(len(rows), *maps.shape[-2:]).numpy()


def load_picks(run: Path) -> dict[str, np.ndarray]:
    """The picks of ``run``'s newest replay: ``expert``, ``held`` bool [P]; ``height`` m [P] at the pick
    pixel; ``heightmap`` [P, H, W] float32 m before the pick; ``pixel`` [P, 2] int (row, col); ``action``
    [P, 3] int64; ``hand_size`` (px of the in-hand image)."""
    meta, frames, picks, _ = _replay_frames(run)
    picks = picks.nonzero().squeeze(1)
    maps = _heights(meta, frames, "heightmap", picks)
    action = frames["action"][picks].long()
    pixel = action[:, :2].numpy()
    return {"expert": frames["is_expert"][picks].reshape(-1).bool().numpy(),
            "held": frames["holding"][picks + 1].reshape(-1).bool().numpy(),
            "height": maps[np.arange(len(picks)), pixel[:, 0], pixel[:, 1]], "heightmap": maps, "pixel": pixel,
            "action": action.numpy(), "hand_size": int(frames["in_hand"].shape[-1]),
            "num_rotations": _num_rotations(run)}


def load_places(run: Path) -> dict[str, np.ndarray]:
    """The places of ``run``'s newest replay (transitions from a holding hand): ``expert`` bool [P]; ``heightmap``
    [P, H, W] and ``in_hand`` [P, h, h] float32 m before the place; ``action`` [P, 3] int64; ``holding`` True."""
    meta, frames, _, places = _replay_frames(run)
    places = places.nonzero().squeeze(1)
    return {"expert": frames["is_expert"][places].reshape(-1).bool().numpy(),
            "heightmap": _heights(meta, frames, "heightmap", places), "in_hand": _heights(meta, frames, "in_hand", places),
            "action": frames["action"][places].long().numpy(), "holding": True}


def _hand(p: dict, rows: np.ndarray) -> tuple[torch.Tensor, torch.Tensor]:
    """The ``in_hand`` ``[B, 1, h, h]`` and ``holding`` ``[B, 1]`` inputs of Q for ``rows`` of picks or places."""
    if p.get("holding"):
        return torch.from_numpy(p["in_hand"][rows]).unsqueeze(1), torch.ones(len(rows), 1, dtype=torch.bool)
    return torch.zeros(len(rows), 1, p["hand_size"], p["hand_size"]), torch.zeros(len(rows), 1, dtype=torch.bool)


def _num_rotations(run: Path) -> int:
    """The run's ``env.num_rotations`` (its resolved config)."""
    from omegaconf import OmegaConf

    return int(OmegaConf.load(run / "config_resolved.yaml").env.num_rotations)


def centroid_distance(heightmap: np.ndarray, pixel: np.ndarray, surface: float, max_region: int) -> float:
    """Pixels from ``pixel`` (row, col) to the centroid of the object region under it (nan: none, or too large)."""
    region = object_region(heightmap, pixel, surface, max_region)
    if region is None:
        return float("nan")
    return float(np.hypot(*(region.mean(0) - pixel)))


def object_region(heightmap: np.ndarray, pixel: np.ndarray, surface: float, max_region: int) -> np.ndarray | None:
    """``[n, 2]`` (row, col) of the object region under ``pixel`` (None: bare surface, or a region too large)."""
    _, labels = cv2.connectedComponents((heightmap > surface).astype(np.uint8), connectivity=4)
    label = labels[pixel[0], pixel[1]]
    if label == 0:
        return None
    region = np.argwhere(labels == label)
    return region if len(region) <= max_region else None


def closing_span(region: np.ndarray, angle: float) -> float:
    """Pixels the region spans along the closing direction ``(cos angle, sin angle)`` (rows, cols), edges included."""
    projection = region @ np.array([np.cos(angle), np.sin(angle)])
    return float(projection.max() - projection.min() + 1.0)


def auroc(score: np.ndarray, label: np.ndarray) -> float:
    """Probability that a random positive scores above a random negative (ties count half); nan without both."""
    pos, neg = score[label][:, None], score[~label][None, :]
    if pos.size == 0 or neg.size == 0:
        return float("nan")
    return float((pos > neg).mean() + 0.5 * (pos == neg).mean())


def world_model(run: Path):
    """The world model of ``run``'s ``checkpoint.pt`` that its greedy planner reads (the averaged one of a run trained
    with ``agent.greedy_ema_decay``)."""
    from ldm_rl.agents import load_agent
    from ldm_rl.world_model import DynamicsModel

    agent, _ = load_agent(run / "checkpoint.pt")
    model = next((m for m in agent.greedy_policy.modules() if isinstance(m, DynamicsModel)), None)
    if model is None:
        raise SystemExit(f"{run}/checkpoint.pt holds agent {agent.name!r}, which has no world model")
    return model


def model_reading(model, p: dict, rows: np.ndarray, batch: int = 64,
                  rotation: int | None = None) -> tuple[np.ndarray, np.ndarray]:
    """The world model on the picks ``rows`` (at rotation bin ``rotation`` instead of the one taken, if given):
    (predicted holding [n] bool, p_drop [n] float)."""
    holds, drops = [], []
    with torch.no_grad():
        for start in range(0, len(rows), batch):
            r = rows[start:start + batch]
            heightmap = torch.from_numpy(p["heightmap"][r]).unsqueeze(1)
            action = torch.from_numpy(p["action"][r]).clone()
            if rotation is not None:
                action[:, 2] = rotation
            empty_hand = torch.zeros_like(heightmap[..., :p["hand_size"], :p["hand_size"]])
            pred = model.predict(heightmap, empty_hand, torch.zeros(len(r), 1, dtype=torch.bool), action)
            before = model.frame_classes(heightmap, action).long()  # [n, 1, S, S]
            prob = torch.softmax(pred.logits.float(), dim=1)  # [n, K, S, S]
            lower = (prob * (torch.arange(prob.shape[1]).view(1, -1, 1, 1) < before)).sum(1, keepdim=True)
            drops.append(geometry.center_crop(lower, 12).flatten(1).mean(1).numpy())
            holds.append(pred.holding.reshape(-1).numpy())
    return np.concatenate(holds), np.concatenate(drops)


def swept_choice(p_drop: np.ndarray, taken: np.ndarray, sweep: int) -> np.ndarray:
    """``[n]`` rotation bins: per pick, the bin of the highest ``p_drop`` ``[n, R]`` among ``taken`` ``[n]`` and the
    ``sweep − 1`` bins evenly spaced after it (``taken + j·R/sweep`` mod R; first on ties)."""
    r = p_drop.shape[1]
    bins = (taken[:, None] + np.arange(sweep)[None, :] * (r // sweep)) % r  # [n, K]
    return bins[np.arange(len(bins)), np.take_along_axis(p_drop, bins, 1).argmax(1)]


def over_training(held: np.ndarray, fits: np.ndarray, parts: int) -> list[tuple[int, int, float, float]]:
    """``(first, end, held share, fitting share)`` of ``parts`` consecutive, equal parts (the last one takes the
    remainder) of picks in the order taken: ``held`` and ``fits`` bool ``[P]``."""
    if len(held) != len(fits):
        raise ValueError(f"held and fits must have one entry per pick, got {len(held)} and {len(fits)}")
    if isinstance(parts, bool) or not isinstance(parts, int) or parts < 1:
        raise ValueError(f"parts must be an int >= 1, got {parts!r}")
    size = len(held) // parts
    if size == 0:
        return []
    bounds = [(k * size, (k + 1) * size if k < parts - 1 else len(held)) for k in range(parts)]
    return [(a, b, float(held[a:b].mean()), float(fits[a:b].mean())) for a, b in bounds]


def report(run: Path, surface: float, max_region: int, model: bool, opening: float = 0.07,
           resolution: float = 0.003125, rotations: bool = False, parts: int = 5) -> None:
    p = load_picks(run)
    bare = p["height"] <= surface
    regions = [None if b else object_region(m, px, surface, max_region)
               for m, px, b in zip(p["heightmap"], p["pixel"], bare)]
    dist = np.array([np.nan if r is None else float(np.hypot(*(r.mean(0) - px))) for r, px in zip(regions, p["pixel"])])
    print(f"\n{run} ({len(bare)} picks)")
    print("| who | outcome | picks | on bare surface | on an object: median px to its centroid |")
    print("|---|---|---|---|---|")
    for who, is_expert in (("expert", True), ("agent", False)):
        for outcome, held in (("held", True), ("empty", False)):
            m = (p["expert"] == is_expert) & (p["held"] == held)
            if m.any():
                d = dist[m & ~np.isnan(dist)]
                median = f"{np.median(d):.1f}" if len(d) else "-"
                print(f"| {who} | {outcome} | {int(m.sum())} | {bare[m].mean():.0%} | {median} |")
    agent = ~p["expert"] & ~np.isnan(dist)
    bands = []
    for lo, hi in BANDS:
        m = agent & (dist >= lo) & (dist < hi)
        bands.append(f"{lo}–{hi if hi < 10_000 else '∞'} px: {int(p['held'][m].sum())}/{int(m.sum())}")
    print("agent's picks on an object that held, by distance to its centroid: " + ", ".join(bands))
    angles = p["action"][:, 2] * np.pi / p["num_rotations"]
    span = np.array([np.nan if r is None else closing_span(r, a) * resolution * 100 for r, a in zip(regions, angles)])
    print(f"\n| picks on an object, by its span along the closing direction (cm; open fingers {opening * 100:.1f}) | "
          + " | ".join(f"{lo:g}–{hi:g}" if hi < 100 else f"≥ {lo:g}" for lo, hi in SPAN_BANDS) + " |")
    print("|---" * (len(SPAN_BANDS) + 1) + "|")
    for who, is_expert in (("expert", True), ("agent", False)):
        m = (p["expert"] == is_expert) & ~np.isnan(span)
        cells = []
        for lo, hi in SPAN_BANDS:
            b = m & (span >= lo) & (span < hi)
            cells.append(f"{int(p['held'][b].sum())} / {int(b.sum())}")
        print(f"| {who}: held / picks | " + " | ".join(cells) + " |")
    mine = ~p["expert"] & ~np.isnan(span)  # the agent's on-object picks, in the order taken
    rows = over_training(p["held"][mine], span[mine] < opening * 100, parts)
    if rows:
        print(f"\nthe agent's {int(mine.sum())} picks on an object over training, in {parts} parts in the order taken")
        print("| picks | held | span under the opening |")
        print("|---|---|---|")
        for a, b, held_share, fit_share in rows:
            print(f"| {a + 1}–{b} | {held_share:.2f} | {fit_share:.2f} |")
    if model:
        rows = np.nonzero(~bare)[0]
        ldm = world_model(run)
        holds, drops = model_reading(ldm, p, rows)
        print("\n| picks on an object | count | held | the model predicts held: of the held / of the empty | "
              "mean p_drop: held / empty | AUROC of p_drop |")
        print("|---|---|---|---|---|---|")
        for who, is_expert in (("expert", True), ("agent", False)):
            m = p["expert"][rows] == is_expert
            held = p["held"][rows][m]
            hold, drop = holds[m], drops[m]
            mean = lambda x: f"{x.mean():.2f}" if x.size else "-"
            print(f"| {who} | {int(m.sum())} | {int(held.sum())} | {int((hold & held).sum())} / {int((hold & ~held).sum())} | "
                  f"{mean(drop[held])} / {mean(drop[~held])} | {auroc(drop, held):.2f} |")
        agent_rows = ~p["expert"][rows]
        cells = []
        for lo, hi in SPAN_BANDS:
            b = agent_rows & (span[rows] >= lo) & (span[rows] < hi)
            cells.append(f"{drops[b].mean():.2f} ({int(b.sum())})" if b.any() else "-")
        print("\nthe agent's picks, mean p_drop by span along the closing direction (cm): "
              + ", ".join(f"{lo:g}–{hi:g}: {c}" for (lo, hi), c in zip(SPAN_BANDS, cells)))
        if rotations:
            mine = rows[agent_rows & ~np.isnan(span[rows])]
            r = p["num_rotations"]
            spans = np.array([[closing_span(regions[i], k * np.pi / r) * resolution * 100 for k in range(r)] for i in mine])
            by_rotation = np.stack([model_reading(ldm, p, mine, rotation=k)[1] for k in range(r)], 1)  # [n, R]
            taken, n = p["action"][mine, 2], len(mine)
            fits = lambda bins: f"{(spans[np.arange(n), bins] < opening * 100).mean():.2f}"
            sweeps = [k for k in (2, 4, r) if r % k == 0 and k <= r]
            print(f"\nthe agent's {n} picks on an object: share whose span along the closing direction is under "
                  f"{opening * 100:.1f} cm")
            print("| the rotation taken | " + " | ".join(f"the highest p_drop of K = {k}" for k in sweeps)
                  + " | the best rotation there is |")
            print("|---" * (len(sweeps) + 2) + "|")
            print(f"| {fits(taken)} | " + " | ".join(fits(swept_choice(by_rotation, taken, k)) for k in sweeps)
                  + f" | {(spans.min(1) < opening * 100).mean():.2f} |")


CENTRED = 4.0  # px (1.25 cm): a grasp within this of its object's centroid is centred


def grasp_quality(p: dict, i: int, action, surface: float, max_region: int, opening: float,
                  resolution: float) -> tuple[bool, bool]:
    """(fits, fits and centred) of pick ``action`` (row, col, rot) on the scene of pick ``i`` of ``p``."""
    row, col, rot = (int(x) for x in action)
    region = object_region(p["heightmap"][i], np.array([row, col]), surface, max_region)
    if region is None:
        return False, False
    fits = closing_span(region, rot * np.pi / p["num_rotations"]) * resolution < opening
    return fits, fits and float(np.hypot(*(region.mean(0) - [row, col]))) < CENTRED


def proposal_reading(agent, p: dict, rows: np.ndarray, surface: float, max_region: int, opening: float,
                     resolution: float, batch: int = 10) -> dict[str, int]:
    """The greedy planner's proposals on the picks ``rows`` of ``p``: counts of fitting and fitting-centred
    proposals, of states with one such, of Q's first proposal and of V's choice being one."""
    planner = agent.greedy_policy.eval()
    hp = planner.hyperparameters(greedy=True)
    out = dict.fromkeys(("states", "proposals", "fit", "good", "any good", "first good", "chosen fit",
                         "chosen good"), 0)
    with torch.no_grad():
        for start in range(0, len(rows), batch):
            r = rows[start:start + batch]
            heightmap = torch.from_numpy(p["heightmap"][r]).unsqueeze(1)
            hand = torch.zeros(len(r), 1, p["hand_size"], p["hand_size"])
            holding = torch.zeros(len(r), 1, dtype=torch.bool)
            _, candidates = planner.propose(heightmap, hand, holding, hp, greedy=True)
            chosen = planner.score(heightmap, hand, holding, candidates, 0.0)[0].argmax(1)
            for j, i in enumerate(r):
                quality = [grasp_quality(p, i, a, surface, max_region, opening, resolution) for a in candidates[j]]
                out["states"] += 1
                out["proposals"] += len(quality)
                out["fit"] += sum(f for f, _ in quality)
                out["good"] += sum(g for _, g in quality)
                out["any good"] += any(g for _, g in quality)
                out["first good"] += quality[0][1]
                out["chosen fit"] += quality[int(chosen[j])][0]
                out["chosen good"] += quality[int(chosen[j])][1]
    return out


def expert_ranks(q_maps: torch.Tensor, action: torch.Tensor) -> tuple[np.ndarray, np.ndarray]:
    """Where the expert's action stands in Q's map: ``q_maps`` ``[P, R, H, W]`` (``-inf`` = never proposed), ``action``
    ``[P, 3]`` (row, col, rotation) -> (entries strictly above it, max − its value) per proposable pick ``[P']``."""
    flat = q_maps.flatten(1)
    height, width = q_maps.shape[-2:]
    index = (action[:, 2].long() * height + action[:, 0].long()) * width + action[:, 1].long()
    own = flat.gather(1, index[:, None])
    live = torch.isfinite(own).squeeze(1)
    above = (flat > own).sum(1)
    gap = flat.amax(1, keepdim=True) - own
    return above[live].numpy(), gap[live].squeeze(1).numpy()


def rank_reading(agent, p: dict, rows: np.ndarray, batch: int = 10) -> str:
    """The expert's pick (or place) on ``rows`` in the greedy planner's Q map (the averaged weights of a run trained
    with ``agent.greedy_ema_decay``: what its greedy decisions read): proposable ones, first / in the top 10, median
    entries above it and median gap to the map's best (Q's fitted units)."""
    q = agent.greedy_policy.q_network.eval()
    ranks, gaps, pixels, turned = [], [], [], []
    with torch.no_grad():
        for start in range(0, len(rows), batch):
            r = rows[start:start + batch]
            maps = q(torch.from_numpy(p["heightmap"][r]).unsqueeze(1), *_hand(p, r)).float()
            action = torch.from_numpy(p["action"][r]).reshape(-1, 3).long()
            above, gap = expert_ranks(maps, action)
            ranks.append(above)
            gaps.append(gap)
            best = geometry.flat_to_action(maps.flatten(1).argmax(1), *maps.shape[-2:])  # [B, 3] Q's argmax
            pixels.append((best[:, :2] - action[:, :2]).float().norm(dim=-1).numpy())
            turned.append((best[:, 2] != action[:, 2]).numpy())
    ranks, gaps, pixels, turned = (np.concatenate(v) for v in (ranks, gaps, pixels, turned))
    if not len(ranks):
        return f"0 of {len(rows)} proposable"
    return (f"{len(ranks)} of {len(rows)} proposable; first {int((ranks == 0).sum())}, top 10 {int((ranks < 10).sum())}; "
            f"median {np.median(ranks):.0f} entries above it, {np.median(gaps):.3f} below the best; Q's argmax a median "
            f"{np.median(pixels):.1f} px from it, within 2 px at its rotation in {int(((pixels <= 2) & ~turned).sum())}")


def fit_margin(agent, p: dict, rows: np.ndarray, steps: int, lr: float, margin: float = 0.1, seed: int = 0,
               temperature: float = 0.0) -> list[float]:
    """Fit the Q of ``agent``'s greedy planner (the averaged copy of a run trained with ``agent.greedy_ema_decay``,
    else the online one) on the picks (or places) ``rows`` with the expert margin term alone (4 per step; soft max
    at ``temperature`` > 0); returns the term's value every 50 steps."""
    from ldm_rl.objectives import SpatialDQNLoss

    q = agent.greedy_policy.q_network.requires_grad_(True)  # an averaged copy is built frozen
    loss = SpatialDQNLoss(q, expert_margin_weight=1.0, expert_margin=margin, expert_margin_rows=4,
                          expert_margin_temperature=temperature)
    optimiser = torch.optim.Adam(list(loss.q_network_params.values(True, True)), lr=lr)
    rng, trace = np.random.default_rng(seed), []
    for step in range(steps):
        r = rng.choice(rows, 4, replace=False)
        in_hand, holding = _hand(p, r)
        data = TensorDict({"heightmap": torch.from_numpy(p["heightmap"][r]).unsqueeze(1), "in_hand": in_hand,
                           "holding": holding, "action": torch.from_numpy(p["action"][r]),
                           "is_expert": torch.ones(4, 1, dtype=torch.bool)}, batch_size=[4])
        loss.q_network.train()
        optimiser.zero_grad()
        term = loss.expert_margin_loss(loss.q_network, data)
        if term.requires_grad:  # else every drawn pick's action is one Q never proposes (-inf): nothing to fit
            term.backward()
            optimiser.step()
        if step % 50 == 0 or step == steps - 1:
            trace.append(float(term.detach()))
    return trace


def value_margin_reading(agent, p: dict, rows: np.ndarray, margin: float, batch: int = 10,
                         grad: bool = False) -> torch.Tensor:
    """Per expert place (or pick) of ``rows``, how far V of the greedy planner ranks the expert's predicted outcome
    below the best of its Q's proposals (``agent.value_margin_weight``'s hinge: ``max_i [V(f(s, a_i)) + margin·1(a_i ≠
    a_E)] − V(f(s, a_E))``, the proposals those of the loss's target proposal, N = ``num_target_candidates``; Q and
    the LDM in eval mode, V in eval mode with its gradient when ``grad``): ``[n]`` float32, V's units."""
    from ldm_rl.objectives.value_lookahead import expert_outcome_gaps

    planner, loss = agent.greedy_policy, agent.loss
    value = planner.value_network

    def score(predicted):
        training = [(module, module.training) for module in value.modules()]
        value.eval()  # its BatchNorm statistics fixed; eval_mode would also drop the gradient
        try:
            with torch.set_grad_enabled(grad):
                return value(predicted.heightmap, predicted.in_hand).float()
        finally:
            for module, flag in training:
                module.training = flag

    out = []
    for start in range(0, len(rows), batch):
        r = rows[start:start + batch]
        in_hand, holding = _hand(p, r)
        out.append(expert_outcome_gaps(planner.q_network, planner.dynamics, score,
                                       torch.from_numpy(p["heightmap"][r]).unsqueeze(1), in_hand, holding,
                                       torch.from_numpy(p["action"][r]).reshape(-1, 3).long(),
                                       loss.num_target_candidates, margin, loss.target_proposal))
    return torch.cat(out)


def value_rank_line(agent, p: dict, rows: np.ndarray) -> str:
    """V's ranking of the expert's predicted outcome among its Q's proposals' on ``rows``: how often it leads them
    all, and the median lead of the best proposal over it (V's units)."""
    gap = value_margin_reading(agent, p, rows, margin=0.0).numpy()
    return (f"the expert's outcome first by V in {int((gap <= 0).sum())} of {len(gap)}; the best proposal's lead over "
            f"it: median {np.median(gap):+.4f}, mean {gap.mean():+.4f}")


def fit_value_margin(agent, p: dict, rows: np.ndarray, steps: int, lr: float, margin: float,
                     seed: int = 0) -> list[float]:
    """Fit the V of ``agent``'s greedy planner with the value margin term alone (``agent.value_margin_weight``; 4
    expert rows per step, Adam at ``lr``); returns the term's value every 50 steps."""
    if agent.loss.value_scale.log_floor is not None:
        raise SystemExit("--value-margin-steps fits a linear V; this run's V is on a log scale (agent.value_log_floor)")
    value = agent.greedy_policy.value_network.requires_grad_(True)  # an averaged copy is built frozen
    optimiser = torch.optim.Adam(value.parameters(), lr=lr)
    rng, trace = np.random.default_rng(seed), []
    for step in range(steps):
        term = value_margin_reading(agent, p, rng.choice(rows, 4, replace=False), margin, grad=True).clamp_min(0).mean()
        if term.requires_grad:
            optimiser.zero_grad()
            term.backward()
            optimiser.step()
        if step % 50 == 0 or step == steps - 1:
            trace.append(float(term.detach()))
    return trace


def padded_q(q, frame_pad: int):
    """A QFCN with ``q``'s settings and weights whose frames are padded by ``frame_pad`` px (``agent.q_frame_pad``)."""
    from ldm_rl.models.q_fcn import QFCN

    padded = QFCN(q.max_height, q.num_classes, q.num_rotations, q.width, frame_margin=q.frame_margin,
                  pick_min_height=q.pick_min_height, head_channels=q.head_channels, frame_pad=frame_pad)
    padded.load_state_dict(q.state_dict())
    return padded


def proposals_report(run: Path, surface: float, max_region: int, opening: float, resolution: float,
                     margin_steps: int, margin_lr: float, frame_pad: int = 0, margin_temperature: float = 0.0,
                     weights: str = "checkpoint.pt") -> None:
    from ldm_rl.agents import load_agent

    p = load_picks(run)
    agent, _ = load_agent(run / weights)
    if agent.name != "ldm":
        raise SystemExit(f"--proposals reads an LDM agent's planner; {run}/{weights} holds agent {agent.name!r}")
    if frame_pad:
        agent.greedy_policy.q_network = padded_q(agent.greedy_policy.q_network, frame_pad)
    expert = np.nonzero(p["expert"])[0]
    mine = np.nonzero(~p["expert"])[0]
    if len(expert) <= 100 + 4 * (margin_steps > 0):
        raise SystemExit(f"{run}'s replay has {len(expert)} expert picks: --proposals needs more than 100")
    groups = (("expert (last 100)", expert[-100:]), ("agent (last 100)", mine[-100:]))
    readings = [("as trained", name, proposal_reading(agent, p, rows, surface, max_region, opening, resolution))
                for name, rows in groups]
    ranks = [("as trained", rank_reading(agent, p, expert[-100:]))]
    if margin_steps:
        trace = fit_margin(agent, p, expert[:-100], margin_steps, margin_lr, temperature=margin_temperature)
        print(f"\nthe margin term over {margin_steps} steps on the other {len(expert) - 100} expert picks"
              f"{f' (soft max, τ = {margin_temperature:g})' if margin_temperature else ''}: "
              + " → ".join(f"{t:.3f}" for t in trace))
        readings += [(f"after {margin_steps} margin steps", name,
                      proposal_reading(agent, p, rows, surface, max_region, opening, resolution)) for name, rows in groups]
        ranks.append((f"after {margin_steps} margin steps", rank_reading(agent, p, expert[-100:])))
    print(f"\n{run}: the greedy planner's pick proposals (fitting: span under {opening * 100:.1f} cm; centred: within "
          f"{CENTRED:g} px of the object's centroid{f'; Q read in frames padded by {frame_pad} px' if frame_pad else ''})")
    print("| Q | pick states | proposals fitting / fitting and centred | states with one fitting and centred | "
          "Q's first proposal fitting and centred | V's choice fitting / fitting and centred |")
    print("|---|---|---|---|---|---|")
    for when, name, r in readings:
        n = r["states"]
        print(f"| {when} | {name} | {r['fit'] / r['proposals']:.2f} / {r['good'] / r['proposals']:.2f} | "
              f"{r['any good']} / {n} | {r['first good']} / {n} | {r['chosen fit']} / {r['chosen good']} of {n} |")
    print("\nthe expert's pick in Q's whole map, last 100 expert pick states:")
    for when, line in ranks:
        print(f"  {when}: {line}")


def save_fitted(agent, run: Path, weights: str, path: Path, note: str) -> None:
    """Write ``agent``'s policy weights (its Q fitted by ``--margin-steps``) to ``path`` as a ``best_policy.pt`` is
    written, under the meta of ``run``/``weights`` plus ``note``: a checkpoint ``place_outcomes.py`` and
    ``recipes/evaluate.py`` play like any other."""
    from ldm_rl.run.checkpoint import read_checkpoint_meta, save_checkpoint

    meta = {**read_checkpoint_meta(run / weights), "note": note}
    path.parent.mkdir(parents=True, exist_ok=True)
    save_checkpoint(path, {"agent": agent.policy_state_dict()}, meta=meta)
    print(f"saved the fitted weights to {path}")


def places_report(run: Path, margin_steps: int, margin_lr: float, margin_temperature: float = 0.0,
                  weights: str = "checkpoint.pt", save: Path | None = None, value_margin_steps: int = 0,
                  value_margin: float = 0.01) -> None:
    """The expert's place in ``run``'s Q map on its last 100 expert place states, before and after ``margin_steps``
    of Q's margin; with ``value_margin_steps``, V's ranking of the expert's predicted outcome on the same states
    before and after that many steps of V's margin (``value_margin``: its lead, V's units) on the other expert places
    (``save``: where to write the fitted weights, see :func:`save_fitted`)."""
    from ldm_rl.agents import load_agent

    p = load_places(run)
    agent, _ = load_agent(run / weights)
    if agent.name != "ldm":
        raise SystemExit(f"--places reads an LDM agent's Q; {run}/{weights} holds agent {agent.name!r}")
    expert = np.nonzero(p["expert"])[0]
    if len(expert) <= 100 + 4 * (margin_steps > 0 or value_margin_steps > 0):
        raise SystemExit(f"{run}'s replay has {len(expert)} expert places: --places needs more than 100")
    ranks = [("as trained", rank_reading(agent, p, expert[-100:]))]
    if margin_steps:
        trace = fit_margin(agent, p, expert[:-100], margin_steps, margin_lr, temperature=margin_temperature)
        print(f"the margin term over {margin_steps} steps on the other {len(expert) - 100} expert places: "
              + " → ".join(f"{t:.3f}" for t in trace))
        ranks.append((f"after {margin_steps} margin steps", rank_reading(agent, p, expert[-100:])))
    values = []
    if value_margin_steps:
        values.append(("as trained", value_rank_line(agent, p, expert[-100:])))
        trace = fit_value_margin(agent, p, expert[:-100], value_margin_steps, margin_lr, value_margin)
        print(f"V's margin term (lead {value_margin:g}) over {value_margin_steps} steps on the other "
              f"{len(expert) - 100} expert places: " + " → ".join(f"{t:.4f}" for t in trace))
        values.append((f"after {value_margin_steps} steps of V's margin", value_rank_line(agent, p, expert[-100:])))
    if save is not None and (margin_steps or value_margin_steps):
        fitted = " and ".join(part for part in (
            margin_steps and f"Q (--margin-steps {margin_steps} --margin-temperature {margin_temperature:g})",
            value_margin_steps and f"V (--value-margin-steps {value_margin_steps} --value-margin {value_margin:g})")
            if part)
        save_fitted(agent, run, weights, save, f"{fitted} fitted by benchmarks/pick_outcomes.py --places, "
                    f"--margin-lr {margin_lr:g}")
    print(f"\n{run}: the expert's place in Q's whole map, last 100 expert place states ({weights}):")
    for when, line in ranks:
        print(f"  {when}: {line}")
    if values:
        print(f"V on the same states, the expert's predicted outcome against its Q's {agent.loss.num_target_candidates} "
              "proposals':")
        for when, line in values:
            print(f"  {when}: {line}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("runs", nargs="+", type=Path, help="training run folders (each with a replay-* folder)")
    parser.add_argument("--surface", type=float, default=0.012, help="m: a pick pixel not above it is bare surface")
    parser.add_argument("--max-region", type=int, default=1500, help="px: larger regions are containers, not objects")
    parser.add_argument("--model", action="store_true", help="also score the run's world model on the picks")
    parser.add_argument("--opening", type=float, default=0.07, help="m: the open fingers' gap (the env's gripper: 7 cm)")
    parser.add_argument("--rotations", action="store_true",
                        help="with --model: also read the model at every rotation of the agent's picks")
    parser.add_argument("--parts", type=int, default=5, help="the agent's picks over training: in this many parts")
    parser.add_argument("--proposals", action="store_true",
                        help="an LDM agent's run: its greedy planner's pick proposals on the last expert and agent picks")
    parser.add_argument("--margin-steps", type=int, default=0,
                        help="with --proposals or --places: first fit Q with the expert margin term alone for this many steps")
    parser.add_argument("--places", action="store_true",
                        help="an LDM agent's run: the expert's places in its Q map (instead of every pick reading)")
    parser.add_argument("--margin-lr", type=float, default=1e-3, help="Adam's learning rate of --margin-steps")
    parser.add_argument("--margin-temperature", type=float, default=0.0,
                        help="τ of --margin-steps' soft max (agent.expert_margin_temperature; 0 = the hard max)")
    parser.add_argument("--frame-pad", type=int, default=0,
                        help="with --proposals: read the run's Q weights in frames padded by this many px (agent.q_frame_pad)")
    parser.add_argument("--weights", default="checkpoint.pt",
                        help="with --proposals: the weights file in each run folder to read (best_policy.pt: the selected ones)")
    parser.add_argument("--value-margin-steps", type=int, default=0,
                        help="with --places: also read V's ranking of the expert's predicted outcome, and fit V with "
                             "its expert margin alone (agent.value_margin_weight) for this many steps")
    parser.add_argument("--value-margin", type=float, default=0.01,
                        help="the lead of --value-margin-steps (agent.value_margin; V's units)")
    parser.add_argument("--save-weights", type=Path, default=None,
                        help="with --places and --margin-steps: write the fitted weights to this file (a checkpoint "
                             "benchmarks/place_outcomes.py and recipes/evaluate.py play)")
    args = parser.parse_args()
    if args.weights not in ("checkpoint.pt", "best_policy.pt"):
        parser.error(f"--weights must be checkpoint.pt or best_policy.pt (a file in the run folder), got {args.weights!r}")
    if args.weights != "checkpoint.pt" and not (args.proposals or args.places):
        parser.error(f"--weights {args.weights} names the weights --proposals reads: pass --proposals too")
    if args.margin_steps < 0 or (args.margin_steps and not (args.proposals or args.places)):
        parser.error(f"--margin-steps must be >= 0 and goes with --proposals or --places, got {args.margin_steps}")
    if args.places and (args.proposals or args.model):
        parser.error("--places reads the expert's places alone: leave out --proposals and --model")
    if args.value_margin_steps < 0 or (args.value_margin_steps and not args.places):
        parser.error(f"--value-margin-steps must be >= 0 and goes with --places, got {args.value_margin_steps}")
    if not args.value_margin > 0:
        parser.error(f"--value-margin must be > 0 (V's units), got {args.value_margin!r}")
    if args.save_weights is not None and not (args.places and (args.margin_steps or args.value_margin_steps)
                                              and len(args.runs) == 1):
        parser.error(f"--save-weights {args.save_weights} writes the Q (or V) that --margin-steps (--value-margin-steps) "
                     "fits on one run's places: pass --places, one of them and one run")
    if args.frame_pad and not args.proposals:
        parser.error(f"--frame-pad {args.frame_pad} pads the Q that --proposals reads: pass --proposals too")
    if not args.margin_lr > 0:
        parser.error(f"--margin-lr must be > 0, got {args.margin_lr!r}")
    if not args.margin_temperature >= 0:
        parser.error(f"--margin-temperature must be >= 0, got {args.margin_temperature!r}")
    if args.parts < 1:
        parser.error(f"--parts must be >= 1, got {args.parts}")
    if args.rotations and not args.model:
        parser.error("--rotations reads the world model: pass --model too")
    if not args.opening > 0:
        parser.error(f"--opening must be a positive gap in metres (the env's gripper: 0.07), got {args.opening!r}")
    torch.set_num_threads(1)
    for run in args.runs:
        if args.places:
            places_report(run, args.margin_steps, args.margin_lr, args.margin_temperature, args.weights,
                          args.save_weights, args.value_margin_steps, args.value_margin)
            continue
        report(run, args.surface, args.max_region, args.model, args.opening, rotations=args.rotations, parts=args.parts)
        if args.proposals:
            proposals_report(run, args.surface, args.max_region, args.opening, 0.003125, args.margin_steps,
                             args.margin_lr, args.frame_pad, args.margin_temperature, args.weights)


if __name__ == "__main__":
    main()
