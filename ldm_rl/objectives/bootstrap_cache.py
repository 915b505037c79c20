"""``BootstrapCache``: what the target networks say about a replayed transition's next state, kept until
they change.

A transition's bootstrap (the target Q map's proposals for ``s'``, the target LDM's predictions of them,
the target V's scores, the target Q's max) depends only on ``s'`` and on the target networks, and the
target networks change only at a copy (:class:`~ldm_rl.objectives.TargetSync`, every 100 updates by
default). Prioritized replay draws the same transitions again and again between two copies (the expert
ones above all), so the losses keep each row's bootstrap here and recompute only the rows they have not
seen since the last copy: the targets are exactly those of a fresh computation.

Rows are keyed by the replay's frame ``index`` (the ``index`` key of a TorchRL replay sample) and checked
against ``s'`` itself — its depth classes (heightmap and in-hand image, uint8) and hand state, everything
the agent networks read of it — so a replay slot overwritten since is recomputed, never served stale.
Entries are stored as tensors (``[M, ...]``, grown by doubling up to ``capacity``); lookups are one
batched comparison. Heights given to :meth:`put` are kept as uint8 depth classes, which the agent networks
read exactly as they read the heights (:func:`~ldm_rl.models.blocks.encode_heights`).
"""

from __future__ import annotations

import torch

from ldm_rl import geometry

__all__ = ["BootstrapCache"]


