"""The loop closer: for each new keyframe, describe -> candidates -> verify -> consistency.

:class:`LoopCloser` owns the place-recognition descriptor (:class:`attnloop.AttentionDescriptor`) and
the keyframe database (:class:`attnloop.index.LoopCandidateDetector`). It reads the keyframe graph (the
current pose estimates, the distances along it) but never changes it: :meth:`LoopCloser.close` returns
the accepted :class:`LoopClosure` s and the caller adds them as loop edges.

Example:
    >>> import torch
    >>> from slam.config import LoopClosureConfig
    >>> closer = LoopCloser(LoopClosureConfig(), descriptor=torch.nn.Identity())
    >>> closer.queries
    []
"""
from __future__ import annotations

import logging
from dataclasses import dataclass, field
from typing import Dict, List, Optional, Sequence

import numpy as np
import torch

from slam.keyframe_graph import KeyframeGraph
from slam.lie import se3_between
from slam.loop.verification import DriftLimits, Verification, verify_candidate
from slam.odometry.frontend import Keyframe
from slam.timing import StageTimer

logger = logging.getLogger(__name__)
Tensor = torch.Tensor

__all__ = ["LoopCloser", "LoopClosure", "LoopQuery", "build_descriptor"]


@dataclass
class LoopClosure:
    """An accepted, geometrically verified loop between keyframes ``kf_a < kf_b``.

    Attributes:
        kf_a, kf_b: keyframe ids; the edge measures ``T_ab`` (pose of b in a).
        frame_a, frame_b: input indices of the two keyframes.
        timestamp_a, timestamp_b: their timestamps.
        similarity: descriptor cosine similarity of the pair.
        num_inliers: RANSAC inliers of the verification.
        T_ab: ``(7,)`` float64 measured relative pose, in the tracked camera's frame (the colour camera's
            when the frames are unregistered).
        information: ``(6, 6)`` float64 information of ``T_ab`` from the registration (unscaled; the back
            end scales it by ``LoopClosureConfig.information_scale``).
        verification: the full :class:`~slam.loop.verification.Verification` (disagreement, bound).
    """

    kf_a: int
    kf_b: int
    frame_a: int
    frame_b: int
    timestamp_a: float
    timestamp_b: float
    similarity: float
    num_inliers: int
    T_ab: Tensor
    information: Optional[Tensor] = None
    verification: Optional[Verification] = None


@dataclass
class LoopQuery:
    """One query of the keyframe database (for the loop-closure evaluation).

    Attributes:
        kf: query keyframe id.
        top_kf: most similar eligible keyframe id (-1 when none was eligible).
        top_score: its similarity (``-inf`` when none).
        threshold: the query's adaptive threshold.
        candidates: ids that passed the threshold (and consistency) and were sent to verification.
        verified: ids accepted by geometric verification.
        rejections: ``{candidate id: reason}`` for candidates that failed verification.
    """

    kf: int
    top_kf: int
    top_score: float
    threshold: float
    candidates: List[int]
    verified: List[int]
    rejections: Dict[int, str] = field(default_factory=dict)


def build_descriptor(config, timer: Optional[StageTimer] = None) -> torch.nn.Module:
    """The :class:`attnloop.AttentionDescriptor` of a :class:`slam.config.DescriptorConfig`, in eval mode."""
    from attnloop import AttentionDescriptor

    timer = timer or StageTimer()
    with timer("descriptor_init"):
        model = AttentionDescriptor(backbone=config.backbone, fusion=config.fusion, num_rnn=config.num_rnn,
                                    seed=config.seed, pretrained=config.pretrained, weights=config.weights)
        model.eval()
        if config.device:
            model = model.to(config.device)
    return model


