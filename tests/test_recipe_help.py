"""``python recipes/<name>.py --help`` (ldm_rl.run.help): what the recipe does and writes first, then only
the config groups it reads, then its primary config's keys with their comments; exit code 0."""

import os
import re
import subprocess
import sys
from pathlib import Path

import pytest
from omegaconf import OmegaConf

from ldm_rl.run.help import recipe_help

ROOT = Path(__file__).resolve().parents[1]
CONF = ROOT / "conf"
HYDRA_RECIPES = sorted(p.stem for p in (ROOT / "recipes").glob("*.py") if "@hydra.main" in p.read_text())

# recipe: (a phrase of its header, the groups it reads, a comment line of its primary config)
EXPECTED = {
    "train_dynamics": ("trains the dynamics model", {"env", "model", "loss", "logger", "demos", "dynamics", "experiment"},
                       "# auto = cuda when available, else cpu"),
    "generate_demos": ("collects scripted-expert demonstrations", {"env", "demos"}, "# seed of the scenes and of the expert's noise"),
    "render_expert_strip": ("draws it as a PNG", {"env", "demos"}, "# the scene (env.reset(seed=seed))"),
    "train_policy": ("trains an agent online",
                     {"env", "model", "loss", "agent", "planner", "replay", "schedule", "logger", "experiment"},
                     "# how training steps are collected"),
    "evaluate": ("plays a checkpoint's greedy policy", {"+experiment"}, "# greedy episodes to play"),
}
ALL_GROUPS = {p.name for p in CONF.iterdir() if p.is_dir()}


def run_help(stem, *args):
    env = dict(os.environ, OMP_NUM_THREADS="1", MKL_NUM_THREADS="1")
    return subprocess.run([sys.executable, str(ROOT / "recipes" / f"{stem}.py"), *args], capture_output=True, text=True,
                          timeout=120, env=env, cwd=ROOT)


def groups_section(text):
    """``{group: options line}`` of the 'Config groups it reads' section."""
    match = re.search(r"^Config groups it reads.*\n((?:  .*\n)+)", text, re.M)
    if match is None:
        return {}
    return {m.group(1): m.group(2) for m in re.finditer(r"^  (\+?\w+):\s+(.*)$", match.group(1), re.M)}


def test_every_hydra_recipe_is_checked():
    assert set(HYDRA_RECIPES) == set(EXPECTED)


@pytest.mark.parametrize("stem", sorted(EXPECTED))
def test_help_says_what_the_recipe_does_and_lists_only_its_groups(stem):
    phrase, groups, comment = EXPECTED[stem]
    done = run_help(stem, "--help")
    assert done.returncode == 0, done.stderr
    text = done.stdout
    header = text.split("\nUsage:")[0]
    assert text.startswith(f"recipes/{stem}.py ") and phrase in " ".join(header.splitlines()[:3]), header
    assert re.search(r"\bwrites\b", header, re.I), f"the header of {stem} does not say what it writes"
    assert "python recipes/" + stem + ".py " in header  # an example command
    listed = groups_section(text)
    assert set(listed) == groups, listed
    for group in ALL_GROUPS - {g.lstrip("+") for g in groups}:
        assert not re.search(rf"\b{group}[=/]", text), f"{stem} --help mentions the group {group!r} it does not read"
    if stem in ("train_dynamics", "generate_demos", "render_expert_strip"):
        assert "planner" not in text and "agent" not in text
    for group in groups - {"experiment", "+experiment"}:  # every option named, the default marked
        options = sorted(p.stem for p in (CONF / group).glob("*.yaml"))
        assert listed[group].replace("*", "").split(", ") == options
        assert listed[group].count("*") == 1
    presets = [name for name in sorted(p.stem for p in (CONF / "experiment").glob("*.yaml"))
               if f"recipes/{stem}.py" in (CONF / "experiment" / f"{name}.yaml").read_text()]
    for name in presets:
        assert name in text
    if stem == "train_dynamics":
        assert presets and all(p.startswith("table1_") for p in presets)
        assert "curves_" not in text and "generalization_" not in text
    assert comment in text  # the primary config's key docs
    outside = ("DESIGN" + ".md", "../" + "shared")  # split: the repository never spells them out (test_api_composition)
    assert not any(name in text for name in outside)
    assert "README.md" in text and "docs/" in text


