"""The public API composes with plain TorchRL: root exports, a model by name, keys that never clobber data,
quiet env wrapping, a clear closed-env error, an imagined env RandomPolicy drives, clear errors for empty
batches and missing keys, docs that match the code, and docs/api.md's complete pipeline, run here."""

from __future__ import annotations

import ast
import importlib.util
import re
import subprocess
import sys
import warnings
from pathlib import Path

import pytest
import torch
from tensordict import TensorDict
from torchrl.data import LazyTensorStorage, TensorDictReplayBuffer

import ldm_rl
from dyn_helpers import one_torch_thread  # noqa: F401  (fixture)
from dyn_helpers import tiny_model, transitions

ROOT = Path(__file__).resolve().parents[1]
API_DOC = ROOT / "docs" / "api.md"
EXAMPLE = ROOT / "docs" / "examples" / "compose_pipeline.py"

pytestmark = pytest.mark.usefixtures("one_torch_thread")


def _states(n):
    return transitions(n).select("heightmap", "in_hand", "holding")


# ----------------------------------------------------------------------------------------- the package root
def test_root_exports_keys_and_helpers_and_stays_light():
    from ldm_rl import keys
    from ldm_rl.envs.torchrl_env import EnvClosedError, expert_policy, make_env, unwrap
    from ldm_rl.world_model import make_dynamics_model

    for name in keys.__all__:
        assert getattr(ldm_rl, name) is getattr(keys, name), name
    assert ldm_rl.FORESIGHT_KEYS == (("next", "pred_heightmap"), ("next", "pred_in_hand"), ("next", "pred_holding"))
    assert (ldm_rl.unwrap, ldm_rl.make_env, ldm_rl.expert_policy) == (unwrap, make_env, expert_policy)
    assert ldm_rl.make_dynamics_model is make_dynamics_model and ldm_rl.EnvClosedError is EnvClosedError
    assert set(keys.__all__) | {"unwrap", "make_dynamics_model", "make_env", "keys"} <= set(ldm_rl.__all__)
    with pytest.raises(AttributeError, match="nope"):
        ldm_rl.nope  # noqa: B018
    heavy = subprocess.run(
        [sys.executable, "-c", "import sys, ldm_rl; ldm_rl.HEIGHTMAP; print(sorted(m for m in ('torch', 'torchrl', "
         "'pybullet', 'hydra') if m in sys.modules))"], capture_output=True, text=True, cwd=ROOT, timeout=60)
    assert heavy.stdout.strip() == "[]", heavy.stdout + heavy.stderr


# ----------------------------------------------------------------------------------------- a model by name
def test_make_dynamics_model_reads_the_task_and_model_configs():
    from omegaconf import OmegaConf

    from ldm_rl.world_model import DynamicsModel

    stacking = ldm_rl.make_dynamics_model("ldm64", task="block_stacking", preset="lite", overrides=["model.width=0.0625"])
    assert isinstance(stacking, DynamicsModel) and stacking.training
    env_cfg = OmegaConf.load(ROOT / "conf" / "env" / "block_stacking.yaml")
    assert stacking.max_height == env_cfg.max_height and stacking.num_rotations == env_cfg.num_rotations
    assert (stacking.frame, stacking.frame_size, stacking.num_classes) == ("local", 64, 21)
    house = ldm_rl.make_dynamics_model("ldm128", task="ldm_rl/HouseBuilding-v0", overrides=["model.width=0.0625"])
    assert house.max_height == OmegaConf.load(ROOT / "conf" / "env" / "house_building.yaml").max_height
    assert house.frame_size == 128 and house.max_height != stacking.max_height
    naive = ldm_rl.make_dynamics_model("naive", task="bin_packing", overrides=["model.width=0.0625"])
    assert naive.frame == "global"
    narrow = sum(p.numel() for p in stacking.parameters())
    wider = sum(p.numel() for p in ldm_rl.make_dynamics_model("ldm64", overrides=["model.width=0.125"]).parameters())
    assert wider > narrow  # the override reached the network


