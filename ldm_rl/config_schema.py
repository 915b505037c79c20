"""Typed configuration: the schema of each recipe's primary config ``conf/<recipe>.yaml``.

The pattern (docs/reliability.md has the long form):

1. **One dataclass per config group** (``EnvConfig``, ``ModelConfig``, ...). Each field has the type and,
   through :func:`spec`, the allowed range or choices and a short doc; an optional ``check(node)``
   static method holds cross-field rules. Values live in the YAML files, so most fields default to
   ``MISSING``.
2. **One dataclass per primary config** (``TrainDynamicsConfig`` for ``conf/train_dynamics.yaml``, ...) with a field per group it reads,
   stored by :func:`register_configs` in Hydra's ConfigStore as ``schema/<name>`` (package
   ``_global_``); the primary YAML lists ``- optional schema: <name>`` first in its defaults. A recipe
   imports this module (registration runs at import), so Hydra rejects a wrong type or an unknown
   key while composing, even for ``--cfg job``.
3. :func:`validate_config` checks ranges, choices and cross-field rules (and types again, for code
   that composed without the schema); every problem is reported on one line.
4. A recipe's ``if __name__ == "__main__":`` calls ``ldm_rl.run.cli.check_command_line`` before ``main()``: it
   composes the command line as Hydra will, validates it, handles ``resume=true`` (the run's own
   overrides are replayed), and on any problem prints ``error: ...`` (one line) and exits with code 2
   before Hydra creates an output folder and before torch is imported.

Importing this module is light: hydra and omegaconf only.
"""

import dataclasses
import re
import typing
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, ClassVar, List, Mapping, Optional

from omegaconf import MISSING, DictConfig, OmegaConf


__all__ = [
    "ConfigError",
    "Rule",
    "spec",
    "EnvConfig",
    "HandRuleConfig",
    "ModelConfig",
    "LossConfig",
    "LoggerConfig",
    "NoiseConfig",
    "StripConfig",
    "DemosConfig",
    "MetricsConfig",
    "DynamicsConfig",
    "TrainDynamicsConfig",
    "DemosRunConfig",
    "SCHEMAS",
    "register_schema",
    "register_configs",
    "validate_config",
    "config_differences",
]


class ConfigError(ValueError):
    """A composed config that is typed right but not usable (out of range, contradictory)."""


# ------------------------------------------------------------------------------------------ rules


@dataclass(frozen=True)
class Rule:
    """Allowed values of one field: bounds, choices, a multiple, a regular expression; ``doc`` says what it is."""

    ge: float | None = None
    gt: float | None = None
    le: float | None = None
    lt: float | None = None
    choices: tuple | None = None
    multiple_of: int | None = None
    pattern: str | None = None
    doc: str = ""
    allowed: str | None = None  # the allowed values in words, when the rule alone would not say it well
    exists: bool = False  # a path (relative to the working directory) that must exist; null passes

    def describe(self) -> str:
        """The allowed values in words, e.g. ``in [0, 1)``, ``> 0``, ``one of 'csv', 'none'``."""
        if self.allowed is not None:
            return self.allowed
        if self.exists:
            return "null or an existing path"
        if self.choices is not None:
            return "one of " + ", ".join(repr(c) if c is not None else "null" for c in self.choices)
        if self.pattern is not None:
            return f"matching {self.pattern}"
        low = (f"[{_num(self.ge)}" if self.ge is not None else f"({_num(self.gt)}" if self.gt is not None else None)
        high = (f"{_num(self.le)}]" if self.le is not None else f"{_num(self.lt)})" if self.lt is not None else None)
        if low and high:
            text = f"in {low}, {high}"
        elif low:
            text = f">= {_num(self.ge)}" if self.ge is not None else f"> {_num(self.gt)}"
        elif high:
            text = f"<= {_num(self.le)}" if self.le is not None else f"< {_num(self.lt)}"
        else:
            text = "any value"
        if self.multiple_of:
            text += f" and a multiple of {self.multiple_of}"
        return text

    def violated(self, value: Any) -> bool:
        if value is None:  # Optional fields: null is allowed where the type says so
            return False
        if self.exists:
            return not Path(str(value)).expanduser().exists()
        if self.choices is not None:
            return value not in self.choices
        if self.pattern is not None:
            return not (isinstance(value, str) and re.fullmatch(self.pattern, value))
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            return False
        if value != value:  # NaN
            return True
        return bool(
            (self.ge is not None and value < self.ge)
            or (self.gt is not None and value <= self.gt)
            or (self.le is not None and value > self.le)
            or (self.lt is not None and value >= self.lt)
            or (self.multiple_of and value % self.multiple_of)
        )


def _num(x: float) -> str:
    return f"{x:g}" if isinstance(x, float) else str(x)


def spec(default: Any = MISSING, **rule: Any) -> Any:
    """A dataclass field with a :class:`Rule` (``ge``, ``gt``, ``le``, ``lt``, ``choices``,
    ``multiple_of``, ``pattern``, ``doc``) in its metadata; ``default`` as for ``dataclasses.field``."""
    return field(default=default, metadata={"rule": Rule(**rule)})


def group(cls: type) -> Any:
    """A field holding a nested group dataclass."""
    return field(default_factory=cls)


# ------------------------------------------------------------------------- light pre-flight facts

# objects each task accepts (the envs raise the same for other counts: tests/test_config.py checks both agree)
OBJECT_COUNTS = {"ldm_rl/HouseBuilding-v0": (3, 3), "ldm_rl/BottleArrangement-v0": (1, 6)}
# pixels per side of the heightmap and of each rotation's Q map (ldm_rl.geometry.HEIGHTMAP_SIZE; tested equal)
HEIGHTMAP_PIXELS = 128


# ------------------------------------------------------------------------------------ the schema


