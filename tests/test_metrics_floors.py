"""The SR's trivial floors (majority pick outcome, no change) and the place SR at several IoU thresholds,
as properties on seeded synthetic transitions, plus their path to evaluate() and aggregate_table1.py."""

import json
import subprocess
import sys
from pathlib import Path

import pytest
import torch
from tensordict import TensorDict

from ldm_rl.world_model.metrics import (MetricSettings, floor_transition_metrics, format_report, summarize,
                                        summarize_floors, transition_metrics)

MAX_HEIGHT, K = 0.15, 21
STEP = MAX_HEIGHT / (K - 1)  # metres per depth class
SETTINGS = MetricSettings(max_height=MAX_HEIGHT, num_classes=K)


def squares(rows: torch.Tensor, cols: torch.Tensor, side: int | torch.Tensor, size: int = 128) -> torch.Tensor:
    """[N] top-left corners -> [N,1,size,size] bool masks of side×side squares (no loop over samples)."""
    r = torch.arange(size).view(1, size, 1)
    c = torch.arange(size).view(1, 1, size)
    side = torch.as_tensor(side).reshape(-1, 1, 1)
    rows, cols = rows.view(-1, 1, 1), cols.view(-1, 1, 1)
    return ((r >= rows) & (r < rows + side) & (c >= cols) & (c < cols + side)).unsqueeze(1)


def dataset(n: int, seed: int, *, success: float = 0.9, place_changes: bool = True) -> TensorDict:
    """n transitions, picks and places alternating at random; heights on the class grid (+ sub-class noise).

    Picks succeed with probability ``success``; a place adds a 10×10 block (class 4) at a random spot
    unless ``place_changes`` is False (then its next heightmap only gets sub-class noise).
    """
    g = torch.Generator().manual_seed(seed)
    rand = lambda *shape: torch.rand(*shape, generator=g)  # noqa: E731
    holding = rand(n) < 0.5
    base = squares(torch.randint(0, 100, (n,), generator=g), torch.randint(0, 100, (n,), generator=g), 16).float()
    before = base * STEP * torch.randint(1, 8, (n, 1, 1, 1), generator=g) + (rand(n, 1, 128, 128) - 0.5) * 0.4 * STEP
    block = squares(torch.randint(0, 110, (n,), generator=g), torch.randint(0, 110, (n,), generator=g), 10).float() * 4 * STEP
    noise = (rand(n, 1, 128, 128) - 0.5) * 0.4 * STEP  # both |noises| < 0.2 class: no class boundary is crossed
    place_next = before + noise + (block if place_changes else 0.0)
    pick_next = before - base * STEP  # the picked object's top layer goes
    next_heightmap = torch.where(holding.view(n, 1, 1, 1), place_next, pick_next)
    next_holding = torch.where(holding, torch.zeros(n, dtype=torch.bool), rand(n) < success)
    action = torch.stack((torch.randint(0, 128, (n,), generator=g), torch.randint(0, 128, (n,), generator=g),
                          torch.randint(0, 8, (n,), generator=g)), -1)
    return TensorDict({"heightmap": before, "in_hand": torch.zeros(n, 1, 24, 24), "holding": holding.unsqueeze(-1),
                       "action": action, "next": {"heightmap": next_heightmap, "holding": next_holding.unsqueeze(-1)}},
                      batch_size=[n])


def floors(data: TensorDict, settings: MetricSettings = SETTINGS) -> dict:
    return summarize_floors(floor_transition_metrics(data, settings))


def scores(data: TensorDict, pred_heightmap: torch.Tensor, pred_holding: torch.Tensor) -> dict:
    return summarize(transition_metrics(pred_heightmap, pred_holding, data, SETTINGS), SETTINGS)


@pytest.mark.parametrize("seed", range(4))
def test_no_change_floor_is_100_percent_when_places_change_nothing(seed):
    data = dataset(64, seed, success=1.0, place_changes=False)
    f = floors(data)
    assert f["floor_sr_place"] == 1.0 and f["floor_sr_pick"] == 1.0 and f["floor_sr"] == 1.0
    changed = floors(dataset(64, seed, success=1.0, place_changes=True))
    assert changed["floor_sr_place"] == 0.0  # every place adds a block: "no change" is always wrong
    assert changed["floor_sr"] == pytest.approx(changed["n_pick"] / 64)


