"""Networks: reference parameter count, shapes, head routing."""

import pytest
import torch

from dyn_helpers import one_torch_thread  # noqa: F401  (fixture)
from ldm_rl.models import DepthUNet, TwoHeadDynamicsNet, count_parameters, encode_depth_inputs

pytestmark = pytest.mark.usefixtures("one_torch_thread")


def test_paper_head_matches_reference_parameter_count():
    # the reference head (K = 11 classes, 22 input planes) has 24,893,963 parameters
    assert count_parameters(DepthUNet(22, 11, width=1.0)) == 24_893_963


def test_unet_output_shape_and_width_scaling():
    net = DepthUNet(42, 21, width=0.125).eval()
    assert net(torch.zeros(2, 42, 64, 64)).shape == (2, 21, 64, 64)
    assert count_parameters(DepthUNet(42, 21, 0.25)) < count_parameters(DepthUNet(42, 21, 0.5)) / 3


def test_hand_is_padded_into_the_frame_centre():
    frame = torch.zeros(1, 1, 64, 64, dtype=torch.uint8)
    hand = torch.full((1, 1, 24, 24), 3, dtype=torch.uint8)
    x = encode_depth_inputs(frame, hand, num_classes=5)
    assert x.shape == (1, 10, 64, 64)
    assert x[0, 5 + 3, 20:44, 20:44].all() and x[0, 5 + 3].sum() == 24 * 24
    assert x[0, 5 + 0].sum() == 64 * 64 - 24 * 24 and x[0, 0].all()


def _head_grads(net, holding):
    net.zero_grad(set_to_none=True)
    frames = torch.randint(0, 5, (len(holding), 1, 32, 32))
    hands = torch.randint(0, 5, (len(holding), 1, 24, 24))
    return net(frames, hands, torch.tensor(holding))


def _grad_norm(module):
    grads = [p.grad for p in module.parameters()]
    return None if all(g is None for g in grads) else sum(float(g.abs().sum()) for g in grads if g is not None)


def test_only_the_needed_head_gets_gradients():
    torch.manual_seed(0)
    net = TwoHeadDynamicsNet(num_classes=5, width=0.125)
    _head_grads(net, [False, False, False]).sum().backward()
    assert _grad_norm(net.pick) > 0 and _grad_norm(net.place) is None
    _head_grads(net, [True, True]).sum().backward()
    assert _grad_norm(net.place) > 0 and _grad_norm(net.pick) is None
    # mixed batch: the loss of a pick sample alone gives the place head no gradient
    out = _head_grads(net, [False, True, True])
    out[0].sum().backward()
    assert _grad_norm(net.pick) > 0 and not _grad_norm(net.place)


def test_routing_equals_running_each_head_on_its_samples():
    torch.manual_seed(0)
    net = TwoHeadDynamicsNet(num_classes=5, width=0.125).eval()
    frames = torch.randint(0, 5, (4, 1, 32, 32))
    hands = torch.randint(0, 5, (4, 1, 24, 24))
    holding = torch.tensor([True, False, True, False])
    out = net(frames, hands, holding)
    x = encode_depth_inputs(frames, hands, 5)
    torch.testing.assert_close(out[1::2], net.pick(x[1::2]))
    torch.testing.assert_close(out[0::2], net.place(x[0::2]))


def test_speed_benchmark_alternatives_compute_the_same_function():
    """benchmarks/bench_upconv.py times Winograd and single-call up-convs as exact stand-ins for ours."""
    from benchmark_loader import load_benchmark

    bench = load_benchmark("bench_upconv")
    diffs = bench.check_exact()
    assert set(diffs) == {"winograd", "transposed", "3x3+shuffle"}
    assert all(d < 1e-12 for d in diffs.values()), diffs
