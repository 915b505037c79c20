"""LDMLoss / focal loss."""

import pytest
import torch
import torch.nn.functional as F

from dyn_helpers import one_thread, tiny_model, transitions
from dyn_helpers import one_torch_thread  # noqa: F401  (fixture)
from ldm_rl.objectives import LDMLoss, depth_class_weights, focal_loss

pytestmark = pytest.mark.usefixtures("one_torch_thread")


def test_focal_loss_is_cross_entropy_at_gamma_zero():
    torch.manual_seed(0)
    logits, target = torch.randn(3, 7, 5, 5), torch.randint(0, 7, (3, 5, 5))
    ce = F.cross_entropy(logits, target, reduction="none").flatten(1).mean(1)
    torch.testing.assert_close(focal_loss(logits, target, gamma=0.0), ce)
    ce_smooth = F.cross_entropy(logits, target, reduction="none", label_smoothing=0.1).flatten(1).mean(1)
    torch.testing.assert_close(focal_loss(logits, target, gamma=0.0, label_smoothing=0.1), ce_smooth)


def test_focal_loss_down_weights_easy_pixels_and_applies_class_weights():
    logits = torch.tensor([[[4.0], [0.0]], [[0.5], [0.0]]]).view(2, 2, 1)  # sample 0 easy, sample 1 hard
    target = torch.zeros(2, 1, dtype=torch.long)
    ce, focal = focal_loss(logits, target, gamma=0.0), focal_loss(logits, target, gamma=2.0)
    assert (focal < ce).all() and focal[0] / ce[0] < focal[1] / ce[1]
    weighted = focal_loss(logits, target, gamma=2.0, weight=torch.tensor([3.0, 1.0]))
    torch.testing.assert_close(weighted, 3 * focal)


def test_reference_class_weight_rule():
    counts = torch.tensor([9e5, 5e4, 3e4, 1e4, 5e3, 2e3, 1e3, 500, 100, 10, 0])
    expected = torch.tensor([1, 1, 1, 1.61, 2.30, 3.22, 3.91, 4.60, 6.21, 8.52, 1])
    torch.testing.assert_close(depth_class_weights(counts), expected, atol=0.01, rtol=0)


def test_loss_keys_and_set_keys():
    loss = LDMLoss(tiny_model().train(), gamma=2.0, class_weights="auto")
    td = transitions(4)
    out = loss(td)
    assert set(out.keys()) == {"loss_dynamics", "pixel_accuracy", "changed_pixel_accuracy"}
    assert out["loss_dynamics"].requires_grad and out["loss_dynamics"].dim() == 0
    assert loss.class_counts.sum() == 4 * 64 * 64 and loss.class_weights().shape == (21,)
    td.rename_key_("heightmap", "scene")
    with pytest.raises(ValueError, match="missing"):
        loss(td)
    loss.set_keys(heightmap="scene")
    assert torch.isfinite(loss(td)["loss_dynamics"])


def test_loss_rejects_bad_targets_and_weights():
    loss = LDMLoss(tiny_model())
    td = transitions(2)
    td["next", "heightmap"] = torch.full_like(td["heightmap"], float("nan"))
    with pytest.raises(ValueError, match="next"):
        loss(td)
    with pytest.raises(ValueError, match="class_weights"):
        LDMLoss(tiny_model(), class_weights=torch.ones(3))


def test_loss_decreases_when_overfitting_a_tiny_batch():
    torch.manual_seed(0)
    loss = LDMLoss(tiny_model().train(), gamma=2.0)
    td = transitions(4)
    opt = torch.optim.Adam(loss.parameters(), lr=3e-3)
    with one_thread():
        first = loss(td)["loss_dynamics"].item()
        for _ in range(20):
            value = loss(td)["loss_dynamics"]
            opt.zero_grad()
            value.backward()
            opt.step()
        loss.eval()
        assert loss(td)["loss_dynamics"].item() < 0.5 * first


def test_gripper_symmetries_show_each_sample_mirrored_and_write_logits_for_the_untouched_one():
    """Each sample reaches the network as one of the four mirrors of its own crop and in-hand image (the same for
    both), the loss is the focal loss against the equally mirrored target, and the written logits, mirrored
    back, are what the network says about the untouched transition's frame. Eval mode is the plain loss."""
    from ldm_rl import geometry

    model = tiny_model().train()
    loss = LDMLoss(model, gamma=2.0, class_weights=None, write_logits=True, gripper_symmetries=True).train()
    td = transitions(32, seed=1)
    gen = torch.Generator().manual_seed(1)  # noise on every pixel: no crop equals a mirror of itself
    for key in ("heightmap", "in_hand", ("next", "heightmap")):
        td.set(key, td.get(key) + 0.02 * torch.rand(td.get(key).shape, generator=gen))
    flat = lambda key: td.get(key).reshape(32, *td.get(key).shape[1:])  # noqa: E731
    seen, hand, _, _ = model.net_inputs(flat("heightmap"), flat("in_hand"), td.get("action").long())
    _, target = model.frame_targets(flat("heightmap"), flat(("next", "heightmap")), td.get("action").long())
    calls = []
    forward = model.net.forward
    model.net.forward = lambda *a: calls.append(a) or forward(*a)
    torch.manual_seed(3)
    out = loss(td)
    (frame_in, hand_in, holding_in, _), = calls
    mirrors = [(r, c) for r in (False, True) for c in (False, True)]
    used = []
    for i in range(32):
        def mirrored(x, r, c):
            return geometry.mirror_crops(x[i:i + 1], torch.tensor([r]), torch.tensor([c]))[0]
        match = [m for m in mirrors if torch.equal(frame_in[i], mirrored(seen, *m)) and torch.equal(hand_in[i], mirrored(hand, *m))]
        assert len(match) == 1, f"sample {i} reached the network as {len(match)} of its four mirrors, not one"
        used.append(match[0])
    assert len(set(used)) == 4  # all four symmetries drawn over 32 samples
    model.net.forward = forward
    with torch.no_grad():
        logits = model.net(frame_in, hand_in, holding_in)
    rows = torch.tensor([r for r, _ in used]); cols = torch.tensor([c for _, c in used])
    want = focal_loss(logits, geometry.mirror_crops(target, rows, cols)[:, 0], gamma=2.0).mean()
    torch.testing.assert_close(out["loss_dynamics"].detach(), want, rtol=1e-5, atol=1e-6)
    torch.testing.assert_close(td.get("next_logits"), geometry.mirror_crops(logits, rows, cols))
    loss.eval()
    plain = LDMLoss(model, gamma=2.0, class_weights=None).eval()
    torch.testing.assert_close(loss(td)["loss_dynamics"], plain(td)["loss_dynamics"])


def test_gripper_symmetries_refuse_the_naive_models_global_frame():
    with pytest.raises(ValueError, match="gripper_symmetries needs the LDM's gripper-aligned local frame, got frame='global'"):
        LDMLoss(tiny_model(name="naive"), gripper_symmetries=True)