class BootstrapCache:
    """Per-transition tensors keyed by replay index, verified against ``s'``; :meth:`clear` at each target copy.

    Args:
        capacity: most transitions kept between two clears (later rows are computed, not kept).
        max_height: metres of the top depth class; num_classes: K depth classes (≤ 256).
    """

    def __init__(self, capacity: int, *, max_height: float, num_classes: int) -> None:
        if not isinstance(capacity, int) or isinstance(capacity, bool) or capacity < 1:
            raise ValueError(f"capacity must be a positive int (transitions kept between target copies), got {capacity!r}")
        if not 2 <= num_classes <= 256:
            raise ValueError(f"num_classes must be in [2, 256] to store depth classes as uint8, got {num_classes!r}")
        self.capacity, self.max_height, self.num_classes = capacity, float(max_height), int(num_classes)
        self._size = 0
        self._store: dict[str, torch.Tensor] = {}
        self.hits = self.lookups = 0

    def __len__(self) -> int:
        return self._size

    @property
    def hit_rate(self) -> float:
        """Fraction of the rows looked up since construction that were served from the cache."""
        return self.hits / self.lookups if self.lookups else 0.0

    def clear(self) -> None:
        """Forget every entry (the target networks changed); the storage is kept for reuse."""
        self._size = 0

    def classes(self, heights: torch.Tensor) -> torch.Tensor:
        """Heights (metres) -> uint8 depth classes, the form the cache keeps."""
        return geometry.heights_to_classes(heights, self.max_height, self.num_classes).to(torch.uint8)

    def heights(self, classes: torch.Tensor) -> torch.Tensor:
        """uint8 depth classes -> float32 heights (metres)."""
        return geometry.classes_to_heights(classes.long(), self.max_height, self.num_classes)

    def _key(self, index, heightmap, in_hand, holding) -> dict[str, torch.Tensor]:
        rows = index.numel() if torch.is_tensor(index) else None
        sizes = [x.shape[0] if torch.is_tensor(x) and x.dim() else None for x in (heightmap, in_hand, holding)]
        if rows is None or index.is_floating_point() or sizes != [rows] * 3:
            raise ValueError(f"index must be an integer tensor [B] with heightmap, in_hand and holding of B rows; got "
                             f"index {tuple(index.shape) if torch.is_tensor(index) else type(index).__name__} and "
                             f"{sizes} rows")
        return {"index": index.reshape(-1).long(), "heightmap": self.classes(heightmap), "in_hand": self.classes(in_hand),
                "holding": holding.reshape(-1).bool()}

    def lookup(self, index, heightmap, in_hand, holding) -> tuple[torch.Tensor, torch.Tensor]:
        """``(slot [B] int64, found [B] bool)`` for next states ``heightmap [B, 1, H, W]`` m, ``in_hand
        [B, 1, h, h]`` m, ``holding [B]`` bool of the replay rows ``index [B]`` (slot -1 where not found)."""
        key = self._key(index, heightmap, in_hand, holding)
        size = self._size
        slot = torch.full_like(key["index"], -1)
        found = torch.zeros_like(key["holding"])
        rows = torch.zeros(0, dtype=torch.long)
        if size:
            match = key["index"][:, None] == self._store["index"][None, :size]
            hit, where = match.max(1)
            rows = hit.nonzero().squeeze(1)
        if rows.numel():
            cand = where.index_select(0, rows)
            same = torch.ones_like(rows, dtype=torch.bool)
            for name in ("heightmap", "in_hand", "holding"):
                equal = self._store[name].index_select(0, cand) == key[name].index_select(0, rows)
                same &= equal.reshape(rows.numel(), -1).all(1)
            slot[rows[same]] = cand[same]
            found[rows[same]] = True
        self.lookups += found.numel()
        self.hits += int(found.sum())
        return slot, found

    def get(self, slot: torch.Tensor, name: str) -> torch.Tensor:
        """The stored ``name`` values of ``slot [b]`` (found slots), ``[b, ...]``."""
        return self._store[name].index_select(0, slot)

    def put(self, index, heightmap, in_hand, holding, values: dict[str, torch.Tensor]) -> None:
        """Keep ``values`` (each ``[B, ...]``, same shapes every call) for the rows ``index [B]`` with next
        states ``heightmap``, ``in_hand``, ``holding``. A row already kept under its index is replaced (its
        slot was overwritten in the replay); repeated indices keep their first row; rows beyond
        ``capacity`` are dropped."""
        key = self._key(index, heightmap, in_hand, holding)
        rows = _first_occurrences(key["index"])
        entries = {**{name: value.index_select(0, rows) for name, value in key.items()},
                   **{name: value.detach().index_select(0, rows) for name, value in values.items()}}
        size = self._size
        old = torch.full_like(entries["index"], -1)
        if size:
            match = entries["index"][:, None] == self._store["index"][None, :size]
            hit, where = match.max(1)
            old = torch.where(hit, where, old)
        fresh = (old < 0).nonzero().squeeze(1)
        room = min(fresh.numel(), self.capacity - size)
        slots = old.clone()
        slots[fresh[:room]] = torch.arange(size, size + room, device=slots.device)
        keep = slots >= 0
        self._reserve(entries, size + room)
        for name, value in entries.items():
            self._store[name].index_copy_(0, slots[keep], value[keep])
        self._size = size + room

    def _reserve(self, entries: dict[str, torch.Tensor], needed: int) -> None:
        """Grow the storage (doubling, at most ``capacity`` rows) to hold ``needed`` rows."""
        have = next(iter(self._store.values())).shape[0] if self._store else 0
        if self._store and set(self._store) != set(entries):
            raise ValueError(f"put() must give the same values every time: {sorted(self._store)} vs {sorted(entries)}")
        if needed <= have:
            return
        rows = min(self.capacity, max(needed, 2 * have, 64))
        for name, value in entries.items():
            grown = value.new_zeros((rows, *value.shape[1:]))
            if have:
                grown[:have] = self._store[name][:have]
            self._store[name] = grown


def _first_occurrences(index: torch.Tensor) -> torch.Tensor:
    """Positions of the first occurrence of each distinct value of ``index [B]``, in order."""
    same = index[:, None] == index[None, :]
    earlier = torch.tril(same, diagonal=-1).any(1)
    return (~earlier).nonzero().squeeze(1)
