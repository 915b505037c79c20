"""The Hydra front door: each recipe's primary config (conf/<recipe>.yaml) composes, every recipe honours Hydra's CLI, and the typed schema
(ldm_rl.config_schema) stops wrong types, out-of-range values and contradictions in one line, before any
work and without an output folder."""

import copy
import importlib.util
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest
from hydra import compose, initialize_config_dir
from hydra.errors import ConfigCompositionException
from omegaconf import OmegaConf

from ldm_rl import config_schema  # registers the schemas, as every recipe does at import

ROOT = Path(__file__).resolve().parents[1]
CONF = ROOT / "conf"
RECIPES = sorted(p for p in (ROOT / "recipes").glob("*.py") if not p.name.startswith("_"))
REPORTS = sorted(p.stem for p in (ROOT / "ldm_rl" / "reports").glob("*.py") if not p.name.startswith("_"))
GROUPS = ("env", "model", "loss", "logger", "demos", "dynamics")


def make_cfg(*overrides, config_name="train_dynamics"):
    with initialize_config_dir(version_base="1.3", config_dir=str(CONF)):
        return compose(config_name=config_name, overrides=list(overrides))


def test_config_composes_with_every_group_and_overrides():
    cfg = make_cfg("seed=3", "logger=tensorboard")
    assert cfg.seed == 3 and cfg.device == "auto" and cfg.threads == 1 and cfg.resume is False
    assert cfg.logger.backend == "tensorboard"
    for group in GROUPS:
        assert group in cfg, f"config group {group!r} missing from conf/train_dynamics.yaml"
    config_schema.validate_config(cfg, config_schema.TrainDynamicsConfig)


@pytest.mark.parametrize("group", GROUPS)
def test_every_option_of_every_group_composes_and_is_valid(group):
    options = sorted(p.stem for p in (CONF / group).glob("*.yaml"))
    assert options, f"conf/{group}/ has no options"
    for option in options:
        cfg = make_cfg(f"{group}={option}")
        config_schema.validate_config(cfg, config_schema.TrainDynamicsConfig)
        assert OmegaConf.select(cfg, f"hydra.runtime.choices.{group}", default=option) == option


def _leaves(node, prefix=""):
    for key, value in node.items():
        if key == "defaults":
            continue
        if isinstance(value, dict):
            yield from _leaves(value, f"{prefix}{key}.")
        else:
            yield f"{prefix}{key}", value


def _primary_config_of(preset_text: str) -> str:
    """The primary config of the recipe a preset's header names (``python recipes/<name>.py``)."""
    match = re.search(r"python recipes/(\w+)\.py", preset_text)
    if not match:
        return "train_dynamics"
    recipe = (ROOT / "recipes" / f"{match.group(1)}.py").read_text()
    return re.search(r'config_name="(\w+)"', recipe).group(1)


@pytest.mark.parametrize("preset", sorted(p.stem for p in (CONF / "experiment").glob("*.yaml")))
def test_experiment_presets_compose_and_set_what_they_say(preset):
    """Each preset composes with its recipe's primary config, and every value it sets (and every group it
    overrides) is in the composed config."""
    file = CONF / "experiment" / f"{preset}.yaml"
    text = file.read_text()
    config_name = _primary_config_of(text)
    defaults = OmegaConf.to_container(OmegaConf.load(CONF / f"{config_name}.yaml")).get("defaults", [])
    plus = "" if any(isinstance(d, dict) and "experiment" in d for d in defaults) else "+"  # evaluate.yaml: +experiment=
    cfg = make_cfg(f"{plus}experiment={preset}", config_name=config_name)
    raw = OmegaConf.to_container(OmegaConf.load(file), resolve=False)
    leaves = list(_leaves(raw))
    assert leaves or raw.get("defaults"), f"{preset} sets nothing"
    for key, value in leaves:
        if (isinstance(value, str) and "${" in value) or key.startswith("hydra."):  # e.g. hydra.sweeper.params
            continue
        assert OmegaConf.select(cfg, key) == value, f"{preset}: {key}"
    for entry in raw.get("defaults", []):
        for target, option in (entry.items() if isinstance(entry, dict) else []):
            group = target.split()[-1].strip("/")
            expected = OmegaConf.load(CONF / group / f"{option}.yaml")  # its own defaults list is not a key
            assert all(cfg[group].get(key) == expected.get(key) for key in _IDENTITY_KEYS if key in expected), preset
            assert cfg[group].keys() >= expected.keys() - {"defaults"}, preset
    if config_name == "train_dynamics":
        config_schema.validate_config(cfg, config_schema.TrainDynamicsConfig)


_IDENTITY_KEYS = ("id", "name", "backend")  # the key that says which option of a group is in the config


def _group_choices(config_name: str):
    """(group, option, identity key, its value) for every option of every group of a primary config whose
    options carry an identity key (``logger.backend``, ``env.id``, ``agent.name``, ``model.name``)."""
    defaults = OmegaConf.to_container(OmegaConf.load(CONF / f"{config_name}.yaml")).get("defaults", [])
    groups = [next(iter(d)) for d in defaults if isinstance(d, dict)]
    for group in groups:
        if group in ("schema", "experiment") or not (CONF / group).is_dir():
            continue
        for option in sorted(p.stem for p in (CONF / group).glob("*.yaml")):
            raw = OmegaConf.load(CONF / group / f"{option}.yaml")
            for key in _IDENTITY_KEYS:
                if key in raw:
                    yield group, option, key, raw[key]
                    break


def _presets_of_configs_with_groups():
    """Presets whose recipe's primary config selects groups (evaluate.yaml has none to select)."""
    for file in sorted((CONF / "experiment").glob("*.yaml")):
        if any(True for _ in _group_choices(_primary_config_of(file.read_text()))):
            yield file.stem


