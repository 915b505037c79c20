"""Optional ``torch.compile`` of the networks' inference passes (planner decisions, lookahead targets).

A network opts in with :class:`CompiledInference`; :func:`compile_inference` switches every such
network inside a module on or off. Only calls in eval mode without gradients run compiled (the
planner's and the targets' predictions); training passes stay eager, so gradients, BatchNorm statistics
and optimiser steps are untouched. Outputs equal the eager ones up to float summation order (tested).

Cost: inductor compiles each network on its first compiled call (≈ 0.5–1 min per network on one CPU
thread, a C++ compiler required; torch caches the result on disk, so later runs on the same machine
start in seconds). Target networks work because the parameters are graph inputs, not constants: the first
pass with the target weights swapped in by TorchRL's ``to_module`` compiles one more graph per network (its
guards see the swapped tensors as plain attributes; ``TORCH_LOGS=recompiles`` shows it), which every later
target pass reuses, the target syncs copying into those tensors in place.
"""

from __future__ import annotations

from typing import Callable

import torch
from torch import nn

__all__ = ["CompiledInference", "compile_inference"]


class CompiledInference:
    """Mixin for an ``nn.Module``: :meth:`_inference` runs ``fn`` compiled in eval mode without gradients
    once :func:`compile_inference` switched it on, eager otherwise. The compiled function is not part of
    the module's state (never pickled, never copied): a copy compiles its own on first use."""

    _compile_inference = False

    def _inference(self, fn: Callable[[torch.Tensor], torch.Tensor], x: torch.Tensor, *, dynamic_batch: bool) -> torch.Tensor:
        """``fn(x)``, compiled where switched on and this is an inference call. ``dynamic_batch``: the
        batch size varies between calls (one graph for every size instead of one per size)."""
        if not self._compile_inference or self.training or torch.is_grad_enabled():
            return fn(x)
        compiled = self.__dict__.get("_compiled_fn")
        if compiled is None:
            compiled = self.__dict__["_compiled_fn"] = torch.compile(fn, dynamic=False)
        if dynamic_batch:
            torch._dynamo.maybe_mark_dynamic(x, 0)
        return compiled(x)

    def __getstate__(self):
        state = self.__dict__.copy()  # what nn.Module pickles and deep-copies, less the compiled function
        state.pop("_compiled_fn", None)
        return state


def compile_inference(module: nn.Module, enabled: bool = True) -> nn.Module:
    """Switch compiled inference on (or off) for every :class:`CompiledInference` network in ``module``;
    returns ``module``. Compilation happens lazily, on each network's first inference call."""
    if not isinstance(module, nn.Module):
        raise ValueError(f"module must be a torch.nn.Module, got {type(module).__name__}")
    if not isinstance(enabled, bool):
        raise ValueError(f"enabled must be a bool, got {enabled!r}")
    for m in module.modules():
        if isinstance(m, CompiledInference):
            m._compile_inference = enabled
            m.__dict__.pop("_compiled_fn", None)
    return module