@pytest.mark.parametrize(
    "kwargs, match",
    [
        ({"model": "ldm65"}, r"model must be one of \['ldm128', 'ldm64', 'naive'\], got 'ldm65'"),
        ({"task": "stacking"}, "task must be one of .*block_stacking.*ldm_rl/BlockStacking-v0.*got 'stacking'"),
        ({"preset": "huge"}, "preset must be one of .*got 'huge'"),
        ({"overrides": ["model.width=-1"]}, "model.width=-1.0 is out of range"),
        ({"overrides": ["model.nope=1"]}, "model.nope"),
        ({"overrides": "model.width=1"}, "overrides must be a list"),
        ({"config_dir": "/nonexistent"}, "no Hydra configs at /nonexistent"),
    ],
)
def test_make_dynamics_model_rejects_bad_input_in_one_line(kwargs, match):
    with pytest.raises(ValueError, match=match) as err:
        ldm_rl.make_dynamics_model(**kwargs)
    assert "\n" not in str(err.value)


def test_make_dynamics_model_inside_a_hydra_app_leaves_its_state():
    from hydra import compose, initialize_config_dir
    from hydra.core.global_hydra import GlobalHydra

    with initialize_config_dir(config_dir=str(ROOT / "conf"), version_base="1.3"):
        ldm_rl.make_dynamics_model(overrides=["model.width=0.0625"])
        assert GlobalHydra.instance().is_initialized()
        assert compose("train_dynamics", overrides=["model=naive"]).model.name == "naive"


# ----------------------------------------------------------------------------------------- keys that never clobber
def test_default_out_keys_leave_a_replay_sample_intact():
    from ldm_rl.world_model import ForesightTransform, make_dynamics_module

    model = tiny_model()
    replay = TensorDictReplayBuffer(storage=LazyTensorStorage(8), batch_size=4)
    replay.extend(transitions(8))
    sample = replay.sample()
    real = sample["next"].clone()
    out = make_dynamics_module(model)(sample)
    for key in ("heightmap", "in_hand", "holding"):
        assert torch.equal(out["next", key], real[key]), key
    pred = model.predict(sample["heightmap"], sample["in_hand"], sample["holding"], sample["action"])
    assert torch.equal(out[ldm_rl.FORESIGHT_KEYS[0]], pred.heightmap)
    replay.append_transform(ForesightTransform(model))
    foresight = replay.sample()
    assert set(ldm_rl.FORESIGHT_KEYS) <= set(foresight.keys(include_nested=True))
    assert not torch.equal(foresight["next", "pred_heightmap"], foresight["next", "heightmap"])


# ----------------------------------------------------------------------------------------- environments
def test_make_env_adds_transforms_quietly_and_unwrap_sees_through_layers(monkeypatch):
    from torchrl.envs import StepCounter, TransformedEnv
    from torchrl.envs.transforms import _base

    from ldm_rl.envs.base import PickPlaceEnv

    monkeypatch.setattr(_base, "_AUTO_UNWRAP_WARNING_EMITTED", False)  # TorchRL warns once per process
    env = ldm_rl.make_env("ldm_rl/BlockStacking-v0", num_objects=2, transforms=[StepCounter(max_steps=2)])
    try:
        assert isinstance(env, TransformedEnv) and [type(t).__name__ for t in env.transform] == ["DTypeCastTransform",
                                                                                                 "StepCounter"]
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            wrapped = TransformedEnv(env, StepCounter(step_count_key="outer_count"))
            env.append_transform(StepCounter(step_count_key="inner_count"))
        assert isinstance(ldm_rl.unwrap(wrapped), PickPlaceEnv) and ldm_rl.unwrap(wrapped) is ldm_rl.unwrap(env)
        wrapped.set_seed(0)
        rollout = wrapped.rollout(3, ldm_rl.expert_policy(wrapped))
        assert rollout["next", "step_count"][:, 0].tolist() == [1, 2]  # max_steps=2 truncates
        assert rollout["next", "outer_count"][:, 0].tolist() == rollout["next", "inner_count"][:, 0].tolist() == [1, 2]
    finally:
        env.close()
    with pytest.raises(ValueError, match="Transform"):
        ldm_rl.make_env("ldm_rl/BlockStacking-v0", transforms=[lambda td: td])
    with pytest.raises(ValueError, match="single"):
        ldm_rl.unwrap(object())


