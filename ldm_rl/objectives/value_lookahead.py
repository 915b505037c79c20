"""``LookaheadLoss``: the Q and V losses of the LDM agent with one-step lookahead targets (paper §3.4).

Conventions (the reference's, which make ``Q̂(s, a) = V(f(s, a))`` right at the last step): ``V(s)``
includes the reward received on *arriving* in ``s``, so for a transition ``(s, a, r, s')``

* ``y_V = r + γ·(1 − terminated)·max_{a' ∈ Ā_N(s')} V⁻(f⁻(s', a'))`` is the target of ``V(s')`` — on the
  real next state and (option ``value_on_prediction``, the reference's t = 1 term) on the model's
  prediction ``f(s, a)``, the kind of state V scores when planning;
* ``y_Q = r + γ·(1 − terminated)·max_{a'} Q⁻(s', a')`` is the target of ``Q(s, a)`` (plain DQN max;
  option ``q_target="lookahead"``: ``y_Q = y_V``, the same return estimated through the lookahead, so Q
  learns to propose what V ranks first and avoids a max over R·H·W noisy entries);
* the reward head learns ``R(s') ≈ r`` on the same states (Random Shooting and Dyna-Q use it);
* with V's termination head (``VCNN(termination_head=True)``, not in the paper), ``T(s')`` learns the
  ``terminated`` flag on the same states (binary cross-entropy, ``loss_termination``), and V's Huber trains only
  the value head ``W`` of ``V = T·R + (1 − T)·W``: every V above (targets, planner) is the composed one.

``Ā_N(s')`` are N proposals drawn from the target Q map by
:func:`~ldm_rl.planning.sampling.sample_candidates` (argmax with inhibition by default: deterministic
targets). With ``double_value`` the best proposal is chosen by the online V and scored by the target V,
both on the target LDM's predictions (double estimation, as double DQN: the max of noisy scores is
biased upwards, the score of an independently chosen candidate is not). The target Q map is computed ONCE per state and serves both targets; the whole minibatch is
planned in one batched pass (``lookahead``), terminal transitions skipped. Target networks are the
``target_*_params`` of this module (TorchRL's ``convert_to_functional``), synced by a TorchRL target
updater (``HardUpdate``). Predictions for targets run in eval mode without gradients.

Priorities (reference): ``td_error = |V(s') − y_V|`` per sample, written into the batch under the
``priority`` key; losses are Huber (smooth L1) weighted by ``priority_weight`` when present. With a V on the log
scale (``VCNN(value_log_floor=ε)``, not in the paper) V's Huber and ``td_error`` read ``log V`` against
``log(max(y_V, ε))``; the targets themselves, their clamps and bounds, and every planner stay on the linear scale.
"""

from __future__ import annotations

import contextlib
import functools
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from tensordict import TensorDict, TensorDictBase, TensorDictParams
from tensordict.utils import NestedKey
from torch import nn

from ldm_rl import geometry, keys
from ldm_rl.objectives.bootstrap_cache import BootstrapCache
from ldm_rl.objectives.q_scale import QScale
from ldm_rl.objectives.reward_head import predicted_next_state
from ldm_rl.objectives.transition_loss import TransitionKeys, TransitionLoss
from ldm_rl.planning.lookahead import lookahead
from ldm_rl.planning.sampling import sample_candidates
from ldm_rl.torch_utils import eval_mode, swapped_parameters

__all__ = ["LookaheadLoss", "VALUE_AUGMENTATIONS", "draw_value_augmentation"]

VALUE_AUGMENTATIONS = (None, "quarter_turns", "shifts", "symmetries")


def _check_shift(shift) -> int:
    if isinstance(shift, bool) or not isinstance(shift, int) or shift < 1:
        raise ValueError(f"value_shift must be an int >= 1 (pixels), got {shift!r}")
    return shift


RAISE_REGIONS = ("object", "top")


def _check_raise(levels, height, region="object") -> tuple[int, float | None]:
    if isinstance(levels, bool) or not isinstance(levels, int) or levels < 0:
        raise ValueError(f"value_raise_levels must be an int >= 0 (0 = off), got {levels!r}")
    if region not in RAISE_REGIONS:
        raise ValueError(f"value_raise_region must be one of {RAISE_REGIONS}, got {region!r}")
    if levels == 0:
        return 0, None
    if isinstance(height, bool) or not isinstance(height, (int, float)) or not (0 < height < 1):
        raise ValueError(f"value_raise_height must be metres in (0, 1) when value_raise_levels={levels}, got {height!r}")
    return levels, float(height)