@dataclass
class EnvConfig:
    """``conf/env/*.yaml``: the task (``ldm_rl.envs``)."""

    id: str = spec(doc="gymnasium id, e.g. ldm_rl/BlockStacking-v0")
    num_objects: int = spec(ge=1, doc="objects in the scene")
    max_steps: Optional[int] = spec(None, ge=1, doc="primitives per episode; null = 2*num_objects + 4")
    num_rotations: int = spec(8, ge=2, multiple_of=2, doc="rotation bins k*pi/R")
    max_height: float = spec(gt=0, le=1, doc="metres of the top depth class")
    demo_procedure: str = spec("direct", choices=("direct", "deconstruct"), doc="expert demo procedure")
    failed_pick_memory: int = spec(0, ge=0, le=64, doc="picks that came up empty, remembered until the hand changes and "
                                   "never proposed again (0 = off; ldm_rl.envs.memory)")
    scene_memory: int = spec(0, ge=0, le=64, doc="scenes seen with an empty hand this episode, remembered for the "
                             "lookahead's revisit rule (0 = off; ldm_rl.envs.memory)")
    train_object_counts: Optional[List[int]] = spec(
        None, doc="object counts drawn per training episode and expert demo (null = num_objects); evaluation uses num_objects")
    finger_spinning_friction: float = spec(
        0.0, ge=0, doc="torsional friction of the gripper's finger pads (conf/env: 0.1, the anchor's; the default 0 is the "
        "physics of runs before 2026-11-27, whose stored configs lack the key)")
    progress_reward: float = spec(
        0.0, ge=0, le=1, doc="bin packing only: reward per block coming to rest in the bin, given back when one "
        "leaves it or on a failure (0 = off, the paper's sparse reward; ldm_rl.envs.tasks.bin_packing)")

    @staticmethod
    def check(node: DictConfig, prefix: str) -> list[str]:
        if node.get("progress_reward") and node.id != "ldm_rl/BinPacking-v0":
            return [f"{prefix}progress_reward={node.progress_reward}: only ldm_rl/BinPacking-v0 has a progress term "
                    f"(got id {node.id}); set 0"]
        low, high = OBJECT_COUNTS.get(node.id, (1, None))
        allowed = f"exactly {low}" if low == high else f"in {low}..{high}" if high is not None else f"at least {low}"
        counts = [("num_objects", node.num_objects)]
        if node.get("train_object_counts") is not None:
            if len(node.train_object_counts) == 0:
                return [f"{prefix}train_object_counts=[]: give null or a non-empty list of object counts"]
            counts += [("train_object_counts", n) for n in node.train_object_counts]
        for key, n in counts:
            if n < low or (high is not None and n > high):
                return [f"{prefix}{key}={n if key == 'num_objects' else list(node.train_object_counts)}: "
                        f"{node.id} takes {allowed} objects"]
        return []


@dataclass
class HandRuleConfig:
    center_size: int = spec(32, ge=1, le=128, doc="side of the central window of the hand-state rule")
    before_threshold: int = spec(25, ge=0, doc="occupied pixels needed before the action")
    after_threshold: int = spec(25, ge=0, doc="occupied pixels allowed after the action")
    kind: str = spec("occupancy", choices=("occupancy", "removal"),
                     doc="occupancy: the reference's rule; removal: a pick holds iff the pixels under the fingers dropped")
    removal_size: int = spec(12, ge=1, le=128, doc="removal: side of the central window under the fingers")
    removal_fraction: float = spec(0.5, ge=0, lt=1, doc="removal: fraction of that window that must drop by a class")


@dataclass
class ModelConfig:
    """``conf/model/*.yaml``: the dynamics model (``ldm_rl.world_model.build_dynamics_model``)."""

    name: str = spec(choices=("ldm", "naive"), doc="LDM or the Naive baseline")
    preset: str = spec(choices=("paper", "lite"), doc="network size")
    width: float = spec(gt=0, le=4, doc="channel multiplier of the lite preset")
    crop_size: int = spec(ge=32, le=128, multiple_of=16, doc="side of B_a in pixels")
    num_depth_classes: int = spec(ge=2, le=256, doc="depth classes K")
    num_rotations: int = spec(ge=2, multiple_of=2, doc="rotation bins; must equal env.num_rotations")
    hand_rule: HandRuleConfig = group(HandRuleConfig)
    hand_crop_mode: str = spec("bilinear", choices=("bilinear", "nearest"), doc="crop mode of the predicted in-hand image")
    action_sigma: float = spec(2.0, gt=0, doc="Naive only: std (px) of the action blob")
    height_anchor: Optional[float] = spec(None, gt=0, doc="LDM only: metres; the crop lowered by how far the highest "
                                          "point under the fingers stands above it (null = the paper)")


@dataclass
class LossConfig:
    """``conf/loss/*.yaml``: ``ldm_rl.objectives.LDMLoss``."""

    gamma: float = spec(ge=0, doc="focal exponent")
    class_weights: Any = MISSING  # null | "auto" | list of K floats (checked below)
    label_smoothing: float = spec(0.0, ge=0, lt=1, doc="label smoothing epsilon")
    gripper_symmetries: bool = spec(False, doc="LDM only: train on the four mirrors of the gripper's frame")

    @staticmethod
    def check(node: DictConfig, prefix: str) -> list[str]:
        value = node.class_weights
        if value is None or value == "auto":
            return []
        if OmegaConf.is_list(value) and all(isinstance(v, (int, float)) and not isinstance(v, bool) and v >= 0 for v in value):
            return []
        return [f"{prefix}class_weights={_show(value)}: must be null, 'auto' or a list of K non-negative numbers"]


@dataclass
class LoggerConfig:
    """``conf/logger/*.yaml``: ``ldm_rl.run.outputs.make_logger`` (TorchRL's ``get_logger``; docs/logging.md)."""

    backend: str = spec(choices=("csv", "tensorboard", "wandb", "mlflow", "none"), doc="TorchRL logger")
    exp_name: str = MISSING
    project: Optional[str] = spec(None, doc="wandb project; null = ldm_rl")
    group: Optional[str] = spec(None, doc="wandb run group, e.g. one per sweep")
    mode: Optional[str] = spec(None, choices=(None, "online", "offline", "disabled"),
                               doc="wandb mode; null = $WANDB_MODE, else online")
    tracking_uri: Optional[str] = spec(None, doc="mlflow store: a folder or a server/database URI; null = ./mlruns")


@dataclass
class NoiseConfig:
    position: float = spec(0.0, ge=0, le=0.1, doc="expert position jitter, metres")
    random_action_prob: float = spec(0.0, ge=0, le=1, doc="probability of a random action")
    rotation_prob: float = spec(0.0, ge=0, le=1, doc="probability of the expert's position at a random other rotation")


@dataclass
class StripConfig:
    out: Optional[str] = None
    scale: int = spec(2, ge=1, le=16, doc="PNG pixels per heightmap pixel")


@dataclass
class DemosConfig:
    """``conf/demos/*.yaml``: ``recipes/generate_demos.py`` (and the noise of in-process demos)."""

    num_steps: Optional[int] = spec(ge=1, doc="transitions to collect")
    num_episodes: Optional[int] = spec(ge=1, doc="episodes to collect")
    procedure: str = spec(choices=("direct", "deconstruct"), doc="expert demo procedure")
    noise: NoiseConfig = group(NoiseConfig)
    out: Optional[str] = None
    progress: bool = True
    strip: StripConfig = group(StripConfig)

    @staticmethod
    def check(node: DictConfig, prefix: str) -> list[str]:
        steps, episodes = node.num_steps, node.num_episodes
        if steps is not None and episodes is not None:
            return [f"{prefix}num_steps={steps} and {prefix}num_episodes={episodes} are both set: give exactly one "
                    f"(e.g. {prefix}num_steps=null {prefix}num_episodes={episodes})"]
        if steps is None and episodes is None:
            return [f"{prefix}num_steps and {prefix}num_episodes are both null: give exactly one"]
        return []


@dataclass
class MetricsConfig:
    region_size: int = spec(64, ge=1, le=128, doc="side of B_a for L1 in the region")
    iou_threshold: float = spec(0.75, gt=0, le=1, doc="IoU a place needs to count as correct")
    height_tolerance: float = spec(1.0, ge=0, doc="mean class error a place may have")


