"""benchmarks/place_outcomes.py: the tilt of a resting block, the rank correlation, the place rows, bad arguments."""

from __future__ import annotations

import math

import numpy as np
import pytest

from benchmark_loader import load_benchmark


def rotation(axis: str, degrees: float) -> np.ndarray:
    c, s = math.cos(math.radians(degrees)), math.sin(math.radians(degrees))
    return {"x": np.array([[1, 0, 0], [0, c, -s], [0, s, c]]), "y": np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]]),
            "z": np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])}[axis]


def test_tilt_is_the_angle_to_the_nearest_face_down_pose():
    bench = load_benchmark("place_outcomes")
    assert bench.tilt_degrees(np.eye(3)) == pytest.approx(0.0, abs=1e-6)
    assert bench.tilt_degrees(rotation("z", 70.0)) == pytest.approx(0.0, abs=1e-6)  # yaw is not tilt
    assert bench.tilt_degrees(rotation("x", 90.0)) == pytest.approx(0.0, abs=1e-6)  # on another face: not tilted
    assert bench.tilt_degrees(rotation("x", 30.0) @ rotation("z", 50.0)) == pytest.approx(30.0, abs=1e-4)
    assert bench.tilt_degrees(rotation("y", 60.0)) == pytest.approx(30.0, abs=1e-4)  # 60 off z, 30 off x
    stacked = np.stack([np.eye(3), rotation("y", 20.0)])
    assert bench.tilt_degrees(stacked) == pytest.approx([0.0, 20.0], abs=1e-4)


def test_rank_correlation_is_spearmans_with_ties_and_nan_for_constants():
    bench = load_benchmark("place_outcomes")
    x = np.array([0.05, 0.02, 0.09, 0.04])
    assert bench.rank_correlation(x, x ** 3) == pytest.approx(1.0)
    assert bench.rank_correlation(x, -x) == pytest.approx(-1.0)
    assert math.isnan(bench.rank_correlation(x, np.ones(4)))
    assert math.isnan(bench.rank_correlation(x[:1], x[:1]))
    # ties get their average rank: ranks (0.5, 0.5, 2) against (0, 1, 2)
    expect = np.corrcoef([0.5, 0.5, 2.0], [0.0, 1.0, 2.0])[0, 1]
    assert bench.rank_correlation(np.array([1.0, 1.0, 3.0]), np.array([1.0, 2.0, 3.0])) == pytest.approx(expect)


def block(in_bin=True, tilt=0.0, height=0.04, lying=0.04):
    return {"in_bin": in_bin, "tilt": tilt, "height": height, "lying": lying}


def test_place_rows_keep_only_places_into_the_bin_and_read_the_rest_pose():
    bench = load_benchmark("place_outcomes")
    snapshots = [
        {"held": None, "step": 0, "blocks": {1: block(in_bin=False), 2: block(in_bin=False)}},  # a pick
        {"held": 1, "step": 1, "blocks": {1: block(in_bin=False, tilt=15.0), 2: block(in_bin=False)}},  # place 1
        {"held": None, "step": 2, "blocks": {1: block(tilt=25.0, height=0.09), 2: block(in_bin=False)}},
        {"held": 2, "step": 3, "blocks": {1: block(tilt=25.0, height=0.09), 2: block(in_bin=False)}},  # place 2: misses
        {"held": None, "step": 4, "blocks": {1: block(tilt=25.0, height=0.09), 2: block(in_bin=False, height=0.043)}},
    ]
    rows = bench.place_rows(snapshots, tilt=10.0)
    assert rows == [{"tilted": True, "raised": True, "tilted_in_hand": True, "step": 1}]
    snapshots[2]["blocks"][1] = block(tilt=5.0, height=0.045)  # level, within the 6 mm slack
    snapshots[1]["blocks"][1] = block(in_bin=False, tilt=5.0)
    assert bench.place_rows(snapshots, tilt=10.0) == [
        {"tilted": False, "raised": False, "tilted_in_hand": False, "step": 1}]


@pytest.mark.parametrize("argv, message", [
    (["--episodes", "0"], "--episodes must be >= 1, got 0"),
    (["--tilt", "90"], "--tilt must be in (0, 90) degrees, got 90.0"),
    (["--planner", "name"], "--planner takes KEY=VALUE items, got 'name'"),
])
def test_place_outcomes_refuses_bad_arguments_in_one_line(argv, message, capsys):
    bench = load_benchmark("place_outcomes")
    with pytest.raises(SystemExit):
        bench.parse_args(["run/checkpoint.pt", *argv])
    assert message in capsys.readouterr().err


def test_planner_settings_are_read_as_numbers_and_flags():
    bench = load_benchmark("place_outcomes")
    args = bench.parse_args(["c.pt", "--planner", "uncertainty_penalty=0.25", "name=tree", "depth=2",
                             "empty_picks_last=true"])
    assert args.planner == {"uncertainty_penalty": 0.25, "name": "tree", "depth": 2, "empty_picks_last": True}


def test_place_outcomes_refuses_a_missing_checkpoint_in_one_line(tmp_path, capsys):
    bench = load_benchmark("place_outcomes")
    with pytest.raises(SystemExit) as exit_info:
        bench.main([str(tmp_path / "nowhere" / "checkpoint.pt"), "--episodes", "1"])
    message = str(exit_info.value)
    assert message.startswith("error: ") and "nowhere" in message and "\n" not in message
    assert not any(tmp_path.iterdir())  # nothing written
