"""ldm_rl: visual foresight with a Local Dynamics Model (Kohler & Platt), TorchRL-native.

Importing the package is cheap on purpose: torchrl, pybullet and friends are imported by the
submodules that need them (``ldm_rl.envs``, ``ldm_rl.models``...), never here.
"""

__version__ = "0.1.0"
