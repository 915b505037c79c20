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