@pytest.mark.parametrize("preset", list(_presets_of_configs_with_groups()))
def test_an_explicit_group_choice_wins_over_every_preset(preset):
    """``experiment=<preset> logger=tensorboard`` logs to TensorBoard: no preset overwrites the key that names a
    group's option, so whatever the command line selects is what runs (smoke used to set logger.backend)."""
    config_name = _primary_config_of((CONF / "experiment" / f"{preset}.yaml").read_text())
    defaults = OmegaConf.to_container(OmegaConf.load(CONF / f"{config_name}.yaml")).get("defaults", [])
    plus = "" if any(isinstance(d, dict) and "experiment" in d for d in defaults) else "+"
    checked = 0
    for group, option, key, value in _group_choices(config_name):
        cfg = make_cfg(f"{plus}experiment={preset}", f"{group}={option}", config_name=config_name)
        assert cfg[group][key] == value, f"experiment={preset} {group}={option} composed {group}.{key}={cfg[group][key]!r}"
        checked += 1
    assert checked >= 4, f"{config_name}: no group with an identity key found"


def test_unknown_option_is_rejected():
    with pytest.raises(ConfigCompositionException):
        make_cfg("logger=nonexistent")


def test_user_config_dir_extends_groups(tmp_path):
    (tmp_path / "logger").mkdir()
    (tmp_path / "logger" / "mine.yaml").write_text("backend: none\nexp_name: mine\n")
    with initialize_config_dir(version_base="1.3", config_dir=str(CONF)):
        cfg = compose(config_name="train_dynamics", overrides=["logger=mine", f"hydra.searchpath=[file://{tmp_path}]"])
    assert cfg.logger.exp_name == "mine"


def run_recipe(recipe, *args, cwd, env=None):
    return subprocess.run([sys.executable, str(recipe), *args], cwd=cwd, capture_output=True, text=True, timeout=300, env=env)


def test_every_documented_recipe_is_collected_here():
    """The recipe tests below run for each file of recipes/: every recipe the README and docs mention is
    one of them, and the main ones are Hydra apps (so they get the --help / --cfg checks)."""
    text = (ROOT / "README.md").read_text() + "".join(p.read_text() for p in (ROOT / "docs").glob("*.md"))
    documented = set(re.findall(r"recipes/(\w+\.py)", text))
    names = {p.name for p in RECIPES}
    assert documented and documented <= names, documented - names
    hydra_apps = {p.name for p in RECIPES if "@hydra.main" in p.read_text()}
    assert {"train_dynamics.py", "generate_demos.py"} <= hydra_apps


def test_the_report_tools_the_docs_name_exist():
    text = (ROOT / "README.md").read_text() + "".join(p.read_text() for p in (ROOT / "docs").glob("*.md"))
    documented = set(re.findall(r"ldm_rl\.reports\.(\w+)", text))
    assert len(REPORTS) == 6 and documented and documented <= set(REPORTS), documented - set(REPORTS)


@pytest.mark.parametrize("name", REPORTS)
def test_report_tools_run_as_modules_from_any_directory(name, tmp_path):
    done = subprocess.run([sys.executable, "-m", f"ldm_rl.reports.{name}", "--help"], cwd=tmp_path, capture_output=True,
                          text=True, env={**os.environ, "OMP_NUM_THREADS": "1"})
    assert done.returncode == 0, done.stderr
    assert done.stdout.startswith(f"usage: python -m ldm_rl.reports.{name}"), done.stdout[:200]


@pytest.mark.parametrize("recipe", RECIPES, ids=lambda p: p.name)
def test_recipe_help_and_cfg_work_from_any_directory(recipe, tmp_path):
    helped = run_recipe(recipe, "--help", cwd=tmp_path)
    assert helped.returncode == 0, helped.stderr
    if "@hydra.main" not in recipe.read_text():  # a plain report tool (argparse), e.g. aggregate_table1.py
        assert "usage:" in helped.stdout
        return
    assert "Powered by Hydra" in helped.stdout
    config_name = re.search(r'config_name="(\w+)"', recipe.read_text()).group(1)
    primary = (CONF / f"{config_name}.yaml").read_text()
    groups = [g for g in ("env", "logger") if re.search(rf"^  - {g}:", primary, re.M)]
    assert "env" not in groups or "env:" in helped.stdout  # the groups each recipe reads: tests/test_recipe_help.py
    required = []
    if re.search(r"^checkpoint: \?\?\?", primary, re.M):  # evaluate.py: the one required key must name a file
        (tmp_path / "checkpoint.pt").write_bytes(b"")
        required = [f"checkpoint={tmp_path / 'checkpoint.pt'}"]
    shown = run_recipe(recipe, "--cfg", "job", "seed=11", *required, *(["logger=none"] if "logger" in groups else []),
                       cwd=tmp_path)
    assert shown.returncode == 0, shown.stderr
    assert "seed: 11" in shown.stdout and ("logger" not in groups or "backend: none" in shown.stdout)


# --------------------------------------------------------------------------------- bad configs

