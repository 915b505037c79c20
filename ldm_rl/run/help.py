"""``python recipes/<name>.py --help``: what the recipe does and writes, the config groups it reads, every key.

:func:`ldm_rl.run.cli.check_command_line` calls :func:`print_recipe_help` when ``--help`` is given
(``--hydra-help``, ``--info`` and ``--cfg`` still go to Hydra). The text comes from the config files, so each
thing is written in one place:

1. **What the recipe does and writes**: its primary config's ``hydra.help.header`` (each recipe has its
   own primary config, ``conf/<name>.yaml``, listing only the groups it reads).
2. **The groups it reads**: those of the primary config's defaults list (not ``schema``); ``experiment``
   lists the presets whose comments run this recipe (``python recipes/<name>.py ...``), also when the
   primary config has no ``experiment`` default (then they are added with ``+experiment=NAME``).
3. **Every key with its meaning**: the primary config's own keys and the chosen option file of each
   group, comments included (the comments are the key docs).
4. The primary config's ``hydra.help.footer``.

Importing this module is light: omegaconf only.
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import Iterable, Sequence

from omegaconf import OmegaConf

__all__ = ["recipe_help", "print_recipe_help"]

_WIDTH = 110


def _raw_help(primary: dict, key: str, stem: str) -> str:
    """``hydra.help.<key>`` of the unresolved primary config, with the app/job name filled in."""
    help_node = (primary.get("hydra") or {}).get("help") or {}
    text = str(help_node.get(key) or "")
    app_name = str(help_node.get("app_name") or f"ldm_rl {stem}")
    return text.replace("${hydra.help.app_name}", app_name).replace("${hydra.job.name}", stem)


def _default_groups(primary: dict) -> list[tuple[str, str | None]]:
    """``(group, default option)`` of the primary config's defaults list, without ``schema``, ``_self_`` and the
    groups chosen by interpolation (``experiment_agent: ${experiment}_${agent}``: not the user's to choose)."""
    found = []
    for entry in primary.get("defaults") or []:
        if not isinstance(entry, dict):
            continue
        for key, value in entry.items():
            group = str(key).split()[-1].lstrip("/")  # "optional schema", "override /env"
            if group != "schema" and "/" not in group and "${" not in str(value):
                found.append((group, None if value is None else str(value)))
    return found


def _options(group: str, conf_dirs: Sequence[Path]) -> list[str]:
    names = {p.stem for d in conf_dirs for p in (d / group).glob("*.yaml")}
    return sorted(names)


def _option_file(group: str, option: str, conf_dirs: Sequence[Path]) -> Path | None:
    return next((d / group / f"{option}.yaml" for d in conf_dirs if (d / group / f"{option}.yaml").is_file()), None)


def _base_files(group: str, option_file: Path, conf_dirs: Sequence[Path]) -> list[Path]:
    """The files an option extends through its defaults list (``- base/common@_here_``: ``conf/<group>/base/
    common.yaml``), in merge order; an entry naming another group (``override /env: ...``) is not one."""
    found = []
    for entry in OmegaConf.to_container(OmegaConf.load(option_file)).get("defaults") or []:
        if isinstance(entry, str) and entry != "_self_":
            name = entry.split("@")[0]
            path = next((d / group / f"{name}.yaml" for d in conf_dirs if (d / group / f"{name}.yaml").is_file()), None)
            if path is not None:
                found += _base_files(group, path, conf_dirs) + [path]
    return found


def _presets_for(stem: str, conf_dirs: Sequence[Path]) -> list[str]:
    """The ``experiment/`` presets whose comments show a command of ``recipes/<stem>.py``."""
    needle = f"recipes/{stem}.py"
    return [name for name in _options("experiment", conf_dirs)
            if needle in _option_file("experiment", name, conf_dirs).read_text()]


def _top_level_blocks(text: str) -> list[tuple[str | None, list[str]]]:
    """The YAML text cut at its top-level keys: ``(key, lines)``, each block with the comments above its key."""
    blocks: list[tuple[str | None, list[str]]] = []
    pending: list[str] = []
    for line in text.splitlines():
        key = re.match(r"([A-Za-z_][\w-]*):", line)
        if key:
            blocks.append((key.group(1), pending + [line]))
            pending = []
        elif blocks and line.startswith((" ", "\t")):  # inside the last key's node (blank lines included)
            blocks[-1][1].extend(pending + [line])
            pending = []
        else:  # a comment or blank line at column 0: it belongs to the next key
            pending.append(line)
    if pending:
        blocks.append((None, pending))
    return blocks


def _own_keys(text: str) -> str:
    """The primary config's text without its defaults list (and the comments above it) and its ``hydra`` node."""
    kept = [lines for key, lines in _top_level_blocks(text) if key not in ("defaults", "hydra")]
    return "\n".join(line for lines in kept for line in lines).strip("\n")


def _without_defaults(text: str) -> str:
    """An option's text without its defaults list (the comments above it stay: they describe the option)."""
    kept = [[line for line in lines if line.lstrip().startswith("#") or not line.strip()] if key == "defaults" else lines
            for key, lines in _top_level_blocks(text)]
    return "\n".join(line for lines in kept for line in lines).strip("\n")


def _indent(text: str, prefix: str = "  ") -> str:
    return "\n".join(prefix + line if line.strip() else "" for line in text.splitlines())


def _chosen(overrides: Iterable[str], groups: Iterable[str]) -> dict[str, str]:
    """``GROUP=OPTION`` (or ``+GROUP=OPTION``) choices on the command line."""
    names = set(groups)
    chosen = {}
    for text in overrides:
        match = re.fullmatch(r"\+?(\w+)=([\w.-]+)", text)
        if match and match.group(1) in names:
            chosen[match.group(1)] = match.group(2)
    return chosen


def _example(groups, presets, has_experiment, conf_dirs) -> str:
    """A ``GROUP=OPTION`` that changes something: another option of a group, else a preset."""
    for group, default in groups:
        other = [n for n in _options(group, conf_dirs) if n != default]
        if other:
            return f"{group}={other[-1]}"
    return f"{'' if has_experiment else '+'}experiment={presets[0]}"


def recipe_help(recipe_file: str, *, config_name: str, config_path: str = "../conf",
                config_dir: str | None = None, overrides: Sequence[str] = (),
                checkpoint_name: str | None = None) -> str:
    """The ``--help`` text of ``recipe_file`` (a recipe composing ``<config_path>/<config_name>.yaml``).

    ``config_dir`` (``--config-dir``) adds its options to the listing; ``GROUP=OPTION`` in ``overrides``
    changes which option's keys are shown; ``checkpoint_name`` (a resumable recipe) adds the resume line.
    Raises ``FileNotFoundError`` if the primary config file is not found.
    """
    recipe = Path(recipe_file).resolve()
    stem = recipe.stem
    conf = (recipe.parent / config_path).resolve()
    conf_dirs = ([Path(config_dir).expanduser().resolve()] if config_dir else []) + [conf]
    primary_file = next((d / f"{config_name}.yaml" for d in conf_dirs if (d / f"{config_name}.yaml").is_file()), None)
    if primary_file is None:
        raise FileNotFoundError(f"--config-name {config_name}: no {config_name}.yaml in {', '.join(map(str, conf_dirs))}")
    text = primary_file.read_text()
    primary = OmegaConf.to_container(OmegaConf.create(text), resolve=False)
    shown_primary = primary_file.relative_to(conf.parent) if primary_file.is_relative_to(conf.parent) else primary_file

    groups = _default_groups(primary)
    presets = _presets_for(stem, conf_dirs)
    has_experiment = any(g == "experiment" for g, _ in groups)
    groups = [(g, d) for g, d in groups if g != "experiment"]
    chosen = {g: d for g, d in groups if d is not None}
    chosen.update(_chosen(overrides, [g for g, _ in groups] + ["experiment"]))

    out = [_raw_help(primary, "header", stem), ""]

    command = f"python recipes/{stem}.py"
    out.append(f"Usage: {command} [GROUP=OPTION ...] [KEY=VALUE ...] [FLAGS]" if groups or presets
               else f"Usage: {command} [KEY=VALUE ...] [FLAGS]")
    if groups or presets:
        out.append(f"  GROUP=OPTION        choose a group's option (below), e.g. "
                   f"{_example(groups, presets, has_experiment, conf_dirs)}")
    out += [
        "  KEY=VALUE           set any key shown below, e.g. seed=1; a wrong type or value stops in one line",
        "  -m                  sweep every combination (-m seed=0,1,2), one job folder each under multirun/",
        "  --cfg job           print the composed config and exit without running",
        "  --config-dir DIR    add your own options as DIR/<group>/<name>.yaml",
    ]
    if checkpoint_name:
        out.append(f"  resume=true hydra.run.dir=DIR   continue a stopped run from DIR/{checkpoint_name}")
    out += [
        "  --hydra-help        Hydra's own flags and groups (launcher, sweeper, job logging)",
        "Each run writes to its own folder, outputs/<date>/<time>/ (or hydra.run.dir=DIR).",
        "",
    ]

    if groups or presets:
        out.append("Config groups it reads (GROUP=OPTION; * = default; an option's keys: conf/<group>/<option>.yaml):")
        width = max(len(g) for g in [g for g, _ in groups] + ["experiment"]) + 3
        for group, default in groups:
            names = [n + ("*" if n == default else "") for n in _options(group, conf_dirs)]
            out.append(f"  {group + ':':<{width}}{', '.join(names) or '(no options found)'}")
        if presets:
            how = "experiment:" if has_experiment else "+experiment:"
            note = "none by default" if has_experiment else f"not in {primary_file.name}'s defaults: add with +experiment=NAME"
            line = f"  {how:<{width}}{', '.join(presets)}  ({note})"
            out.append(line if len(line) <= _WIDTH else f"  {how:<{width}}{', '.join(presets)}\n  {'':<{width}}({note})")
        out.append("")

    out += [f"Keys of {shown_primary} (types, ranges and choices: ldm_rl/config_schema.py):", _indent(_own_keys(text)), ""]
    for group, option in [(g, chosen.get(g)) for g, _ in groups] + [("experiment", chosen.get("experiment"))]:
        if option is None:
            continue
        option_file = _option_file(group, option, conf_dirs)
        if option_file is None:
            continue  # an unknown option: the run itself reports it in one line
        files = _base_files(group, option_file, conf_dirs) + [option_file]
        where = ", then ".join(str(f.relative_to(conf.parent) if f.is_relative_to(conf.parent) else f) for f in files)
        if group == "experiment":
            out += [f"experiment={option} ({where}):", _indent(option_file.read_text().strip("\n")), ""]
            per_agent = _option_file("experiment_agent", f"{option}_{chosen.get('agent')}", conf_dirs)
            if per_agent is not None:  # the preset's settings for the chosen agent
                shown = per_agent.relative_to(conf.parent) if per_agent.is_relative_to(conf.parent) else per_agent
                out += [f"experiment={option} with agent={chosen.get('agent')} ({shown}):",
                        _indent(per_agent.read_text().strip("\n")), ""]
            continue
        body = "\n\n".join(_without_defaults(f.read_text()) for f in files)
        out += [f"Keys of {group}={option} ({where}, under {group}.):", _indent(body), ""]

    out.append(_raw_help(primary, "footer", stem) or "Docs: README.md, docs/.")
    return "\n".join(out).rstrip() + "\n"


def print_recipe_help(recipe_file: str, **kwargs) -> None:
    """Print :func:`recipe_help` on stdout (arguments as there)."""
    print(recipe_help(recipe_file, **kwargs), end="", flush=True)
