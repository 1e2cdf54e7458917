"""Loop-candidate detection: index search, adaptive threshold, temporal consistency (per query keyframe)."""
from __future__ import annotations

import numbers
from collections import deque
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
    """Parameters of :class:`LoopCandidateDetector`.

    Per query keyframe ``q``: the eligible keyframes are those with ``id <= q - window``; the ``top_k``
    most similar are taken from the index; a candidate is accepted when its similarity exceeds the
    adaptive threshold of the query's similarity distribution (:mod:`attnloop.threshold`, estimated on every
    eligible keyframe, or on exactly ``threshold_samples`` of them spread evenly over the eligible ones when
    there are more) and, if
    ``consistency > 1``, when each of the ``consistency - 1`` previous queries also had a candidate
    above its threshold within ``consistency_radius`` ids of it (a revisit lasts several keyframes).
    """

    top_k: int = 5  # neighbours taken from the index per query
    window: int = 30  # exclusion window in keyframe ids: ids > query_id - window are never candidates
    consistency: int = 1  # consecutive queries that must agree (1 = off)
    consistency_radius: int = 5  # ids within this distance count as the same place for consistency
    threshold_samples: int = 4096  # max eligible keyframes used to estimate the similarity distribution
    threshold: ThresholdConfig = field(default_factory=ThresholdConfig)
    index: IndexConfig = field(default_factory=IndexConfig)

    def __post_init__(self) -> None:
        for name in ("top_k", "window", "consistency", "consistency_radius", "threshold_samples"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, numbers.Integral):
                raise ValueError(f"LoopDetectorConfig.{name} must be an integer, got {value!r}")
        if self.top_k < 1 or self.window < 0 or self.consistency < 1 or self.consistency_radius < 0:
            raise ValueError("LoopDetectorConfig: need top_k >= 1, window >= 0, consistency >= 1, "
                             "consistency_radius >= 0")
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
        top_ids: the raw top-k neighbours ``(K,)`` before threshold and consistency (for evaluation).
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
    """Per-keyframe loop-candidate selection: index search, adaptive threshold, temporal consistency.

    The SLAM system calls :meth:`add_and_query` once per new keyframe; each call first queries the
    database of earlier keyframes (outside the exclusion window), then adds the new keyframe.

    Args:
        config: :class:`LoopDetectorConfig`.

    Example:
        >>> det = LoopCandidateDetector(LoopDetectorConfig(window=5))
        >>> gen = torch.Generator().manual_seed(0)
        >>> places = torch.randn(40, 64, generator=gen)
        >>> for i in range(40):
        ...     out = det.add_and_query(places[i] + 0.1 * torch.randn(64, generator=gen), keyframe_id=i)
        >>> out = det.add_and_query(places[3] + 0.1 * torch.randn(64, generator=gen), keyframe_id=40)
        >>> out.ids[:1].tolist(), out.scores.shape == out.ids.shape
        ([3], True)
        >>> det.similarities(40)[0].shape
        torch.Size([36])
    """

    def __init__(self, config: LoopDetectorConfig | None = None) -> None:
        self.config = config or LoopDetectorConfig()
        self.index = KeyframeIndex(self.config.index)
        # Threshold-passing ids of the previous queries (newest last), for temporal consistency.
        self._history: deque = deque(maxlen=max(self.config.consistency - 1, 0))

    def __len__(self) -> int:
        return len(self.index)

    def query(self, descriptor, keyframe_id: int) -> LoopCandidates:
        """Candidates for a query keyframe without adding it or updating the consistency history."""
        return self._query(descriptor, int(keyframe_id), update=False)

    def add_and_query(self, descriptor, keyframe_id: int, timestamp: float | None = None) -> LoopCandidates:
        """Query the database with a new keyframe, then add it.

        Args:
            descriptor: ``(D,)`` descriptor of the new keyframe (tensor on any device, or array).
            keyframe_id: its id, larger than every id added before.
            timestamp: optional, stored with it.

        Returns:
            :class:`LoopCandidates` (tensors on the descriptor's device).
        """
        kid = int(keyframe_id)
        last = self.index.last_id
        if last is not None and kid <= last:
            raise ValueError(f"keyframe_id {kid} must be larger than the last added id {last}")
        out = self._query(descriptor, kid, update=True)
        self.index.add(descriptor, ids=[kid], timestamps=None if timestamp is None else [timestamp])
        return out

    def _query(self, descriptor, kid: int, update: bool) -> LoopCandidates:
        cfg = self.config
        if isinstance(descriptor, Tensor) and descriptor.dim() != 1 or (
                not isinstance(descriptor, Tensor) and np.ndim(descriptor) != 1):
            raise ValueError(f"descriptor must have shape (D,), got {tuple(np.shape(descriptor))}")
        device = descriptor.device if isinstance(descriptor, Tensor) else torch.device("cpu")
        max_id = kid - cfg.window
        top_ids, top_sims = self.index.search(descriptor, k=cfg.top_k, max_id=max_id)
        _, dist = self.index.similarities(descriptor, max_id=max_id, max_samples=cfg.threshold_samples)
        thr = float(adaptive_threshold(dist.cpu(), cfg.threshold))
        above = top_sims.cpu() > thr
        passed_ids = top_ids.cpu()[above]
        passed_sims = top_sims.cpu()[above]
        keep = torch.tensor([self._consistent(int(c)) for c in passed_ids], dtype=torch.bool)
        if update and self._history.maxlen:
            self._history.append(passed_ids.numpy().copy())
        return LoopCandidates(ids=passed_ids[keep].to(device), scores=passed_sims[keep].to(device),
                              threshold=thr, top_ids=top_ids, top_scores=top_sims)

    def _consistent(self, candidate: int) -> bool:
        need = self.config.consistency - 1
        if need == 0:
            return True
        streak = 0
        for prev in reversed(self._history):
            if prev.size and np.any(np.abs(prev - candidate) <= self.config.consistency_radius):
                streak += 1
            else:
                break
        return streak >= need

    def similarities(self, query_id: int, window: int | None = None) -> tuple[Tensor, Tensor]:
        """Exact similarities of a stored keyframe to every keyframe with ``id <= query_id - window``.

        For the loop-closure evaluation (precision/recall over all pairs).

        Args:
            query_id: id of a stored keyframe.
            window: exclusion window (default ``config.window``; ``1`` = all earlier keyframes).

        Returns:
            ids ``(M,)`` (long) and similarities ``(M,)`` (float32), in id order.
        """
        w = self.config.window if window is None else int(window)
        return self.index.similarities(self.index.descriptors_of([query_id])[0], max_id=int(query_id) - w)