BAD_COMMANDS = [
    ("train_dynamics.py", ["dynamics.iterations=abc", "--cfg", "job"],
     "error: dynamics.iterations=abc: Value 'abc' of type 'str' could not be converted to Integer"),
    ("train_dynamics.py", ["dynamics.lr=-1"], "error: dynamics.lr=-1.0 is out of range: must be in (0, 1] (Adam learning rate)"),
    ("train_policy.py", ["agent.greedy_ema_decay=1"], "error: agent.greedy_ema_decay=1.0 is out of range: must be in (0, 1)"),
    ("train_policy.py", ["agent.greedy_ema_tail=0.5"], "error: agent.greedy_ema_tail=0.5 is set but agent.greedy_ema_decay "
     "is null: the tail shortens an average, set the decay of the longest one"),
    ("train_policy.py", ["agent.greedy_ema_model=false"], "error: agent.greedy_ema_model=false is set but "
     "agent.greedy_ema_decay is null: there is no average to leave the model out of"),
    ("train_dynamics.py", ["env.num_objects=0"], "error: env.num_objects=0 is out of range: must be >= 1 (objects in the scene)"),
    ("train_dynamics.py", ["dynamics.iterations=-1"], "error: dynamics.iterations=-1 is out of range: must be >= 1 (training iterations)"),
    ("generate_demos.py", ["demos.num_episodes=3"],
     "error: demos.num_steps=5000 and demos.num_episodes=3 are both set: give exactly one (e.g. demos.num_steps=null "
     "demos.num_episodes=3)"),
    ("train_dynamics.py", ["dynamics.iteration=300"], "Key 'iteration' not in 'DynamicsConfig'"),
    ("train_dynamics.py", ["model=naive", "loss.gripper_symmetries=true"],
     "error: loss.gripper_symmetries=true mirrors the LDM's gripper-aligned frame; model=naive has none"),
    ("train_dynamics.py", ["dynamics.data=demos/typo"], "error: dynamics.data='demos/typo' is invalid: must be null or an existing path"),
    ("train_dynamics.py", ["resume=true"], "error: resume=true continues a run in its folder: add hydra.run.dir="),
    ("generate_demos.py", ["resume=true"], "error: resume=true: generate_demos has nothing to resume"),
    ("train_policy.py", ["agent.target_proposal.mode=softmax"],
     "error: agent.bootstrap_cache=4096 needs deterministic target proposals: agent.target_proposal.mode=softmax"),
    ("train_policy.py", ["agent=fcdqn", "agent.bootstrap_cache=8"],
     "error: agent.bootstrap_cache=8 is set but only agent=ldm caches its bootstraps (agent.name=fcdqn)"),
    ("train_policy.py", ["agent=rs", "agent.value_augmentation=quarter_turns"],
     "error: agent.value_augmentation='quarter_turns' is set but only agent=ldm uses it (agent.name=rs)"),
    ("train_policy.py", ["agent.q_log_floor=0"], "error: agent.q_log_floor=0.0 is out of range: must be in (0, 1)"),
    ("train_policy.py", ["agent=rs", "agent.q_log_floor=0.01"],
     "error: agent.q_log_floor=0.01 is set but agent=rs builds no Q network"),
    ("train_policy.py", ["agent=rs", "agent.q_pick_min_height=0.015"],
     "error: agent.q_pick_min_height=0.015 is set but agent=rs builds no Q network"),
    ("train_policy.py", ["agent.q_pick_min_height=-0.01"], "error: agent.q_pick_min_height=-0.01 is out of range"),
    ("train_policy.py", ["agent.value_augmentation=flips"], "agent.value_augmentation='flips' is invalid: must be one of"),
    ("train_policy.py", ["agent=fcdqn", "agent.value_log_floor=0.01"],
     "error: agent.value_log_floor=0.01 is set but only agent=ldm uses it (agent.name=fcdqn)"),
    ("train_policy.py", ["agent.value_log_floor=0.01", "agent.termination_head=true"],
     "error: agent.value_log_floor=0.01 cannot be combined with agent.termination_head=true"),
    ("train_policy.py", ["agent.value_log_floor=1.5"], "error: agent.value_log_floor=1.5 is out of range: must be in (0, 1)"),
    ("train_policy.py", ["agent=fcdqn", "agent.value_margin_weight=1.0"],
     "error: agent.value_margin_weight=1.0 is set but only agent=ldm decides by V(f(s, a)) (agent.name=fcdqn)"),
    ("train_policy.py", ["agent.value_margin=0"], "error: agent.value_margin=0.0 is out of range"),
    ("train_policy.py", ["agent=dynaq", "agent.termination_head=true"],
     "error: agent.termination_head=true is set but only agent=ldm uses it (agent.name=dynaq)"),
    ("train_policy.py", ["agent=fcdqn", "agent.value_shift=2"],
     "error: agent.value_shift=2 is set but only agent=ldm uses it (agent.name=fcdqn)"),
    ("train_policy.py", ["agent.value_shift=0"], "error: agent.value_shift=0 is out of range"),
    ("train_policy.py", ["agent.value_raise_levels=2"],
     "error: agent.value_raise_levels=2 needs agent.value_raise_height (metres of one level, e.g. 0.04 for the cubes)"),
    ("train_policy.py", ["agent=fcdqn", "agent.value_raise_levels=2", "agent.value_raise_height=0.04"],
     "error: agent.value_raise_height=0.04 is set but only agent=ldm uses it (agent.name=fcdqn); "
     "agent.value_raise_levels=2 is set but only agent=ldm uses it (agent.name=fcdqn)"),
    ("train_policy.py", ["agent.value_raise_region=tower"],
     "error: agent.value_raise_region='tower' is invalid: must be one of null, 'object', 'top'"),
    ("train_policy.py", ["agent=fcdqn", "agent.value_raise_region=top"],
     "error: agent.value_raise_region='top' is set but only agent=ldm uses it (agent.name=fcdqn)"),
    ("train_policy.py", ["schedule.updates_per_step=0"], "error: schedule.updates_per_step=0.0 is out of range"),
    ("train_policy.py", ["env=house_building", "env.num_objects=9"],
     "error: env.num_objects=9: ldm_rl/HouseBuilding-v0 takes exactly 3 objects"),
    ("train_dynamics.py", ["env=bottle_arrangement", "env.num_objects=7"],
     "error: env.num_objects=7: ldm_rl/BottleArrangement-v0 takes in 1..6 objects"),
    ("train_policy.py", ["env=house_building", "env.train_object_counts=[2,3]"],
     "error: env.train_object_counts=[2, 3]: ldm_rl/HouseBuilding-v0 takes exactly 3 objects"),
    ("train_policy.py", ["env=house_building", "env.progress_reward=0.03"],
     "error: env.progress_reward=0.03: only ldm_rl/BinPacking-v0 has a progress term (got id ldm_rl/HouseBuilding-v0); set 0"),
    ("train_policy.py", ["env=bin_packing", "env.progress_reward=2"], "error: env.progress_reward=2.0 is out of range"),
    ("train_policy.py", ["model.hand_rule.kind=area"], "error: model.hand_rule.kind='area' is invalid: must be one of "
     "'occupancy', 'removal'"),
    ("evaluate.py", [f"checkpoint={ROOT / 'README.md'}", "hand_rule=area"], "error: hand_rule='area' is invalid: must be one of"),
    ("evaluate.py", [], "error: checkpoint is missing: set checkpoint=<value> (a checkpoint.pt written by recipes/train_policy.py)"),
    ("evaluate.py", ["checkpoint=runs/typo.pt"], "error: checkpoint='runs/typo.pt' is invalid: must be an existing file"),
    pytest.param("train_policy.py", ["device=cuda"], "error: device=cuda: this machine has no NVIDIA driver",
                 marks=pytest.mark.skipif(any(Path(p).exists() for p in ("/dev/nvidiactl", "/proc/driver/nvidia/version",
                                                                           "/dev/kfd")), reason="a GPU driver is here")),
    ("train_policy.py", ["compile=true", "device=mps"], "compile=true is not supported with device=mps (inductor here: cpu and cuda); use compile=false"),
    pytest.param("train_dynamics.py", ["logger=mlflow"], "error: logger=mlflow needs the 'mlflow' package, which is not installed",
                 marks=pytest.mark.skipif(importlib.util.find_spec("mlflow") is not None, reason="mlflow is installed")),
]


