"""FC-DQN: the Q FCN alone, acting on its Q map and trained with DQN targets (the paper's model-free baseline).

Policy :class:`~ldm_rl.planning.q_map.QMapPolicy` (argmax when greedy, one ``softmax(Q/τ)`` draw while exploring),
loss :class:`~ldm_rl.objectives.SpatialDQNLoss`; one Adam optimiser with StepLR, the Q gradient clamp and a
:class:`~ldm_rl.objectives.TargetSync` every ``target_update_interval`` updates, as the LDM agent's Q.
"""

from __future__ import annotations

from tensordict import TensorDictBase

from ldm_rl.agents.base import TargetNetworkAgent
from ldm_rl.objectives.dqn import SpatialDQNLoss
from ldm_rl.planning.q_map import QMapPolicy

__all__ = ["FCDQNAgent"]


class FCDQNAgent(TargetNetworkAgent):
    """The FC-DQN baseline: :class:`QMapPolicy` trained by :class:`SpatialDQNLoss`. ``lr`` /
    ``weight_decay``: dicts with a ``q`` entry (other entries are not used)."""

    name = "fcdqn"

    def __init__(self, policy: QMapPolicy, loss: SpatialDQNLoss, *, q_grad_clip: float | None = 1.0, **kwargs) -> None:
        super().__init__(policy, loss, {"q": policy.q_network}, q_grad_clip=q_grad_clip, **kwargs)

    def pretrain_update(self, batch: TensorDictBase) -> dict[str, float]:
        """Nothing to pretrain: FC-DQN has no model, and its Q network learns in :meth:`update` only, as
        the LDM agent's Q does (``schedule.pretrain_updates`` trains the LDM agent's model alone)."""
        return {}

    def update(self, batch: TensorDictBase) -> dict[str, float]:
        self._train_mode()
        out = self.loss(batch)
        self._step(out["loss_q"])
        return {key: float(value.detach()) for key, value in out.items()}
