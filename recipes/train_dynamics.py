"""Train the dynamics model (LDM(64) | LDM(128) | Naive) on noisy expert transitions; report L1 and SR.

    python recipes/train_dynamics.py                                   # default: block stacking, LDM(64), lite
    python recipes/train_dynamics.py model=naive dynamics.iterations=1000
    python recipes/train_dynamics.py dynamics.data=demos/block_stacking model.preset=paper device=cuda
    python recipes/train_dynamics.py -m experiment=table1_block_stacking model=ldm64,ldm128,naive seed=0,1,2
    python recipes/train_dynamics.py resume=true hydra.run.dir=outputs/2025-01-01/12-00-00   # continue a run

Writes to the Hydra run directory: the logger's scalars (``logger=csv`` default: train_dynamics/scalars/dynamics/*.csv,
one per metric, read with ``ldm_rl.run.outputs.read_scalars``; tensorboard | wandb | mlflow | none, docs/logging.md),
checkpoint.pt (every dynamics.checkpoint_every iterations, at the end, and on SIGINT/SIGTERM), final_metrics.json,
curve.csv (one line per evaluation: SR overall / picks / places, L1, the floors; ldm_rl/reports/plot_sample_efficiency.py),
sr_vs_iteration.png, predictions.png (before | predicted | true | |error|), config_resolved.yaml and train_dynamics.log
(what the console showed). Progress: a bar with ETA on a terminal, else a plain line every 10 % or 30 s.

Resume: ``resume=true hydra.run.dir=<the run's folder>`` replays the run's own overrides (from its
``.hydra/overrides.yaml``) and continues from its checkpoint; the result equals an uninterrupted run's
bit for bit. A sweep resumes by rerunning its command with ``resume=true`` (each job continues its own
folder). Loading a trained model: ``ldm_rl.world_model.factory.load_dynamics_checkpoint(path)``.
"""

from __future__ import annotations

import json
import logging
import os
import sys
import time

import hydra
from omegaconf import DictConfig, OmegaConf

from ldm_rl.config_schema import ConfigError, TrainDynamicsConfig, config_differences, validate_config  # registers the schema
from ldm_rl.run.cli import check_command_line

CHECKPOINT = "checkpoint.pt"
log = logging.getLogger("train_dynamics")


def load_transitions(cfg: DictConfig):
    """The demo TensorDict: ``cfg.dynamics.data`` (verified by ``load_demos``) if set, else
    ``num_demo_steps`` noisy expert steps collected now with the ``cfg.demos`` noise/procedure."""
    if cfg.dynamics.data:
        from ldm_rl.data.demos import load_demos

        return load_demos(hydra.utils.to_absolute_path(str(cfg.dynamics.data)))
    from ldm_rl.data.demos import collect_demos

    demos = cfg.demos  # the noise and procedure of recipes/generate_demos.py
    log.info("collecting %d noisy expert transitions on %s (%d objects)", int(cfg.dynamics.num_demo_steps), cfg.env.id,
             int(cfg.env.num_objects))
    return collect_demos(
        OmegaConf.to_container(cfg.env, resolve=True),
        num_steps=int(cfg.dynamics.num_demo_steps),
        seed=int(cfg.seed),
        procedure=demos.procedure,
        noise=OmegaConf.to_container(demos.noise, resolve=True),
        progress=bool(demos.progress),
    )


def _env_choice() -> str:
    from hydra.core.hydra_config import HydraConfig

    try:
        return str(HydraConfig.get().runtime.choices.get("env"))
    except ValueError:
        return "unknown"


def _short(path) -> str:
    rel = os.path.relpath(path)
    return path if rel.startswith("..") else rel


def resume_hint(out_dir) -> str:
    """The command that continues this run."""
    from hydra.core.hydra_config import HydraConfig
    from hydra.types import RunMode

    try:
        multirun = HydraConfig.get().mode == RunMode.MULTIRUN
    except ValueError:
        multirun = False
    if multirun:
        return "rerun the sweep's command with resume=true (same hydra.sweep.dir)"
    return f"python {_short(os.path.abspath(__file__))} resume=true hydra.run.dir={_short(str(out_dir))}"