@pytest.mark.parametrize("recipe, args, expected", BAD_COMMANDS, ids=lambda x: " ".join(x) if isinstance(x, list) else None)
def test_a_bad_config_stops_in_one_line_without_an_output_folder(recipe, args, expected, tmp_path):
    done = run_recipe(ROOT / "recipes" / recipe, *args, cwd=tmp_path)
    assert done.returncode == 2, done.stderr
    assert done.stdout == ""
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: ") and expected in lines[0], done.stderr
    assert list(tmp_path.iterdir()) == [], "a failed command must not leave files behind"


def test_compile_without_a_cxx_compiler_stops_in_one_line(tmp_path):
    done = run_recipe(ROOT / "recipes" / "train_policy.py", "compile=true", cwd=tmp_path,
                      env={**os.environ, "CXX": "no-such-compiler-here"})
    assert done.returncode == 2 and list(tmp_path.iterdir()) == [], done.stderr
    assert done.stderr.strip() == ("error: compile=true needs a C++ compiler for inductor on the CPU and no-such-compiler-here "
                                   "is not on PATH (install g++ or set CXX); use compile=false")


def test_evaluate_refuses_a_dynamics_checkpoint_in_one_line(tmp_path):
    from ldm_rl.run.checkpoint import save_checkpoint

    dynamics = save_checkpoint(tmp_path / "ldm" / "checkpoint.pt", {"model": {}}, meta={"kind": "dynamics"})
    work = tmp_path / "work"
    work.mkdir()
    done = run_recipe(ROOT / "recipes" / "evaluate.py", f"checkpoint={dynamics}", cwd=work)
    assert done.returncode == 2 and list(work.iterdir()) == [], done.stderr
    assert done.stderr.strip() == (f"error: checkpoint={dynamics} holds a dynamics checkpoint: this recipe reads an agent's "
                                   "(a checkpoint.pt of recipes/train_policy.py)")


def test_evaluate_refuses_more_candidates_than_the_checkpoints_q_map_in_one_line(tmp_path):
    from ldm_rl.geometry import HEIGHTMAP_SIZE
    from ldm_rl.run.checkpoint import save_checkpoint

    assert config_schema.HEIGHTMAP_PIXELS == HEIGHTMAP_SIZE  # the pre-flight's light copy of the constant
    agent = save_checkpoint(tmp_path / "run" / "checkpoint.pt", {"agent": {}},
                            meta={"kind": "agent", "config": {"model": {"num_rotations": 4}}})
    work = tmp_path / "work"
    work.mkdir()
    done = run_recipe(ROOT / "recipes" / "evaluate.py", f"checkpoint={agent}", "planner.num_candidates=65537", cwd=work)
    assert done.returncode == 2 and list(work.iterdir()) == [], done.stderr
    assert done.stderr.strip() == ("error: planner.num_candidates=65537 is more than the checkpoint's Q map holds: at most "
                                   "65536 (4 rotations x 128x128 pixels)")


def test_the_preflight_object_counts_are_the_envs_own():
    """OBJECT_COUNTS refuses exactly what the envs refuse (one count past each end)."""
    import gymnasium as gym

    from ldm_rl.envs import register_envs

    register_envs()
    for env_id, (low, high) in config_schema.OBJECT_COUNTS.items():
        for count in (low - 1, high + 1):
            with pytest.raises(ValueError, match="num_objects"):
                gym.make(env_id, num_objects=count).unwrapped.close()
        gym.make(env_id, num_objects=high).unwrapped.close()


def test_the_command_line_check_imports_no_torch():
    code = (
        "import sys\n"
        "from ldm_rl.run.cli import check_command_line\n"
        f"argv = [{str(ROOT / 'recipes' / 'train_dynamics.py')!r}, 'dynamics.lr=-1']\n"
        "try:\n    check_command_line(argv[0], config_name='train_dynamics', argv=argv, checkpoint_name='checkpoint.pt')\n"
        "except SystemExit as stop:\n    assert stop.code == 2\n"
        "assert 'torch' not in sys.modules, 'the pre-flight imported torch'\n"
        "argv = argv[:1] + ['seed=4']\n"
        "assert check_command_line(argv[0], config_name='train_dynamics', argv=argv) == argv\n"
    )
    subprocess.run([sys.executable, "-c", code], check=True, capture_output=True, text=True)


