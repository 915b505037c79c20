"""Agents: the one place where the policy, its losses and its optimizers are put together.

``AGENTS`` maps ``cfg.agent.name`` to a builder ``(cfg, max_height) -> Agent``: the paper's agent
(``ldm``) and the baselines (``fcdqn``, ``rs``, ``dynaq``); ``recipes/train_policy.py`` runs any of them.
"""

from __future__ import annotations

from typing import Any, Callable, Mapping

__all__ = ["AGENTS", "PLANNERS", "build_agent", "build_ldm_agent", "build_fcdqn_agent", "build_rs_agent", "build_dynaq_agent",
           "load_agent"]


def _plain(node) -> dict:
    """A Hydra/OmegaConf node (or dict) -> a plain dict with every ``_target_`` node instantiated."""
    from hydra.utils import instantiate
    from omegaconf import DictConfig, OmegaConf

    if isinstance(node, DictConfig):
        node = OmegaConf.to_container(node, resolve=True)
    return {key: instantiate(value) if isinstance(value, Mapping) and "_target_" in value else value
            for key, value in dict(node or {}).items()}


def _diverse_planner():
    from ldm_rl.planning.planner import LookaheadPlanner

    return LookaheadPlanner


def _tree_planner():
    from ldm_rl.planning.tree_planner import TreePlanner

    return TreePlanner


# ``cfg.planner.name`` -> a function returning the LDM agent's planner class, built as
# ``cls(q_network, dynamics, value_network, **cfg.planner without name)`` (a TensorDictModule writing ``action``)
PLANNERS: dict[str, Callable[[], type]] = {"diverse": _diverse_planner, "tree": _tree_planner}


def _ldm_planner(planner_cfg: Mapping[str, Any], q_network, dynamics, value_network, *, gamma: float,
                 q_log_floor: float | None = None):
    """The planner named by ``planner.name`` (configs written before the key existed: ``diverse``); a planner
    that backs up returns (``tree``) gets the agent's ``gamma`` unless its config sets one, and every planner the
    scale Q is fitted on (``agent.q_log_floor``, which ``planner.q_blend`` reads Q back with)."""
    kwargs = _plain(planner_cfg)
    name = kwargs.pop("name", "diverse")
    if name not in PLANNERS:
        raise ValueError(f"planner.name must be one of {sorted(PLANNERS)}, got {name!r}")
    from ldm_rl.planning.tree_planner import TREE_KEYS

    # the schema gives every planner the tree's keys, null unless planner=tree set them: a null key takes the
    # tree's default (a one-step run's weights planned with planner.name=tree), and the others never see them
    if name == "tree":
        kwargs = {key: value for key, value in kwargs.items() if not (key in TREE_KEYS and value is None)}
        kwargs.setdefault("gamma", gamma)
    else:
        kwargs = {key: value for key, value in kwargs.items() if key not in TREE_KEYS}
    return PLANNERS[name]()(q_network, dynamics, value_network, q_log_floor=q_log_floor, **kwargs)


def _dynamics_loss(loss_cfg: Mapping[str, Any], dynamics):
    """The LDM's focal loss of ``cfg.loss`` (class weights: null | auto | a list of K floats), writing the
    frame logits the agents reuse."""
    import torch

    from ldm_rl.objectives import LDMLoss

    loss_cfg = _plain(loss_cfg)
    class_weights = loss_cfg.get("class_weights")
    if class_weights is not None and not isinstance(class_weights, str):
        class_weights = torch.tensor(list(class_weights), dtype=torch.float32)
    return LDMLoss(dynamics, gamma=float(loss_cfg.get("gamma", 2.0)), class_weights=class_weights,
                   label_smoothing=float(loss_cfg.get("label_smoothing", 0.0)), write_logits=True,
                   gripper_symmetries=bool(loss_cfg.get("gripper_symmetries", False)))