@dataclass
class DynamicsConfig:
    """``conf/dynamics/*.yaml``: ``recipes/train_dynamics.py``."""

    data: Optional[str] = spec(None, exists=True, doc="a demo folder written by recipes/generate_demos.py")
    num_demo_steps: int = spec(ge=2, doc="in-process demo transitions when data is null")
    val_fraction: float = spec(gt=0, lt=1, doc="held-out fraction")
    iterations: int = spec(ge=1, doc="training iterations")
    batch_size: int = spec(ge=1, doc="transitions per step")
    lr: float = spec(gt=0, le=1, doc="Adam learning rate")
    lr_decay: float = spec(gt=0, le=1, doc="LR factor per decay step")
    lr_decay_every: int = spec(ge=1, doc="iterations per LR decay step")
    weight_decay: float = spec(0.0, ge=0, doc="Adam weight decay")
    autocast: Optional[str] = spec(None, choices=(None, "bf16"), doc="autocast of the loss forward")
    eval_every: int = spec(ge=1, doc="iterations between evaluations")
    eval_batch_size: int = spec(64, ge=1, doc="evaluation batch")
    grid_samples: int = spec(6, ge=1, doc="rows of predictions.png")
    checkpoint_every: int = spec(100, ge=0, doc="iterations between checkpoints; 0 = only at the end and on a stop signal")
    metrics: MetricsConfig = group(MetricsConfig)


@dataclass
class SeedAndThreads:
    """The keys every recipe's primary config has at its top level."""

    seed: int = spec(0, ge=0, doc="seed of every RNG")
    threads: Optional[int] = spec(1, ge=1, le=1024, doc="torch intra-op threads; null = torch's default")


@dataclass
class RunSettings(SeedAndThreads):
    """The top-level keys of the recipes that run networks: a seed, threads and a device."""

    device: str = spec("auto", pattern=r"auto|cpu|cuda(:\d+)?|mps|xpu(:\d+)?", allowed="auto, cpu, cuda, cuda:N or mps",
                       doc="torch device")


@dataclass
class DemosRunConfig(SeedAndThreads):
    """``conf/generate_demos.yaml`` and ``conf/render_expert_strip.yaml``: the task and the expert."""

    env: EnvConfig = group(EnvConfig)
    demos: DemosConfig = group(DemosConfig)


@dataclass
class TrainDynamicsConfig(RunSettings):
    """``conf/train_dynamics.yaml``: the groups, plus seed / device / threads / resume."""

    env: EnvConfig = group(EnvConfig)
    model: ModelConfig = group(ModelConfig)
    loss: LossConfig = group(LossConfig)
    logger: LoggerConfig = group(LoggerConfig)
    demos: DemosConfig = group(DemosConfig)
    dynamics: DynamicsConfig = group(DynamicsConfig)
    resume: bool = False

    @staticmethod
    def check(node: DictConfig, prefix: str) -> list[str]:
        found = []
        env_r, model_r = node.env.num_rotations, node.model.num_rotations
        if env_r != model_r:
            found.append(f"model.num_rotations={model_r} differs from env.num_rotations={env_r}: the model's rotation bins "
                         "must be the env's")
        weights, k = node.loss.class_weights, node.model.num_depth_classes
        if OmegaConf.is_list(weights) and len(weights) != k:
            found.append(f"loss.class_weights has {len(weights)} entries: must have model.num_depth_classes={k}")
        anchor = node.model.get("height_anchor")
        if anchor is not None and node.model.name != "ldm":
            found.append(f"model.height_anchor={_show(anchor)} shifts the LDM's local frame; model={node.model.name} has none")
        elif anchor is not None and not anchor < node.env.max_height:
            found.append(f"model.height_anchor={_show(anchor)} must be below env.max_height={_show(node.env.max_height)} "
                         "(metres of the top depth class)")
        if node.loss.get("gripper_symmetries") and node.model.name != "ldm":
            found.append(f"loss.gripper_symmetries=true mirrors the LDM's gripper-aligned frame; model={node.model.name} has none")
        return found


# ------------------------------------------------------------------ the agent (recipes/train_policy.py)


def _schedule_problem(value: Any, key: str, *, positive: bool) -> str | None:
    """A planner/replay value: a number (> 0 or >= 0) or a ``{_target_: ldm_rl.schedules.X, ...}`` node."""
    if isinstance(value, (int, float)) and not isinstance(value, bool):
        bad = value <= 0 if positive else value < 0
        return f"{key}={_show(value)}: must be {'> 0' if positive else '>= 0'}" if bad or value != value else None
    if OmegaConf.is_dict(value) and str(value.get("_target_", "")).startswith("ldm_rl.schedules."):
        return None
    return (f"{key}={_show(value)}: must be a number or a schedule "
            "{_target_: ldm_rl.schedules.Linear | StepDecay | StepLinear | Exponential | Constant, ...}")


@dataclass
class TargetProposalConfig:
    mode: str = spec("argmax", choices=("softmax", "argmax"), doc="how the target's proposals are drawn")
    tau: float = spec(1.0, gt=0, doc="proposal temperature, Q units")
    beta: float = spec(1.0, ge=0, doc="inhibition height, Q units")
    sigma: float = spec(2.0, ge=0, doc="inhibition width, pixels")
    sigma_rot: float = spec(1.0, ge=0, doc="inhibition width, rotation bins")


@dataclass
class PerNetwork:
    q: float = spec(gt=0, le=1, doc="Q FCN")
    value: float = spec(gt=0, le=1, doc="V CNN and its reward head")
    dynamics: float = spec(gt=0, le=1, doc="the LDM")


@dataclass
class PerNetworkDecay:
    q: float = spec(0.0, ge=0, doc="Q FCN")
    value: float = spec(0.0, ge=0, doc="V CNN")
    dynamics: float = spec(0.0, ge=0, doc="the LDM")


