"""Dynamics core: exact SE(2) equivariance, exact locality, the hand-state rule, input validation."""

import pytest
import torch

from dyn_helpers import TINY, block_scenes, tiny_model
from dyn_helpers import one_torch_thread  # noqa: F401  (fixture)
from ldm_rl.world_model.metrics import action_region_mask
from ldm_rl.world_model import HandStateRule

pytestmark = pytest.mark.usefixtures("one_torch_thread")

R = 8


def _rotate_scene_and_action(heightmap, action):
    """Rotate by +90° when the bin k < R/2 (k -> k + R/2), else by −90° (k -> k − R/2)."""
    r, c, k = action.unbind(-1)
    plus = k < R // 2
    rot_plus = torch.rot90(heightmap, 1, dims=(-2, -1))  # new[127 − c, r] = old[r, c]
    rot_minus = torch.rot90(heightmap, -1, dims=(-2, -1))  # new[c, 127 − r] = old[r, c]
    scene = torch.where(plus.view(-1, 1, 1, 1), rot_plus, rot_minus)
    new_action = torch.where(
        plus.unsqueeze(-1), torch.stack((127 - c, r, k + R // 2), -1), torch.stack((c, 127 - r, k - R // 2), -1)
    )
    return scene, new_action, plus


@pytest.mark.parametrize("crop_size", [64, 128])
def test_prediction_is_exactly_equivariant_to_quarter_turns(crop_size):
    model = tiny_model(crop_size=crop_size)
    n = 8
    heightmap = block_scenes(n, seed=1)
    in_hand = torch.rand(n, 1, 24, 24) * 0.05
    holding = (torch.arange(n) % 2 == 0).unsqueeze(-1)
    action = torch.stack((torch.randint(0, 128, (n,)), torch.randint(0, 128, (n,)), torch.arange(n)), -1)
    with torch.no_grad():
        pred = model.predict(heightmap, in_hand, holding, action)
        scene_r, action_r, plus = _rotate_scene_and_action(heightmap, action)
        pred_r = model.predict(scene_r, in_hand, holding, action_r)
    expected = torch.where(
        plus.view(-1, 1, 1, 1), torch.rot90(pred.heightmap, 1, dims=(-2, -1)), torch.rot90(pred.heightmap, -1, dims=(-2, -1))
    )
    assert torch.equal(pred_r.heightmap, expected)
    assert torch.equal(pred_r.logits, pred.logits)
    assert torch.equal(pred_r.in_hand, pred.in_hand)
    assert torch.equal(pred_r.holding, pred.holding)
    assert not torch.equal(pred.heightmap, heightmap)  # the check is not vacuous


@pytest.mark.parametrize("crop_size", [64, 128])
def test_pixels_outside_the_action_square_are_bit_identical(crop_size):
    model = tiny_model(crop_size=crop_size)
    n = 6
    heightmap = block_scenes(n, seed=2) + torch.rand(n, 1, 128, 128) * 1e-3  # not on the class grid
    action = torch.stack((torch.randint(0, 128, (n,)), torch.randint(0, 128, (n,)), torch.randint(0, R, (n,))), -1)
    holding = torch.zeros(n, 1, dtype=torch.bool)
    with torch.no_grad():
        pred = model.predict(heightmap, torch.zeros(n, 1, 24, 24), holding, action)
    outside = ~action_region_mask(action, crop_size, R)
    assert outside.sum() > 0
    assert torch.equal(pred.heightmap[outside], heightmap[outside])
    inside_changed = (pred.heightmap != heightmap) & ~outside
    assert inside_changed.any()


def test_naive_model_predicts_the_whole_image():
    model = tiny_model(name="naive")
    hm = block_scenes(2)
    pred = model.predict(hm, torch.zeros(2, 1, 24, 24), torch.tensor([[False], [True]]), torch.tensor([[5, 5, 0], [100, 90, 3]]))
    assert pred.logits.shape == (2, 21, 128, 128) and pred.heightmap.shape == hm.shape


def test_hand_state_rule_on_hand_made_crops():
    rule = HandStateRule()
    empty = torch.zeros(1, 1, 64, 64, dtype=torch.uint8)

    def with_block(side, value=3):
        x = empty.clone()
        x[..., 32 - side // 2 : 32 - side // 2 + side, 32 - side // 2 : 32 - side // 2 + side] = value
        return x

    assert rule(with_block(8), empty).item()  # 64 object pixels, then none: grasped
    assert not rule(with_block(5), empty).item()  # 25 pixels is not > 25
    assert not rule(with_block(8), with_block(6)).item()  # 36 > 25 left behind: failed pick
    assert rule(with_block(8), with_block(5)).item()  # 25 left is <= 25
    off_centre = empty.clone()
    off_centre[..., 0:10, 0:10] = 3  # outside the central 32x32
    assert not rule(off_centre, empty).item()
    strict = HandStateRule(center_size=32, before_threshold=100, after_threshold=0)
    assert not strict(with_block(8), empty).item()


def test_removal_rule_reads_a_pick_from_a_stack_or_beside_a_neighbour_as_held():
    """The occupancy rule reads a block taken off a 2-stack, or picked beside a neighbour, as a failed pick (the
    window stays occupied); the removal rule reads what dropped under the fingers, and never holds after a place."""
    occupancy, removal = HandStateRule(), HandStateRule(kind="removal")
    floor = torch.zeros(1, 1, 64, 64, dtype=torch.uint8)
    two_stack, one_block = floor.clone(), floor.clone()
    two_stack[..., 26:38, 26:38] = 6
    one_block[..., 26:38, 26:38] = 3
    beside = floor.clone()
    beside[..., 26:38, 26:38] = 3
    beside[..., 26:38, 40:48] = 3  # a neighbour inside the central 32 x 32, outside the 12 x 12 under the fingers
    neighbour_only = beside.clone()
    neighbour_only[..., 26:38, 26:38] = 0
    pick, place = torch.tensor([True]), torch.tensor([False])
    for before, after in ((two_stack, one_block), (beside, neighbour_only)):
        assert not occupancy(before, after).item()
        assert removal(before, after, pick).item()
        assert not removal(before, after, place).item()  # a place always opens the hand
    assert removal(one_block, floor, pick).item() and occupancy(one_block, floor).item()  # the plain pick: both agree
    assert not removal(one_block, one_block, pick).item()  # nothing moved: a failed pick
    half = one_block.clone()
    half[..., 26:32, 26:38] = 0  # half the window under the fingers dropped: not more than 0.5
    assert not removal(one_block, half, pick).item()
    assert HandStateRule(kind="removal", removal_fraction=0.4)(one_block, half, pick).item()
    with pytest.raises(ValueError, match="needs `picking`"):
        removal(one_block, floor)
    for bad, message in (({"kind": "area"}, "kind must be one of"), ({"removal_fraction": 1.0}, "removal_fraction"),
                         ({"removal_size": 0}, "removal_size")):
        with pytest.raises(ValueError, match=message):
            HandStateRule(**bad)


def test_the_model_reads_holding_with_its_rule_and_the_hand_before():
    """DynamicsModel passes the hand state before the action to the rule: the same predicted frames give holding'
    after a pick and never after a place under the removal rule."""
    model = tiny_model()
    model.hand_rule = HandStateRule(kind="removal")
    hm = torch.zeros(2, 1, 128, 128)
    hm[:, :, 58:70, 58:70] = 0.04
    action = torch.tensor([[64, 64, 0], [64, 64, 0]])
    logits = torch.zeros(2, 21, 64, 64)
    logits[:, 0] = 10.0  # predicted frame: all floor, the block gone
    pred = model.next_state_from_logits(hm, torch.zeros(2, 1, 24, 24), torch.tensor([[False], [True]]), action, logits)
    assert pred.holding.reshape(-1).tolist() == [True, False]


def test_predicted_in_hand_is_the_centre_of_the_crop_after_a_grasp():
    model = tiny_model()
    hm = torch.zeros(1, 1, 128, 128)
    hm[..., 60:70, 60:70] = 0.04
    with torch.no_grad():
        pred = model.predict(hm, torch.zeros(1, 1, 24, 24), torch.tensor([[False]]), torch.tensor([[64, 64, 0]]))
    if pred.holding.item():
        assert torch.equal(pred.in_hand[0, 0], hm[0, 0, 52:76, 52:76])
    else:
        assert (pred.in_hand == 0).all()


@pytest.mark.parametrize(
    "field, value, message",
    [
        ("heightmap", torch.zeros(2, 1, 64, 64), "heightmap"),
        ("heightmap", torch.full((2, 1, 128, 128), float("nan")), "NaN"),
        ("in_hand", torch.full((2, 1, 24, 24), float("inf")), "in_hand"),
        ("in_hand", torch.zeros(3, 1, 24, 24), "in_hand"),
        ("action", torch.tensor([[1.0, 2.0, 0.0], [1.0, 2.0, 0.0]]), "action"),
        ("action", torch.tensor([[1, 2, 8], [1, 2, 0]]), "action"),
        ("action", torch.tensor([[1, 200, 0], [1, 2, 0]]), "action"),
        ("holding", torch.zeros(2, 2, dtype=torch.bool), "holding"),
        ("holding", torch.full((2, 1), 0.5), "holding"),
    ],
)
def test_bad_inputs_are_rejected_with_a_clear_message(field, value, message):
    model = tiny_model()
    inputs = {
        "heightmap": torch.zeros(2, 1, 128, 128),
        "in_hand": torch.zeros(2, 1, 24, 24),
        "holding": torch.zeros(2, 1, dtype=torch.bool),
        "action": torch.tensor([[1, 2, 0], [3, 4, 5]]),
    }
    inputs[field] = value
    with pytest.raises(ValueError, match=message):
        model.predict(**inputs)


def test_leading_batch_dims_are_kept():
    model = tiny_model()
    hm = block_scenes(6).reshape(2, 3, 1, 128, 128)
    pred = model.predict(hm, torch.zeros(2, 3, 1, 24, 24), torch.zeros(2, 3, 1, dtype=torch.bool), torch.full((2, 3, 3), 5))
    assert pred.heightmap.shape == (2, 3, 1, 128, 128) and pred.holding.shape == (2, 3, 1)
    assert pred.logits.shape == (2, 3, 21, 64, 64)


# ------------------------------------------------------------------ the height-anchored frame (model.height_anchor)

def _anchored_pair(anchor=0.08):
    """(plain, anchored): the same random weights, max_height 0.25 m (block stacking's), anchor in metres."""
    from ldm_rl.world_model import build_dynamics_model

    torch.manual_seed(0)
    plain = build_dynamics_model(dict(TINY), 0.25).eval()
    anchored = build_dynamics_model({**TINY, "height_anchor": anchor}, 0.25).eval()
    anchored.load_state_dict(plain.state_dict())
    return plain, anchored


def _column(levels: int) -> torch.Tensor:
    """[1, 1, 128, 128]: a column of ``levels`` 4 cm cubes (13 px) centred at (64, 64) and one cube on the table 20 px
    away, inside the crop."""
    scene = torch.zeros(1, 1, 128, 128)
    scene[..., 58:71, 58:71] = 0.04 * levels
    scene[..., 58:71, 84:97] = 0.04
    return scene


def test_height_anchor_changes_nothing_up_to_the_anchor():
    plain, anchored = _anchored_pair(0.08)  # class 6: a 2-cube column's top
    n = 6
    heightmap = block_scenes(n, seed=3)  # blocks of 4 or 8 cm: every top at or below the anchor
    in_hand, holding = torch.rand(n, 1, 24, 24) * 0.04, (torch.arange(n) % 2 == 0).unsqueeze(-1)
    action = torch.stack((torch.randint(20, 108, (n,)), torch.randint(20, 108, (n,)), torch.arange(n)), -1)
    with torch.no_grad():
        a, b = plain.predict(heightmap, in_hand, holding, action), anchored.predict(heightmap, in_hand, holding, action)
        picks = ~holding.reshape(-1)
        held_a = plain.held_outcome(heightmap[picks], action[picks], a.logits[picks])
        held_b = anchored.held_outcome(heightmap[picks], action[picks], b.logits[picks])
    for x, y in zip((*a, *held_a), (*b, *held_b)):
        assert torch.equal(x, y)


def test_height_anchor_predicts_a_taller_stack_as_one_of_the_anchors_height_raised():
    plain, anchored = _anchored_pair(0.08)
    hand = torch.zeros(1, 1, 24, 24)
    hand[..., 6:19, 6:19] = 0.04  # holding a cube: a place on the column
    holding, action = torch.ones(1, 1, dtype=torch.bool), torch.tensor([[64, 64, 0]])
    three, four = _column(3), _column(4)  # tops 12 and 16 cm, lowered by 4 and 8 cm to the anchor's 8 cm
    with torch.no_grad():
        p3, p4 = anchored.predict(three, hand, holding, action), anchored.predict(four, hand, holding, action)
        q3, q4 = plain.predict(three, hand, holding, action), plain.predict(four, hand, holding, action)
    assert torch.equal(p3.logits, p4.logits) and not torch.equal(q3.logits, q4.logits)  # one frame for both
    c3, c4 = anchored.classes(p3.heightmap).long(), anchored.classes(p4.heightmap).long()
    raised = c4 - c3  # 4 cm (3.2 classes) up where the network predicted above its frame's floor (up to the top class)
    assert ((raised == 0) | (raised == 3) | (raised == 4) | (c4 == anchored.num_classes - 1)).all() and (raised >= 3).any()
    # the targets of the loss: a cube set on either column is the same target in the network's frame
    before3, target3 = anchored.frame_targets(three, _column(4), action)
    before4, target4 = anchored.frame_targets(four, _column(5), action)
    assert torch.equal(before3, before4) and torch.equal(target3, target4)
    plain_before, plain_target = plain.frame_targets(four, _column(5), action)
    assert torch.equal(plain_target, plain.frame_classes(_column(5), action)) and not torch.equal(plain_target, target4)


def test_height_anchor_maps_predictions_back_and_rejects_bad_settings():
    _, anchored = _anchored_pair(0.08)
    predicted, before = torch.tensor([0, 0, 5, 0]).view(1, 1, 2, 2), torch.tensor([2, 9, 1, 4]).view(1, 1, 2, 2)
    shift = torch.tensor(0.05).view(1, 1, 1, 1)  # 4 classes of 1.25 cm
    assert anchored.from_model_frame(predicted, before, shift).flatten().tolist() == [2, 4, 9, 4]
    # the shift is measured under the fingers: 3 cm above the 8 cm anchor at a 11 cm block, none beside it, none for
    # less than half a class (0.625 cm) above it
    scene = torch.zeros(3, 1, 128, 128)
    scene[:, :, 58:71, 58:71] = torch.tensor([0.11, 0.11, 0.086]).view(3, 1, 1, 1)
    shifts = anchored.frame_shift(scene, torch.tensor([[64, 64, 2], [64, 90, 0], [64, 64, 0]])).flatten()
    assert torch.allclose(shifts, torch.tensor([0.03, 0.0, 0.0]))
    from ldm_rl.world_model import build_dynamics_model

    with pytest.raises(ValueError, match=r"height_anchor must be None or metres in \(0, max_height=0.25\), got 0.3"):
        build_dynamics_model({**TINY, "height_anchor": 0.3}, 0.25)
    with pytest.raises(ValueError, match="the Naive model's global frame has none"):
        build_dynamics_model({**TINY, "name": "naive", "height_anchor": 0.08}, 0.25)


def test_height_anchor_config_errors_name_the_setting():
    from test_config import make_cfg

    from ldm_rl import config_schema

    with pytest.raises(config_schema.ConfigError, match="model.height_anchor=0.3 must be below env.max_height=0.25"):
        config_schema.validate_config(make_cfg("model.height_anchor=0.3"), config_schema.TrainDynamicsConfig)
    with pytest.raises(config_schema.ConfigError, match="model=naive has none"):
        config_schema.validate_config(make_cfg("model=naive", "model.height_anchor=0.08"), config_schema.TrainDynamicsConfig)
    config_schema.validate_config(make_cfg("model.height_anchor=0.08"), config_schema.TrainDynamicsConfig)
