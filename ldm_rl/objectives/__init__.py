"""Training objectives: the LDM focal loss, the agent's lookahead Q/V losses and their target updater."""

from ldm_rl.objectives.bootstrap_cache import BootstrapCache
from ldm_rl.objectives.focal import depth_class_weights, focal_loss
from ldm_rl.objectives.ldm_loss import LDMLoss
from ldm_rl.objectives.target_sync import TargetSync
from ldm_rl.objectives.value_lookahead import LookaheadLoss

__all__ = ["BootstrapCache", "LDMLoss", "LookaheadLoss", "TargetSync", "focal_loss", "depth_class_weights"]
