"""Train the dynamics model (LDM(64) | LDM(128) | Naive) on noisy expert transitions; report L1 and SR.

    python recipes/train_dynamics.py                                   # default: block stacking, LDM(64), lite
    python recipes/train_dynamics.py model=naive dynamics.iterations=1000
    python recipes/train_dynamics.py dynamics.data=demos/block_stacking model.preset=paper device=cuda
    python recipes/train_dynamics.py -m experiment=table1_block_stacking model=ldm64,ldm128,naive seed=0,1,2

Writes to the Hydra run directory: metrics.csv, the TorchRL logger's scalars, checkpoint.pt,
final_metrics.json, sr_vs_iteration.png and predictions.png (before | predicted | true | |error|).
"""

from __future__ import annotations

import json

import hydra
from omegaconf import DictConfig, OmegaConf


def load_transitions(cfg: DictConfig):
    """The demo TensorDict: ``cfg.dynamics.data`` if set, else ``num_demo_steps`` noisy expert steps
    collected now with the ``cfg.demos`` noise/procedure."""
    if cfg.dynamics.data:
        from ldm_rl.data.demos import load_demos

        return load_demos(hydra.utils.to_absolute_path(str(cfg.dynamics.data)))
    from ldm_rl.data.demos import collect_demos

    demos = cfg.demos  # the noise and procedure of recipes/generate_demos.py
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


@hydra.main(version_base="1.3", config_path="../conf", config_name="config")
def main(cfg: DictConfig) -> dict:
    import torch

    from ldm_rl.metrics import MetricSettings
    from ldm_rl.world_model import build_dynamics_model, count_parameters
    from ldm_rl.objectives import LDMLoss
    from ldm_rl.runtime import atomic_write_text, hydra_output_dir, make_logger, resolve_device, seed_everything, set_threads
    from ldm_rl.world_model.training import REQUIRED_KEYS, model_label, split_transitions, train_dynamics

    set_threads(cfg.threads)
    seed_everything(int(cfg.seed))
    device = resolve_device(cfg.device)
    out_dir = hydra_output_dir()
    data = load_transitions(cfg)
    missing = [key for key in REQUIRED_KEYS if key not in data.keys(include_nested=True)]
    if missing:
        raise ValueError(f"demo data lacks keys {missing}; see the data contract in DESIGN.md")
    meta = data.get_non_tensor("metadata") if "metadata" in data.keys() else None
    if isinstance(meta, dict) and meta.get("env_id") not in (None, cfg.env.id):
        raise ValueError(f"dynamics.data holds {meta['env_id']} demos but env={cfg.env.id}; pick the matching env/experiment")
    max_height = float(cfg.env.max_height)
    data = data.to(device)
    train, val = split_transitions(data, float(cfg.dynamics.val_fraction), int(cfg.seed))
    model = build_dynamics_model(cfg.model, max_height).to(device)
    class_weights = cfg.loss.class_weights
    if class_weights is not None and not isinstance(class_weights, str):
        class_weights = torch.tensor(list(class_weights), dtype=torch.float32)
    loss = LDMLoss(model, gamma=float(cfg.loss.gamma), class_weights=class_weights,
                   label_smoothing=float(cfg.loss.label_smoothing)).to(device)
    settings = MetricSettings(max_height=max_height, num_classes=model.num_classes, num_rotations=model.num_rotations,
                              **OmegaConf.to_container(cfg.dynamics.metrics))
    label, task = model_label(cfg.model), _env_choice()
    print(f"{label} ({cfg.model.preset}, {count_parameters(model):,} params) on {task}: "
          f"{train.shape[0]} train / {val.shape[0]} held-out transitions, device {device}", flush=True)
    d = cfg.dynamics
    final = train_dynamics(
        model, loss, train, val, out_dir=out_dir, settings=settings, iterations=int(d.iterations),
        batch_size=int(d.batch_size), lr=float(d.lr), lr_decay=float(d.lr_decay), lr_decay_every=int(d.lr_decay_every),
        weight_decay=float(d.weight_decay), eval_every=int(d.eval_every), eval_batch_size=int(d.eval_batch_size),
        grid_samples=int(d.grid_samples), logger=make_logger(cfg.logger, out_dir), seed=int(cfg.seed),
        autocast=d.get("autocast"),
        extra_checkpoint={"config": OmegaConf.to_container(cfg, resolve=True), "max_height": max_height},
    )
    summary = {"task": task, "model": label, "preset": str(cfg.model.preset), "seed": int(cfg.seed),
               "train_transitions": int(train.shape[0]), "val_transitions": int(val.shape[0]), **final}
    atomic_write_text(out_dir / "final_metrics.json", json.dumps(summary, indent=2))
    print(f"done: SR {100 * final['sr']:.1f}%  L1 {final['l1_mm']:.2f} mm -> {out_dir}")
    return summary


if __name__ == "__main__":
    main()
