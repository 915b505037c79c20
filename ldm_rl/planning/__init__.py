"""Planning: proposing candidate actions from Q maps and choosing among their imagined outcomes.

``sampling`` is pure tensor code (torch + :mod:`ldm_rl.geometry`); keep this package import free of
torchrl and tensordict.
"""

from ldm_rl.planning.sampling import sample_candidates

__all__ = ["sample_candidates"]