@dataclass
class AgentConfig:
    """``conf/agent/*.yaml``: ``ldm_rl.agents.build_agent``."""

    name: str = spec(choices=("ldm", "fcdqn", "rs", "dynaq"), doc="the agent (ldm_rl.agents.AGENTS)")
    preset: Optional[str] = spec(None, choices=(None, "paper", "lite"), doc="Q/V size; null = model.preset")
    q_width: Optional[float] = spec(None, gt=0, le=4, doc="Q channel multiplier override")
    q_head_channels: Optional[int] = spec(None, ge=1, doc="hidden units of Q's pick/place heads (null = 8 scaled by the width)")
    q_frame_margin: int = spec(0, ge=0, lt=32, doc="pixels at each Q gripper frame's edge never proposed (0 = none)")
    q_frame_pad: int = spec(0, ge=0, le=64, doc="pixels of zeros around the scene before QFCN rotates it into each "
                            "bin's frame (a multiple of 8; 0 = the reference's 128 px frames)")
    q_pick_min_height: float = spec(0.0, ge=0, doc="m: picks on pixels not above it (nothing to grasp) never proposed (0 = none)")
    q_architecture: str = spec("fcn", choices=("fcn", "equivariant"),
                               doc="Q network: QFCN (rotated scenes) | C_2R-equivariant e2cnn net (extra [equivariant])")
    value_width: Optional[float] = spec(None, gt=0, le=4, doc="V channel multiplier override")
    gamma: float = spec(ge=0, le=1, doc="discount of the targets")
    num_target_candidates: int = spec(ge=1, doc="N of the V target's max")
    target_proposal: TargetProposalConfig = group(TargetProposalConfig)
    value_on_prediction: bool = True
    chunk_size: int = spec(64, ge=1, doc="state-candidate pairs per LDM/V pass")
    lr: PerNetwork = group(PerNetwork)
    weight_decay: PerNetworkDecay = group(PerNetworkDecay)
    lr_decay: float = spec(gt=0, le=1, doc="LR factor per decay step")
    lr_decay_every: int = spec(ge=1, doc="updates per LR decay step")
    target_update_interval: int = spec(ge=1, doc="updates between target-network copies")
    q_grad_clip: Optional[float] = spec(None, gt=0, doc="element-wise Q gradient clamp")
    expert_margin_weight: float = spec(0.0, ge=0, doc="λ of DQfD's large-margin term on the expert rows (0 = off)")
    expert_margin: float = spec(0.1, gt=0, doc="l: the lead the expert's action keeps over every other (Q's fitted units)")
    expert_margin_rows: int = spec(4, ge=1, doc="expert rows per batch the margin term reads (a whole-map Q pass each)")
    expert_margin_temperature: float = spec(0.0, ge=0, doc="τ of the margin's soft max over Q's map (Q's fitted units; "
                                            "0 = DQfD's hard max)")
    target_range: Optional[List[float]] = None
    double_value: bool = False
    q_target: str = spec("max", choices=("max", "lookahead"), doc="Q target: r + γ max Q⁻ | the V lookahead target")
    q_log_floor: Optional[float] = spec(None, gt=0, lt=1, doc="Q regresses log(max(target, this)); null = the "
                                        "target itself")
    autocast: Optional[str] = spec(None, choices=(None, "bf16"), doc="ldm: autocast of the update's forward passes")
    return_lower_bound: bool = spec(False, doc="raise the targets to the return the episode collected")
    greedy_ema_decay: Optional[float] = spec(None, gt=0, lt=1, doc="EMA decay of the weights the greedy policy "
                                             "plays (null = the online weights)")
    greedy_ema_tail: Optional[float] = spec(None, gt=0, le=1, doc="the average spans at most this fraction of the "
                                            "updates so far (null = the decay alone)")
    greedy_ema_model: bool = spec(True, doc="ldm, rs: the average covers the world model too (false: the greedy "
                                  "policy plans with the online model)")
    bootstrap_cache: int = spec(0, ge=0, doc="ldm: transitions whose bootstrap is kept until the next target copy "
                                "(0 = off)")
    value_augmentation: Optional[str] = spec(None, choices=(None, "quarter_turns", "shifts", "symmetries"),
                                             doc="ldm: V fitted on next states turned by random quarter turns | "
                                             "moved by random shifts | turned, mirrored and shifted")
    value_shift: Optional[int] = spec(None, ge=1, le=32, doc="ldm: largest shift of value_augmentation=shifts "
                                      "or symmetries, pixels")
    value_raise_levels: int = spec(0, ge=0, le=8, doc="ldm: V fitted on next states with the tallest object raised "
                                   "by a random 0..L levels (0 = off)")
    value_raise_height: Optional[float] = spec(None, gt=0, lt=1, doc="ldm: metres of one level of value_raise_levels")
    value_raise_region: Optional[str] = spec(None, choices=(None, "object", "top"), doc="ldm: what value_raise_levels "
                                             "raises: everything touching the tallest pixel | its top level only")
    target_uncertainty_penalty: float = spec(0.0, ge=0.0, doc="ldm: λ of the V target's V⁻ − λ·H⁻ (nats; 0 = off)")
    termination_head: bool = spec(False, doc="ldm: V composed from a termination head, V = T·R + (1 − T)·W "
                                  "(T fitted on the terminated flag)")
    value_log_floor: Optional[float] = spec(None, gt=0, lt=1, doc="ldm: V's head predicts log V, fitted on "
                                            "log(max(target, this)); null = V itself")
    q_proposal_fit: int = spec(0, ge=0, doc="ldm: target proposals per next state Q is also fitted on, toward "
                               "V⁻ of their prediction (0 = off)")
    value_margin_weight: float = spec(0.0, ge=0, doc="ldm: λ of the large-margin term on V(f(s, a)) of the expert rows: "
                                      "the expert's outcome above Q's proposals' (0 = off)")
    value_margin: float = spec(0.01, gt=0, doc="ldm: l, the lead the expert's predicted outcome keeps in V (V's fitted units)")
    # the baselines' own keys (null unless that agent is chosen; checked below)
    object_height_threshold: Optional[float] = spec(None, gt=0, le=1, doc="rs: metres above which a pixel is an object")
    object_dilation: Optional[int] = spec(None, ge=0, le=64, doc="rs: pixels the object mask grows by")
    imagined_ratio: Optional[float] = spec(None, ge=0, le=16, doc="dynaq: imagined transitions per replayed one")
    imagined_terminal_reward: Optional[float] = spec(None, gt=0, le=1, doc="dynaq: predicted reward that ends an "
                                                     "imagined episode")

    # which agent uses which of the keys above
    BASELINE_KEYS = {"rs": ("object_height_threshold", "object_dilation"),
                     "dynaq": ("imagined_ratio", "imagined_terminal_reward")}

    @staticmethod
    def check(node: DictConfig, prefix: str) -> list[str]:
        found = []
        for agent, names in AgentConfig.BASELINE_KEYS.items():
            for key in names:
                if node.name == agent and node[key] is None:
                    found.append(f"{prefix}{key} is null: agent={agent} needs it (conf/agent/{agent}.yaml)")
                elif node.name != agent and node[key] is not None:
                    found.append(f"{prefix}{key}={_show(node[key])} is set but only agent={agent} uses it "
                                 f"(agent.name={node.name})")
        for key in ("autocast", "value_augmentation", "value_shift", "value_raise_height", "value_raise_region"):
            if node.name != "ldm" and node.get(key) is not None:
                found.append(f"{prefix}{key}={_show(node[key])} is set but only agent=ldm uses it (agent.name={node.name})")
        if node.get("value_raise_levels"):
            if node.name != "ldm":
                found.append(f"{prefix}value_raise_levels={_show(node.value_raise_levels)} is set but only agent=ldm "
                             f"uses it (agent.name={node.name})")
            elif node.get("value_raise_height") is None:
                found.append(f"{prefix}value_raise_levels={_show(node.value_raise_levels)} needs "
                             f"{prefix}value_raise_height (metres of one level, e.g. 0.04 for the cubes)")
        if node.get("value_log_floor") is not None:
            if node.name != "ldm":
                found.append(f"{prefix}value_log_floor={_show(node.value_log_floor)} is set but only agent=ldm uses it "
                             f"(agent.name={node.name})")
            elif node.get("termination_head"):
                found.append(f"{prefix}value_log_floor={_show(node.value_log_floor)} cannot be combined with "
                             f"{prefix}termination_head=true (a composed V has no log head); set one of them off")
        if node.get("value_margin_weight") and node.name != "ldm":
            found.append(f"{prefix}value_margin_weight={_show(node.value_margin_weight)} is set but only agent=ldm "
                         f"decides by V(f(s, a)) (agent.name={node.name}); set it to 0")
        if node.get("termination_head") and node.name != "ldm":
            found.append(f"{prefix}termination_head=true is set but only agent=ldm uses it (agent.name={node.name})")
        if node.get("greedy_ema_tail") is not None and node.get("greedy_ema_decay") is None:
            found.append(f"{prefix}greedy_ema_tail={_show(node.greedy_ema_tail)} is set but {prefix}greedy_ema_decay is "
                         "null: the tail shortens an average, set the decay of the longest one")
        if not node.get("greedy_ema_model", True):
            if node.get("greedy_ema_decay") is None:
                found.append(f"{prefix}greedy_ema_model=false is set but {prefix}greedy_ema_decay is null: there is no "
                             "average to leave the model out of")
            elif node.name not in ("ldm", "rs"):
                found.append(f"{prefix}greedy_ema_model=false is set but agent={node.name} plans with no model")
        if node.name == "rs" and node.get("q_architecture", "fcn") != "fcn":
            found.append(f"{prefix}q_architecture={node.q_architecture} is set but agent=rs builds no Q network")
        if node.name == "rs" and node.get("expert_margin_weight"):
            found.append(f"{prefix}expert_margin_weight={_show(node.expert_margin_weight)} is set but agent=rs builds no "
                         "Q network; set it to 0")
        if node.get("q_frame_pad") and (node.name == "rs" or node.get("q_architecture", "fcn") != "fcn"):
            found.append(f"{prefix}q_frame_pad={_show(node.q_frame_pad)} pads QFCN's rotated frames, which "
                         f"agent={node.name} with q_architecture={node.get('q_architecture', 'fcn')} does not build; set it to 0")
        elif node.get("q_frame_pad", 0) % 8:
            found.append(f"{prefix}q_frame_pad={_show(node.q_frame_pad)} must be a multiple of 8 (the trunk halves its "
                         "input four times)")
        if node.name == "rs" and node.get("q_log_floor") is not None:
            found.append(f"{prefix}q_log_floor={_show(node.q_log_floor)} is set but agent=rs builds no Q network")
        if node.name == "rs" and node.get("q_pick_min_height"):
            found.append(f"{prefix}q_pick_min_height={_show(node.q_pick_min_height)} is set but agent=rs builds no Q "
                         "network (its candidates lie near objects already); set it to 0")
        if node.name != "ldm" and node.get("q_proposal_fit", 0):
            found.append(f"{prefix}q_proposal_fit={node.q_proposal_fit} is set but only agent=ldm uses it "
                         f"(agent.name={node.name}); set it to 0")
        elif node.get("q_proposal_fit", 0) > node.num_target_candidates:
            found.append(f"{prefix}q_proposal_fit={node.q_proposal_fit} exceeds {prefix}num_target_candidates="
                         f"{node.num_target_candidates}: Q can be fitted only on proposals the target scored")
        if node.name != "ldm" and node.target_uncertainty_penalty:
            found.append(f"{prefix}target_uncertainty_penalty={_show(node.target_uncertainty_penalty)} is set but "
                         f"only agent=ldm uses it (agent.name={node.name}); set it to 0")
        cache = node.get("bootstrap_cache", 0)
        if cache and node.name != "ldm":
            found.append(f"{prefix}bootstrap_cache={cache} is set but only agent=ldm caches its bootstraps "
                         f"(agent.name={node.name}); set it to 0")
        elif cache and node.target_proposal.mode != "argmax":
            found.append(f"{prefix}bootstrap_cache={cache} needs deterministic target proposals: "
                         f"{prefix}target_proposal.mode={node.target_proposal.mode} draws new ones every update "
                         "(use argmax, or bootstrap_cache=0)")
        bounds = node.target_range
        if bounds is not None and not (len(bounds) == 2 and bounds[0] < bounds[1]):
            found.append(f"{prefix}target_range={_show(bounds)}: must be null or [low, high] with low < high")
        return found


