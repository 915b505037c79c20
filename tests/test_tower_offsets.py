"""benchmarks/tower_offsets.py: the tower under a cube, its level offsets, the upper part's centre, the place rows."""

from __future__ import annotations

import numpy as np
import pytest

from benchmark_loader import load_benchmark


def stack(*xy, z0=0.02, side=0.04):
    """Cube centres of one tower, bottom first, at the given horizontal positions (metres)."""
    return np.array([[x, y, z0 + i * side] for i, (x, y) in enumerate(xy)])


def test_the_tower_under_a_cube_is_read_bottom_first_and_skips_cubes_beside_it():
    bench = load_benchmark("tower_offsets")
    tower = stack((0.40, 0.00), (0.41, 0.00), (0.41, 0.012))
    beside = np.array([[0.50, 0.10, 0.02], [0.415, 0.03, 0.02]])  # on the floor: far away, and next to the base
    positions = np.concatenate([beside[:1], tower, beside[1:]])  # the tower's cubes at indices 1, 2, 3
    assert bench.tower_below(positions, 3) == [1, 2, 3]
    assert bench.tower_below(positions, 2) == [1, 2]
    assert bench.tower_below(positions, 0) == [0]
    # a cube resting on the floor beside the tower's second level is not under its top
    assert bench.tower_below(positions, 4) == [4]


def test_a_cube_more_than_one_side_away_or_at_the_wrong_height_is_not_below():
    bench = load_benchmark("tower_offsets")
    toppled = np.array([[0.40, 0.00, 0.02], [0.45, 0.00, 0.06]])  # 5 cm over: beyond the 4 cm cube
    assert bench.tower_below(toppled, 1) == [1]
    floating = np.array([[0.40, 0.00, 0.02], [0.40, 0.00, 0.09]])  # 7 cm up: not one side above
    assert bench.tower_below(floating, 1) == [1]


def test_level_offsets_and_the_upper_parts_centre_over_the_base():
    bench = load_benchmark("tower_offsets")
    positions = stack((0.40, 0.00), (0.41, 0.00), (0.42, 0.00), (0.42, 0.015))
    chain = [0, 1, 2, 3]
    assert bench.level_offsets(positions, chain) == pytest.approx([0.01, 0.01, 0.015])
    # the three upper cubes' mean xy (0.41667, 0.005) from the base (0.40, 0.00)
    assert bench.upper_centre_offset(positions, chain) == pytest.approx(np.hypot(1 / 60, 0.005))
    assert bench.upper_centre_offset(positions, [2]) == 0.0
    # offsets that alternate sides cancel in the upper part's centre
    zigzag = stack((0.40, 0.00), (0.41, 0.00), (0.40, 0.00))
    assert bench.upper_centre_offset(zigzag, [0, 1, 2]) == pytest.approx(0.005)


def test_place_rows_keep_places_onto_a_cube_and_read_the_tower_after_them():
    bench = load_benchmark("tower_offsets")
    floor = np.array([[0.40, 0.00, 0.02], [0.30, 0.10, 0.02], [0.30, -0.10, 0.02]])
    two = floor.copy()
    two[1] = [0.408, 0.006, 0.06]  # cube 1 placed on cube 0, 1 cm off
    dropped = two.copy()
    dropped[2] = [0.20, 0.00, 0.02]  # cube 2 placed on the floor
    snapshots = [
        {"held": None, "positions": floor},  # pick cube 1
        {"held": 1, "positions": floor},  # place it on cube 0
        {"held": None, "positions": two},  # pick cube 2
        {"held": 2, "positions": two},  # place it on the floor: no row
        {"held": None, "positions": dropped},
    ]
    rows = bench.place_rows(snapshots)
    assert len(rows) == 1
    assert rows[0]["height"] == 2
    assert rows[0]["offset"] == pytest.approx(0.01)
    assert rows[0]["upper"] == pytest.approx(0.01)


def test_the_summary_splits_the_tallest_towers_by_outcome():
    bench = load_benchmark("tower_offsets")
    played = [
        {"success": True, "places": [{"height": 2, "offset": 0.004, "upper": 0.004},
                                     {"height": 3, "offset": 0.006, "upper": 0.005}]},
        {"success": False, "places": [{"height": 2, "offset": 0.016, "upper": 0.016},
                                      {"height": 3, "offset": 0.010, "upper": 0.021}]},
        {"success": False, "places": [{"height": 2, "offset": 0.020, "upper": 0.020}]},  # no tower of three
    ]
    row = bench.summary("x", played)
    cells = [c.strip() for c in row.strip("|").split("|")]
    assert cells[:3] == ["x", "1 / 3", "5"]
    assert cells[3] == "10 / 11.2"  # median and mean of 4, 6, 16, 10, 20 mm
    assert cells[4] == "40 %"  # 16 and 20 of five
    assert cells[5:] == ["5 (1)", "21 (1)"]


@pytest.mark.parametrize("argv, message", [
    (["c.pt", "--episodes", "0"], "--episodes must be >= 1, got 0"),
    (["c.pt", "--objects", "1"], "--objects must be >= 2 (a tower), got 1"),
    (["c.pt", "--planner", "q_blend"], "--planner takes KEY=VALUE items, got 'q_blend'"),
])
def test_bad_arguments_stop_with_one_line_naming_the_value(argv, message, capsys):
    bench = load_benchmark("tower_offsets")
    with pytest.raises(SystemExit):
        bench.parse_args(argv)
    assert message in capsys.readouterr().err


def test_planner_overrides_set_the_greedy_decisions_keys_as_evaluate_does():
    bench = load_benchmark("tower_offsets")
    assert bench.greedy_settings({"q_blend": 0.25, "empty_picks_last": True}) == {
        "q_blend": 0.25, "greedy_q_blend": 0.25, "empty_picks_last": True}
    assert bench.greedy_settings({"uncertainty_penalty": 1.0})["greedy_uncertainty_penalty"] == 1.0
