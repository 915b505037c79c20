"""Paired comparison of two evaluations on the same scenes (ldm_rl.reports.paired_evaluations)."""

from __future__ import annotations

import json
import math
import random

import pytest

from ldm_rl.reports.paired_evaluations import Paired, PairedCounts, main, pair, pair_counts, paired_files


def evaluation(path, successes: list[int], **overrides) -> str:
    data = {"task": "ldm_rl/BottleArrangement-v0", "num_objects": 4, "episodes": len(successes), "scene_seed": 0,
            "successes": sum(successes), "per_episode": {"success": successes, "length": [8] * len(successes)}}
    data.update(overrides)
    path.write_text(json.dumps(data))
    return str(path)


def test_pair_counts_each_kind_of_scene():
    assert pair([1, 1, 0, 0, 1], [1, 0, 1, 0, 0]) == Paired(both=1, only_a=2, only_b=1, neither=1)


def test_mcnemar_exact_values():
    assert Paired(5, 0, 0, 5).mcnemar_p() == 1.0  # no discordant scene: no evidence either way
    assert Paired(0, 3, 3, 0).mcnemar_p() == 1.0  # an even split
    assert Paired(0, 5, 0, 0).mcnemar_p() == pytest.approx(2 / 32)  # 5 of 5 one way: 2 · 0.5^5
    # 10 discordant scenes split 9 / 1: 2 · (1 + 10) / 1024
    assert Paired(40, 9, 1, 50).mcnemar_p() == pytest.approx(22 / 1024)
    assert Paired(40, 1, 9, 50).mcnemar_p() == Paired(40, 9, 1, 50).mcnemar_p()  # symmetric


def test_mcnemar_rejects_at_its_level_under_no_difference():
    """Under no difference (each discordant scene a fair coin) p < 0.05 in at most about 5 % of draws (exact tests
    are conservative), and a real difference is found most of the time (seeded)."""
    rng = random.Random(0)

    def rejection_rate(p_only_a: float) -> float:
        rejected = 0
        for _ in range(2000):
            only_a = sum(rng.random() < p_only_a for _ in range(30))
            rejected += Paired(50, only_a, 30 - only_a, 20).mcnemar_p() < 0.05
        return rejected / 2000

    assert rejection_rate(0.5) <= 0.06
    assert rejection_rate(0.85) >= 0.9


def test_pair_refuses_unequal_or_non_binary_lists():
    with pytest.raises(ValueError, match="different lengths: 3 and 2"):
        pair([1, 0, 1], [1, 0])
    with pytest.raises(ValueError, match="0 or 1"):
        pair([1, 2], [1, 0])


def test_paired_files_refuses_evaluations_of_other_scenes(tmp_path):
    a = evaluation(tmp_path / "a.json", [1, 0, 1])
    b = evaluation(tmp_path / "b.json", [1, 1, 0], scene_seed=1)
    with pytest.raises(ValueError, match="different scenes: scene_seed 0 vs 1"):
        paired_files(a, b)
    old = tmp_path / "old.json"
    old.write_text(json.dumps({"task": "t", "num_objects": 4, "episodes": 3, "successes": 2}))
    with pytest.raises(ValueError, match="no per_episode outcomes"):
        paired_files(a, old)
    broken = evaluation(tmp_path / "broken.json", [1, 0, 1], per_episode={"length": [8, 8, 8]})
    with pytest.raises(ValueError, match="per_episode.success must be a list"):
        paired_files(a, broken)