@dataclass
class PlannerConfig:
    """``conf/planner/*.yaml``: the LDM agent's planner (``name``: one of ``ldm_rl.agents.PLANNERS``); the
    baselines read ``tau`` (FC-DQN, Dyna-Q) or ``num_candidates``, ``tau_value``, ``chunk_size`` (RS)."""

    name: str = spec("diverse", choices=("diverse", "tree"), doc="the planner (ldm_rl.agents.PLANNERS)")
    num_candidates: int = spec(ge=1, doc="N proposals per decision")
    proposal: str = spec(choices=("softmax", "argmax"), doc="proposal mode while exploring")
    greedy_proposal: str = spec(choices=("softmax", "argmax"), doc="proposal mode under DETERMINISTIC")
    greedy_schedules: str = spec("start", choices=("start", "current"),
                                 doc="schedules under DETERMINISTIC: their start values or the training step's")
    tau: Any = MISSING
    beta: Any = MISSING
    sigma: Any = MISSING
    sigma_rot: Any = MISSING
    tau_value: Any = MISSING
    chunk_size: int = spec(64, ge=1, doc="state-candidate pairs per LDM/V pass")
    autocast: Optional[str] = spec(None, choices=(None, "bf16"), doc="autocast of the Q map and LDM predictions")
    uncertainty_penalty: float = spec(0.0, ge=0.0, doc="λ of the score V − λ·H (H: the LDM's pixel entropy, nats)")
    greedy_uncertainty_penalty: Optional[float] = spec(None, ge=0.0,
                                                       doc="λ of the greedy decisions alone (null = uncertainty_penalty)")
    uncertainty_penalty_on: str = spec("all", choices=("all", "places"),
                                       doc="the primitives λ·H is charged on (places: a pick is scored by V alone)")
    empty_picks_last: bool = spec(False, doc="picks the LDM predicts to come up empty ranked below those predicted to hold")
    pick_outcome: str = spec("mode", choices=("mode", "expected"),
                             doc="a pick scored by V of the LDM's mode, or by its expected value over held and empty")
    pick_rotations: int = spec(1, ge=1, doc="rotations each pick proposal is scored at (divides env.num_rotations)")
    revisits_last: bool = spec(False, doc="places the LDM predicts to recreate a scene seen with an empty hand this "
                               "episode ranked last (needs env.scene_memory > 0)")
    q_blend: float = spec(0.0, ge=0.0, le=1.0, doc="w: the choice made on (1 − w)·(V − λ·H) + w·Q(s, a) (0 = V alone)")
    greedy_q_blend: Optional[float] = spec(None, ge=0.0, le=1.0, doc="w of the greedy decisions alone (null = q_blend)")
    # planner=tree only (conf/planner/tree.yaml sets them; null elsewhere)
    depth: Optional[int] = spec(None, ge=1, doc="primitives looked ahead (tree)")
    branching: Optional[int] = spec(None, ge=1, doc="candidates expanded per node (tree)")
    gamma: Optional[float] = spec(None, ge=0.0, le=1.0, doc="discount of the backed-up scores (tree; the agent's γ)")
    terminal_reward: Optional[float] = spec(None, gt=0.0, doc="a predicted reward above it ends a branch (tree)")
    penalty_depth: Optional[int] = spec(None, ge=1, doc="the first steps of the tree where λ·H is charged (tree)")

    TREE_KEYS = ("depth", "branching", "gamma", "terminal_reward", "penalty_depth")
    REQUIRED_TREE_KEYS = ("depth", "branching", "gamma", "terminal_reward")

    @staticmethod
    def check(node: DictConfig, prefix: str) -> list[str]:
        found = [_schedule_problem(node[key], prefix + key, positive=key in ("tau", "tau_value"))
                 for key in ("tau", "beta", "sigma", "sigma_rot", "tau_value")]
        if node.name != "tree":
            found += [f"{prefix}{key}={_show(node[key])} is read by planner=tree only (got planner={node.name})"
                      for key in PlannerConfig.TREE_KEYS if node[key] is not None]
        else:
            found += [f"{prefix}{key} is missing: planner=tree needs it (conf/planner/tree.yaml)"
                      for key in PlannerConfig.REQUIRED_TREE_KEYS if node[key] is None]
            if node.penalty_depth is not None and node.depth is not None and node.penalty_depth > node.depth:
                found.append(f"{prefix}penalty_depth={node.penalty_depth} is out of range: must be <= "
                             f"{prefix}depth ({node.depth})")
            if node.branching is not None and node.branching > node.num_candidates:
                found.append(f"{prefix}branching={node.branching} is out of range: must be <= "
                             f"{prefix}num_candidates ({node.num_candidates})")
        return [problem for problem in found if problem]