def build_ldm_agent(cfg: Mapping[str, Any], max_height: float):
    """The paper's agent from ``cfg.model`` (the LDM), ``cfg.loss`` (its focal loss), ``cfg.agent``
    (Q/V presets, targets, optimisation) and ``cfg.planner`` (which planner, :data:`PLANNERS`, and its
    proposals and schedules)."""
    from ldm_rl.agents.ldm import LDMAgent
    from ldm_rl.models.q_fcn import build_q_network
    from ldm_rl.models.v_cnn import build_value_network
    from ldm_rl.objectives import LookaheadLoss
    from ldm_rl.world_model import build_dynamics_model

    agent_cfg = _plain(cfg["agent"])
    dynamics = build_dynamics_model(cfg["model"], max_height)
    preset = agent_cfg.get("preset") or cfg["model"].get("preset", "lite")
    common = {"max_height": float(max_height), "num_classes": dynamics.num_classes}
    q_network = build_q_network(preset, num_rotations=dynamics.num_rotations, width=agent_cfg.get("q_width"),
                                frame_margin=int(agent_cfg.get("q_frame_margin") or 0),
                                frame_pad=int(agent_cfg.get("q_frame_pad") or 0),
                                pick_min_height=float(agent_cfg.get("q_pick_min_height") or 0.0),
                                head_channels=agent_cfg.get("q_head_channels"),
                                architecture=str(agent_cfg.get("q_architecture") or "fcn"), **common)
    value_network = build_value_network(preset, width=agent_cfg.get("value_width"),
                                        termination_head=bool(agent_cfg.get("termination_head", False)),
                                        value_log_floor=agent_cfg.get("value_log_floor"), **common)
    planner = _ldm_planner(cfg["planner"], q_network, dynamics, value_network, gamma=float(agent_cfg["gamma"]),
                           q_log_floor=agent_cfg.get("q_log_floor"))
    loss = LookaheadLoss(
        q_network, dynamics, value_network,
        gamma=float(agent_cfg["gamma"]),
        num_target_candidates=int(agent_cfg["num_target_candidates"]),
        target_proposal=dict(agent_cfg.get("target_proposal") or {}),
        value_on_prediction=bool(agent_cfg.get("value_on_prediction", True)),
        chunk_size=int(agent_cfg.get("chunk_size", 64)),
        target_range=agent_cfg.get("target_range"),
        double_value=bool(agent_cfg.get("double_value", False)),
        q_target=str(agent_cfg.get("q_target", "max")),
        return_lower_bound=bool(agent_cfg.get("return_lower_bound", False)),
        bootstrap_cache=int(agent_cfg.get("bootstrap_cache") or 0),
        value_augmentation=agent_cfg.get("value_augmentation"),
        value_shift=int(agent_cfg.get("value_shift") or 4),
        value_raise_levels=int(agent_cfg.get("value_raise_levels") or 0),
        value_raise_height=agent_cfg.get("value_raise_height"),
        value_raise_region=str(agent_cfg.get("value_raise_region") or "object"),
        target_uncertainty_penalty=float(agent_cfg.get("target_uncertainty_penalty") or 0.0),
        q_log_floor=agent_cfg.get("q_log_floor"),
        q_proposal_fit=int(agent_cfg.get("q_proposal_fit") or 0),
        value_margin_weight=float(agent_cfg.get("value_margin_weight") or 0.0),
        value_margin=float(agent_cfg.get("value_margin") or 0.01),
        **_expert_margin(agent_cfg),
    )
    dynamics_loss = _dynamics_loss(cfg["loss"], dynamics)
    return LDMAgent(planner, loss, dynamics_loss, q_grad_clip=agent_cfg.get("q_grad_clip"),
                    autocast=agent_cfg.get("autocast"), **_optimisation(agent_cfg))


def _required(agent_cfg: Mapping[str, Any], name: str, *keys: str) -> list:
    """The values of baseline-specific ``agent`` keys, each of which must be set (one clear error otherwise)."""
    missing = [key for key in keys if agent_cfg.get(key) is None]
    if missing:
        raise ValueError(f"agent={name} needs {', '.join('agent.' + key for key in missing)} (null or absent); "
                         f"see conf/agent/{name}.yaml")
    return [agent_cfg[key] for key in keys]


