"""Training objectives: the LDM focal loss."""

from ldm_rl.objectives.focal import depth_class_weights, focal_loss
from ldm_rl.objectives.ldm_loss import LDMLoss

__all__ = ["LDMLoss", "focal_loss", "depth_class_weights"]