def draw_value_augmentation(kind: str | None, batch: int, *, shift: int = 4, raise_levels: int = 0,
                            raise_height: float | None = None, raise_region: str = "object", device=None):
    """One random draw per row of augmentation ``kind`` (:data:`VALUE_AUGMENTATIONS`; torch's global RNG), returned
    as ``heightmap [batch, 1, H, W] -> the same, transformed``: apply it to several images of a row (the real and
    the predicted next state) to move them alike. ``None``: the identity. ``"quarter_turns"``: a random quarter
    turn; ``"shifts"``: a random whole-pixel offset in ``[−shift, shift]`` per axis (the border read as 0 m);
    ``"symmetries"``: a quarter turn, a mirror (transpose) half the time, then a shift.

    ``raise_levels`` L > 0 (with any ``kind``): then the tallest object is raised by a random whole number of levels
    in ``[0, L]``, ``raise_height`` metres each (:func:`~ldm_rl.geometry.raise_tallest`, pixels above half a level
    counted as object), drawn per row and applied to each image of the row. ``raise_region``: ``"object"`` raises
    everything connected to the highest pixel, ``"top"`` only what lies within half a level of it (the top cube:
    a cube leaning on the stack stays down)."""
    if kind not in VALUE_AUGMENTATIONS:
        raise ValueError(f"value_augmentation must be one of {VALUE_AUGMENTATIONS}, got {kind!r}")
    _check_shift(shift)
    raise_levels, raise_height = _check_raise(raise_levels, raise_height, raise_region)
    band = raise_height / 2 if raise_levels and raise_region == "top" else None
    turns = torch.randint(4, (batch,), device=device) if kind in ("quarter_turns", "symmetries") else None
    mirror = (torch.rand(batch, device=device) < 0.5).view(batch, 1, 1, 1) if kind == "symmetries" else None
    offsets = (torch.randint(-shift, shift + 1, (batch, 2), device=device) if kind in ("shifts", "symmetries")
               else None)
    lift = (torch.randint(raise_levels + 1, (batch,), device=device) * raise_height if raise_levels else None)
    if kind is None and lift is None:
        return lambda heightmap: heightmap

    def transform(heightmap: torch.Tensor) -> torch.Tensor:
        if turns is not None:
            heightmap = geometry.quarter_turns(heightmap, turns)
        if mirror is not None:
            heightmap = torch.where(mirror, heightmap.transpose(-2, -1), heightmap)
        if offsets is not None:
            heightmap = geometry.shift(heightmap, offsets)
        return heightmap if lift is None else geometry.raise_tallest(heightmap, lift, floor=raise_height / 2, band=band)
    return transform


def expert_outcome_gaps(q_network: nn.Module, dynamics: nn.Module, score, heightmap: torch.Tensor,
                        in_hand: torch.Tensor, holding: torch.Tensor, expert: torch.Tensor, num_candidates: int,
                        margin: float, proposal: dict | None = None) -> torch.Tensor:
    """How far a value ranks the expert's predicted outcome below the best of Q's proposals' (the value margin term).

    ``heightmap`` ``[n, 1, H, W]`` float32 (metres), ``in_hand`` ``[n, 1, h, h]``, ``holding`` ``[n]`` or ``[n, 1]``
    bool, ``expert`` ``[n, 3]`` long (row, col, rotation bin): the expert's actions. Q proposes ``num_candidates`` actions
    per state (:func:`sample_candidates` with ``proposal``), the LDM predicts every outcome, Q and the LDM in eval
    mode without gradients; ``score(predicted)`` gives ``[n·(1 + N), 1]`` values of the predicted states (the
    caller sets V's mode and gradient). Returns ``max_i [score(f(s, a_i)) + margin·1(a_i ≠ a_E)] − score(f(s, a_E))``,
    ``[n]`` float32 in the score's units: ≤ 0 once the expert's outcome leads every other proposal's by ``margin``.
    """
    with torch.no_grad(), eval_mode(q_network, dynamics):
        proposals = sample_candidates(q_network(heightmap, in_hand, holding).float(), num_candidates,
                                      **(proposal or {}))  # [n, N, 3]
        actions = torch.cat((expert.unsqueeze(1), proposals), 1)  # [n, 1 + N, 3]: the expert's first
        m = actions.shape[1]
        predicted = dynamics.predict(heightmap.repeat_interleave(m, 0), in_hand.repeat_interleave(m, 0),
                                     holding.repeat_interleave(m, 0), actions.reshape(-1, 3))
    values = score(predicted).reshape(-1, m)
    lead = torch.where((proposals == expert.unsqueeze(1)).all(-1), 0.0, margin)  # [n, N]
    return (values[:, 1:] + lead).amax(1) - values[:, 0]


