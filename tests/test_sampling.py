"""Tests of the planner's diverse proposal sampler (ldm_rl.planning.sampling)."""

import math
import subprocess
import sys

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from ldm_rl.planning import sample_candidates

ALPHA = 1e-3  # significance of the seeded chi-square tests


# --------------------------------------------------------------------------------------------
# helpers (independent of the module)
# --------------------------------------------------------------------------------------------
def circ(a, b, r):
    d = abs(a - b) % r
    return min(d, r - d)


def mahalanobis(a, b, sigma, sigma_rot, r):
    """Distance between two (row, col, rot) actions in units of the inhibition widths."""
    return math.sqrt(((a[0] - b[0]) ** 2 + (a[1] - b[1]) ** 2) / sigma**2 + circ(a[2], b[2], r) ** 2 / sigma_rot**2)


def oracle(q, num, beta, sigma, sigma_rot):
    """Loop-per-row argmax sampler in float64 with a full distance tensor: the documented semantics."""
    _, r, h, w = q.shape
    rot, row, col = torch.meshgrid(torch.arange(r), torch.arange(h), torch.arange(w), indexing="ij")
    result = []
    for qi in q:
        m = qi.double().clone()
        picks = []
        for _ in range(num):
            flat = int(torch.argmax(m))
            k, i, j = flat // (h * w), (flat % (h * w)) // w, flat % w
            picks.append((i, j, k))
            d2 = ((row - i) ** 2 + (col - j) ** 2).double()
            drot = torch.minimum((rot - k).abs(), r - (rot - k).abs()).double()
            pix = torch.exp(-d2 / (2 * sigma**2)) if sigma > 0 else (d2 == 0).double()
            ang = torch.exp(-(drot**2) / (2 * sigma_rot**2)) if sigma_rot > 0 else (drot == 0).double()
            m -= beta * pix * ang
            m[k, i, j] = -math.inf
        result.append(picks)
    return torch.tensor(result, dtype=torch.long)


def chi_square_pvalue(counts, probs):
    """Pearson chi-square p-value of integer ``counts`` against ``probs`` (float64), via the upper gamma."""
    expected = probs * counts.sum()
    stat = ((counts - expected) ** 2 / expected).sum()
    dof = torch.tensor((counts.numel() - 1) / 2, dtype=torch.float64)
    return float(torch.special.gammaincc(dof, stat / 2))


def small_map():
    """R=2, H=W=3 Q map with values spread over [-1, 1] in a scrambled order."""
    gen = torch.Generator().manual_seed(7)
    return torch.linspace(-1, 1, 18, dtype=torch.float64)[torch.randperm(18, generator=gen)].reshape(1, 2, 3, 3)


def flat_index(actions, h, w):
    """(row, col, rot) -> index into a [R, H, W] map."""
    return actions[..., 2] * h * w + actions[..., 0] * w + actions[..., 1]


def peak_map(r=8, h=128, w=128, center=(60, 70, 3), width=15.0, width_rot=1.5):
    rot, row, col = torch.meshgrid(torch.arange(r), torch.arange(h), torch.arange(w), indexing="ij")
    drot = torch.minimum((rot - center[2]).abs(), r - (rot - center[2]).abs())
    d2 = (row - center[0]) ** 2 + (col - center[1]) ** 2
    return (torch.exp(-d2 / (2 * width**2)) * torch.exp(-(drot**2) / (2 * width_rot**2))).float()[None]


# --------------------------------------------------------------------------------------------
# (1) large beta: no two candidates inside each other's inhibition radius
# --------------------------------------------------------------------------------------------
@pytest.mark.parametrize("mode", ["softmax", "argmax"])
def test_large_beta_keeps_candidates_outside_each_others_radius(mode):
    sigma, sigma_rot, r = 3.0, 1.5, 8
    gen = torch.Generator().manual_seed(0)
    # a smooth peak at rotation 0 (so the circular neighbour R-1 is tempting) plus noise, range ~1
    q = peak_map(r, 32, 40, center=(10, 30, 0), width=6.0).expand(4, -1, -1, -1)
    q = q + 0.05 * torch.rand(q.shape, generator=gen)
    kwargs = dict(sigma=sigma, sigma_rot=sigma_rot, mode=mode, tau=0.02, generator=gen)
    cands = sample_candidates(q, 10, beta=1e6, **kwargs)
    for row in cands.tolist():
        dists = [mahalanobis(a, b, sigma, sigma_rot, r) for i, a in enumerate(row) for b in row[:i]]
        assert min(dists) >= 1.0, (row, min(dists))
    # control: without inhibition the same check fails (a cold draw stays on the top of the peak)
    clustered = sample_candidates(q, 10, beta=0.0, **kwargs)
    for row in clustered.tolist():
        assert min(mahalanobis(a, b, sigma, sigma_rot, r) for i, a in enumerate(row) for b in row[:i]) < 1.0