@pytest.mark.parametrize("seed, success", [(0, 0.97), (1, 0.8), (2, 0.3), (3, 0.5), (4, 0.0)])
def test_majority_floor_equals_the_majority_fraction(seed, success):
    data = dataset(200, seed, success=success)
    f = floors(data)
    picks = ~data["holding"].reshape(-1)
    q = data["next", "holding"].reshape(-1)[picks].float().mean().item()
    assert f["floor_sr_pick"] == pytest.approx(max(q, 1 - q))
    assert f["floor_pick_majority_success"] == (1.0 if q >= 0.5 else 0.0)
    assert f["n_pick"] == int(picks.sum()) and f["n_pick"] + f["n_place"] == 200


@pytest.mark.parametrize("seed", range(3))
def test_floors_equal_the_metric_applied_to_the_literal_no_change_model(seed):
    data = dataset(96, seed, success=0.7)
    f = floors(data)
    majority = torch.full((96, 1), bool(f["floor_pick_majority_success"]))
    s = scores(data, data["heightmap"], majority)
    assert (s["sr"], s["sr_pick"], s["sr_place"]) == pytest.approx((f["floor_sr"], f["floor_sr_pick"], f["floor_sr_place"]))
    assert s["l1_mm"] == pytest.approx(f["floor_l1_mm"]) and s["l1_region_mm"] == pytest.approx(f["floor_l1_region_mm"])
    assert f["floor_l1_mm"] > 0


@pytest.mark.parametrize("seed", range(3))
def test_a_perfect_predictor_scores_at_least_every_floor(seed):
    data = dataset(80, seed, success=0.9)
    f, s = floors(data), scores(data, data["next", "heightmap"], data["next", "holding"])
    assert s["sr"] == s["sr_pick"] == s["sr_place"] == 1.0
    assert all(s[k] == 1.0 for k in ("sr_place_iou50", "sr_place_iou75", "sr_place_iou90"))
    assert all(s[k] >= f[k.replace("sr", "floor_sr", 1)] for k in ("sr", "sr_pick", "sr_place"))
    assert s["l1_mm"] == 0.0 <= f["floor_l1_mm"]


def test_place_sr_at_iou_thresholds_is_exact_and_monotone():
    """Five places, each adding a 10×10 block; the prediction shifts it by k = 0..4 columns, so the
    footprint IoU is (10 − k)/(10 + k) = 1, 0.82, 0.67, 0.54, 0.43."""
    n = 5
    rows, cols = torch.full((n,), 40), torch.full((n,), 40)
    before = torch.zeros(n, 1, 128, 128)
    true_next = squares(rows, cols, 10).float() * 4 * STEP
    pred = squares(rows, cols + torch.arange(n), 10).float() * 4 * STEP
    data = TensorDict({"heightmap": before, "holding": torch.ones(n, 1, dtype=torch.bool),
                       "action": torch.tensor([[45, 45, 0]] * n),
                       "next": {"heightmap": true_next, "holding": torch.zeros(n, 1, dtype=torch.bool)}}, batch_size=[n])
    s = scores(data, pred, torch.zeros(n, 1, dtype=torch.bool))
    assert (s["sr_place_iou50"], s["sr_place_iou75"], s["sr_place_iou90"]) == pytest.approx((4 / 5, 2 / 5, 1 / 5))
    assert s["sr_place"] == s["sr_place_iou75"] and s["sr_pick"] != s["sr_pick"]  # no picks: NaN


@pytest.mark.parametrize("seed", range(4))
def test_iou_thresholds_are_monotone_on_noisy_predictions(seed):
    data = dataset(120, seed)
    g = torch.Generator().manual_seed(100 + seed)
    true_next = data["next", "heightmap"]
    # a prediction that gets part of each change wrong: random pixels of the true change dropped
    keep = torch.rand(true_next.shape, generator=g) < torch.rand(120, 1, 1, 1, generator=g)
    pred = torch.where(keep, true_next, data["heightmap"])
    s = scores(data, pred, data["next", "holding"])
    assert s["sr_place_iou50"] >= s["sr_place_iou75"] >= s["sr_place_iou90"]
    assert s["sr_place_iou50"] > s["sr_place_iou90"]  # the thresholds matter on these predictions
    settings_90 = MetricSettings(max_height=MAX_HEIGHT, num_classes=K, iou_threshold=0.9)
    assert summarize(transition_metrics(pred, data["next", "holding"], data, settings_90))["sr_place"] == s["sr_place_iou90"]


def test_bad_iou_thresholds_fail_early():
    with pytest.raises(ValueError, match="in \\(0, 1\\]"):
        MetricSettings(max_height=MAX_HEIGHT, report_iou_thresholds=(0.5, 1.5))
    with pytest.raises(ValueError, match="differ"):
        MetricSettings(max_height=MAX_HEIGHT, report_iou_thresholds=(0.5, 0.501))