def test_main_prints_one_row_per_pair_and_the_pooled_row(tmp_path, capsys):
    files = [evaluation(tmp_path / "s0_plain.json", [1, 0, 0, 1]), evaluation(tmp_path / "s0_lam.json", [1, 1, 1, 0]),
             evaluation(tmp_path / "s1_plain.json", [0, 0, 1, 1]), evaluation(tmp_path / "s1_lam.json", [1, 1, 1, 1])]
    out = tmp_path / "paired.md"
    assert main([*files, "--labels", "plain", "λ", "--out", str(out)]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert lines[0].startswith("| pair | scenes | plain | λ | both | only plain | only λ |")
    assert lines[2].startswith("| s0_plain / s0_lam | 4 | 2 | 3 | 1 | 1 | 2 | 0 |")
    assert lines[3].startswith("| s1_plain / s1_lam | 4 | 2 | 4 | 2 | 0 | 2 | 0 |")
    pooled = Paired(3, 1, 4, 0)
    assert lines[4] == f"| pooled | 8 | 4 | 7 | 3 | 1 | 4 | 0 | {pooled.mcnemar_p():.3g} |"
    assert out.read_text().splitlines() == lines
    assert math.isclose(pooled.mcnemar_p(), 2 * (1 + 5) / 32)


def test_main_refuses_an_odd_number_of_files(tmp_path, capsys):
    with pytest.raises(SystemExit) as exit_info:
        main([evaluation(tmp_path / "a.json", [1])])
    assert exit_info.value.code == 2
    assert "come in pairs" in capsys.readouterr().err


def test_pair_counts_and_the_sign_test():
    paired = pair_counts([6, 5, 8, 3, 4], [7, 5, 6, 3, 2])
    assert paired == PairedCounts(scenes=5, total_a=26, total_b=23, a_higher=2, b_higher=1)
    assert paired.ties == 2 and paired.sign_p() == 1.0  # 2 against 1: no evidence
    assert PairedCounts(10, 60, 40, 9, 1).sign_p() == pytest.approx(Paired(0, 9, 1, 0).mcnemar_p())  # the same test
    assert (paired + paired).total_a == 52 and (paired + paired).ties == 4
    with pytest.raises(ValueError, match="nothing to compare"):
        pair_counts([], [])
    with pytest.raises(ValueError, match="nothing to compare"):
        pair_counts([None, 3], [2, None])  # no scene with a number in both
    for bad in (-1, float("nan"), True, "3"):
        with pytest.raises(ValueError, match=f"finite and non-negative \\(or null\\), got {bad!r}"):
            pair_counts([1, bad], [1, 1])


def test_pair_counts_leaves_out_the_scenes_either_has_no_number_for():
    # pile tops (m): a scene one way did not pack has no pile and drops out of the pair, whichever side it is on
    paired = pair_counts([0.12, None, 0.10, 0.14, None], [0.11, 0.13, 0.10, None, None])
    assert paired == PairedCounts(scenes=2, total_a=pytest.approx(0.22), total_b=pytest.approx(0.21), a_higher=1,
                                  b_higher=0)


def test_main_compares_a_per_episode_count(tmp_path, capsys):
    def bins(path, blocks):
        return evaluation(path, [int(b == 8) for b in blocks], task="ldm_rl/BinPacking-v0", num_objects=8,
                          per_episode={"success": [int(b == 8) for b in blocks], "blocks_in_bin": blocks})

    files = [bins(tmp_path / "plain.json", [6, 5, 8, 3]), bins(tmp_path / "rot.json", [7, 5, 8, 5])]
    assert main([*files, "--count", "blocks_in_bin", "--labels", "plain", "K=8"]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert lines[0] == ("| pair | scenes | plain: mean blocks_in_bin | K=8: mean blocks_in_bin | plain higher | K=8 higher "
                        "| equal | sign test p |")
    assert lines[2] == "| plain / rot | 4 | 5.5 | 6.25 | 0 | 2 | 2 | 0.5 |"
    # the pile top (m) on the scenes both packed: A's 0.12 against B's 0.11 on the only such scene
    piles = [evaluation(tmp_path / f"{n}.json", packed, task="ldm_rl/BinPacking-v0", num_objects=8,
                        per_episode={"success": packed, "pile_top": tops})
             for n, packed, tops in (("a", [1, 0], [0.12, None]), ("b", [1, 1], [0.11, 0.13]))]
    assert main([*piles, "--count", "pile_top"]) == 0
    assert capsys.readouterr().out.splitlines()[2] == "| a / b | 1 | 0.12 | 0.11 | 1 | 0 | 0 | 1 |"
    assert main([*files, "--count", "picks_held"]) == 2  # a count the files do not have: one line naming it
    assert "per_episode.picks_held must be a list with one entry per scene (it has: blocks_in_bin, success)" in \
        capsys.readouterr().err