def _q_network(cfg: Mapping[str, Any], agent_cfg: dict, max_height: float):
    """The Q FCN of ``cfg.agent`` (preset, q_width, q_head_channels, q_architecture, q_frame_margin, q_frame_pad, q_pick_min_height) on the input quantisation of ``cfg.model``."""
    from ldm_rl.geometry import NUM_ROTATIONS
    from ldm_rl.models.q_fcn import build_q_network

    preset = agent_cfg.get("preset") or cfg["model"].get("preset", "lite")
    model = cfg["model"]
    return build_q_network(preset, max_height=float(max_height), num_classes=int(model.get("num_depth_classes", 21)),
                           num_rotations=int(model.get("num_rotations", NUM_ROTATIONS)), width=agent_cfg.get("q_width"),
                           frame_margin=int(agent_cfg.get("q_frame_margin") or 0),
                           frame_pad=int(agent_cfg.get("q_frame_pad") or 0),
                           pick_min_height=float(agent_cfg.get("q_pick_min_height") or 0.0),
                           head_channels=agent_cfg.get("q_head_channels"),
                           architecture=str(agent_cfg.get("q_architecture") or "fcn"))


def _model_and_value(cfg: Mapping[str, Any], agent_cfg: dict, max_height: float):
    """(LDM, its focal loss writing the frame logits, V CNN with its reward head) from ``cfg``."""
    from ldm_rl.models.v_cnn import build_value_network
    from ldm_rl.world_model import build_dynamics_model

    dynamics = build_dynamics_model(cfg["model"], max_height)
    preset = agent_cfg.get("preset") or cfg["model"].get("preset", "lite")
    value_network = build_value_network(preset, max_height=float(max_height), num_classes=dynamics.num_classes,
                                        width=agent_cfg.get("value_width"))
    dynamics_loss = _dynamics_loss(cfg["loss"], dynamics)
    return dynamics, dynamics_loss, value_network


def _expert_margin(agent_cfg: dict) -> dict:
    """The Q losses' expert large-margin keys (absent in checkpoints written before them: off)."""
    return {"expert_margin_weight": float(agent_cfg.get("expert_margin_weight") or 0.0),
            "expert_margin": float(agent_cfg.get("expert_margin") or 0.1),
            "expert_margin_rows": int(agent_cfg.get("expert_margin_rows") or 4),
            "expert_margin_temperature": float(agent_cfg.get("expert_margin_temperature") or 0.0)}


def _optimisation(agent_cfg: dict) -> dict:
    return {"lr": dict(agent_cfg["lr"]), "weight_decay": dict(agent_cfg.get("weight_decay") or {}),
            "lr_decay": float(agent_cfg["lr_decay"]), "lr_decay_every": int(agent_cfg["lr_decay_every"]),
            "target_update_interval": int(agent_cfg["target_update_interval"]),
            "greedy_ema_decay": agent_cfg.get("greedy_ema_decay"), "greedy_ema_tail": agent_cfg.get("greedy_ema_tail"),
            "greedy_ema_model": bool(agent_cfg.get("greedy_ema_model", True))}


def build_fcdqn_agent(cfg: Mapping[str, Any], max_height: float):
    """FC-DQN (``ldm_rl.agents.fc_dqn``): the Q FCN of ``cfg.agent``, exploring by softmax(Q/τ) with the
    proposal temperature ``cfg.planner.tau``; ``cfg.model`` gives only the input quantisation."""
    from ldm_rl.agents.fc_dqn import FCDQNAgent
    from ldm_rl.objectives import SpatialDQNLoss
    from ldm_rl.planning.q_map import QMapPolicy

    agent_cfg = _plain(cfg["agent"])
    q_network = _q_network(cfg, agent_cfg, max_height)
    policy = QMapPolicy(q_network, tau=_plain(cfg["planner"])["tau"])
    loss = SpatialDQNLoss(q_network, gamma=float(agent_cfg["gamma"]), q_log_floor=agent_cfg.get("q_log_floor"),
                          return_lower_bound=bool(agent_cfg.get("return_lower_bound", False)),
                          **_expert_margin(agent_cfg))
    return FCDQNAgent(policy, loss, q_grad_clip=agent_cfg.get("q_grad_clip"), **_optimisation(agent_cfg))