def test_an_env_closed_by_a_collector_says_so():
    from torchrl.collectors import Collector
    from torchrl.envs import TransformedEnv

    env = ldm_rl.make_env("ldm_rl/BlockStacking-v0")
    env.set_seed(0)
    expert = ldm_rl.expert_policy(env)
    collector = Collector(env, expert, frames_per_batch=2, total_frames=2)
    assert next(iter(collector)).batch_size == (2,)
    collector.shutdown()
    assert env.is_closed
    for attempt in (lambda: env.rollout(1), env.reset, lambda: env.set_seed(1), lambda: TransformedEnv(env).reset(),
                    lambda: expert(TensorDict())):
        with pytest.raises(ldm_rl.EnvClosedError, match="environment is closed"):
            attempt()


# ----------------------------------------------------------------------------------------- the imagined env
def test_random_policy_and_a_collector_drive_the_imagined_env_over_start_states():
    from torchrl.collectors import Collector
    from torchrl.envs.utils import RandomPolicy, check_env_specs

    from ldm_rl.world_model import LDMImaginedEnv

    model = tiny_model()
    start = _states(3)
    env = LDMImaginedEnv(model, start_states=start)
    assert env.batch_size == (3,) and env.action_spec.shape == (3, 3)
    check_env_specs(env)
    rollout = env.rollout(2, RandomPolicy(env.action_spec))
    assert rollout.batch_size == (3, 2)
    first = model.predict(start["heightmap"], start["in_hand"], start["holding"], rollout["action"][:, 0])
    assert torch.equal(rollout["heightmap"][:, 0], start["heightmap"])
    assert torch.equal(rollout["next", "heightmap"][:, 0], first.heightmap)
    collector = Collector(env, RandomPolicy(env.action_spec), frames_per_batch=6, total_frames=6)
    assert next(iter(collector)).batch_size == (3, 2)
    collector.shutdown()
    batch_free = LDMImaginedEnv(model)  # the planners' form still takes any batch
    assert batch_free.batch_size == () and batch_free.rollout(2, tensordict=batch_free.reset(_states(4)),
                                                              auto_reset=False).batch_size == (4, 2)
    with pytest.raises(ValueError, match="start state"):
        batch_free.reset()
    with pytest.raises(ValueError, match="differs"):
        LDMImaginedEnv(model, start_states=start, batch_size=[2])


# ----------------------------------------------------------------------------------------- errors
def _empty_and_missing_cases():
    from ldm_rl.models.q_fcn import build_q_network
    from ldm_rl.models.v_cnn import build_value_network
    from ldm_rl.objectives import LDMLoss
    from ldm_rl.planning.planner import LookaheadPlanner
    from ldm_rl.world_model import ForesightTransform, LDMImaginedEnv, make_dynamics_module

    model = tiny_model()
    q = build_q_network("lite", max_height=model.max_height, width=0.125)
    v = build_value_network("lite", max_height=model.max_height, width=0.125)
    return {
        "LDMLoss": LDMLoss(model),
        "ForesightTransform": ForesightTransform(model),
        "LookaheadPlanner": LookaheadPlanner(q, model, v, num_candidates=2),
        "dynamics module": make_dynamics_module(model),
        "LDMImaginedEnv": lambda td: LDMImaginedEnv(model).reset(td),
        "LDMImaginedEnv(start_states=)": lambda td: LDMImaginedEnv(model, start_states=td),
    }


def test_empty_batches_and_missing_keys_raise_clear_errors():
    from ldm_rl.objectives import focal_loss

    data = transitions(2)
    for who, run in _empty_and_missing_cases().items():
        with pytest.raises(ValueError, match="empty batch") as err:
            run(data[:0])
        assert "\n" not in str(err.value), who
        with pytest.raises((ValueError, KeyError), match="holding") as err:
            run(data.exclude("holding"))
        assert "missing" in str(err.value) or "not found" in str(err.value), who
    model = tiny_model()
    with pytest.raises(ValueError, match="empty batch"):
        model.predict(data["heightmap"][:0], data["in_hand"][:0], data["holding"][:0], data["action"][:0])
    with pytest.raises(ValueError, match="non-empty"):
        focal_loss(torch.zeros(0, 21, 4, 4), torch.zeros(0, 4, 4, dtype=torch.long))
    with pytest.raises(ValueError, match=r"target classes must lie in \[0, 21\)"):
        focal_loss(torch.zeros(1, 21, 4, 4), torch.full((1, 4, 4), 21))
    with pytest.raises(ValueError, match="target must be"):
        focal_loss(torch.zeros(1, 21, 4, 4), torch.zeros(1, 5, 4, dtype=torch.long))