@dataclass
class ReplayConfig:
    """``conf/replay/*.yaml``: ``ldm_rl.data.replay.FrameReplay``."""

    capacity: int = spec(ge=2, doc="frames kept")
    batch_size: int = spec(ge=1, doc="transitions per update")
    alpha: float = spec(ge=0, le=1, doc="priority exponent")
    beta: Any = MISSING
    expert_bonus: float = spec(ge=0, doc="demonstration bonus eps_d")
    priority_eps: float = spec(gt=0, doc="priority floor")
    scratch_dir: Optional[str] = None

    @staticmethod
    def check(node: DictConfig, prefix: str) -> list[str]:
        problem = _schedule_problem(node.beta, prefix + "beta", positive=False)
        return [problem] if problem else []


@dataclass
class ScheduleConfig:
    """``conf/schedule/*.yaml``: the loop of ``recipes/train_policy.py``."""

    expert_episodes: int = spec(ge=1, doc="expert episodes seeding the replay buffer")
    expert_procedure: str = spec(choices=("direct", "deconstruct"), doc="their demo procedure")
    expert_noise: NoiseConfig = group(NoiseConfig)
    pretrain_updates: int = spec(0, ge=0, doc="LDM-only updates before acting")
    total_episodes: int = spec(ge=1, doc="training episodes")
    max_wall_clock_s: Optional[float] = spec(None, gt=0, doc="stop after this many seconds")
    updates_per_step: float = spec(gt=0, le=64, doc="updates per environment step (a fraction: every k-th step)")
    eval_every: int = spec(ge=1, doc="updates between evaluations")
    eval_episodes: int = spec(ge=1, doc="episodes per evaluation")
    final_eval_episodes: int = spec(ge=1, doc="episodes of the final evaluation")
    checkpoint_every: int = spec(ge=1, doc="updates between checkpoints (taken at the next episode end)")
    keep_best: bool = True
    progress: bool = True


@dataclass
class CollectorConfig:
    """``collector`` of ``conf/train_policy.yaml``: ``ldm_rl.collectors.make_collector`` (docs/scaling.md)."""

    num_workers: int = spec(1, ge=1, le=1024, doc="env workers; 1 = TorchRL's Collector in the training process")
    sync: bool = True
    frames_per_worker: int = spec(1, ge=1, doc="steps each worker collects between weight refreshes")
    backend: str = spec("process", choices=("process", "distributed"), doc="worker processes here | DistributedCollector")
    launcher: str = spec("mp", choices=("mp", "submitit"), doc="how backend=distributed starts workers")
    tcp_port: Optional[int] = spec(None, ge=1, le=65535, doc="backend=distributed rendezvous port")
    slurm: typing.Dict[str, Any] = field(default_factory=dict)

    @staticmethod
    def check(node: DictConfig, prefix: str) -> list[str]:
        if node.backend == "distributed" and not node.sync:
            return [f"{prefix}sync=false needs {prefix}backend=process: the distributed collector's async batches do "
                    "not say which worker sent them"]
        return []


@dataclass
class TrainPolicyConfig(RunSettings):
    """``conf/train_policy.yaml``: the groups, plus seed / device / threads / resume."""

    env: EnvConfig = group(EnvConfig)
    model: ModelConfig = group(ModelConfig)
    loss: LossConfig = group(LossConfig)
    agent: AgentConfig = group(AgentConfig)
    planner: PlannerConfig = group(PlannerConfig)
    replay: ReplayConfig = group(ReplayConfig)
    schedule: ScheduleConfig = group(ScheduleConfig)
    logger: LoggerConfig = group(LoggerConfig)
    collector: CollectorConfig = group(CollectorConfig)
    resume: bool = False
    compile: bool = spec(False, doc="torch.compile the inference passes (decisions, lookahead targets)")
    # keys a resumed run may change: they only say when the loop stops, so a finished run given a larger budget
    # continues as the run with that budget from the start would have (tests/test_policy_recipe.py)
    RESUME_MAY_CHANGE: ClassVar[tuple[str, ...]] = ("schedule.total_episodes", "schedule.max_wall_clock_s")

    @staticmethod
    def check(node: DictConfig, prefix: str) -> list[str]:
        found = TrainDynamicsConfig.check(node, prefix)
        for key in ("empty_picks_last", "uncertainty_penalty", "greedy_uncertainty_penalty", "uncertainty_penalty_on",
                    "pick_outcome", "pick_rotations", "revisits_last", "q_blend", "greedy_q_blend"):  # the LDM agent's alone
            value = node.planner.get(key)
            if (node.agent.name != "ldm" and value and value not in ("mode", "all")
                    and not (key == "pick_rotations" and value == 1)):
                shown = "true" if value is True else value if isinstance(value, str) else _show(value)
                found.append(f"{prefix}planner.{key}={shown} is set but agent={node.agent.name} does not plan with "
                             "the LDM's proposals: only agent=ldm uses it")
        sweep, rotations = node.planner.get("pick_rotations"), node.env.num_rotations
        if isinstance(sweep, int) and sweep >= 1 and rotations % sweep:
            found.append(f"{prefix}planner.pick_rotations={sweep} must divide env.num_rotations={rotations}: the swept "
                         "rotations are evenly spaced bins of Q's map")
        if node.planner.get("revisits_last") is True and not node.env.get("scene_memory"):
            found.append(f"{prefix}planner.revisits_last=true reads the scenes of env.scene_memory, which is "
                         f"{node.env.get('scene_memory')!r}: set env.scene_memory > 0 (e.g. 8)")
        return found