# --------------------------------------------------------------------------------------------
# (2) beta = 0: softmax(q/tau) draws without replacement
# --------------------------------------------------------------------------------------------
@pytest.mark.parametrize("tau", [0.5, 2.0])
def test_beta_zero_first_and_second_draws_follow_softmax_without_replacement(tau):
    q = small_map()
    n = 6000
    gen = torch.Generator().manual_seed(123)
    cands = sample_candidates(q.expand(n, -1, -1, -1), 2, tau=tau, beta=0.0, generator=gen)
    idx = flat_index(cands, 3, 3)
    p = torch.softmax(q.flatten() / tau, 0)
    first = torch.bincount(idx[:, 0], minlength=18).double()
    assert chi_square_pvalue(first, p) > ALPHA
    # the test has power: the same counts reject the softmax at twice the temperature
    assert chi_square_pvalue(first, torch.softmax(q.flatten() / (2 * tau), 0)) < 1e-6
    # second draw: marginal of a draw without replacement, P(j) = sum_{i != j} p_i p_j / (1 - p_i)
    assert (idx[:, 0] != idx[:, 1]).all()
    joint = p[:, None] * p[None, :] / (1 - p[:, None])
    joint.fill_diagonal_(0)
    second = torch.bincount(idx[:, 1], minlength=18).double()
    assert chi_square_pvalue(second, joint.sum(0)) > ALPHA
    if tau < 1:  # ... and not the first draw's distribution (too close to it to tell at tau = 2)
        assert chi_square_pvalue(second, p) < 1e-6


@pytest.mark.parametrize("mode", ["softmax", "argmax"])
def test_drawing_every_action_is_a_permutation(mode):
    q = torch.randn(3, 2, 3, 4, generator=torch.Generator().manual_seed(1))
    cands = sample_candidates(q, 24, beta=0.0, mode=mode, generator=torch.Generator().manual_seed(2))
    for row in flat_index(cands, 3, 4):
        assert sorted(row.tolist()) == list(range(24))
    if mode == "argmax":  # without inhibition, argmax order is q sorted descending
        assert torch.equal(flat_index(cands, 3, 4), q.flatten(1).argsort(dim=1, descending=True, stable=True))


def test_extreme_temperatures():
    q = small_map().float()
    # tau -> 0 is argmax (no overflow); tau -> inf is uniform
    cold = sample_candidates(q.expand(4, -1, -1, -1), 5, tau=1e-30, generator=torch.Generator().manual_seed(0))
    assert torch.equal(cold, sample_candidates(q.expand(4, -1, -1, -1), 5, mode="argmax"))
    hot = sample_candidates(q.expand(3000, -1, -1, -1), 1, tau=1e30, generator=torch.Generator().manual_seed(0))
    counts = torch.bincount(flat_index(hot[:, 0], 3, 3), minlength=18).double()
    assert chi_square_pvalue(counts, torch.full((18,), 1 / 18, dtype=torch.float64)) > ALPHA


def test_minus_inf_entries_are_never_drawn():
    q = torch.randn(50, 2, 3, 3, generator=torch.Generator().manual_seed(3))
    q[:, :, 1, :] = -math.inf  # 12 drawable entries left
    cands = sample_candidates(q, 12, tau=5.0, sigma=0.5, generator=torch.Generator().manual_seed(4))
    assert (cands[..., 0] != 1).all()
    with pytest.raises(ValueError, match="only 12 entries"):
        sample_candidates(q, 13)


