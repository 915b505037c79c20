"""Generate scripted-expert demonstrations for ``cfg.env`` and save them to ``cfg.demos.out``.

    python recipes/generate_demos.py env=house_building demos.num_steps=5000
    python recipes/generate_demos.py env=bottle_arrangement env.num_objects=4 demos.num_steps=null demos.num_episodes=100 \\
        demos.noise.position=0 demos.noise.random_action_prob=0 demos.out=data/bottles4_expert

Exactly one of ``demos.num_steps`` / ``demos.num_episodes`` (the other null): both set is rejected before
anything runs. The folder is written atomically in the verified format of ``ldm_rl.data.demos``
(float32 heights: loading it gives the in-process data bit for bit). The run folder gets config_resolved.yaml and
generate_demos.log (what the console showed); ``demos.progress``: a bar with ETA on a terminal, else plain lines.
"""

from __future__ import annotations

import logging
import sys

import hydra
from omegaconf import DictConfig, OmegaConf

from ldm_rl.config_schema import DemosRunConfig, validate_config  # registers the schema
from ldm_rl.run.cli import check_command_line

log = logging.getLogger(__name__)


@hydra.main(version_base="1.3", config_path="../conf", config_name="generate_demos")
def main(cfg: DictConfig) -> None:
    from pathlib import Path

    from ldm_rl.data.demos import collect_demos, save_demos
    from ldm_rl.run.outputs import hydra_output_dir, save_resolved_config
    from ldm_rl.torch_utils import seed_everything, set_threads

    validate_config(cfg, DemosRunConfig)  # each job of a sweep; a single run was checked before Hydra started
    set_threads(cfg.threads)
    seed_everything(cfg.seed)
    demos = cfg.demos
    out = Path(hydra.utils.to_absolute_path(str(demos.out))) if demos.out else hydra_output_dir() / "demos"
    save_resolved_config(cfg, hydra_output_dir())
    budget = f"{demos.num_steps} steps" if demos.num_steps is not None else f"{demos.num_episodes} episodes"
    log.info("collecting %s of the %s expert on %s (%d objects)", budget, demos.procedure, cfg.env.id, int(cfg.env.num_objects))
    td = collect_demos(
        OmegaConf.to_container(cfg.env, resolve=True),
        num_steps=demos.num_steps,
        num_episodes=demos.num_episodes,
        seed=cfg.seed,
        procedure=demos.procedure,
        noise=OmegaConf.to_container(demos.noise, resolve=True),
        progress=demos.progress,
    )
    save_demos(td, out)
    meta = td.get_non_tensor("metadata")
    log.info("wrote %d transitions (%d episodes, expert success %.3f) to %s",
             td.batch_size[0], meta["num_episodes"], meta["success_rate"], out)


if __name__ == "__main__":
    sys.argv = check_command_line(__file__, config_name="generate_demos")
    main()
