"""Training objectives: the LDM focal loss, the agents' losses (lookahead Q/V, DQN, Random Shooting, reward head)
and their target updater."""

from ldm_rl.objectives.bootstrap_cache import BootstrapCache
from ldm_rl.objectives.dqn import SpatialDQNLoss
from ldm_rl.objectives.focal import depth_class_weights, focal_loss
from ldm_rl.objectives.ldm_loss import LDMLoss
from ldm_rl.objectives.random_shooting import RandomShootingLoss
from ldm_rl.objectives.reward_head import predicted_next_state, reward_head_loss
from ldm_rl.objectives.target_sync import TargetSync
from ldm_rl.objectives.value_lookahead import LookaheadLoss, draw_value_augmentation

__all__ = ["BootstrapCache", "LDMLoss", "LookaheadLoss", "RandomShootingLoss", "SpatialDQNLoss", "TargetSync",
           "focal_loss", "depth_class_weights", "draw_value_augmentation", "predicted_next_state", "reward_head_loss"]