# --------------------------------------------------------------------------------------------
# (3) rotation wrap-around
# --------------------------------------------------------------------------------------------
@pytest.mark.parametrize("r", [3, 6, 8])
@pytest.mark.parametrize("favour_bin0", [False, True])
def test_rotation_inhibition_wraps_around(r, favour_bin0):
    """A draw at bin R-1 inhibits bin 0 exactly as much as bin R-2: a 1e-3 edge decides the second draw."""
    eps = 1e-3
    q = torch.zeros(1, r, 5, 5)
    q[0, r - 1, 2, 2] = 10.0
    q[0, 0, 2, 2] = 5.0 + (eps if favour_bin0 else 0.0)
    q[0, r - 2, 2, 2] = 5.0 + (0.0 if favour_bin0 else eps)
    for mode, tau in (("argmax", 1.0), ("softmax", 1e-6)):
        cands = sample_candidates(q, 2, beta=1.0, sigma=1.0, sigma_rot=1.0, mode=mode, tau=tau)
        assert cands[0, 0].tolist() == [2, 2, r - 1]
        assert cands[0, 1].tolist() == [2, 2, 0 if favour_bin0 else r - 2]
    # mirror: a draw at bin 0 inhibits bin R-1 like bin 1
    q = torch.zeros(1, r, 5, 5)
    q[0, 0, 2, 2], q[0, 1, 2, 2], q[0, r - 1, 2, 2] = 10.0, 5.0, 5.0 + eps
    assert sample_candidates(q, 2, sigma_rot=1.0, mode="argmax")[0, 1].tolist() == [2, 2, r - 1]


# --------------------------------------------------------------------------------------------
# (4) argmax mode: the reference planner on a single smooth peak
# --------------------------------------------------------------------------------------------
def test_argmax_on_a_smooth_peak_spreads_around_it():
    q = peak_map()  # peak at (60, 70), rotation 3, ~15 px wide
    cands = sample_candidates(q, 10, beta=1.0, sigma=5.0, sigma_rot=1.0, mode="argmax")[0].tolist()
    assert cands[0] == [60, 70, 3]
    assert len({tuple(a) for a in cands}) == 10
    # successive draws spread out: no two candidates in the same rotation closer than sigma ...
    for i, a in enumerate(cands):
        for b in cands[:i]:
            if a[2] == b[2]:
                assert math.dist(a[:2], b[:2]) >= 5.0, (a, b)
    # ... but stay on the peak (within two peak widths, rotation within one bin)
    for a in cands:
        assert math.dist(a[:2], (60, 70)) <= 30.0 and circ(a[2], 3, 8) <= 1
    # no inhibition: the argmax draws are the top pixels, all hugging the peak
    tight = sample_candidates(q, 10, beta=0.0, mode="argmax")[0].tolist()
    assert tight[0] == [60, 70, 3] and max(math.dist(a[:2], (60, 70)) for a in tight) < 2.5


@pytest.mark.parametrize(
    "shape, beta, sigma, sigma_rot",
    [
        ((2, 5, 9, 12), 1.0, 2.0, 1.0),
        ((3, 4, 7, 6), 0.7, 0.0, 1.5),
        ((2, 8, 10, 10), 2.0, 1.5, 0.0),
        ((1, 1, 6, 5), 1.0, 1.0, 1.0),
    ],
)
def test_argmax_matches_a_loop_oracle(shape, beta, sigma, sigma_rot):
    q = torch.randn(shape, generator=torch.Generator().manual_seed(sum(shape)))
    num = 12
    got = sample_candidates(q, num, beta=beta, sigma=sigma, sigma_rot=sigma_rot, mode="argmax")
    assert torch.equal(got, oracle(q, num, beta, sigma, sigma_rot))
    # a smooth peak, jittered so that float32 rounding cannot decide between mirror-image pixels
    peak = peak_map()[..., 40:80, 50:90] + 1e-3 * torch.rand(1, 8, 40, 40, generator=torch.Generator().manual_seed(9))
    got = sample_candidates(peak, 10, beta=beta, sigma=sigma, sigma_rot=sigma_rot, mode="argmax")
    assert torch.equal(got, oracle(peak, 10, beta, sigma, sigma_rot))


# --------------------------------------------------------------------------------------------
# (5) batching and determinism
# --------------------------------------------------------------------------------------------
def test_batched_equals_per_row_in_argmax_mode():
    q = torch.randn(5, 4, 20, 24, generator=torch.Generator().manual_seed(5))
    kwargs = dict(beta=0.8, sigma=2.5, sigma_rot=1.0, mode="argmax")
    batched = sample_candidates(q, 12, **kwargs)
    assert torch.equal(batched, torch.cat([sample_candidates(q[i : i + 1], 12, **kwargs) for i in range(5)]))