@pytest.mark.parametrize("overrides, expected", [
    (["model.crop_size=40"], "model.crop_size=40 is out of range: must be in [32, 128] and a multiple of 16"),
    (["model.num_rotations=4"], "model.num_rotations=4 differs from env.num_rotations=8"),
    (["loss.class_weights=[1,2]"], "loss.class_weights has 2 entries: must have model.num_depth_classes=21"),
    (["device=gpu0"], "device='gpu0' is invalid: must be auto, cpu, cuda, cuda:N or mps"),
    (["logger.backend=neptune"], "logger.backend='neptune' is invalid: must be one of 'csv', 'tensorboard', 'wandb', 'mlflow', "
                                 "'none'"),
    (["logger=wandb", "logger.mode=sometimes"], "logger.mode='sometimes' is invalid: must be one of null, 'online', 'offline', "
                                                "'disabled'"),
    (["dynamics.val_fraction=1.5", "threads=0"], "threads=0 is out of range: must be in [1, 1024] (torch intra-op threads; "
                                                   "null = torch's default); dynamics.val_fraction=1.5 is out of range: "
                                                   "must be in (0, 1) (held-out fraction)"),
    (["demos.num_steps=null"], "demos.num_steps and demos.num_episodes are both null: give exactly one"),
    (["dynamics.autocast=fp8"], "dynamics.autocast='fp8' is invalid: must be one of null, 'bf16'"),
])
def test_validate_config_names_the_key_and_the_allowed_values(overrides, expected):
    with pytest.raises(config_schema.ConfigError) as err:
        config_schema.validate_config(make_cfg(*overrides), config_schema.TrainDynamicsConfig)
    assert str(err.value) == expected or str(err.value).startswith(expected)
    assert "\n" not in str(err.value)


def test_types_and_unknown_keys_fail_at_composition():
    with pytest.raises(ConfigCompositionException):
        make_cfg("dynamics.iterations=abc")
    with pytest.raises(ConfigCompositionException):
        make_cfg("dynamics.iteration=5")
    with pytest.raises(config_schema.ConfigError, match="Key 'iteration' not in 'DynamicsConfig'"):
        config_schema.validate_config(make_cfg("+dynamics.iteration=5"), config_schema.TrainDynamicsConfig)  # Hydra's "+" adds keys to any node
    # configs composed without the schema are typed by validate_config
    # a config composed without the schema (a plain dict) is typed by validate_config
    plain = OmegaConf.create(OmegaConf.to_container(make_cfg(), resolve=False))
    OmegaConf.update(plain, "dynamics.iterations", "abc")
    with pytest.raises(config_schema.ConfigError, match="dynamics.iterations: Value 'abc' of type 'str' could not be converted"):
        config_schema.validate_config(plain, config_schema.TrainDynamicsConfig)


def test_multirun_over_seeds_gives_one_run_per_seed(tmp_path):
    """`-m seed=0,1` (Hydra's basic launcher) runs a real recipe twice, each seed in its own folder."""
    sweep = tmp_path / "sweep"
    done = run_recipe(
        ROOT / "recipes" / "generate_demos.py",
        "-m", "seed=0,1", "demos.num_steps=2", "demos.progress=false", f"hydra.sweep.dir={sweep}",
        cwd=tmp_path,
    )
    assert done.returncode == 0, done.stderr
    from ldm_rl.data.demos import load_demos

    first, second = (load_demos(sweep / str(job) / "demos") for job in (0, 1))
    assert first.batch_size == second.batch_size == (2,)
    assert not (first["heightmap"] == second["heightmap"]).all()  # different seeds, different scenes


def test_a_run_written_before_a_key_existed_resumes_when_the_key_is_at_its_default():
    """Resuming compares the run's stored config with the command's: a key the run lacks is no difference
    when the command gives the schema's default (planner.name, added after runs were written), and is one
    otherwise; without a schema every absent key is one."""
    cfg = make_cfg("experiment=stacking_lite", config_name="train_policy")
    cfg.logger.exp_name = "run"  # an interpolation of Hydra's runtime
    given = OmegaConf.to_container(cfg, resolve=True)
    run = {**given, "planner": {k: v for k, v in given["planner"].items() if k != "name"}}
    schema = config_schema.TrainPolicyConfig
    assert config_schema.config_differences(run, given, schema=schema) == []
    assert config_schema.config_differences(run, given) == ["planner.name: the run has '<absent>', the command gives 'diverse'"]
    other = {**given, "planner": {**given["planner"], "name": "depth2"}}
    assert config_schema.config_differences(run, other, schema=schema) == [
        "planner.name: the run has '<absent>', the command gives 'depth2'"]
    changed = {**given, "agent": {**given["agent"], "gamma": 0.9}}
    assert config_schema.config_differences(run, changed, schema=schema) == [
        "agent.gamma: the run has 0.5, the command gives 0.9"]
    moved = {**given, "device": "cuda" if given["device"] != "cuda" else "cpu"}  # the machine's to choose
    assert config_schema.config_differences(run, moved, schema=schema) == []



@pytest.mark.parametrize("preset", ["curves_block_stacking", "curves_house_building", "curves_bottle_arrangement",
                                    "curves_bin_packing", "table2_block_stacking"])
def test_the_curves_presets_play_averaged_greedy_weights(preset):
    assert make_cfg(f"experiment={preset}", config_name="train_policy").agent.greedy_ema_decay == 0.99


