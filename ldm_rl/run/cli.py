"""The recipes' command-line pre-flight: compose the command line as Hydra will, validate it against the
schema (:mod:`ldm_rl.config_schema`), check what it asks of this machine, replay a resumed run's overrides;
on any problem print ``error: ...`` (one line) and exit with code 2 before Hydra creates an output folder
and before torch is imported.

Importing this module is light: hydra and omegaconf only.
"""

from __future__ import annotations

import sys
from pathlib import Path
from omegaconf import DictConfig, OmegaConf

from ldm_rl.config_schema import HEIGHTMAP_PIXELS, SCHEMAS, ConfigError, EvaluateConfig, _omegaconf_line, config_differences, resume_overrides, validate_config
from ldm_rl.extras import MissingExtraError, require_equivariant_q, require_logger_backend

__all__ = ["check_command_line", "machine_problems"]


def machine_problems(cfg: DictConfig, *, checkpoint_kind: str | None = None) -> list[str]:
    """What a valid config asks of this machine and its files that they cannot give, found without torch: a
    logger package or e2cnn (``agent.q_architecture=equivariant``) that is not installed, a device without a
    driver, an ``evaluate.py`` checkpoint that is not an agent's (``checkpoint_kind="agent"``: the kind the config's ``checkpoint`` must hold). Checked by :func:`check_command_line` before a run starts (not by :func:`validate_config`: a
    config stays valid on another machine)."""
    from ldm_rl.run.checkpoint import CheckpointError, read_checkpoint_meta  # light: no torch

    found = []
    backend = OmegaConf.select(cfg, "logger.backend")
    if backend is not None:
        try:
            require_logger_backend(str(backend))
        except MissingExtraError as err:
            found.append(str(err))
    if OmegaConf.select(cfg, "agent.q_architecture") == "equivariant":
        try:
            require_equivariant_q()
        except MissingExtraError as err:
            found.append(str(err))
    device = OmegaConf.select(cfg, "device")
    problem = _device_problem(str(device)) if device is not None else None
    if problem:
        found.append(problem)
    if OmegaConf.select(cfg, "compile") is True:
        problem = _compile_problem(str(device))
        if problem:
            found.append(problem)
    checkpoint = OmegaConf.select(cfg, "checkpoint")
    if checkpoint_kind is not None and checkpoint is not None:
        try:
            meta = read_checkpoint_meta(checkpoint)
        except (CheckpointError, OSError) as err:
            return found + [f"checkpoint={checkpoint}: {err}"]
        kind = meta.get("kind")
        if kind != checkpoint_kind:
            found.append(f"checkpoint={checkpoint} holds a {kind or 'kindless'} checkpoint: this recipe reads an "
                         f"{checkpoint_kind}'s (a checkpoint.pt of recipes/train_policy.py)")
        else:
            found += _planner_problems(cfg, meta.get("config") or {})
    return found


def _planner_problems(cfg: DictConfig, trained: dict) -> list[str]:
    """``evaluate.py``'s ``planner.num_candidates`` against the checkpoint's Q map (rotations x pixels)."""
    num = OmegaConf.select(cfg, "planner.num_candidates")
    rotations = (trained.get("model") or {}).get("num_rotations") or (trained.get("env") or {}).get("num_rotations")
    if num is None or rotations is None:
        return []
    entries = int(rotations) * HEIGHTMAP_PIXELS**2
    if int(num) > entries:
        return [f"planner.num_candidates={num} is more than the checkpoint's Q map holds: at most {entries} "
                f"({rotations} rotations x {HEIGHTMAP_PIXELS}x{HEIGHTMAP_PIXELS} pixels)"]
    return []


def _compile_problem(device: str) -> str | None:
    """Why ``compile=true`` cannot run on ``device`` here, found without importing torch (None: it can)."""
    import os
    import shutil

    if device == "mps" or device.startswith("xpu"):
        return f"compile=true is not supported with device={device} (inductor here: cpu and cuda); use compile=false"
    if device in ("cpu", "auto"):
        cxx = os.environ.get("CXX", "g++")
        if shutil.which(cxx) is None:
            return (f"compile=true needs a C++ compiler for inductor on the CPU and {cxx} is not on PATH "
                    "(install g++ or set CXX); use compile=false")
    return None


def _device_problem(device: str) -> str | None:
    """A device this machine visibly cannot have, found without importing torch (the runtime checks the rest)."""
    import os
    import platform

    drivers = ("/dev/nvidiactl", "/proc/driver/nvidia/version", "/dev/kfd")  # NVIDIA, ROCm
    if str(device).startswith("cuda") and platform.system() == "Linux" and not any(os.path.exists(p) for p in drivers):
        return f"device={device}: this machine has no NVIDIA driver (no /dev/nvidiactl); use device=cpu or device=auto"
    if device == "mps" and platform.system() != "Darwin":
        return f"device=mps: Apple's MPS exists only on macOS, this is {platform.system()}; use device=cpu or device=auto"
    return None


