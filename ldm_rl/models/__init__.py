"""Pure ``nn.Module`` networks of ldm_rl (no TorchRL, nothing from the layers above).

The LDM depth UNet and its two-head router; the Q FCN and V CNN of the agent.
"""

from ldm_rl.models.blocks import count_parameters
from ldm_rl.models.dynamics_net import TwoHeadDynamicsNet, encode_depth_inputs
from ldm_rl.models.unet import DepthUNet

__all__ = ["DepthUNet", "TwoHeadDynamicsNet", "encode_depth_inputs", "count_parameters"]
