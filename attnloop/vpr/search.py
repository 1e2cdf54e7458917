"""The keyframe index over a descriptor folder: one :class:`attnloop.index.KeyframeIndex`, or one per shard
searched and merged when one would not fit in memory.
"""
from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import torch

from attnloop.index import IndexConfig, KeyframeIndex

#: the fraction of the machine's memory one index may take before the rows are split over several
MEMORY_FRACTION = 0.5


def rows_that_fit(dim: int, config: IndexConfig, memory: int | None = None) -> int:
    """How many ``dim``-d rows one index of ``config`` holds in :data:`MEMORY_FRACTION` of ``memory`` bytes
    (default: the machine's): the stored rows plus, for a structure, its code and links (docs/scale.md)."""
    if memory is None:
        memory = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    per_row = dim * np.dtype(config.storage).itemsize
    if config.backend != "exact":
        per_row += 4 * (config.reduce_dim or dim) + 512  # the code and ~128 links of the graph
    return max(1, int(MEMORY_FRACTION * memory // per_row))


class ShardedIndex:
    """Several :class:`KeyframeIndex` over consecutive row ranges; a search asks each and merges the top k.

    Ids are global row numbers (the order of :func:`attnloop.vpr.load_descriptors`). Every index re-scores its
    answers exactly, so the merge of exact answers is the exact answer (ties to the lower id, as one index).
    """

    def __init__(self, indexes: list[KeyframeIndex]):
        if not indexes:
            raise ValueError("a sharded index needs at least one index (no rows were given)")
        self.indexes = indexes

    @classmethod
    def build(cls, x: np.ndarray, config: IndexConfig | None = None, max_rows: int | None = None) -> ShardedIndex:
        """Index ``(N, D)`` rows, at most ``max_rows`` per index (default: :func:`rows_that_fit`)."""
        if x.ndim != 2 or x.shape[0] == 0:
            raise ValueError(f"rows to index must have shape (N, D) with N >= 1, got {x.shape}")
        config = config or IndexConfig(background=False)
        max_rows = max_rows or rows_that_fit(x.shape[1], config)
        indexes = []
        for start in range(0, x.shape[0], max_rows):
            index = KeyframeIndex(config, dim=x.shape[1])
            index.add(x[start:start + max_rows], ids=np.arange(start, min(start + max_rows, x.shape[0])))
            index.wait()
            indexes.append(index)
        return cls(indexes)

    def search(self, query, k: int = 10) -> tuple[torch.Tensor, torch.Tensor]:
        """``(Q, D)`` queries -> ids ``(Q, K)`` long and similarities ``(Q, K)`` float32, most similar first."""
        found = [index.search(query, k=k) for index in self.indexes]
        ids = torch.cat([i for i, _ in found], dim=1)  # (Q, K * indexes)
        sims = torch.cat([s for _, s in found], dim=1)
        order = np.lexsort((ids.numpy(), -sims.numpy()))[:, :k]  # by similarity, then the lower id
        order = torch.from_numpy(order)
        return ids.gather(1, order), sims.gather(1, order)

    def save(self, folder) -> list[Path]:
        """One ``index-NNNNN.npz`` per index in ``folder`` (replacing older ones)."""
        folder = Path(folder)
        for old in folder.glob("index-*.npz"):
            old.unlink()
        files = [folder / f"index-{k:05d}.npz" for k in range(len(self.indexes))]
        for index, f in zip(self.indexes, files):
            index.save(f)
        return files

    @classmethod
    def load(cls, folder) -> ShardedIndex | None:
        """The indexes saved in ``folder``, or None when there are none."""
        files = sorted(Path(folder).glob("index-*.npz"))
        return cls([KeyframeIndex.load(f) for f in files]) if files else None