@hydra.main(version_base="1.3", config_path="../conf", config_name="train_dynamics")
def main(cfg: DictConfig) -> dict:
    from ldm_rl.run.checkpoint import CheckpointError
    from ldm_rl.run.signals import RunStopped
    from ldm_rl.data.demos import DemoDataError
    from ldm_rl.run.outputs import MissingExtraError, hydra_output_dir

    try:
        return train(cfg)
    except RunStopped as stopped:
        print(f"{stopped}; resume with: {resume_hint(hydra_output_dir())}", file=sys.stderr, flush=True)
        raise SystemExit(stopped.exit_code) from None
    except (ConfigError, CheckpointError, DemoDataError, MissingExtraError) as err:
        print(f"error: {err}", file=sys.stderr, flush=True)
        raise SystemExit(2) from None
    except KeyboardInterrupt:
        print(f"interrupted by SIGINT; the last checkpoint, if any, is in {_short(str(hydra_output_dir()))}", file=sys.stderr,
              flush=True)
        raise SystemExit(130) from None


def train(cfg: DictConfig) -> dict:
    """The run (``main`` without the one-line error reporting)."""
    from ldm_rl.run.checkpoint import clean_stale_temporaries, read_checkpoint_meta
    from ldm_rl.run.outputs import hydra_output_dir

    validate_config(cfg, TrainDynamicsConfig)  # the command line was checked before Hydra started; this covers each job of a sweep
    out_dir = hydra_output_dir()
    config = OmegaConf.to_container(cfg, resolve=True)
    removed = clean_stale_temporaries(out_dir)
    if removed:
        log.info(f"removed {len(removed)} temporary file(s) left by an interrupted save: {', '.join(p.name for p in removed)}")
    checkpoint_path = out_dir / CHECKPOINT
    resuming = checkpoint_path.is_file()
    if resuming:
        meta = read_checkpoint_meta(checkpoint_path)
        if not cfg.resume:
            raise ConfigError(f"{out_dir} already holds a run's checkpoint (iteration {meta.get('iteration')}/"
                              f"{meta.get('iterations')}): continue it with resume=true, or choose another output folder")
        diffs = config_differences(meta.get("config", {}), config, schema=TrainDynamicsConfig)
        if diffs:
            raise ConfigError(f"resume=true: this command's config differs from the run's in {checkpoint_path}: "
                              f"{'; '.join(diffs[:6])} (a resumed run keeps its config)")
    elif cfg.resume:
        log.info(f"resume=true: no checkpoint in {_short(str(out_dir))} yet; starting from iteration 0")

    import numpy as np
    import torch

    import ldm_rl
    from ldm_rl.run.checkpoint import CheckpointError, capture_rng_state, load_checkpoint, restore_rng_state, save_checkpoint
    from ldm_rl.run.signals import RunStopped, StopSignals
    from ldm_rl.world_model.metrics import MetricSettings
    from ldm_rl.objectives import LDMLoss
    from ldm_rl.plots import PlotDependencyError, plot_success_rate
    from ldm_rl.run.progress import progress_bar
    from ldm_rl.run.outputs import atomic_write_text, close_logger, make_logger, save_resolved_config
    from ldm_rl.torch_utils import make_adam, resolve_device, seed_everything, set_threads
    from ldm_rl.world_model import build_dynamics_model, count_parameters
    from ldm_rl.world_model.training import (CURVE_NAME, REQUIRED_KEYS, PrimitiveBalancedSampler, data_fingerprint,
                                             dynamics_update, evaluate, load_loss_state, loss_own_state, model_label,
                                             prediction_grid, split_transitions, write_curve)

    set_threads(cfg.threads)
    seed_everything(int(cfg.seed))
    device = resolve_device(cfg.device)
    save_resolved_config(cfg, out_dir)
    logger = make_logger(cfg.logger, out_dir, config=config)  # before the demos: a missing package fails at once
    data = load_transitions(cfg)
    missing = [key for key in REQUIRED_KEYS if key not in data.keys(include_nested=True)]
    if missing:
        from ldm_rl.data.demos import DemoDataError

        raise DemoDataError(f"demo data lacks keys {missing}; see the data contract in ldm_rl/data/demos.py")
    data_meta = data.get_non_tensor("metadata") if "metadata" in data.keys() else None
    if isinstance(data_meta, dict) and data_meta.get("env_id") not in (None, cfg.env.id):
        raise ConfigError(f"dynamics.data holds {data_meta['env_id']} demos but env.id={cfg.env.id}; pick the matching "
                          "env/experiment")
    fingerprint = data_fingerprint(data)
    checkpoint = None
    if resuming:
        checkpoint = load_checkpoint(checkpoint_path, expect={"kind": "dynamics", "preset": str(cfg.model.preset),
                                                              "task": str(cfg.env.id)}, map_location=device)
        if checkpoint.meta.get("data_sha256") != fingerprint:
            raise CheckpointError(f"checkpoint {checkpoint_path}: the run trained on other transitions than this command "
                                  f"loads (data SHA-256 {str(checkpoint.meta.get('data_sha256'))[:12]}… vs "
                                  f"{fingerprint[:12]}…): the demos changed since the run started")
    max_height = float(cfg.env.max_height)
    data = data.to(device)
    train_set, val = split_transitions(data, float(cfg.dynamics.val_fraction), int(cfg.seed))
    model = build_dynamics_model(cfg.model, max_height).to(device)
    class_weights = cfg.loss.class_weights
    if class_weights is not None and not isinstance(class_weights, str):
        class_weights = torch.tensor(list(class_weights), dtype=torch.float32)
    loss = LDMLoss(model, gamma=float(cfg.loss.gamma), class_weights=class_weights,
                   label_smoothing=float(cfg.loss.label_smoothing),
                   gripper_symmetries=bool(cfg.loss.get("gripper_symmetries", False))).to(device)
    settings = MetricSettings(max_height=max_height, num_classes=model.num_classes, num_rotations=model.num_rotations,
                              **OmegaConf.to_container(cfg.dynamics.metrics))
    label, task = model_label(cfg.model), _env_choice()
    d = cfg.dynamics
    where = f", resuming at iteration {checkpoint.meta['iteration']}/{d.iterations}" if checkpoint else ""
    log.info(f"{label} ({cfg.model.preset}, {count_parameters(model):,} params) on {task}: "
             f"{train_set.shape[0]} train / {val.shape[0]} held-out transitions, device {device}, "
             f"{torch.get_num_threads()} thread(s){where}")
    meta = {"kind": "dynamics", "preset": str(cfg.model.preset), "task": str(cfg.env.id), "model": label,
            "seed": int(cfg.seed), "data_sha256": fingerprint, "config": config, "max_height": max_height,
            "threads": torch.get_num_threads(), "device": str(device), "torch": torch.__version__,
            "ldm_rl": ldm_rl.__version__}
    # the loop, in view: balanced minibatches -> one LDM step -> held-out evaluation -> checkpoint
    optimizer = make_adam(loss.parameters(), lr=float(d.lr), weight_decay=float(d.weight_decay))
    scheduler = torch.optim.lr_scheduler.StepLR(optimizer, step_size=int(d.lr_decay_every), gamma=float(d.lr_decay))
    sampler = PrimitiveBalancedSampler(train_set["holding"], int(d.batch_size), int(cfg.seed))
    iterations = int(d.iterations)
    rows: list[dict] = []  # one per evaluation (curve.csv)
    running: list[float] = []  # the training losses since the last evaluation
    done, elapsed_before = 0, 0.0
    if checkpoint is not None:
        state = checkpoint.state
        done = int(state["iteration"])
        if not 0 <= done <= iterations:
            raise ConfigError(f"resume: the checkpoint is at iteration {done}, outside [0, dynamics.iterations={iterations}]")
        load_loss_state(loss, model, state["model"], state["loss"])
        optimizer.load_state_dict(state["optimizer"])
        scheduler.load_state_dict(state["scheduler"])
        rows, running = [dict(r) for r in state["rows"]], [float(x) for x in state["running"]]
        elapsed_before = float(state["elapsed_s"])
        restore_rng_state(state["rng"], {"sampler": sampler.generator})
    start = time.perf_counter()

    def elapsed() -> float:
        return elapsed_before + time.perf_counter() - start

    def save(iteration: int) -> None:
        state = {"model": model.state_dict(), "loss": loss_own_state(loss, model), "optimizer": optimizer.state_dict(),
                 "scheduler": scheduler.state_dict(), "rng": capture_rng_state({"sampler": sampler.generator}),
                 "iteration": iteration, "rows": rows, "running": running, "elapsed_s": elapsed()}
        with stop.saving():
            save_checkpoint(checkpoint_path, state, meta={**meta, "iteration": iteration, "iterations": iterations,
                                                          "complete": iteration == iterations,
                                                          "metrics": rows[-1] if rows else None})

    loss.train()
    bar = progress_bar(total=iterations, initial=done, desc="train dynamics", unit="it", enabled=True)
    with StopSignals("the current iteration") as stop:
        for iteration in range(done + 1, iterations + 1):
            out = dynamics_update(loss, optimizer, train_set[sampler.sample()], autocast=d.get("autocast"))
            scheduler.step()
            running.append(out["loss_dynamics"].item())
            bar.update(1)
            if iteration % int(d.eval_every) == 0 or iteration == iterations:
                row = {"iteration": iteration, "loss": float(np.mean(running)), "lr": scheduler.get_last_lr()[0],
                       **evaluate(model, val, settings, int(d.eval_batch_size)), "elapsed_s": elapsed()}
                running = []
                rows.append(row)
                write_curve(rows, out_dir / CURVE_NAME)
                if logger is not None:
                    scalars = {f"dynamics/{k}": v for k, v in row.items() if k != "iteration" and isinstance(v, (int, float))}
                    scalars["dynamics/iterations_per_s"] = (iteration - done) / max(time.perf_counter() - start, 1e-9)
                    logger.log_metrics(scalars, step=iteration)
                bar.set_postfix(loss=f"{row['loss']:.4f}", SR=f"{100 * row['sr']:.1f}%", refresh=False)
                log.info(f"[{iteration:>6}/{iterations}] loss {row['loss']:.4f}  L1 {row['l1_mm']:.2f} mm "
                         f"(B_a {row['l1_region_mm']:.2f} mm)  SR {100 * row['sr']:.1f}% "
                         f"(pick {100 * row['sr_pick']:.1f}%, place {100 * row['sr_place']:.1f}%)  {row['elapsed_s']:.0f}s")
            saved = iteration == iterations or (int(d.checkpoint_every) and iteration % int(d.checkpoint_every) == 0)
            if saved:
                save(iteration)
            if stop.requested and iteration < iterations:
                if not saved:
                    save(iteration)
                bar.close()
                raise RunStopped(stop.signal_name or "SIGTERM", iteration, iterations, checkpoint_path)
    bar.close()
    final = rows[-1]
    try:
        plot_success_rate(rows, out_dir / "sr_vs_iteration.png")
        prediction_grid(model, val, out_dir / "predictions.png", int(d.grid_samples), settings)
    except PlotDependencyError as err:
        log.warning(f"{err}: skipping sr_vs_iteration.png and predictions.png")
    close_logger(logger)
    summary = {"task": task, "model": label, "preset": str(cfg.model.preset), "seed": int(cfg.seed),
               "train_transitions": int(train_set.shape[0]), "val_transitions": int(val.shape[0]), **final}
    atomic_write_text(out_dir / "final_metrics.json", json.dumps(summary, indent=2))
    from ldm_rl.world_model.metrics import format_report

    log.info(f"done: SR {100 * final['sr']:.1f}% (floor {100 * final.get('floor_sr', float('nan')):.1f}%)  "
             f"L1 {final['l1_mm']:.2f} mm per pixel -> {out_dir}\n{format_report(final, settings.iou_threshold)}"
             f"{sr_verdict(final, int(cfg.dynamics.iterations))}")
    return summary


def sr_verdict(final: dict, iterations: int) -> str:
    """A last line saying what an SR near its floor (the model that copies its input) means, or ''."""
    floor = final.get("floor_sr")
    if floor is None or final["sr"] - floor >= 0.05:
        return ""
    return (f"\nSR is within 5 points of its floor after {iterations} iterations: expected for a short run (the "
            "2-minute default trains 300); the Table 1 protocol trains 5000 (experiment=table1_<task>, docs/dynamics.md)")


if __name__ == "__main__":
    sys.argv = check_command_line(__file__, config_name="train_dynamics", checkpoint_name=CHECKPOINT)
    main()
