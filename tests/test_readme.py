"""The README's two set-up commands stay true: CI runs the test command verbatim."""

import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def setup_commands():
    readme = (ROOT / "README.md").read_text()
    section = readme.split("## Set-up: two commands", 1)[1].split("\n## ", 1)[0]
    return re.findall(r"```bash\n(.+?)\n```", section)


def test_readme_has_exactly_two_setup_commands_installing_torch_first():
    commands = setup_commands()
    assert len(commands) == 2, commands
    for command in commands:
        assert "\n" not in command and command.startswith("pip install torch==2.13.0 && pip install -e ")


def test_ci_runs_the_readme_test_command_verbatim():
    test_command = setup_commands()[1]
    assert "pytest" in test_command
    ci_lines = (ROOT / ".ci" / "run").read_text().splitlines()
    assert test_command in ci_lines


def test_main_command_runs_a_recipe_that_exists():
    main_command = setup_commands()[0]
    recipe = re.search(r"python (recipes/\S+\.py)", main_command).group(1)
    assert (ROOT / recipe).is_file()