class _Fail(Exception):
    pass


def _fail(message: str) -> None:
    raise _Fail(message)


def _resolved_task_config(cfg: DictConfig) -> dict:
    """The config a recipe's ``main`` sees (no ``hydra`` node), resolved as Hydra resolves it."""
    import copy

    from hydra.core.hydra_config import HydraConfig
    from omegaconf import open_dict, read_write

    HydraConfig.instance().set_config(cfg)
    task = copy.deepcopy(cfg)
    with read_write(task), open_dict(task):
        del task["hydra"]
    return OmegaConf.to_container(task, resolve=True)


def check_command_line(
    recipe_file: str,
    *,
    config_name: str,
    config_path: str = "../conf",
    argv: list[str] | None = None,
    checkpoint_name: str | None = None,
    schema: type | None = None,
) -> list[str]:
    """Compose and check a recipe's command line the way ``@hydra.main`` will, before it runs.

    Call as ``sys.argv = check_command_line(__file__, config_name="train_policy", checkpoint_name="checkpoint.pt")`` above
    ``main()``. ``checkpoint_name`` (resumable recipes) enables ``resume=true``:

    * ``resume=true hydra.run.dir=DIR`` continues the run in ``DIR``: the overrides stored in
      ``DIR/.hydra/overrides.yaml`` are put before the command's own, so the run's config is composed
      again; if ``DIR`` holds a checkpoint, the config must equal the checkpoint's (apart from
      ``resume``), else one error lists the differences.
    * without ``resume=true``, a ``hydra.run.dir`` that already holds a checkpoint is refused (it would
      be overwritten).

    Returns the argv to run (the given one, or with the replayed overrides). On a problem (composition,
    types, ranges, contradictions, resume) prints ``error: <one line>`` on stderr and exits with code 2;
    nothing is created. ``--help`` prints the recipe's own help (:mod:`ldm_rl.run.help`: what it does
    and writes, the groups it reads, every key) and exits 0; ``--hydra-help``, ``--info`` and friends pass
    through untouched. Multirun
    (``-m``) validates the values shared by every job here, and each job validates its own in ``main``.
    """
    argv = list(sys.argv if argv is None else argv)
    from hydra._internal.utils import get_args_parser

    args = get_args_parser().parse_args(argv[1:])  # bad flags: argparse's usage + exit 2, as Hydra would
    if args.help and not args.hydra_help:  # the recipe's own help (ldm_rl/run/help.py), then exit 0
        from ldm_rl.run.help import print_recipe_help

        try:
            print_recipe_help(recipe_file, config_path=args.config_path or config_path,
                              config_name=args.config_name or config_name, config_dir=args.config_dir,
                              overrides=args.overrides, checkpoint_name=checkpoint_name)
        except FileNotFoundError as err:
            print(f"error: {err}", file=sys.stderr, flush=True)
            raise SystemExit(2) from None
        raise SystemExit(0)
    if args.help or args.hydra_help or args.info or args.shell_completion or args.experimental_rerun:
        return argv
    try:
        return _check(recipe_file, argv, args, config_path, config_name, checkpoint_name, schema or SCHEMAS.get(args.config_name) or SCHEMAS[config_name])
    except _Fail as err:
        print(f"error: {err}", file=sys.stderr, flush=True)
        raise SystemExit(2) from None