def test_resume_overrides_give_back_the_runs_config_after_a_preset_default_changed():
    """A run written before a preset changed a default (here: the curves presets' averaged greedy weights, the
    proposal-fit key added since, a list and a string changed too) resumes with the overrides the refusal
    names: composed with them, the command's config equals the run's."""
    given = OmegaConf.to_container(make_cfg("experiment=curves_block_stacking", config_name="train_policy"), resolve=False)
    run = copy.deepcopy(given)
    run["agent"]["greedy_ema_decay"] = None
    run["agent"]["target_range"] = [0.0, 0.5]
    run["planner"]["proposal"] = "argmax"
    del run["agent"]["q_proposal_fit"]  # added after the run was written, at a default that keeps its behaviour
    schema = config_schema.TrainPolicyConfig
    fix = config_schema.resume_overrides(run, given, schema=schema)
    assert sorted(fix) == ["agent.greedy_ema_decay=null", "agent.target_range=[0.0,0.5]", "planner.proposal=argmax"]
    again = OmegaConf.to_container(make_cfg("experiment=curves_block_stacking", *fix, config_name="train_policy"),
                                   resolve=False)
    assert config_schema.config_differences(run, again, schema=schema) == []

def test_runs_written_before_the_finger_pads_torsional_friction_resume_and_rescore_on_their_own_physics():
    """Every task's env config sets the anchor's 0.1; a stored config without the key (runs before 2026-11-27)
    builds its env with 0, and resuming such a run under today's presets is refused with the override that
    gives back its physics, which then composes to the run's config."""
    from ldm_rl.envs.torchrl_env import env_kwargs_from_config

    for path in sorted((CONF / "env").glob("*.yaml")):
        assert OmegaConf.load(path).finger_spinning_friction == 0.1, path.name
    given = OmegaConf.to_container(make_cfg("experiment=curves_house_building", config_name="train_policy"), resolve=False)
    assert env_kwargs_from_config(given["env"])[1]["gripper"] == {"finger_spinning_friction": 0.1}
    run = copy.deepcopy(given)
    del run["env"]["finger_spinning_friction"]
    assert env_kwargs_from_config(run["env"])[1]["gripper"] == {"finger_spinning_friction": 0.0}
    schema = config_schema.TrainPolicyConfig
    assert config_schema.config_differences(run, given, schema=schema) == [
        "env.finger_spinning_friction: the run has '<absent>', the command gives 0.1"]
    fix = config_schema.resume_overrides(run, given, schema=schema)
    assert fix == ["env.finger_spinning_friction=0.0"]
    again = OmegaConf.to_container(make_cfg("experiment=curves_house_building", *fix, config_name="train_policy"),
                                   resolve=False)
    assert config_schema.config_differences(run, again, schema=schema) == []
    with pytest.raises(ValueError, match="env.finger_spinning_friction must be a number >= 0, got -0.1"):
        env_kwargs_from_config({**given["env"], "finger_spinning_friction": -0.1})


def test_every_recipe_defaults_to_the_same_device():
    devices = {name: OmegaConf.load(CONF / f"{name}.yaml").get("device") for name in ("train_dynamics", "train_policy", "evaluate")}
    assert set(devices.values()) == {"auto"}, devices


def test_the_planner_choices_are_the_registered_planners():
    from ldm_rl.agents import PLANNERS

    rule = next(f for f in config_schema.dataclasses.fields(config_schema.PlannerConfig) if f.name == "name")
    assert set(rule.metadata["rule"].choices) == set(PLANNERS)
    assert {OmegaConf.load(p).name for p in (CONF / "planner").glob("*.yaml")} == set(PLANNERS)


def test_the_schema_default_rotation_count_is_the_packages():
    """R is written in ldm_rl.geometry (code) and in the schema's env default (configs; the schema stays
    torch-free): the two agree."""
    from ldm_rl import geometry

    field = next(f for f in config_schema.dataclasses.fields(config_schema.EnvConfig) if f.name == "num_rotations")
    assert field.default == geometry.NUM_ROTATIONS


AGENT_OPTIONS = sorted(p.stem for p in (CONF / "agent").glob("*.yaml"))


def test_every_agent_extends_the_shared_base_and_repeats_none_of_its_defaults():
    """conf/agent/base/common.yaml holds the keys several agents read, once: each agent's file extends it and
    writes only its own keys or a different value; the choices of agent= are the registered agents."""
    from ldm_rl.agents import AGENTS

    assert AGENT_OPTIONS == sorted(AGENTS)
    base = OmegaConf.to_container(OmegaConf.load(CONF / "agent" / "base" / "common.yaml"))
    for name in AGENT_OPTIONS:
        own = OmegaConf.to_container(OmegaConf.load(CONF / "agent" / f"{name}.yaml"))
        assert own.pop("defaults") == ["base/common@_here_", "_self_"], name
        repeated = [key for key, value in own.items() if base.get(key, object()) == value]
        assert not repeated, f"conf/agent/{name}.yaml repeats base/common.yaml's {repeated}"
        cfg = make_cfg(f"agent={name}", config_name="train_policy")
        config_schema.validate_config(cfg, config_schema.TrainPolicyConfig)
        assert cfg.agent.name == name and cfg.agent.gamma == base["gamma"] and cfg.agent.lr.q == base["lr"]["q"]
        for key, value in own.items():
            assert OmegaConf.to_container(cfg.agent)[key] == value, (name, key)  # the agent's own value wins


def test_a_shared_preset_composes_with_every_agent():
    """One preset, every agent (the comparison's sweep agent=ldm,fcdqn,rs,dynaq): the preset's keys reach
    every agent, and each agent keeps its own."""
    for name in AGENT_OPTIONS:
        cfg = make_cfg(f"agent={name}", "experiment=curves_block_stacking", config_name="train_policy")
        config_schema.validate_config(cfg, config_schema.TrainPolicyConfig)
        assert cfg.agent.name == name and cfg.agent.gamma == 0.5 and cfg.agent.q_width == 0.25
    assert make_cfg("agent=rs", config_name="train_policy").agent.q_grad_clip is None
    assert make_cfg("agent=dynaq", config_name="train_policy").agent.imagined_ratio == 1.0