def test_evaluate_reports_floors_independent_of_the_batch_size():
    from dyn_helpers import tiny_model
    from ldm_rl.world_model.training import evaluate

    data = dataset(10, seed=7, success=0.8)
    model = tiny_model()
    small, whole = evaluate(model, data, SETTINGS, batch_size=3), evaluate(model, data, SETTINGS, batch_size=64)
    expected = floors(data)
    for key, value in expected.items():
        assert small[key] == pytest.approx(value) and whole[key] == pytest.approx(value), key
    assert {"sr", "sr_place_iou50", "sr_place_iou75", "sr_place_iou90"} <= small.keys()
    assert small["sr"] == pytest.approx(whole["sr"])
    text = format_report(small)
    assert "floor" in text and f"{100 * expected['floor_sr_pick']:.1f}%" in text and "IoU 0.9" in text


def _run_json(folder: Path, name: str, **values) -> None:
    run = folder / name
    run.mkdir(parents=True)
    (run / "final_metrics.json").write_text(json.dumps({"task": "block_stacking", "preset": "lite", "l1_mm": 0.2, **values}))


def test_aggregate_table1_shows_floors_once_per_held_out_set_and_the_iou_columns(tmp_path):
    shared = {"val_transitions": 200, "l1_region_mm": 0.8, "floor_sr_pick": 0.97, "floor_sr_place": 0.01,
              "floor_l1_mm": 0.5, "floor_l1_region_mm": 2.0, "sr_pick": 0.9, "sr_place_iou75": 0.5, "sr_place_iou90": 0.0}
    for seed, floor in ((0, 0.48), (1, 0.50)):  # two held-out sets, each shared by two models
        for model, sr in (("LDM(64)", 0.7 + seed / 10), ("Naive", 0.3)):
            _run_json(tmp_path, f"{model}-{seed}", model=model, seed=seed, sr=sr, floor_sr=floor, sr_place_iou50=0.9, **shared)
    _run_json(tmp_path, "old", model="LDM(128)", seed=0, sr=0.6)  # written before the floors existed
    out = tmp_path / "table.md"
    subprocess.run([sys.executable, "-m", "ldm_rl.reports.aggregate_table1", str(tmp_path), "--out", str(out)], check=True,
                   capture_output=True)
    text = out.read_text()
    assert "| LDM(64) | 75.0 ± 7.1 (n=2) [83.4] |" in text
    assert "| *floor (no change)* | 49.0 ± 1.4 (n=2) | – |" in text  # 2 held-out sets, not 4 runs
    assert "SR place @ IoU 0.5 | SR place @ IoU 0.75 | SR place @ IoU 0.9" in text
    assert ("| LDM(64) | 75.0 ± 7.1 (n=2) | 90.0 ± 0.0 (n=2) | 90.0 ± 0.0 (n=2) | 50.0 ± 0.0 (n=2) | 0.0 ± 0.0 (n=2) | "
            "0.20 ± 0.00 (n=2) | 0.80 ± 0.00 (n=2) |") in text
    assert ("| *floor* | 49.0 ± 1.4 (n=2) | 97.0 ± 0.0 (n=2) | 1.0 ± 0.0 (n=2) | 1.0 ± 0.0 (n=2) | 1.0 ± 0.0 (n=2) | "
            "0.50 ± 0.00 (n=2) | 2.00 ± 0.00 (n=2) |") in text
    assert "| LDM(128) | 60.0 (n=1) | – | – | – | – | 0.20 (n=1) | – |" in text  # one seed: no ± 0


def test_ldm_zero_shot_benchmark_reads_the_stack_level_at_the_action():
    """benchmarks/ldm_zero_shot.py: a place's level is the objects stacked at its pixel after it, a pick's before it,
    the highest pixel within ±2 px of the action over one object's height."""
    from benchmark_loader import load_benchmark

    bench = load_benchmark("ldm_zero_shot")
    before, after = torch.zeros(4, 1, 128, 128), torch.zeros(4, 1, 128, 128)
    before[0, :, 40:50, 40:50] = 0.08  # a pick on a 2-stack (lands 2 px outside the cube's edge: still read)
    after[1, :, 60:70, 60:70] = 0.16  # a place making a 4-stack
    before[1, :, 60:70, 60:70] = 0.12
    after[2, :, 10:20, 10:20] = 0.04  # a place that lands away from its pixel: the table there
    data = TensorDict({"heightmap": before, "holding": torch.tensor([[False], [True], [True], [False]]),
                       "action": torch.tensor([[51, 45, 0], [65, 65, 3], [100, 100, 0], [5, 5, 0]]),
                       "next": {"heightmap": after}}, batch_size=[4])
    assert bench.levels(data, 0.04).tolist() == [2, 4, 0, 0]