def _check(recipe_file, argv, args, config_path, config_name, checkpoint_name, schema) -> list[str]:
    import os

    from hydra._internal.hydra import Hydra
    from hydra._internal.utils import create_automatic_config_search_path
    from hydra.core.global_hydra import GlobalHydra
    from hydra.core.override_parser.overrides_parser import OverridesParser
    from hydra.types import RunMode

    from ldm_rl.run.checkpoint import CheckpointError, read_checkpoint_meta

    recipe_file = os.path.abspath(recipe_file)
    stem = Path(recipe_file).stem
    config_name = args.config_name or config_name
    config_path = args.config_path or config_path
    multirun, show = bool(args.multirun), args.cfg is not None
    try:
        parsed = OverridesParser.create().parse_overrides(args.overrides)
    except Exception as err:
        _fail(_omegaconf_line(err))
    if checkpoint_name is None and any(o.key_or_group == "resume" for o in parsed):
        _fail(f"{' '.join(o.input_line for o in parsed if o.key_or_group == 'resume')}: {stem} has nothing to resume "
              "(it writes no checkpoint)")
    search_path = create_automatic_config_search_path(recipe_file, None, config_path)
    if args.config_dir is not None:
        from hydra.core.config_search_path import SearchPathQuery

        config_dir = os.path.abspath(args.config_dir)
        if not os.path.isdir(config_dir):
            _fail(f"--config-dir {config_dir}: no such folder")
        search_path.prepend(provider="command-line", path=f"file://{config_dir}", anchor=SearchPathQuery(provider="schema"))
    GlobalHydra.instance().clear()
    hydra = Hydra.create_main_hydra2(task_name=stem, config_search_path=search_path)

    def compose(overrides: list[str], where: str = "") -> DictConfig:
        try:
            return hydra.compose_config(config_name, overrides, run_mode=RunMode.MULTIRUN if multirun else RunMode.RUN)
        except Exception as err:
            _fail(_omegaconf_line(err) + where)

    try:
        cfg = compose(list(args.overrides))
        resume = cfg.get("resume") is True
        run_dir_given = any(o.key_or_group == "hydra.run.dir" for o in parsed)
        checkpoint = None
        if not multirun and not show and checkpoint_name is not None:
            run_dir = Path(str(cfg.hydra.run.dir)).absolute()
            checkpoint = run_dir / checkpoint_name
            if resume:
                if not run_dir_given:
                    _fail("resume=true continues a run in its folder: add hydra.run.dir=<the run's folder> (the stop message "
                          "prints the full command)")
                stored_file = run_dir / str(cfg.hydra.output_subdir or ".hydra") / "overrides.yaml"
                if not stored_file.is_file():
                    _fail(f"resume=true: {run_dir} is not a run folder ({stored_file.name} missing under "
                          f"{cfg.hydra.output_subdir}/); nothing to resume")
                stored = OmegaConf.to_container(OmegaConf.load(stored_file))
                keep = []
                for text in stored or []:
                    (o,) = OverridesParser.create().parse_overrides([text])
                    if o.key_or_group != "resume" and text not in args.overrides:
                        keep.append(text)
                argv = _splice(argv, list(args.overrides), keep + list(args.overrides))
                cfg = compose(keep + list(args.overrides), f" (replaying the run's overrides from {stored_file})")
            elif run_dir_given and checkpoint.is_file():
                try:
                    meta = read_checkpoint_meta(checkpoint)
                    if meta.get("iteration") is not None:
                        where = f" (iteration {meta['iteration']}/{meta.get('iterations')})"
                    elif meta.get("episodes") is not None:
                        where = f" (episode {meta['episodes']}, {meta.get('updates')} updates)"
                    else:
                        where = ""
                except CheckpointError:
                    where = ""
                _fail(f"{run_dir} already holds a run's checkpoint{where}: continue it with resume=true, or choose a new "
                      "hydra.run.dir")
        try:
            validate_config(cfg, schema)
        except ConfigError as err:
            _fail(str(err))
        if not show:
            problems = machine_problems(cfg, checkpoint_kind="agent" if issubclass(schema, EvaluateConfig) else None)
            if problems:
                _fail("; ".join(problems))
        if resume and checkpoint is not None and checkpoint.is_file():
            try:
                meta = read_checkpoint_meta(checkpoint)
            except CheckpointError as err:
                _fail(str(err))
            try:
                given = _resolved_task_config(cfg)
            except Exception as err:
                _fail(_omegaconf_line(err))
            ignore = ("resume", "device", *getattr(schema, "RESUME_MAY_CHANGE", ()))
            diffs = config_differences(meta.get("config", {}), given, ignore=ignore, schema=schema)
            if diffs:
                shown = "; ".join(diffs[:6]) + ("; ..." if len(diffs) > 6 else "")
                fix = resume_overrides(meta.get("config", {}), given, ignore=ignore, schema=schema)
                hint = f"; to resume it as it ran, add: {' '.join(fix)}" if fix and len(fix) == len(diffs) else ""
                _fail(f"resume=true: this command's config differs from the run's in {checkpoint}: {shown} (a resumed run "
                      f"keeps its config; start a new run to change it){hint}")
        return argv
    finally:
        GlobalHydra.instance().clear()


def _splice(argv: list[str], old: list[str], new: list[str]) -> list[str]:
    """argv with its block of overrides ``old`` (contiguous, as argparse requires) replaced by ``new``."""
    rest = argv[1:]
    n = len(old)
    for i in range(len(rest) - n + 1):
        if rest[i : i + n] == old:
            return [argv[0], *rest[:i], *new, *rest[i + n :]]
    return [argv[0], *[a for a in rest if a not in old], *new]  # pragma: no cover - argparse keeps them contiguous