def _differences(a, b, prefix=""):
    """Dotted keys whose values differ between two composed configs (``hydra`` left out)."""
    for key in sorted(set(a) | set(b)):
        if key == "hydra":
            continue
        left, right = a.get(key), b.get(key)
        if isinstance(left, dict) and isinstance(right, dict):
            yield from _differences(left, right, f"{prefix}{key}.")
        elif left != right:
            yield f"{prefix}{key}"


@pytest.mark.parametrize("preset, task_keys", [
    # the Table 2 cure: the training scenes' object counts (evaluations stay on 3 blocks) and the LDM's height anchor
    # (no transition of that training reaches it: the zero-shot places onto taller columns do)
    # and, for the ldm agent, V − 0.25·H in the greedy decisions' places and Q's vote in them (conf/experiment_agent/)
    ("table2_block_stacking", {"env.train_object_counts", "model.height_anchor", "planner.greedy_uncertainty_penalty",
                               "planner.uncertainty_penalty_on", "planner.greedy_q_blend"}),
    # each task's own settings and budget, as its preset and docs/policy.md ("Reproducing the comparison") say
    # and, for the ldm agent, V fitted on shifted states (conf/experiment_agent/)
    ("curves_house_building", {"agent.gamma", "agent.lr.value", "agent.value_augmentation"}),
    # and the reported house rows' planner: the depth-2 tree, predicted empty picks last, the pick mask
    ("curves_house_building_tree", {"agent.gamma", "agent.lr.value", "agent.value_augmentation", "agent.q_pick_min_height",
                                    "planner.name", "planner.depth", "planner.branching", "planner.gamma",
                                    "planner.terminal_reward", "planner.empty_picks_last"}),
    ("curves_bottle_arrangement", {"agent.gamma", "schedule.total_episodes", "agent.value_augmentation",
                                   "agent.q_pick_min_height", "planner.empty_picks_last", "planner.uncertainty_penalty",
                                   "planner.greedy_uncertainty_penalty"}),
    # and, for the ldm agent, Q's scale and its fit on its own proposals (conf/experiment_agent/)
    ("curves_bin_packing", {"agent.gamma", "schedule.total_episodes", "agent.q_log_floor", "agent.q_proposal_fit",
                            "agent.q_pick_min_height", "model.hand_rule.kind", "env.failed_pick_memory",
                            "agent.expert_margin_weight", "agent.q_frame_pad", "agent.expert_margin_temperature",
                            "planner.greedy_uncertainty_penalty"}),
])
def test_a_task_preset_differs_from_block_stackings_only_where_it_says(preset, task_keys):
    """The comparison's presets share curves_block_stacking's settings; a preset changes only the env and the
    keys it documents, so the four tasks' curves are one protocol."""
    base = OmegaConf.to_container(make_cfg("experiment=curves_block_stacking", config_name="train_policy"))
    cfg = OmegaConf.to_container(make_cfg(f"experiment={preset}", config_name="train_policy"))
    changed = {key for key in _differences(base, cfg) if not key.startswith("env.") or key in task_keys}
    assert changed == task_keys
    if preset == "table2_block_stacking":
        assert cfg["env"]["train_object_counts"] == [2, 3] and cfg["env"]["num_objects"] == base["env"]["num_objects"] == 3
        assert {key for key in _differences(base, cfg)} == task_keys  # same env otherwise


