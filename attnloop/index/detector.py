"""Loop-candidate detection: index search and adaptive threshold (per query keyframe)."""
from __future__ import annotations

import numbers
from dataclasses import dataclass, field

import numpy as np
import torch

from attnloop.index.config import IndexConfig
from attnloop.index.database import KeyframeIndex
from attnloop.threshold import ThresholdConfig, adaptive_threshold

Tensor = torch.Tensor

__all__ = ["LoopCandidateDetector", "LoopCandidates", "LoopDetectorConfig"]


@dataclass(frozen=True)
class LoopDetectorConfig:
    """Parameters of :class:`LoopCandidateDetector`: of the keyframes with ``id <= q - window``, the ``top_k``
    most similar above the adaptive threshold (:mod:`attnloop.threshold`) of their similarities."""

    top_k: int = 5  # neighbours taken from the index per query
    window: int = 30  # exclusion window in keyframe ids: ids > query_id - window are never candidates
    threshold_samples: int = 4096  # max eligible keyframes used to estimate the similarity distribution
    threshold: ThresholdConfig = field(default_factory=ThresholdConfig)
    index: IndexConfig = field(default_factory=IndexConfig)

    def __post_init__(self) -> None:
        for name in ("top_k", "window", "threshold_samples"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, numbers.Integral):
                raise ValueError(f"LoopDetectorConfig.{name} must be an integer, got {value!r}")
        if self.top_k < 1 or self.window < 0:
            raise ValueError(f"LoopDetectorConfig: need top_k >= 1 and window >= 0, got {self.top_k}, {self.window}")
        if self.threshold_samples < self.threshold.min_samples:
            raise ValueError(f"LoopDetectorConfig.threshold_samples ({self.threshold_samples}) must be >= "
                             f"threshold.min_samples ({self.threshold.min_samples})")


@dataclass
class LoopCandidates:
    """The answer to one query keyframe.

    Attributes:
        ids: accepted candidate keyframe ids ``(M,)`` (long), most similar first.
        scores: their cosine similarities ``(M,)`` (float32).
        threshold: the query's adaptive threshold (``inf`` when too few keyframes were eligible).
        top_ids: the raw top-k neighbours ``(K,)`` before the threshold (for evaluation).
        top_scores: their similarities ``(K,)``.
    """

    ids: Tensor
    scores: Tensor
    threshold: float
    top_ids: Tensor
    top_scores: Tensor

    def __len__(self) -> int:
        return int(self.ids.numel())


class LoopCandidateDetector:
    """Per-keyframe loop-candidate selection (:meth:`add_and_query` once per new keyframe).

    Args:
        config: :class:`LoopDetectorConfig`.
    """

    def __init__(self, config: LoopDetectorConfig | None = None) -> None:
        self.config = config or LoopDetectorConfig()
        self.index = KeyframeIndex(self.config.index)

    def __len__(self) -> int:
        return len(self.index)

    def query(self, descriptor, keyframe_id: int) -> LoopCandidates:
        """Candidates for a query keyframe without adding it."""
        cfg = self.config
        if np.ndim(descriptor) != 1:
            raise ValueError(f"descriptor must have shape (D,), got {tuple(np.shape(descriptor))}")
        device = descriptor.device if isinstance(descriptor, Tensor) else torch.device("cpu")
        max_id = int(keyframe_id) - cfg.window
        top_ids, top_sims = self.index.search(descriptor, k=cfg.top_k, max_id=max_id)
        _, dist = self.index.similarities(descriptor, max_id=max_id, max_samples=cfg.threshold_samples)
        thr = float(adaptive_threshold(dist.cpu(), cfg.threshold))
        above = top_sims.cpu() > thr
        return LoopCandidates(ids=top_ids.cpu()[above].to(device), scores=top_sims.cpu()[above].to(device),
                              threshold=thr, top_ids=top_ids, top_scores=top_sims)

    def add(self, descriptor, keyframe_id: int, timestamp: float | None = None) -> None:
        """Add a keyframe to the database (after :meth:`query`, when the caller decides to keep it).

        Args:
            descriptor: ``(D,)`` descriptor of the keyframe (tensor on any device, or array).
            keyframe_id: its id, larger than every id added before.
            timestamp: optional, stored with it.
        """
        self.index.add(descriptor, ids=[int(keyframe_id)], timestamps=None if timestamp is None else [timestamp])

    def add_and_query(self, descriptor, keyframe_id: int, timestamp: float | None = None) -> LoopCandidates:
        """Query the database with a new keyframe, then add it (:meth:`query`, then :meth:`add`).

        Args:
            descriptor: ``(D,)`` descriptor of the new keyframe (tensor on any device, or array).
            keyframe_id: its id, larger than every id added before.
            timestamp: optional, stored with it.

        Returns:
            :class:`LoopCandidates` (tensors on the descriptor's device).
        """
        out = self.query(descriptor, keyframe_id)
        self.add(descriptor, keyframe_id, timestamp)
        return out