def test_softmax_is_deterministic_given_a_generator():
    q = torch.randn(4, 8, 16, 16, generator=torch.Generator().manual_seed(6))
    draw = lambda seed: sample_candidates(q, 10, generator=torch.Generator().manual_seed(seed))  # noqa: E731
    assert torch.equal(draw(0), draw(0))
    assert not torch.equal(draw(0), draw(1))


@settings(max_examples=30, deadline=None)
@given(
    r=st.integers(1, 5), h=st.integers(1, 7), w=st.integers(1, 7), b=st.integers(0, 3),
    beta=st.sampled_from([0.0, 0.5, 3.0, 1e6]), sigma=st.sampled_from([0.0, 0.7, 2.0]),
    sigma_rot=st.sampled_from([0.0, 1.0]), tau=st.sampled_from([1e-3, 1.0, 50.0]),
    mode=st.sampled_from(["softmax", "argmax"]), seed=st.integers(0, 2**31 - 1), data=st.data(),
)
def test_candidates_are_distinct_in_range_and_q_untouched(r, h, w, b, beta, sigma, sigma_rot, tau, mode, seed, data):
    num = data.draw(st.integers(1, r * h * w))
    gen = torch.Generator().manual_seed(seed)
    q = torch.randn(b, r, h, w, generator=gen, dtype=torch.float64)
    before = q.clone()
    cands = sample_candidates(q, num, tau=tau, beta=beta, sigma=sigma, sigma_rot=sigma_rot, mode=mode, generator=gen)
    assert cands.shape == (b, num, 3) and cands.dtype == torch.long
    assert torch.equal(q, before)
    for axis, size in enumerate((h, w, r)):
        assert ((cands[..., axis] >= 0) & (cands[..., axis] < size)).all()
    for row in flat_index(cands, h, w):
        assert len(set(row.tolist())) == num


# --------------------------------------------------------------------------------------------
# (6) bad inputs
# --------------------------------------------------------------------------------------------
Q = torch.zeros(2, 2, 3, 3)


@pytest.mark.parametrize(
    "q, num, kwargs, match",
    [
        (Q, 19, {}, "num must be an int in \\[1, R\\*H\\*W = 18\\]"),
        (Q, 0, {}, "num must be"),
        (Q, 2.0, {}, "num must be"),
        (Q, True, {}, "num must be"),
        (Q, 2, {"tau": 0.0}, "tau must be a positive"),
        (Q, 2, {"tau": -1.0}, "tau must be a positive"),
        (Q, 2, {"tau": math.inf}, "tau must be a positive"),
        (Q, 2, {"beta": -0.1}, "beta must be"),
        (Q, 2, {"beta": math.nan}, "beta must be"),
        (Q, 2, {"sigma": -1.0}, "sigma must be"),
        (Q, 2, {"sigma_rot": -1.0}, "sigma_rot must be"),
        (Q, 2, {"mode": "greedy"}, "mode must be one of"),
        (Q, 2, {"generator": 3}, "generator must be"),
        (Q[0], 2, {}, "q must be a \\[B, R, H, W\\]"),
        (Q.numpy(), 2, {}, "q must be a \\[B, R, H, W\\]"),
        (Q.long(), 2, {}, "floating-point dtype"),
        (torch.full((1, 2, 3, 3), math.nan), 2, {}, "NaN"),
        (torch.full((1, 2, 3, 3), math.inf), 2, {}, "\\+inf"),
    ],
)
def test_bad_inputs_raise_one_line_value_errors(q, num, kwargs, match):
    with pytest.raises(ValueError, match=match) as info:
        sample_candidates(q, num, **kwargs)
    assert "\n" not in str(info.value)


def test_float32_overflow_of_the_working_map_is_reported():
    q = torch.tensor([3e38, 0.0, 0.0]).reshape(1, 1, 1, 3)
    with pytest.raises(ValueError, match="overflows float32"):
        sample_candidates(q, 3, beta=3e38, sigma=10.0, mode="argmax")
    assert sample_candidates(q, 3, beta=1.0, sigma=10.0, mode="argmax")[0, :, 1].tolist() == [0, 2, 1]


def test_planning_package_import_is_light():
    code = (
        "import sys, ldm_rl.planning; "
        "print(sorted(m for m in sys.modules if m.split('.')[0] in ('torchrl', 'tensordict', 'ldm_rl')))"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    # ldm_rl.keys: the key names the package root exports (plain strings, no imports)
    assert out.strip() == "['ldm_rl', 'ldm_rl.geometry', 'ldm_rl.keys', 'ldm_rl.planning', 'ldm_rl.planning.sampling']"