@dataclass
class RenderConfig:
    """``render`` of ``conf/evaluate.yaml``: pictures of the first evaluation episodes (``ldm_rl.plots``)."""

    episodes: int = spec(0, ge=0, doc="episodes to draw (the first ones); 0 = no pictures")
    decisions: bool = True
    gif: bool = True
    fps: float = spec(1.0, gt=0, le=30, doc="frames (steps) per second of episodes.gif")


@dataclass
class PlannerOverrides:
    """``evaluate.yaml``'s ``planner``: keys set over the checkpoint's planner (null = the checkpoint's)."""

    name: Optional[str] = spec(None, choices=(None, "diverse", "tree"), doc="the planner")
    num_candidates: Optional[int] = spec(None, ge=1, doc="Q's proposals scored by V (1 = Q's argmax alone)")
    uncertainty_penalty: Optional[float] = spec(None, ge=0.0, doc="λ of V − λ·H (these greedy decisions' λ)")
    uncertainty_penalty_on: Optional[str] = spec(None, choices=(None, "all", "places"),
                                                 doc="the primitives λ·H is charged on")
    empty_picks_last: Optional[bool] = spec(None, doc="predicted empty picks ranked below those predicted to hold")
    pick_outcome: Optional[str] = spec(None, choices=(None, "mode", "expected"),
                                       doc="a pick scored by V of the LDM's mode, or by its expected value")
    pick_rotations: Optional[int] = spec(None, ge=1, doc="rotations each pick proposal is scored at")
    revisits_last: Optional[bool] = spec(None, doc="places predicted to recreate a scene seen with an empty hand ranked "
                                         "last (needs scene memory)")
    q_blend: Optional[float] = spec(None, ge=0.0, le=1.0, doc="w: the choice made on (1 − w)·(V − λ·H) + w·Q(s, a)")
    depth: Optional[int] = spec(None, ge=1, doc="tree: primitives looked ahead")
    branching: Optional[int] = spec(None, ge=1, doc="tree: candidates expanded per node")
    terminal_reward: Optional[float] = spec(None, gt=0.0, doc="tree: a predicted reward above it ends a branch")
    gamma: Optional[float] = spec(None, ge=0.0, le=1.0, doc="tree: discount (null = the agent's)")
    penalty_depth: Optional[int] = spec(None, ge=1, doc="tree: the first steps where λ·H is charged (null = every depth)")


@dataclass
class EvaluateConfig(RunSettings):
    """``conf/evaluate.yaml``: ``recipes/evaluate.py``."""

    checkpoint: str = spec(exists=True, allowed="an existing file", doc="a checkpoint.pt written by recipes/train_policy.py")
    episodes: int = spec(ge=1, doc="greedy episodes")
    num_objects: Optional[int] = spec(None, ge=1, doc="objects (null = the checkpoint's)")
    max_steps: Optional[int] = spec(None, ge=1, doc="primitives per episode (null = 2*objects + 4)")
    preset: Optional[str] = spec(None, choices=(None, "paper", "lite"), doc="the preset the checkpoint must hold")
    failed_pick_memory: Optional[int] = spec(None, ge=0, le=64, doc="env.failed_pick_memory (null = the checkpoint's)")
    scene_memory: Optional[int] = spec(None, ge=0, le=64, doc="env.scene_memory (null = the checkpoint's)")
    finger_spinning_friction: Optional[float] = spec(
        None, ge=0, doc="env.finger_spinning_friction (null = the checkpoint's: 0 for runs before 2026-11-27)")
    q_pick_min_height: Optional[float] = spec(None, ge=0, doc="m: agent.q_pick_min_height (null = the checkpoint's; 0 = off)")
    height_anchor: Optional[float] = spec(None, ge=0, doc="m: the LDM's model.height_anchor (null = the checkpoint's; 0 = none)")
    hand_rule: Optional[str] = spec(None, choices=(None, "occupancy", "removal"),
                                    doc="model.hand_rule.kind the world model reads holding' with (null = the checkpoint's)")
    online_weights: bool = spec(False, doc="play the online weights of a run trained with agent.greedy_ema_decay, "
                                           "not their average")
    progress: bool = True
    render: RenderConfig = group(RenderConfig)
    planner: PlannerOverrides = group(PlannerOverrides)

    @staticmethod
    def check(node: DictConfig, prefix: str) -> list[str]:
        if node.render.episodes > node.episodes:
            return [f"{prefix}render.episodes={node.render.episodes} exceeds {prefix}episodes={node.episodes}: only "
                    "played episodes can be drawn"]
        return []


# the schema of each primary config, by its name (conf/<name>.yaml lists `- optional schema: <name>`)
SCHEMAS: dict[str, type] = {"train_dynamics": TrainDynamicsConfig, "generate_demos": DemosRunConfig,
                             "render_expert_strip": DemosRunConfig, "train_policy": TrainPolicyConfig,
                             "evaluate": EvaluateConfig}


def register_schema(name: str, node: type) -> None:
    """Make ``node`` the schema of the primary config ``conf/<name>.yaml``: stored in Hydra's ConfigStore
    as ``schema/<name>`` (package ``_global_``) and used by :func:`validate_config` /
    :func:`check_command_line` for that config. Call it at import time of the module defining ``node``."""
    from hydra.core.config_store import ConfigStore

    SCHEMAS[name] = node
    ConfigStore.instance().store(group="schema", name=name, node=node, package="_global_")


def register_configs() -> None:
    """Store every schema of :data:`SCHEMAS` in Hydra's ConfigStore (idempotent; runs at import)."""
    for name, node in list(SCHEMAS.items()):
        register_schema(name, node)


register_configs()


# ------------------------------------------------------------------------------------- validation


def _show(value: Any) -> str:
    if OmegaConf.is_config(value):
        value = OmegaConf.to_container(value, resolve=False)
    if value is None:
        return "null"
    return repr(value) if isinstance(value, str) else str(value)


def _nested_schema(tp: Any) -> type | None:
    args = typing.get_args(tp)
    candidates = (tp, *args)
    for c in candidates:
        if dataclasses.is_dataclass(c):
            return c
    return None