class LookaheadLoss(TransitionLoss):
    """Q loss, V loss (real and predicted next states) and reward-head loss with lookahead targets.

    Args:
        q_network: ``(heightmap, in_hand, holding) -> [B, R, H, W]`` with ``action_values(..., action) -> [B]``.
        dynamics: the :class:`~ldm_rl.world_model.DynamicsModel` (only its target copy is used here; the
            LDM's own loss is :class:`~ldm_rl.objectives.LDMLoss`).
        value_network: ``(heightmap, in_hand) -> [B, 1]`` with ``value_and_reward``.
        gamma: discount γ (γ = 1 is the paper's ``r + max Q̂``; the reference uses 0.95).
        num_target_candidates: N of the target's ``max`` over ``Ā_N(s')``.
        target_proposal: keyword arguments of ``sample_candidates`` for the target proposals
            (``mode``, ``tau``, ``beta``, ``sigma``, ``sigma_rot``).
        value_on_prediction: also fit ``V(f(s, a))`` to ``y_V`` (uses ``next_logits`` from the LDM loss
            when the batch holds them, else one eval-mode prediction).
        chunk_size: state-candidate pairs per LDM/V pass of the targets.
        target_range: ``(low, high)`` the returns can take, or None; the bootstrapped next-state values
            and both targets are clamped into it. Every
            task here rewards only on termination, with a reward in [0, 1], so returns lie in [0, 1]: the
            clamp stops the max over predicted states (amplified by 1/(1−γ)) from feeding on itself
            (measured: y_V 0.9 → 3.6 within 200 updates without it).
        target_uncertainty_penalty: λ ≥ 0: the target's max over ``Ā_N(s')`` scores each proposal
            ``V⁻(f⁻(s', a')) − λ·H⁻(s', a')``, ``H⁻`` the target LDM's mean pixel entropy (nats; with
            ``double_value`` the online choice is penalised alike). 0 = the paper; not in the paper.
        q_log_floor: None (the paper: Q regresses ``y_Q``) or ε in (0, 1): Q regresses ``log(max(y_Q, ε))``
            (:class:`~ldm_rl.objectives.q_scale.QScale`; the targets themselves are unchanged). Not in the paper.
        double_value: choose the target candidate with the online V, score it with the target V.
        q_target: ``"max"`` (the paper: ``r + γ max Q⁻(s')``) or ``"lookahead"`` (``y_Q = y_V``).
        return_lower_bound: raise both targets to the batch's ``return_to_go`` where it is higher
            (:meth:`~ldm_rl.objectives.TransitionLoss.lower_bounded`; not in the paper).
        bootstrap_cache: keep up to this many transitions' bootstraps (keyed by the batch's ``index``)
            until the next target copy (:class:`~ldm_rl.objectives.BootstrapCache`; 0 = off). The
            targets are the same; only rows not seen since the last copy run the target networks.
        value_augmentation: ``None`` or ``"quarter_turns"``: V (and its reward head) is fitted on each next
            state turned by its own random multiple of 90° about the heightmap's centre (torch's global
            RNG). Every task here is invariant under it (square workspace, scenes drawn uniformly with
            random yaws, physics and success blind to a turn about the vertical); Q and the LDM are
            equivariant to quarter turns by construction, the V CNN is not, and it is the one network fitted
            on whole scenes. The targets are computed on the states as stored (a turn leaves them unchanged).
            ``"shifts"``: each next state moved by its own random whole-pixel offset, uniform in
            ``[−value_shift, value_shift]`` per axis, the uncovered border read as table (0 m): the random
            shifts of DrQ / RAD. A scene's value does not depend on where on the table it stands; V's fully
            connected head is the one part of the agent that can tell, and it can memorise the few scenes seen.
            ``"symmetries"``: all of the workspace's exact pixel symmetries at once — a random quarter turn, a
            mirror (transpose) with probability 1/2, then a random shift (the in-hand image is left as it is).
        value_shift: the largest shift of ``"shifts"`` and ``"symmetries"``, pixels (≥ 1). An object standing
            within that many pixels of the workspace's edge may be cut by a shift: keep it to a few pixels.
        value_raise_levels: L ≥ 0 (0 = off; not in the paper): V (and its reward head) is fitted on each next state
            (real and predicted) with its tallest object raised by a random number of levels in ``[0, L]``, ``value_raise_height``
            metres each, as if that many objects stood under it, toward the same targets. Block stacking's value
            depends on how many blocks are not yet on the tower, not on the tower's height: a 2-stack beside a
            loose block is as far from done as a 4-stack beside one. Trained on 2 and 3 blocks, V has only seen
            towers of at most three, and on 5 blocks rated "a 4-stack beside a fallen block" as solved
            (docs/policy.md, "Table 2 (blocks)"); raised towers show it that a loose block beside a tall one is
            not. A task prior, right for stacking; not for tasks whose goal has a height (house building).
        value_raise_height: metres of one level (block stacking: the cube's 0.04 m); needed when L > 0.
        value_raise_region: ``"object"``: everything connected to the tallest pixel goes up (a cube touching the
            stack goes up with it); ``"top"``: only what lies within half a level of the top (the top cube), so a
            cube leaning on a raised stack stays beside it — the scene the ``"object"`` raise never shows V
            (docs/policy.md, "V fitted on raised towers").
        q_proposal_fit: M in [0, N]: Q is also fitted, at each live next state ``s'``, on the first M of its
            target proposals ``Ā_N(s')`` (the target Q map's best, then the next after inhibition), toward
            ``V⁻(f⁻(s', a'))``, the score the target already computed for them (clamped to ``target_range``):
            the model-based ``Q̂(s', a') = V(f(s', a'))`` of the paper, on actions Q itself ranks high, not only
            on the action taken. A proposal Q rates high and V rates low (a pick that would come up empty) is
            pushed down. Costs one Q training pass per pair; 0 = off (the paper). Not in the paper.
        expert_margin_weight, expert_margin, expert_margin_rows, expert_margin_temperature: λ (0 = off, the
            paper), l, the row cap and the soft max's τ (0 = the hard max) of DQfD's large-margin term on the
            expert rows, added to ``loss_q`` as λ times it and reported as ``expert_margin`` (:meth:`~ldm_rl.objectives.TransitionLoss.expert_margin_loss`): Q, which only
            proposes, learns to rank the expert's pose first. Not in the paper.
        value_margin_weight, value_margin: λ_V (0 = off, the paper) and l_V (V's fitted units) of the same
            large-margin term on the scores the agent decides by, ``V(f(s, a))`` (:meth:`value_margin_loss`), on
            the first ``expert_margin_rows`` expert rows: V learns to rank the predicted outcome of the expert's
            action above those of Q's proposals. Added to ``loss_value`` as λ_V times it and reported as
            ``value_margin``. Not in the paper.
    """

    @dataclass
    class _AcceptedKeys(TransitionKeys):
        """Input/output keys; change them with ``loss.set_keys(...)``."""

        next_logits: NestedKey = keys.NEXT_LOGITS

    default_keys = _AcceptedKeys
    tensor_keys: _AcceptedKeys

    q_network: nn.Module
    q_network_params: TensorDictParams
    target_q_network_params: TensorDictParams
    value_network: nn.Module
    value_network_params: TensorDictParams
    target_value_network_params: TensorDictParams
    dynamics: nn.Module
    dynamics_params: TensorDictParams
    target_dynamics_params: TensorDictParams

    def __init__(
        self,
        q_network: nn.Module,
        dynamics: nn.Module,
        value_network: nn.Module,
        *,
        gamma: float = 0.95,
        num_target_candidates: int = 10,
        target_proposal: dict | None = None,
        value_on_prediction: bool = True,
        chunk_size: int = 64,
        target_range: tuple[float, float] | None = None,
        double_value: bool = False,
        q_target: str = "max",
        return_lower_bound: bool = False,
        bootstrap_cache: int = 0,
        value_augmentation: str | None = None,
        value_shift: int = 4,
        value_raise_levels: int = 0,
        value_raise_height: float | None = None,
        value_raise_region: str = "object",
        target_uncertainty_penalty: float = 0.0,
        q_log_floor: float | None = None,
        q_proposal_fit: int = 0,
        expert_margin_weight: float = 0.0,
        expert_margin: float = 0.1,
        expert_margin_rows: int = 4,
        expert_margin_temperature: float = 0.0,
        value_margin_weight: float = 0.0,
        value_margin: float = 0.01,
    ) -> None:
        super().__init__()
        for name, value, ok, want in (("value_margin_weight", value_margin_weight, lambda v: v >= 0, "a number >= 0 (0 = off)"),
                                      ("value_margin", value_margin, lambda v: v > 0, "a number > 0 (V's fitted units)")):
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not ok(value):
                raise ValueError(f"{name} must be {want}, got {value!r}")
        self.value_margin_weight, self.value_margin = float(value_margin_weight), float(value_margin)
        self.q_scale = QScale(q_log_floor)
        self.value_scale = QScale(getattr(value_network, "value_log_floor", None))
        self.set_expert_margin(expert_margin_weight, expert_margin, expert_margin_rows, expert_margin_temperature)
        if isinstance(target_uncertainty_penalty, bool) or not isinstance(target_uncertainty_penalty, (int, float)) \
                or not target_uncertainty_penalty >= 0:
            raise ValueError(f"target_uncertainty_penalty must be a number >= 0 (V units per nat), "
                             f"got {target_uncertainty_penalty!r}")
        self.target_uncertainty_penalty = float(target_uncertainty_penalty)
        if value_augmentation not in VALUE_AUGMENTATIONS:
            raise ValueError(f"value_augmentation must be one of {VALUE_AUGMENTATIONS}, got {value_augmentation!r}")
        self.value_augmentation = value_augmentation
        self.value_shift = _check_shift(value_shift)
        self.value_raise_levels, self.value_raise_height = _check_raise(value_raise_levels, value_raise_height,
                                                                        value_raise_region)
        self.value_raise_region = value_raise_region
        self.return_lower_bound = bool(return_lower_bound)
        if q_target not in ("max", "lookahead"):
            raise ValueError(f"q_target must be 'max' or 'lookahead', got {q_target!r}")
        self.q_target, self.double_value = q_target, bool(double_value)
        if target_range is not None and not (len(target_range) == 2 and target_range[0] < target_range[1]):
            raise ValueError(f"target_range must be None or (low, high) with low < high, got {target_range!r}")
        self.target_range = None if target_range is None else (float(target_range[0]), float(target_range[1]))
        if not 0.0 <= gamma <= 1.0:
            raise ValueError(f"gamma must be in [0, 1], got {gamma!r}")
        if not isinstance(num_target_candidates, int) or num_target_candidates < 1:
            raise ValueError(f"num_target_candidates must be a positive int, got {num_target_candidates!r}")
        if isinstance(q_proposal_fit, bool) or not isinstance(q_proposal_fit, int) \
                or not 0 <= q_proposal_fit <= num_target_candidates:
            raise ValueError(f"q_proposal_fit must be an int in [0, num_target_candidates={num_target_candidates}], "
                             f"got {q_proposal_fit!r}")
        self.q_proposal_fit = q_proposal_fit
        self.convert_to_functional(q_network, "q_network", create_target_params=True)
        self.convert_to_functional(value_network, "value_network", create_target_params=True)
        self.convert_to_functional(dynamics, "dynamics", create_target_params=True)
        self.gamma, self.num_target_candidates = float(gamma), num_target_candidates
        self.target_proposal = {"mode": "argmax", "tau": 1.0, "beta": 1.0, "sigma": 2.0, "sigma_rot": 1.0, **(target_proposal or {})}
        self.value_on_prediction, self.chunk_size = bool(value_on_prediction), int(chunk_size)
        if not isinstance(bootstrap_cache, int) or isinstance(bootstrap_cache, bool) or bootstrap_cache < 0:
            raise ValueError(f"bootstrap_cache must be an int >= 0 (0 = off), got {bootstrap_cache!r}")
        if bootstrap_cache and self.target_proposal["mode"] != "argmax":
            raise ValueError(f"bootstrap_cache={bootstrap_cache} needs deterministic target proposals "
                             f"(target_proposal mode 'argmax'), got mode {self.target_proposal['mode']!r}")
        self.bootstrap_cache = BootstrapCache(bootstrap_cache, max_height=dynamics.max_height,
                                              num_classes=dynamics.num_classes) if bootstrap_cache else None

    @property
    def termination(self) -> bool:
        """Whether V has a termination head (:class:`~ldm_rl.models.v_cnn.VCNN`'s ``termination_head``): then
        the loss also fits it, ``loss_termination``, binary cross-entropy toward ``terminated``."""
        return getattr(self.value_network, "termination_head", None) is not None

    @property
    def out_keys(self) -> list[str]:
        return ["loss_q", "loss_value", "loss_reward", *(["loss_termination"] if self.termination else []),
                "q_target", "value_target", "state_value", "td_error",
                *(["expert_margin"] if self.expert_margin_weight else []),
                *(["value_margin"] if self.value_margin_weight else [])]

    @contextlib.contextmanager
    def target_networks(self):
        """Within the block ``self.q_network`` / ``value_network`` / ``dynamics`` carry the target weights."""
        with swapped_parameters(self.q_network, self.target_q_network_params), \
                swapped_parameters(self.value_network, self.target_value_network_params), \
                swapped_parameters(self.dynamics, self.target_dynamics_params):
            yield

    def targets_changed(self) -> None:
        """Called by :class:`~ldm_rl.objectives.TargetSync` after each copy: the cached bootstraps are stale."""
        if self.bootstrap_cache is not None:
            self.bootstrap_cache.clear()

    def targets(self, tensordict: TensorDictBase) -> tuple[torch.Tensor, torch.Tensor]:
        """``(y_Q, y_V)``, each ``[B, 1]`` float32, for a flat batch of transitions (target networks)."""
        return self._targets(tensordict)[:2]

    @torch.no_grad()
    def _targets(self, tensordict: TensorDictBase):
        """``(y_Q, y_V, fit)``: the targets and, with ``q_proposal_fit`` M > 0, ``fit = (rows [b], actions
        [b, M, 3], values [b, M])``: the live rows, their next states' first M target proposals and those
        proposals' clamped target scores (else None)."""
        k = self.tensor_keys
        fit = None
        reward = tensordict.get(k.reward).reshape(-1, 1).float()
        live = ~tensordict.get(k.terminated).reshape(-1).bool()
        q_next = torch.zeros_like(reward)
        v_next = torch.zeros_like(reward)
        rows = live.nonzero().squeeze(1)
        if rows.numel():
            heightmap = tensordict.get((keys.NEXT, k.heightmap)).index_select(0, rows)
            in_hand = tensordict.get((keys.NEXT, k.in_hand)).index_select(0, rows)
            holding = tensordict.get((keys.NEXT, k.holding)).reshape(-1, 1).bool().index_select(0, rows)
            index = tensordict.get(k.index, None)
            boot = self._bootstrap(None if index is None else index.reshape(-1).index_select(0, rows),
                                   heightmap, in_hand, holding)
            q_next[rows] = self.q_scale.decode(boot["q_max"])
            scores = boot["target_values"]
            if self.double_value:  # (target V, online V) of each predicted state: [b, N, 2]
                online = self._online_values(boot)
                if self.target_uncertainty_penalty:
                    online = online - self.target_uncertainty_penalty * boot["entropy"]
                scores = torch.stack((scores, online), -1)
            if self.target_range is not None:  # a state's value is a return too: bootstrap from values in range
                scores, q_next = scores.clamp(*self.target_range), q_next.clamp(*self.target_range)
            if self.q_proposal_fit:
                m = self.q_proposal_fit
                fit = (rows, boot["target_actions"], (scores[..., 0] if self.double_value else scores)[:, :m])
            if self.double_value:
                best = scores[..., 1].argmax(1, keepdim=True)
                v_next[rows] = scores[..., 0].gather(1, best)
            else:
                v_next[rows] = scores.amax(1, keepdim=True)
        y_v = self.lower_bounded(reward + self.gamma * v_next, tensordict)
        y_q = y_v.clone() if self.q_target == "lookahead" else self.lower_bounded(reward + self.gamma * q_next, tensordict)
        if self.target_range is not None:
            y_q, y_v = y_q.clamp(*self.target_range), y_v.clamp(*self.target_range)
        return y_q, y_v, fit

    def _bootstrap(self, index, heightmap, in_hand, holding) -> dict[str, torch.Tensor]:
        """What the target networks say about the next states ``[b]``, from the cache where it has them:
        ``q_max [b, 1]``, ``target_values [b, N]`` (target V of each proposal's predicted state, less
        ``λ·entropy`` with a ``target_uncertainty_penalty``) and, for ``double_value``, the predicted states as depth classes ``next_heightmap [b, N, 1, H, W]`` and
        ``next_in_hand [b, N, 1, h, h]`` (uint8)."""
        cache = self.bootstrap_cache if index is not None else None
        if cache is None:
            return self._fresh_bootstrap(heightmap, in_hand, holding)
        slot, found = cache.lookup(index, heightmap, in_hand, holding)
        miss = (~found).nonzero().squeeze(1)
        if miss.numel() == found.numel():
            fresh = self._fresh_bootstrap(heightmap, in_hand, holding)
            cache.put(index, heightmap, in_hand, holding, fresh)
            return fresh
        hit = found.nonzero().squeeze(1)
        out = {name: cache.get(slot.index_select(0, hit), name) for name in self._bootstrap_names()}
        if miss.numel():
            parts = [x.index_select(0, miss) for x in (heightmap, in_hand, holding)]
            fresh = self._fresh_bootstrap(*parts)
            cache.put(index.index_select(0, miss), *parts, fresh)
            out = {name: torch.empty((found.numel(), *value.shape[1:]), dtype=value.dtype, device=value.device)
                   .index_copy_(0, hit, value).index_copy_(0, miss, fresh[name]) for name, value in out.items()}
        return out

    def _bootstrap_names(self) -> tuple[str, ...]:
        names = ("q_max", "target_values") + (("next_heightmap", "next_in_hand") if self.double_value else ())
        names += ("target_actions",) if self.q_proposal_fit else ()
        return names + (("entropy",) if self.double_value and self.target_uncertainty_penalty else ())

    def _fresh_bootstrap(self, heightmap, in_hand, holding) -> dict[str, torch.Tensor]:
        """:meth:`_bootstrap` computed with the target networks, in one batched pass."""
        with self.target_networks(), eval_mode(self.q_network, self.value_network, self.dynamics):
            q_map = self.q_network(heightmap, in_hand, holding).float()  # float32 also under bf16 autocast
            candidates = sample_candidates(q_map, self.num_target_candidates, **self.target_proposal)
            result = lookahead(self.dynamics, self.value_network, heightmap, in_hand, holding, candidates,
                               chunk_size=self.chunk_size, with_states=self.double_value,
                               with_entropy=bool(self.target_uncertainty_penalty))
        out = {"q_max": q_map.flatten(1).amax(1, keepdim=True), "target_values": result.values.float()}
        if self.q_proposal_fit:
            out["target_actions"] = candidates[:, : self.q_proposal_fit]
        if self.target_uncertainty_penalty:
            out["target_values"] = out["target_values"] - self.target_uncertainty_penalty * result.entropy
            if self.double_value:  # the online choice among the same predictions is penalised alike
                out["entropy"] = result.entropy
        if self.double_value:  # V reads heights as depth classes: uint8 classes are exact and 4x smaller
            classes = geometry.heights_to_classes
            out["next_heightmap"] = classes(result.next_heightmap, self.dynamics.max_height, self.dynamics.num_classes).to(torch.uint8)
            out["next_in_hand"] = classes(result.next_in_hand, self.dynamics.max_height, self.dynamics.num_classes).to(torch.uint8)
        return out

    def _online_values(self, boot: dict[str, torch.Tensor]) -> torch.Tensor:
        """``[b, N]``: the online V of the predicted states in ``boot`` (eval mode, chunks of ``chunk_size``)."""
        b, n = boot["target_values"].shape
        decode = functools.partial(geometry.classes_to_heights, max_height=self.dynamics.max_height,
                                   num_classes=self.dynamics.num_classes)
        heightmap, in_hand = boot["next_heightmap"].flatten(0, 1), boot["next_in_hand"].flatten(0, 1)
        with eval_mode(self.value_network):
            values = [self.value_network(decode(heightmap[i : i + self.chunk_size].long()),
                                         decode(in_hand[i : i + self.chunk_size].long())).float()
                      for i in range(0, b * n, self.chunk_size)]
        return torch.cat(values).reshape(b, n)

    def _proposal_fit_loss(self, tensordict, weight, rows, actions, values) -> torch.Tensor:
        """Huber loss of ``Q(s', a')`` against ``values`` for the live rows' next states ``s'`` and their
        proposals ``actions [b, M, 3]`` (each pair weighted by its row's importance weight; 0 without rows)."""
        if rows.numel() == 0:
            return weight.new_zeros(())
        k, m = self.tensor_keys, actions.shape[1]
        state = [tensordict.get((keys.NEXT, key)).index_select(0, rows).repeat_interleave(m, 0)
                 for key in (k.heightmap, k.in_hand)]
        holding = tensordict.get((keys.NEXT, k.holding)).reshape(-1).bool().index_select(0, rows).repeat_interleave(m)
        q_pred = self.q_network.action_values(*state, holding, actions.reshape(-1, 3)).reshape(-1, 1)
        loss = F.smooth_l1_loss(q_pred, self.q_scale.encode(values.reshape(-1, 1)), reduction="none")
        return (loss * weight.index_select(0, rows).repeat_interleave(m, 0)).mean()

    def value_margin_loss(self, tensordict: TensorDictBase) -> torch.Tensor | None:
        """DQfD's large-margin term on the lookahead's scores of the batch's expert rows; None when off.

        For each of the first ``expert_margin_rows`` rows whose ``is_expert`` is set, with ``a_E`` its action and
        ``a_1 … a_N`` the online Q's proposals at ``s`` (``sample_candidates`` with the target proposal's settings,
        N = ``num_target_candidates``; eval mode, no gradient), the online LDM predicts every outcome (eval mode, no
        gradient) and the online V scores them, on its fitted scale: ``max(0, max_i [V(f(s, a_i)) + l·1(a_i ≠ a_E)]
        − V(f(s, a_E)))``, zero once the expert's outcome leads every proposal's by ``l``. Returns the mean over those
        rows, ``[]`` float32 (0 without expert rows); the gradient reaches V alone. The TD loss tells V what states
        are worth on average; this term tells it, on the states the demonstrations come from, that the outcome the
        expert chose ranks above the ones the agent would pick among. Costs (N + 1) LDM predictions and V passes
        per row.
        """
        if not self.value_margin_weight:
            return None
        k = self.tensor_keys
        rows = self.expert_rows(tensordict, "value_margin_weight")
        if rows.numel() == 0:
            return tensordict.get(k.heightmap).new_zeros(())
        heightmap, in_hand = (tensordict.get(key).index_select(0, rows) for key in (k.heightmap, k.in_hand))
        holding = tensordict.get(k.holding).reshape(-1, 1).bool().index_select(0, rows)
        expert = tensordict.get(k.action).reshape(-1, 3).long().index_select(0, rows)
        gaps = expert_outcome_gaps(
            self.q_network, self.dynamics,
            lambda predicted: self._fitted_value(self.value_network(predicted.heightmap, predicted.in_hand).float()),
            heightmap, in_hand, holding, expert, self.num_target_candidates, self.value_margin, self.target_proposal)
        return gaps.clamp_min(0).mean()

    def _fitted_value(self, value: torch.Tensor) -> torch.Tensor:
        """V ``[B, 1]`` on the scale its loss reads: itself, or ``log V`` for a log-scale V (whose V = exp(head) > 0;
        the clamp only guards an exponential that underflowed)."""
        return value if self.value_scale.log_floor is None else value.clamp_min(torch.finfo(value.dtype).tiny).log()

    def _draw_augmentation(self, batch: int, device):
        """:func:`draw_value_augmentation` of this loss's ``value_augmentation``, ``value_shift`` and raise."""
        return draw_value_augmentation(self.value_augmentation, batch, shift=self.value_shift,
                                       raise_levels=self.value_raise_levels, raise_height=self.value_raise_height,
                                       raise_region=self.value_raise_region,
                                       device=device)

    def forward(self, tensordict: TensorDictBase) -> TensorDict:
        self.check_batch(tensordict)
        k = self.tensor_keys
        q_target, v_target, fit = self._targets(tensordict)
        weight = self.importance_weights(tensordict, q_target)

        def huber(pred, target):
            return (F.smooth_l1_loss(pred, target, reduction="none") * weight).mean()

        fitted_target = self.value_scale.encode(v_target)

        def value_huber(value):
            """V's Huber on its fitted scale (log V against log(max(y_V, ε)) with a log-scale V)."""
            return huber(self._fitted_value(value), fitted_target)

        state = [tensordict.get(key) for key in (k.heightmap, k.in_hand, k.holding)]
        q_pred = self.q_network.action_values(*state, tensordict.get(k.action)).reshape(-1, 1)
        next_heightmap = tensordict.get((keys.NEXT, k.heightmap))
        next_in_hand = tensordict.get((keys.NEXT, k.in_hand))
        reward = tensordict.get(k.reward).reshape(-1, 1).float()
        terminated = tensordict.get(k.terminated).reshape(-1, 1).float()
        augmented = self._draw_augmentation(next_heightmap.shape[0], next_heightmap.device)

        def fitted(heightmap):
            """(V, R, termination loss or None) of next states ``heightmap`` [B, 1, H, W]. With a termination
            head, V's Huber trains the value head alone: T and R enter V detached, each fitted on its own label."""
            if not self.termination:
                return (*self.value_network.value_and_reward(heightmap, next_in_hand), None)
            going_on, r, logit = self.value_network.heads(heightmap, next_in_hand)
            bce = F.binary_cross_entropy_with_logits(logit.float(), terminated, reduction="none")
            return self.value_network.compose(going_on, r.detach(), logit.detach()), r, (bce * weight).mean()

        v_real, r_real, loss_termination = fitted(augmented(next_heightmap))
        loss_value, loss_reward = value_huber(v_real), huber(r_real, reward)
        if self.value_on_prediction:
            predicted = predicted_next_state(self.dynamics, tensordict, logits_key=k.next_logits,
                                             state_keys=(k.heightmap, k.in_hand, k.holding, k.action))
            v_pred, r_pred, bce_pred = fitted(augmented(predicted.heightmap))
            loss_value = loss_value + value_huber(v_pred)
            loss_reward = loss_reward + huber(r_pred, reward)
            loss_termination = None if bce_pred is None else loss_termination + bce_pred
        td_error = (self._fitted_value(v_real.detach()) - fitted_target).abs().reshape(-1)
        tensordict.set(k.priority, td_error)
        loss_q = huber(q_pred, self.q_scale.encode(q_target))
        if fit is not None:
            loss_q = loss_q + self._proposal_fit_loss(tensordict, weight, *fit)
        margin = self.expert_margin_loss(self.q_network, tensordict)
        if margin is not None:
            loss_q = loss_q + self.expert_margin_weight * margin
        value_margin = self.value_margin_loss(tensordict)
        if value_margin is not None:
            loss_value = loss_value + self.value_margin_weight * value_margin
        out = {"loss_q": loss_q, "loss_value": loss_value, "loss_reward": loss_reward}
        if margin is not None:
            out["expert_margin"] = margin.detach()
        if value_margin is not None:
            out["value_margin"] = value_margin.detach()
        if loss_termination is not None:
            out["loss_termination"] = loss_termination
        out.update(q_target=q_target.mean(), value_target=v_target.mean(), state_value=v_real.detach().mean(),
                   td_error=td_error.mean())
        return TensorDict(out, batch_size=[])