def build_rs_agent(cfg: Mapping[str, Any], max_height: float):
    """Random Shooting (``ldm_rl.agents.random_shooting``): ``cfg.planner.num_candidates`` near-object
    candidates (``agent.object_height_threshold``, ``agent.object_dilation``) scored by R + γV through the
    LDM of ``cfg.model``; no Q network is built."""
    from ldm_rl.agents.random_shooting import RandomShootingAgent
    from ldm_rl.objectives import RandomShootingLoss
    from ldm_rl.planning.random_shooting import RandomShootingPlanner

    agent_cfg = _plain(cfg["agent"])
    height, dilation = _required(agent_cfg, "rs", "object_height_threshold", "object_dilation")
    dynamics, dynamics_loss, value_network = _model_and_value(cfg, agent_cfg, max_height)
    planner_cfg = _plain(cfg["planner"])
    gamma, rule = float(agent_cfg["gamma"]), {"height_threshold": float(height), "dilation": int(dilation)}
    planner = RandomShootingPlanner(dynamics, value_network, num_candidates=int(planner_cfg["num_candidates"]),
                                    gamma=gamma, tau_value=planner_cfg["tau_value"],
                                    chunk_size=int(planner_cfg.get("chunk_size", 64)), **rule)
    loss = RandomShootingLoss(dynamics, value_network, gamma=gamma,
                              num_target_candidates=int(agent_cfg["num_target_candidates"]),
                              value_on_prediction=bool(agent_cfg.get("value_on_prediction", True)),
                              chunk_size=int(agent_cfg.get("chunk_size", 64)),
                              return_lower_bound=bool(agent_cfg.get("return_lower_bound", False)), **rule)
    return RandomShootingAgent(planner, loss, dynamics_loss, **_optimisation(agent_cfg))


def build_dynaq_agent(cfg: Mapping[str, Any], max_height: float):
    """Dyna-Q (``ldm_rl.agents.dyna_q``): FC-DQN plus ``agent.imagined_ratio`` transitions per replayed one
    imagined by the LDM of ``cfg.model`` with rewards from the V CNN's reward head."""
    from ldm_rl.agents.dyna_q import DynaQAgent
    from ldm_rl.objectives import SpatialDQNLoss
    from ldm_rl.planning.q_map import QMapPolicy

    agent_cfg = _plain(cfg["agent"])
    ratio, terminal = _required(agent_cfg, "dynaq", "imagined_ratio", "imagined_terminal_reward")
    q_network = _q_network(cfg, agent_cfg, max_height)
    _, dynamics_loss, value_network = _model_and_value(cfg, agent_cfg, max_height)
    policy = QMapPolicy(q_network, tau=_plain(cfg["planner"])["tau"])
    loss = SpatialDQNLoss(q_network, gamma=float(agent_cfg["gamma"]), q_log_floor=agent_cfg.get("q_log_floor"),
                          return_lower_bound=bool(agent_cfg.get("return_lower_bound", False)),
                          **_expert_margin(agent_cfg))
    return DynaQAgent(policy, loss, dynamics_loss, value_network, imagined_ratio=float(ratio),
                      terminal_reward=float(terminal),
                      reward_on_prediction=bool(agent_cfg.get("value_on_prediction", True)),
                      q_grad_clip=agent_cfg.get("q_grad_clip"), **_optimisation(agent_cfg))


AGENTS: dict[str, Callable] = {"ldm": build_ldm_agent, "fcdqn": build_fcdqn_agent, "rs": build_rs_agent,
                               "dynaq": build_dynaq_agent}


def build_agent(cfg: Mapping[str, Any], max_height: float):
    """The agent named by ``cfg.agent.name`` (one of :data:`AGENTS`)."""
    name = cfg["agent"].get("name")
    if name not in AGENTS:
        raise ValueError(f"agent.name must be one of {sorted(AGENTS)}, got {name!r}")
    return AGENTS[name](cfg, max_height)


