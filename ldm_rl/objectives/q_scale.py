"""``QScale``: the scale on which a Q map regresses its returns, linear (the paper) or logarithmic.

Every policy here uses Q only to *rank* actions within one state (argmax, proposals drawn with inhibition or
from ``softmax(Q / τ)``), so Q may regress any increasing map of the return. The log map
``q = log(max(y, floor))`` (van Seijen et al., NeurIPS 2019: a logarithmic mapping for small action gaps)
makes the gap between two actions depend on their returns' *ratio*, not their difference. With a sparse
terminal reward ``R`` and discount γ, a state ``k`` primitives from the end is worth ≈ ``γ^k R`` and a wasted
primitive (a pick that comes up empty) costs a factor γ: on a linear scale that gap is ``(1 − γ)·γ^k·R``
(0.005 at the start of an 8-block bin-packing episode, where γ = 0.87, k = 15, R ≈ 0.3), two orders of
magnitude below the spread of the returns Q is fitted on; on the log scale it is ``log(1/γ)`` = 0.14 at every
step. Returns below ``floor`` (failures, 0) all map to ``log(floor)``.
"""

from __future__ import annotations

import torch

__all__ = ["QScale"]


class QScale:
    """``encode``: returns ``[*]`` -> Q's regression targets; ``decode``: Q values -> returns.

    Args:
        log_floor: None (linear: Q regresses the return itself) or ε in (0, 1): Q regresses
            ``log(max(y, ε))``; returns at or below ε are not told apart.
    """

    def __init__(self, log_floor: float | None = None) -> None:
        if log_floor is not None and (isinstance(log_floor, bool) or not isinstance(log_floor, (int, float))
                                      or not 0 < log_floor < 1):
            raise ValueError(f"q_log_floor must be null (linear Q) or a number in (0, 1) (the smallest return "
                             f"the log scale tells apart), got {log_floor!r}")
        self.log_floor = None if log_floor is None else float(log_floor)

    def encode(self, returns: torch.Tensor) -> torch.Tensor:
        """Q's regression target for ``returns`` (same shape)."""
        return returns if self.log_floor is None else returns.clamp_min(self.log_floor).log()

    def decode(self, q: torch.Tensor) -> torch.Tensor:
        """The return a Q value stands for (same shape); the inverse of :meth:`encode` above the floor."""
        return q if self.log_floor is None else q.exp()
