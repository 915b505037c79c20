"""The scene-seed streams of a run: the values every kept run used, written once."""

from ldm_rl.seeds import SEED_BLOCK, evaluation_scenes, expert_scenes, held_out_scenes, training_scenes


def test_the_streams_keep_the_values_every_kept_run_used():
    assert SEED_BLOCK == 1_000_000
    assert [training_scenes(s) for s in (0, 2)] == [0, 2_000_000]
    assert [evaluation_scenes(s) for s in (0, 2)] == [1_000_000, 1_000_002]
    assert [held_out_scenes(s) for s in (0, 3)] == [2_000_000, 2_000_003]
    assert [expert_scenes(s) for s in (0, 1)] == [10_000, 10_001]
    # seed 0: the four streams start at least 10k scenes apart
    starts = sorted((training_scenes(0), evaluation_scenes(0), held_out_scenes(0), expert_scenes(0)))
    assert min(b - a for a, b in zip(starts, starts[1:])) >= 10_000