def test_each_recipe_has_its_own_primary_config_with_only_the_groups_it_reads():
    """conf/<recipe>.yaml is the recipe's primary config, and its groups are the ones its code reads
    (``cfg.<group>``, the recipe or the library function it hands ``cfg`` to)."""
    for stem in HYDRA_RECIPES:
        source = (ROOT / "recipes" / f"{stem}.py").read_text()
        assert re.search(r'config_name="(\w+)"', source).group(1) == stem
        defaults = OmegaConf.to_container(OmegaConf.load(CONF / f"{stem}.yaml"))["defaults"]
        groups = {str(k).split()[-1] for d in defaults if isinstance(d, dict) for k in d} - {"schema", "experiment",
                                                                                               "experiment_agent"}
        unread = {g for g in groups if not re.search(rf"\bcfg\.{g}\b|cfg\[\"{g}\"\]", source)}
        if stem == "train_policy":  # hands cfg to ldm_rl.agents.build_agent, which reads model, loss, agent, planner
            unread -= {"model", "loss", "agent", "planner"}
        assert not unread, (stem, unread)


def test_chosen_option_and_user_config_dir(tmp_path):
    (tmp_path / "env").mkdir()
    (tmp_path / "env" / "my_table.yaml").write_text("# my own table\nid: ldm_rl/BlockStacking-v0\n")
    text = recipe_help(str(ROOT / "recipes" / "train_dynamics.py"), config_name="train_dynamics", config_dir=str(tmp_path),
                       overrides=["env=house_building", "seed=3"], checkpoint_name="checkpoint.pt")
    listed = groups_section(text)
    assert "my_table" in listed["env"] and "block_stacking*" in listed["env"]
    assert "Keys of env=house_building (conf/env/house_building.yaml" in text
    assert "env=block_stacking" not in text
    assert "resume=true hydra.run.dir=DIR" in text


def test_an_option_that_extends_a_base_shows_both_files_in_merge_order():
    """agent=fcdqn's keys live mostly in conf/agent/base/common.yaml: --help shows the base, then the option's
    own keys and description, without the defaults list."""
    text = recipe_help(str(ROOT / "recipes" / "train_policy.py"), config_name="train_policy", overrides=["agent=fcdqn"])
    section = text.split("Keys of agent=fcdqn (conf/agent/base/common.yaml, then conf/agent/fcdqn.yaml, under agent.):")[1]
    section = section.split("\nKeys of ")[0]
    assert section.index("  gamma: 0.95") < section.index("  # FC-DQN baseline") < section.index("  name: fcdqn")
    assert "\n  defaults:" not in section and "  - base/common@_here_" not in section


def test_other_hydra_flags_still_reach_hydra():
    done = run_help("train_dynamics", "--hydra-help")
    assert done.returncode == 0, done.stderr
    assert "Hydra (" in done.stdout and "hydra/launcher" in done.stdout


def test_unknown_config_name_is_one_line_error():
    done = run_help("train_dynamics", "--config-name", "nope", "--help")
    assert done.returncode == 2
    assert done.stderr.strip().count("\n") == 0 and done.stderr.startswith("error: --config-name nope")


def test_help_shows_a_presets_settings_for_the_chosen_agent():
    """conf/experiment_agent/ is chosen by the preset and the agent, not listed as a group; --help with the two
    shows that file's keys."""
    text = run_help("train_policy", "--help", "experiment=curves_bin_packing", "agent=ldm").stdout
    assert "experiment_agent:" not in text.split("Keys of")[0]
    assert "conf/experiment_agent/curves_bin_packing_ldm.yaml" in text and "q_proposal_fit: 3" in text
    other = run_help("train_policy", "--help", "experiment=curves_bin_packing", "agent=rs").stdout
    assert "with agent=rs" not in other and "q_proposal_fit: 3" not in other  # rs has no such file