class LoopCloser:
    """Loop detection and verification for each new keyframe (see the module docstring).

    Args:
        config: :class:`slam.config.LoopClosureConfig`.
        descriptor: a model mapping ``(1, 3, H, W)`` uint8 images to ``(1, D)`` L2-normalised descriptors
            (default: built from ``config.descriptor``).
        timer: where the stages' times go (``descriptor``, ``loop_detection``, ``verification``).
    """

    def __init__(self, config, descriptor: Optional[torch.nn.Module] = None,
                 timer: Optional[StageTimer] = None):
        from attnloop.index import LoopCandidateDetector

        self.config = config
        self.timer = timer or StageTimer()
        self.descriptor = descriptor if descriptor is not None else build_descriptor(config.descriptor, self.timer)
        self.detector = LoopCandidateDetector(config.detector)
        self._queries: List[LoopQuery] = []
        self._kf_of_id: Dict[int, int] = {}  # detector id -> keyframe id

    @property
    def queries(self) -> List[LoopQuery]:
        """One entry per query so far."""
        return list(self._queries)

    @torch.no_grad()
    def describe(self, kf: Keyframe) -> Tensor:
        """``(D,)`` descriptor of a keyframe's (downsized) RGB image."""
        img = torch.from_numpy(np.ascontiguousarray(kf.rgb)).permute(2, 0, 1)[None]
        dev = next(iter(self.descriptor.buffers()), None)
        if dev is not None:
            img = img.to(dev.device)
        return self.descriptor(img)[0]

    def _detector_id(self, kf: Keyframe) -> int:
        # the detector's ids are frame indices, so that its exclusion window counts frames, not keyframes
        return int(kf.frame_index)

    def limits(self, a: int, b: int, graph: KeyframeGraph) -> DriftLimits:
        """The bound on the disagreement between a loop ``a -> b`` and the current estimate of it."""
        cfg = self.config
        return DriftLimits(cfg.max_drift_translation, cfg.max_drift_rotation_deg)

    def close(self, kf: Keyframe, keyframes: Sequence[Keyframe], graph: KeyframeGraph) -> List[LoopClosure]:
        """Query the database with a new keyframe, verify its candidates, add it to the database.

        Args:
            kf: the new keyframe (already in ``graph``).
            keyframes: every keyframe so far, by id (their features).
            graph: the keyframe graph (read only: poses and distances).

        Returns:
            the accepted loops (the caller adds them to the graph).
        """
        cfg = self.config
        with self.timer("descriptor"):
            desc = self.describe(kf)
        did = self._detector_id(kf)
        with self.timer("loop_detection"):
            cands = self.detector.add_and_query(desc, keyframe_id=did, timestamp=kf.timestamp)
        self._kf_of_id[did] = kf.id
        top_kf = self._kf_of_id[int(cands.top_ids[0])] if cands.top_ids.numel() else -1
        top_score = float(cands.top_scores[0]) if cands.top_scores.numel() else float("-inf")
        query = LoopQuery(kf.id, top_kf, top_score, float(cands.threshold),
                          [self._kf_of_id[int(c)] for c in cands.ids[: cfg.max_candidates]], [])
        self._queries.append(query)
        accepted = []
        for cand_id, score in zip(query.candidates, cands.scores[: cfg.max_candidates].tolist()):
            a = keyframes[cand_id]
            with self.timer("verification"):
                estimate = se3_between(graph.estimate(a.id), graph.estimate(kf.id))
                v = verify_candidate(a.features, kf.features, estimate, self.limits(a.id, kf.id, graph), cfg)
            if not v.accepted:
                query.rejections[cand_id] = v.reason
                logger.info("loop candidate %d -> %d rejected: %s", cand_id, kf.id, v.reason)
                continue
            query.verified.append(cand_id)
            loop = LoopClosure(a.id, kf.id, a.frame_index, kf.frame_index, a.timestamp, kf.timestamp, float(score),
                               v.num_inliers, v.T_ab, v.information, v)
            accepted.append(loop)
            logger.info("loop accepted: keyframe %d (frame %d) <-> keyframe %d (frame %d), %d inliers",
                        loop.kf_a, loop.frame_a, loop.kf_b, loop.frame_b, loop.num_inliers)
        return accepted