def _problems(node: DictConfig, schema: type, prefix: str) -> list[str]:
    found: list[str] = []
    hints = typing.get_type_hints(schema)
    for f in dataclasses.fields(schema):
        key = prefix + f.name
        if f.name not in node or OmegaConf.is_missing(node, f.name):
            rule = f.metadata.get("rule")
            what = f" ({rule.doc})" if rule is not None and rule.doc else ""
            found.append(f"{key} is missing: set {key}=<value>{what}")
            continue
        sub = _nested_schema(hints[f.name])
        try:
            value = node[f.name] if (sub is not None or "rule" in f.metadata) else None
        except Exception as err:  # an interpolation that does not resolve
            found.append(f"{key}: {_first_line(err)}")
            continue
        if sub is not None:
            if value is not None:
                found += _problems(value, sub, key + ".")
            continue
        rule = f.metadata.get("rule")
        if rule is not None and rule.violated(value):
            what = f" ({rule.doc})" if rule.doc else ""
            kind = "is invalid" if rule.choices is not None or rule.pattern is not None or rule.exists else "is out of range"
            found.append(f"{key}={_show(value)} {kind}: must be {rule.describe()}{what}")
    check: Callable | None = getattr(schema, "check", None)
    if check is not None and not found:
        found += check(node, prefix)
    return found


def _first_line(err: BaseException) -> str:
    lines = [ln.strip() for ln in str(err).splitlines() if ln.strip()]
    return lines[0] if lines else type(err).__name__


def validate_config(cfg: DictConfig | Mapping[str, Any], schema: type) -> None:
    """Raise :class:`ConfigError` (one line listing every problem) unless ``cfg`` fits ``schema``:
    types and keys (merged into the structured schema, so configs composed without the schema are
    checked too), then each field's :class:`Rule` and each group's ``check``."""
    if not OmegaConf.is_config(cfg):
        cfg = OmegaConf.create(dict(cfg))
    task = OmegaConf.to_container(cfg, resolve=False)
    task.pop("hydra", None)
    try:
        typed = OmegaConf.merge(OmegaConf.structured(schema), task)
    except Exception as err:
        raise ConfigError(_omegaconf_line(err)) from None
    problems = _problems(typed, schema, "")
    if problems:
        raise ConfigError("; ".join(problems))


def _message_lines(err: BaseException) -> tuple[list[tuple[bool, str]], str | None]:
    """(indented?, text) lines of an error and its causes without OmegaConf's key/type trailer; the key."""
    lines: list[tuple[bool, str]] = []
    key = None
    for raw in str(err).splitlines():
        text = raw.strip()
        if not text:
            continue
        if text.startswith("full_key:"):
            key = text.split(":", 1)[1].strip() or None
            continue
        if text.startswith(("reference_type=", "object_type=")):
            continue
        if text.startswith("Config search path"):
            break
        lines.append((raw[:1] in ("\t", " "), text))
    cause = err.__cause__
    if cause is not None and str(cause) and str(cause) not in str(err):
        more, cause_key = _message_lines(cause)
        lines += more
        key = key or cause_key
    return lines, key


def _omegaconf_line(err: BaseException) -> str:
    """One line from an OmegaConf / Hydra error: what is wrong and the key or override it concerns."""
    lines, key = _message_lines(err)
    pieces: list[str] = []
    listing = False  # "Available options in 'model':" followed by one indented option per line
    for indented, text in lines:
        if indented and pieces and (listing or pieces[-1].endswith(":")):
            pieces[-1] += (", " if listing else " ") + text
            listing = True
        else:
            pieces.append(text.rstrip("."))
            listing = False
    prefix = "Error merging override "
    if len(pieces) > 1 and pieces[0].startswith(prefix):  # "<override>: <why>"
        return f"{pieces[0][len(prefix):]}: " + "; ".join(pieces[1:])
    text = "; ".join(pieces) or type(err).__name__
    if key and key not in text:
        text = f"{key}: {text}"
    return text


def _schema_default(schema: type | None, key: str) -> Any:
    """The default of field ``key`` of the dataclass ``schema`` (``MISSING`` when none or no schema)."""
    for f in dataclasses.fields(schema) if schema is not None else ():
        if f.name == key:
            return f.default if f.default is not dataclasses.MISSING else MISSING
    return MISSING


def config_differences(run: Mapping[str, Any], given: Mapping[str, Any], ignore: tuple[str, ...] = ("resume", "device"),
                       prefix: str = "", schema: type | None = None) -> list[str]:
    """``key: run has X, the command gives Y`` for each leaf where two resolved configs differ; the keys in
    ``ignore`` are the command's to choose (``device``: where the run continues, a property of the machine).

    With ``schema`` (the dataclass of ``given``), a key the run's config lacks is no difference when the
    command gives the schema's default: a key added after the run was written, whose default keeps the
    behaviour the run had (e.g. ``planner.name: diverse``)."""
    return [f"{key}: the run has {_show(a)}, the command gives {_show(b)}"
            for key, a, b, _ in _differing_leaves(run, given, ignore, prefix, schema)]


def resume_overrides(run: Mapping[str, Any], given: Mapping[str, Any], ignore: tuple[str, ...] = ("resume", "device"),
                     schema: type | None = None) -> list[str]:
    """The command-line overrides (``key=value``) that give the run's value for each leaf
    :func:`config_differences` reports: what resumes a run after a preset's default changed. A leaf the run lacks (a
    key added after it was written) gets the schema's default, the behaviour the run had; without one it is left out."""
    fix = []
    for key, a, _, default in _differing_leaves(run, given, ignore, "", schema):
        if a == "<absent>":  # a key added after the run was written: its schema default is the behaviour the run had
            if default is MISSING:
                continue
            a = default
        fix.append(f"{key}={_override_value(a)}")
    return fix


def _differing_leaves(run, given, ignore, prefix, schema):
    """``(dotted key, run's value, command's value, the schema's default or MISSING)`` for each differing leaf (see
    :func:`config_differences`)."""
    hints = typing.get_type_hints(schema) if schema is not None else {}
    for key in sorted(set(run) | set(given)):
        if prefix + key in ignore:
            continue
        a, b = run.get(key, "<absent>"), given.get(key, "<absent>")
        if isinstance(a, Mapping) and isinstance(b, Mapping):
            yield from _differing_leaves(a, b, ignore, f"{prefix}{key}.", _nested_schema(hints.get(key)))
        elif key not in run and b == _schema_default(schema, key):
            continue
        elif a != b:
            yield prefix + key, a, b, _schema_default(schema, key)


def _override_value(value) -> str:
    """A resolved config value as Hydra's override grammar reads it back."""
    if value is None:
        return "null"
    if isinstance(value, bool):
        return str(value).lower()
    if isinstance(value, (list, tuple)):
        return "[" + ",".join(_override_value(v) for v in value) + "]"
    if isinstance(value, Mapping):
        return "{" + ",".join(f"{k}:{_override_value(v)}" for k, v in value.items()) + "}"
    return str(value)