# ----------------------------------------------------------------------------------------- docs match the code
def test_the_documented_ldm_loss_defaults_are_the_codes():
    import inspect

    from ldm_rl.objectives import LDMLoss

    defaults = {k: p.default for k, p in inspect.signature(LDMLoss.__init__).parameters.items()
                if p.default is not inspect.Parameter.empty}
    assert defaults == {"gamma": 2.0, "class_weights": None, "label_smoothing": 0.0, "write_logits": False,
                        "gripper_symmetries": False}
    shown = re.search(r"LDMLoss\(model, (.+?)\)\n", API_DOC.read_text()).group(1)
    assert dict(kv.split("=") for kv in shown.split(", ")) == {k: repr(v) for k, v in defaults.items()}
    assert "default ``None`` = uniform" in LDMLoss.__doc__
    loss = LDMLoss(tiny_model())
    assert loss.class_weights() is None  # uniform, as documented


def test_api_doc_imports_resolve_and_it_embeds_the_example_verbatim():
    text = API_DOC.read_text()
    blocks = re.findall(r"```python\n(.*?)```", text, flags=re.S)
    assert blocks[-1] == EXAMPLE.read_text()
    for block in blocks:
        for node in ast.walk(ast.parse(block)):
            if isinstance(node, ast.ImportFrom):
                module = importlib.import_module(node.module)
                for alias in node.names:
                    assert hasattr(module, alias.name), f"{node.module}.{alias.name} (docs/api.md)"
    for link in re.findall(r"\]\(([^)#]+)\)", text):
        assert (API_DOC.parent / link).is_file(), link


def test_no_file_points_outside_the_repository():
    hits = []
    for path in [*ROOT.glob("*.md"), *(p for d in ("ldm_rl", "recipes", "conf", "docs", "tests", "benchmarks")
                                       for p in (ROOT / d).rglob("*") if p.suffix in (".py", ".md", ".yaml"))]:
        text = path.read_text(errors="replace")
        for needle in ("DESIGN" + ".md", "../" + "shared"):
            if needle in text:
                hits.append(f"{path.relative_to(ROOT)}: {needle}")
    assert not hits, hits


# ----------------------------------------------------------------------------------------- the complete pipeline
def _load_example():
    spec = importlib.util.spec_from_file_location("compose_pipeline", EXAMPLE)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


@pytest.mark.slow
def test_the_documented_pipeline_runs_with_tiny_sizes():
    example = _load_example()
    with warnings.catch_warnings():
        warnings.simplefilter("error", FutureWarning)  # TorchRL's deprecations would reach the user
        out = example.main(frames=8, batch_size=4, updates=2, imagined_steps=2, planner_steps=2, num_candidates=3,
                           ldm_width=0.0625, net_width=0.125, seed=0)
    assert len(out["losses"]) == 2 and all(torch.isfinite(torch.tensor(out["losses"])))
    sample = out["sample"]
    assert sample.batch_size == (4,) and set(ldm_rl.FORESIGHT_KEYS) <= set(sample.keys(include_nested=True))
    assert sample["next", "heightmap"].shape == sample["next", "pred_heightmap"].shape == (4, 1, 128, 128)
    assert out["foresight_l1_mm"] >= 0
    assert out["dream"].batch_size == (4, 2) and out["dream"]["next", "heightmap"].shape == (4, 2, 1, 128, 128)
    episode = out["episode"]
    assert episode["action"].shape == (2, 3) and episode["candidate_actions"].shape == (2, 3, 3)
    chosen = [(episode["candidate_actions"][i] == episode["action"][i]).all(-1) for i in range(2)]
    assert all(bool(c.any()) for c in chosen)  # greedy: the action is one of the candidates
    assert out["replay_size"] == 8 + 2  # expert frames + the planner's exploring frames
