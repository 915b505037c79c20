"""``TargetSync``: TorchRL's ``HardUpdate`` that copies the whole network state, buffers included.

TorchRL's target updaters copy only the source entries that require grad, so a target network with
BatchNorm keeps the running statistics it had when its loss was built: in eval mode it then predicts
with the wrong normalisation (measured on the LDM agent: 17 % of the target LDM's predicted pixels
differed from the online model's after 20 model-only updates and a sync). ``TargetSync`` copies every
parameter *and* buffer of every ``target_*_params`` of the loss, so after each copy the target networks'
eval-mode outputs equal the online networks'. It is the one updater every agent uses.

A copy happens on every ``interval``-th :meth:`step` (TorchRL's ``HardUpdate`` counts ``interval − 1``)
and on :meth:`sync`, which the training loop calls once the networks are ready to act (after any
model-only pretraining). After each copy the loss is told through its ``targets_changed()`` hook, when
it has one (the bootstrap caches of the agents' losses are dropped there).
"""

from __future__ import annotations

from torchrl.objectives import HardUpdate, LossModule

__all__ = ["TargetSync"]


class TargetSync(HardUpdate):
    """Copy all of ``loss``'s source networks (parameters and buffers) into its target networks every
    ``interval`` calls of :meth:`step` (``interval`` ≥ 1; ``counter`` is TorchRL's, in [0, interval))."""

    def __init__(self, loss: LossModule, *, interval: int) -> None:
        if not isinstance(interval, int) or isinstance(interval, bool) or interval < 1:
            raise ValueError(f"interval must be a positive int (updates between target copies), got {interval!r}")
        super().__init__(loss, value_network_update_interval=interval - 1)
        self.interval = interval

    def init_(self) -> None:
        """TorchRL's initial copy, then widen the copied set to every entry (buffers too) whose target is
        stored apart from its source."""
        super().init_()
        sources, targets = {}, {}
        for name in self._source_names:
            source, target = getattr(self.loss_module, name), getattr(self.loss_module, "target_" + name)
            kept = [key for key, value in source.items(True, True) if not target.get(key).is_set_to(value.data)]
            sources[name] = source.select(*kept)
            targets["target_" + name] = target.select(*kept)
        self._sources = type(self._sources)(sources, []).lock_()
        self._targets = type(self._targets)(targets, []).lock_()

    def step(self) -> None:
        copying = self.counter == self.value_network_update_interval
        super().step()
        if copying:
            self._changed()

    def sync(self) -> None:
        """Copy now (the step counter is left as it is)."""
        for name, source in self._sources.items():
            self._targets.get("target_" + name).data.copy_(source.data)
        self._changed()

    def _changed(self) -> None:
        hook = getattr(self.loss_module, "targets_changed", None)
        if callable(hook):
            hook()