@pytest.mark.parametrize("agent, fit, floor", [("ldm", 3, 0.01), ("fcdqn", 0, 0.01), ("dynaq", 0, 0.01), ("rs", 0, None)])
def test_a_presets_settings_for_one_agent_reach_that_agent_only(agent, fit, floor):
    """conf/experiment_agent/<experiment>_<agent>.yaml: bin packing's Q scale for every agent with a Q network,
    the proposal fit and the house's and bottles' V augmentation for the ldm agent only (each refused for the others), and the
    command line still wins."""
    cfg = make_cfg("experiment=curves_bin_packing", f"agent={agent}", config_name="train_policy")
    assert cfg.agent.get("q_proposal_fit") == fit and cfg.agent.get("q_log_floor") == floor
    config_schema.validate_config(cfg, config_schema.TrainPolicyConfig)
    mine = make_cfg("experiment=curves_bin_packing", f"agent={agent}", "agent.q_log_floor=null", config_name="train_policy")
    assert mine.agent.get("q_log_floor") is None
    house = make_cfg("experiment=curves_house_building", f"agent={agent}", config_name="train_policy")
    assert house.agent.get("q_log_floor") is None
    assert house.agent.gamma == 0.8  # the house's discount is the task's, every agent's (curves_house_building.yaml)
    # the house's and the bottles' V augmentation reaches the ldm agent only (the others refuse the key)
    assert house.agent.get("value_augmentation") == ("shifts" if agent == "ldm" else None)
    config_schema.validate_config(house, config_schema.TrainPolicyConfig)
    bottles = make_cfg("experiment=curves_bottle_arrangement", f"agent={agent}", config_name="train_policy")
    assert bottles.agent.get("value_augmentation") == ("shifts" if agent == "ldm" else None)
    # the bottles' and bin packing's pick mask reaches every agent with a Q network (rs refuses the key)
    assert bottles.agent.get("q_pick_min_height", 0.0) == (0.0 if agent == "rs" else 0.015)
    assert cfg.agent.get("q_pick_min_height", 0.0) == (0.0 if agent == "rs" else 0.015)
    # and its expert margin, its soft max, read in 32 px padded frames (every Q agent; rs has no Q and refuses the keys)
    assert cfg.agent.get("expert_margin_weight", 0.0) == (0.0 if agent == "rs" else 1.0)
    assert cfg.agent.get("expert_margin_temperature", 0.0) == (0.0 if agent == "rs" else 0.02)
    assert cfg.agent.get("q_frame_pad", 0) == (0 if agent == "rs" else 32)
    assert bottles.agent.get("expert_margin_weight", 0.0) == house.agent.get("q_frame_pad", 0) == 0
    # bin packing's hand-state rule is the task's (experiment file), the other presets keep the reference's
    assert cfg.model.hand_rule.kind == "removal" and bottles.model.hand_rule.kind == house.model.hand_rule.kind == "occupancy"
    # bin packing's failed-pick memory is the task's too (every agent), the other presets leave it off
    assert cfg.env.failed_pick_memory == 8 and bottles.env.failed_pick_memory == house.env.failed_pick_memory == 0
    # and its predicted empty picks ranked last reach the ldm agent's planner only
    assert bottles.planner.empty_picks_last is (agent == "ldm") and house.planner.empty_picks_last is False
    # and so does V − λ·H (λ = 0.25 nats⁻¹ exploring, 1.0 in the greedy decisions)
    assert bottles.planner.uncertainty_penalty == (0.25 if agent == "ldm" else 0.0) and house.planner.uncertainty_penalty == 0.0
    assert bottles.planner.greedy_uncertainty_penalty == (1.0 if agent == "ldm" else None)
    assert house.planner.greedy_uncertainty_penalty is None
    # bin packing's greedy decisions score V − 1.0·H (the ldm agent's planner only); its exploring stays at V alone
    assert cfg.planner.greedy_uncertainty_penalty == (1.0 if agent == "ldm" else None)
    assert cfg.planner.uncertainty_penalty == 0.0
    # and so do block stacking's Table 2 preset's (the learning-curve preset keeps V alone)
    table2 = make_cfg("experiment=table2_block_stacking", f"agent={agent}", config_name="train_policy")
    assert table2.planner.greedy_uncertainty_penalty == (0.25 if agent == "ldm" else None)
    assert table2.planner.uncertainty_penalty == 0.0
    # and Q's vote in those greedy decisions alone (w = 0.25; exploring keeps V − λ·H alone)
    assert table2.planner.greedy_q_blend == (0.25 if agent == "ldm" else None) and table2.planner.q_blend == 0.0
    # charged on its places alone (a pick's entropy chose picks that come up empty on 4 and 5 blocks)
    assert table2.planner.uncertainty_penalty_on == ("places" if agent == "ldm" else "all")
    assert bottles.planner.uncertainty_penalty_on == cfg.planner.uncertainty_penalty_on == "all"
    assert make_cfg("experiment=curves_block_stacking", f"agent={agent}", config_name="train_policy").planner.greedy_uncertainty_penalty is None
    config_schema.validate_config(bottles, config_schema.TrainPolicyConfig)
    if agent != "rs":
        from ldm_rl.agents import build_agent

        built = build_agent(bottles, float(bottles.env.max_height))
        assert built.policy.q_network.pick_min_height == 0.015
        # every Q agent's heads keep the reference's 8 hidden units at the curves' width 0.25; a config written
        # before the key (a checkpoint's) builds the 2 it was trained with, so its weights load
        assert bottles.agent.q_width == 0.25 and built.policy.q_network.head_channels == 8
        from omegaconf import OmegaConf

        bottles.logger.exp_name = "run"  # resolved outside a Hydra run
        older = OmegaConf.to_container(bottles, resolve=True)
        del older["agent"]["q_head_channels"]
        assert build_agent(older, float(bottles.env.max_height)).policy.q_network.head_channels == 2
        assert getattr(built.policy, "empty_picks_last", False) is (agent == "ldm")
        assert getattr(built.policy, "uncertainty_penalty", 0.0) == (0.25 if agent == "ldm" else 0.0)
        if agent == "ldm":
            assert built.policy.penalty(greedy=True) == 1.0 and built.policy.penalty(greedy=False) == 0.25


@pytest.mark.parametrize("agent", ["ldm", "fcdqn", "rs", "dynaq"])
def test_the_house_tree_preset_is_the_reported_house_protocol_and_the_paper_planner_one_override_away(agent):
    """experiment=curves_house_building_tree composes, for the ldm agent, to the command of the reported heads8
    house rows (curves_house_building with planner=tree, predicted empty picks last and the pick mask), builds a
    TreePlanner, and gives the one-step planner back with planner=diverse; the other agents get the pick mask
    where they have a Q network and nothing of the ldm agent's planner."""
    from omegaconf import OmegaConf

    from ldm_rl.agents import build_agent
    from ldm_rl.planning.tree_planner import TreePlanner

    tree = make_cfg("experiment=curves_house_building_tree", f"agent={agent}", config_name="train_policy")
    config_schema.validate_config(tree, config_schema.TrainPolicyConfig)
    assert tree.planner.name == "tree" and tree.planner.depth == 2 and tree.agent.value_augmentation == (
        "shifts" if agent == "ldm" else None)
    assert tree.agent.get("q_pick_min_height", 0.0) == (0.0 if agent == "rs" else 0.015)
    assert tree.planner.empty_picks_last is (agent == "ldm")
    if agent == "ldm":
        reported = make_cfg("experiment=curves_house_building", "planner=tree", "planner.empty_picks_last=true",
                            "agent.q_pick_min_height=0.015", config_name="train_policy")
        assert OmegaConf.to_container(tree) == OmegaConf.to_container(reported)
        assert isinstance(build_agent(tree, float(tree.env.max_height)).policy, TreePlanner)
        paper = make_cfg("experiment=curves_house_building_tree", "planner=diverse", config_name="train_policy")
        config_schema.validate_config(paper, config_schema.TrainPolicyConfig)
        assert not isinstance(build_agent(paper, float(paper.env.max_height)).policy, TreePlanner)