def load_agent(path, *, preset: str | None = None, device="cpu", planner: Mapping[str, Any] | None = None,
               q_pick_min_height: float | None = None, hand_rule: str | None = None, height_anchor: float | None = None):
    """Rebuild the agent saved by ``recipes/train_policy.py`` at ``path``; returns ``(agent, config)``.

    ``preset``: when given, the checkpoint must hold that preset (one clear error otherwise). ``planner``:
    keys set over the checkpoint's planner config (the LDM agent's weights planned another way, e.g.
    ``{"name": "tree", "depth": 2}``; a tree planner's unset keys take :class:`~ldm_rl.planning.TreePlanner`'s
    defaults and the agent's γ). ``q_pick_min_height`` (m): Q's empty-pick mask set over the checkpoint's
    ``agent.q_pick_min_height`` (0 = off; a setting of the network, not a weight). ``hand_rule``: the world
    model's ``model.hand_rule.kind`` (``"occupancy"`` | ``"removal"``; a rule, not a weight). ``height_anchor``: the
    LDM's ``model.height_anchor`` (metres; 0 = none): how its frame is shifted in height, not a weight (the same weights
    predict alike up to the anchor). The returned config holds what was actually built.
    """
    from ldm_rl.run.checkpoint import CheckpointError, load_checkpoint

    expect = {"kind": "agent", **({"preset": preset} if preset is not None else {})}
    checkpoint = load_checkpoint(path, expect=expect, map_location=device)
    cfg = checkpoint.meta["config"]
    if planner:
        if cfg["agent"]["name"] != "ldm":
            raise CheckpointError(f"planner overrides {dict(planner)} apply to the ldm agent's planner; {path} "
                                  f"holds agent {cfg['agent']['name']!r}")
        cfg = {**cfg, "planner": {**cfg["planner"], **_plain(planner)}}
    if q_pick_min_height is not None:
        if cfg["agent"]["name"] == "rs":
            raise CheckpointError(f"q_pick_min_height={q_pick_min_height!r} masks a Q network's picks; {path} holds "
                                  "agent 'rs', which has none")
        max_height = float(cfg["env"]["max_height"])
        if not 0 <= float(q_pick_min_height) < max_height:
            raise CheckpointError(f"q_pick_min_height must be in [0, max_height = {max_height}) metres for {path}, got "
                                  f"{q_pick_min_height!r}")
        cfg = {**cfg, "agent": {**cfg["agent"], "q_pick_min_height": float(q_pick_min_height)}}
    if hand_rule is not None:
        if cfg["agent"]["name"] == "fcdqn":
            raise CheckpointError(f"hand_rule={hand_rule!r} is the world model's; {path} holds agent 'fcdqn', which has none")
        model = cfg["model"]
        cfg = {**cfg, "model": {**model, "hand_rule": {**(model.get("hand_rule") or {}), "kind": str(hand_rule)}}}
    if height_anchor is not None:
        max_height = float(cfg["env"]["max_height"])
        if cfg["agent"]["name"] == "fcdqn" or cfg["model"].get("name", "ldm") != "ldm":
            raise CheckpointError(f"height_anchor={height_anchor!r} shifts the LDM's frame; {path} holds agent "
                                  f"{cfg['agent']['name']!r} with model {cfg['model'].get('name')!r}")
        if not 0 <= float(height_anchor) < max_height:
            raise CheckpointError(f"height_anchor must be in [0, max_height = {max_height}) metres (0 = none) for {path}, "
                                  f"got {height_anchor!r}")
        cfg = {**cfg, "model": {**cfg["model"], "height_anchor": float(height_anchor) or None}}
    agent = build_agent(cfg, float(cfg["env"]["max_height"])).to(device)
    agent.load_policy_state_dict(checkpoint.state["agent"])  # best_policy.pt holds no target copies
    return agent.eval(), cfg
