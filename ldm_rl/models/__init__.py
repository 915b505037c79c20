"""Networks of ldm_rl: the LDM depth UNet, its two-head router, and the model factory."""

from ldm_rl.models.dynamics_net import TwoHeadDynamicsNet, encode_depth_inputs
from ldm_rl.models.factory import PRESET_WIDTHS, build_dynamics_model, count_parameters
from ldm_rl.models.unet import DepthUNet

__all__ = ["DepthUNet", "TwoHeadDynamicsNet", "encode_depth_inputs", "build_dynamics_model", "count_parameters", "PRESET_WIDTHS"]
