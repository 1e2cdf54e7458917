"""The loop closer: for each new keyframe, describe -> candidates -> verify -> consistency.

:class:`LoopCloser` owns the place-recognition descriptor, the keyframe database
(:class:`attnloop.index.LoopCandidateDetector`) and the group-consistency check; it reads the keyframe graph but
never changes it: :meth:`LoopCloser.close` returns a :class:`LoopUpdate` that the caller applies
(docs/pipeline.md, "What each stage does" and "Long runs").

Example:
    >>> import torch
    >>> from slam.config import LoopClosureConfig
    >>> closer = LoopCloser(LoopClosureConfig(), descriptor=torch.nn.Identity())
    >>> closer.queries
    []
"""
from __future__ import annotations

import dataclasses
import logging
import math
from dataclasses import dataclass, field
from typing import Callable, Dict, List, Optional, Sequence

import numpy as np
import torch

from attnloop import AttentionDescriptor
from attnloop.index import LoopCandidateDetector
from attnloop.presets import DEFAULT_BACKBONE_SETTINGS
from slam.keyframe_graph import KeyframeGraph
from slam.lie import quat_angle, se3_between
from slam.loop.acceptance import drift_limits
from slam.loop.consistency import GroupConsistency
from slam.loop.verification import DriftLimits, Verification, verify_candidate
from slam.odometry.frontend import Keyframe
from slam.timing import StageTimer

logger = logging.getLogger(__name__)
Tensor = torch.Tensor

__all__ = ["LoopCloser", "LoopClosure", "LoopQuery", "LoopUpdate", "build_descriptor"]


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
        id: the hypothesis number (order of verification).
        path_length: metres travelled between the two keyframes along the graph when it was verified.
        settled: its measurement agrees with the estimate it was verified against within
            ``LoopClosureConfig.settled_translation`` / ``settled_rotation_deg``: the estimate already
            satisfies it.
        consistent: kept by the group check (set by the loop closer): in the largest group of mutually
            consistent loops, with local support (:mod:`slam.loop.consistency`); only those are edges of
            the graph. Its ``status`` is ``"inconsistent"`` otherwise.
        switched_off: the back end's robust kernel gave it a weight below
            ``BackendConfig.switch_off_weight`` in its last optimisation (set by the system).
        weight: its last kernel weight in the back end (1 before any optimisation).
        edge: its index in ``KeyframeGraph.edges`` (-1 until the caller adds it).
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
    id: int = -1
    path_length: float = float("nan")
    settled: bool = False
    consistent: bool = True
    switched_off: bool = False
    weight: float = 1.0
    edge: int = -1

    @property
    def status(self) -> str:
        """``"kept"``, ``"inconsistent"`` (outside the consistent group) or ``"switched_off"`` (by the back end)."""
        if not self.consistent:
            return "inconsistent"
        return "switched_off" if self.switched_off else "kept"


@dataclass
class LoopUpdate:
    """What one :meth:`LoopCloser.close` call changed.

    Attributes:
        new: the loops verified during the call (each with its ``status``).
        changed: earlier loops that entered or left the consistent group.
        revisit: a kept new loop repeats an earlier keyframe (the ``repeats`` given to :meth:`LoopCloser.close`):
            the query keyframe was not added to the database, and the caller may release it.
    """

    new: List[LoopClosure] = field(default_factory=list)
    changed: List[LoopClosure] = field(default_factory=list)
    revisit: bool = False

    def __bool__(self) -> bool:
        return bool(self.new or self.changed)


@dataclass
class LoopQuery:
    """One query of the keyframe database (for the loop-closure evaluation).

    Attributes:
        kf: query keyframe id.
        top_kf: most similar eligible keyframe id (-1 when none was eligible). Eligible: outside the
            detector's time window and not joined to the query by an edge of the keyframe graph (its
            odometry parent: a loop to it would count that registration twice; a weak edge, forced after
            a tracking loss, measured nothing and joins nothing).
        top_score: its similarity (``-inf`` when none).
        threshold: the query's adaptive threshold.
        candidates: eligible ids that passed the threshold (and consistency) and were sent to verification.
        verified: ids accepted by geometric verification.
        rejections: ``{candidate id: reason}`` for candidates that failed verification or were not verified
            (the query repeats an earlier one: :meth:`LoopCloser.close`).
        followed: not a database query: the keyframe followed a revisit and repeats the keyframe nearest to it
            around the one that revisit repeated (:meth:`LoopCloser.close`); ``top_kf`` is that keyframe,
            ``top_score`` and ``threshold`` NaN (no descriptor was computed).
    """

    kf: int
    top_kf: int
    top_score: float
    threshold: float
    candidates: List[int]
    verified: List[int]
    rejections: Dict[int, str] = field(default_factory=dict)
    followed: bool = False


def build_descriptor(config, timer: Optional[StageTimer] = None) -> torch.nn.Module:
    """The :class:`attnloop.AttentionDescriptor` of a :class:`slam.config.DescriptorConfig`, in eval mode."""
    timer = timer or StageTimer()
    with timer("descriptor_init"):
        model = AttentionDescriptor(**config.settings())
        model.eval()
        if config.device:
            model = model.to(config.device)
    return model


class LoopCloser:
    """Loop detection and verification for each new keyframe.

    Args:
        config: :class:`slam.config.LoopClosureConfig`.
        descriptor: a model mapping ``(1, 3, H, W)`` uint8 images to ``(1, D)`` L2-normalised descriptors
            (default: built from ``config.descriptor``).
        timer: where the stages' times go (``descriptor``, ``loop_detection``, ``verification``).
    """

    def __init__(self, config, descriptor: Optional[torch.nn.Module] = None,
                 timer: Optional[StageTimer] = None):
        self.config = config
        self.timer = timer or StageTimer()
        self.descriptor = descriptor if descriptor is not None else build_descriptor(config.descriptor, self.timer)
        # the threshold calibrated for this descriptor (LoopClosureConfig.threshold_by_backbone): a backbone's
        # default recipe, tap, stages and input size with its pretrained weights; anything else keeps its own
        backbone = getattr(self.descriptor, "backbone_name", None)
        recipe = getattr(self.descriptor, "recipe", None)
        net = getattr(self.descriptor, "backbone", None)
        pretrained = getattr(self.descriptor, "pretrained", None)
        pretrained = bool(config.descriptor.pretrained) if pretrained is None else bool(pretrained)
        # any fusion mode (they share a scale), and any seed without RNNs (it then seeds nothing)
        ref = None if recipe is None else type(recipe)()
        default = (recipe is not None and pretrained
                   and dataclasses.replace(recipe, fusion=ref.fusion,
                                           seed=recipe.seed if recipe.num_rnn else ref.seed) == ref
                   and all(getattr(net, key, None) == value
                           for key, value in DEFAULT_BACKBONE_SETTINGS.get(backbone, {}).items()))
        calibrated = getattr(config, "threshold_by_backbone", {}).get(backbone) if default else None
        detector = config.detector if calibrated is None else dataclasses.replace(config.detector, threshold=calibrated)
        self.threshold = detector.threshold
        logger.info("loop detector threshold (%s): %s", backbone or "custom descriptor", self.threshold)
        self.detector = LoopCandidateDetector(detector)
        self.consistency = GroupConsistency(config.consistency, compare_across_losses=not config.recover_after_loss)
        self._queries: List[LoopQuery] = []
        self._loops: List[LoopClosure] = []  # every hypothesis, by id
        self._kf_of_id: Dict[int, int] = {}  # detector id -> keyframe id
        self._id_of_kf: Dict[int, int] = {}  # keyframe id -> detector id, for the keyframes in the database
        self._place: Optional[tuple[int, int]] = None  # the last keyframe, when a revisit: (it, the one it repeats)
        self._t0: Optional[float] = None
        self._last_id = -1
        self._warned_stamps = False
        self._last_stamp: float | None = None

    @property
    def queries(self) -> List[LoopQuery]:
        """One entry per query so far."""
        return list(self._queries)

    @property
    def hypotheses(self) -> List[LoopClosure]:
        """Every verified loop so far (kept or not), by id."""
        return list(self._loops)

    def descriptor_of(self, kf_id: int) -> Optional[Tensor]:
        """``(D,)`` float32 the descriptor of keyframe ``kf_id`` as the database holds it, or None (a revisit)."""
        did = self._id_of_kf.get(int(kf_id))
        return None if did is None else self.detector.index.descriptors_of([did])[0]

    @torch.no_grad()
    def describe(self, kf: Keyframe) -> Tensor:
        """``(D,)`` descriptor of a keyframe's (downsized) RGB image."""
        img = torch.from_numpy(np.ascontiguousarray(kf.rgb)).permute(2, 0, 1)[None]
        # where the module lives: its parameters, else its buffers
        held = next(iter(self.descriptor.parameters()), None)
        held = held if held is not None else next(iter(self.descriptor.buffers()), None)
        if held is not None:
            img = img.to(held.device)
        return self.descriptor(img)[0]

    def _detector_id(self, kf: Keyframe) -> int:
        # milliseconds since the first keyframe: the detector's window is a time (equal stamps: the next integer)
        if self._t0 is None:
            self._t0 = float(kf.timestamp)
        ms = int(round((float(kf.timestamp) - self._t0) * 1000.0))
        if self._last_stamp is not None and float(kf.timestamp) <= self._last_stamp and not self._warned_stamps:
            self._warned_stamps = True
            logger.warning("keyframe %d's timestamp %.6g s is not later than the previous keyframe's: the loop "
                           "detector's window (%d ms) is measured in timestamps, so with repeated stamps it "
                           "spans that many keyframes and no loop is found; give frames their capture times "
                           "in seconds", kf.id, float(kf.timestamp), self.detector.config.window)
        self._last_id = max(ms, self._last_id + 1)
        self._last_stamp = float(kf.timestamp)
        return self._last_id

    def limits(self, path_length: float) -> DriftLimits:
        """The bound on the disagreement between a loop and the current estimate of it, for keyframes
        ``path_length`` metres apart along the graph (:func:`slam.loop.acceptance.drift_limits`); none across a
        tracking loss (``inf``) with ``LoopClosureConfig.recover_after_loss``."""
        if not math.isfinite(path_length) and self.config.recover_after_loss:
            return DriftLimits(math.inf, math.inf)
        return drift_limits(path_length, self.config.drift)

    def close(self, kf: Keyframe, keyframes: Sequence[Keyframe], graph: KeyframeGraph,
              through_loops: bool = False, min_loop_weight: float = 0.0,
              repeats: Optional[Callable[[LoopClosure], bool]] = None) -> LoopUpdate:
        """Query the database with a new keyframe, verify its candidates, check the group, add it to the
        database unless it repeats an earlier keyframe.

        Args:
            kf: the new keyframe (already in ``graph``).
            keyframes: every keyframe so far, by id (their features).
            graph: the keyframe graph (read only: estimates and distances).
            through_loops: the distance that bounds the disagreement may take the loops (else: the odometry chain).
            min_loop_weight: loops the back end trusts less than this are no shortcut.
            repeats: whether a loop joins the query to an earlier keyframe that stands for it (None: no loop
                does). A kept loop that repeats makes the update a ``revisit``: the query is not added to the
                database and the less similar candidates are not verified. A keyframe after a revisit is first
                verified against the database's keyframe nearest to its estimate within two edges of the one
                repeated; when that loop is kept and repeats too, no descriptor is computed
                (``LoopQuery.followed``).

        Returns:
            :class:`LoopUpdate` (the caller applies it to the graph).
        """
        did = self._detector_id(kf)
        update, seen = LoopUpdate(), {}
        follow = self._follow(kf, graph, did) if repeats is not None else None
        if follow is not None:
            query = LoopQuery(kf.id, follow, math.nan, math.nan, [follow], [], followed=True)
            update = self._verify(kf, keyframes, graph, query, [(follow, math.nan)], through_loops, min_loop_weight,
                                  repeats, seen, follow=True)
            if update.new and update.new[0].consistent:
                self._queries.append(query)
                self._place, update.revisit = (kf.id, follow), True
                return update
        desc, query, eligible = self._query_database(kf, graph, did)
        more = self._verify(kf, keyframes, graph, query, eligible, through_loops, min_loop_weight, repeats, seen)
        update.new += more.new
        update.changed += [lp for lp in more.changed if lp not in update.changed and lp not in update.new]
        repeated = [lp for lp in update.new if lp.consistent and repeats(lp)] if repeats is not None else []
        update.revisit = bool(repeated)
        self._place = (kf.id, repeated[0].kf_a) if repeated else None
        if not update.revisit:
            self.detector.add(desc, keyframe_id=did, timestamp=kf.timestamp)
            self._kf_of_id[did], self._id_of_kf[kf.id] = kf.id, did
        return update

    def _query_database(self, kf: Keyframe, graph: KeyframeGraph, did: int):
        """Describe ``kf`` and query the database: its ``(D,)`` descriptor, its :class:`LoopQuery` (recorded) and
        the eligible candidates ``(keyframe id, similarity)``, most similar first."""
        with self.timer("descriptor"):
            desc = self.describe(kf)
        with self.timer("loop_detection"):
            cands = self.detector.query(desc, keyframe_id=did)
        joined = graph.joined(kf.id)  # already measured by an edge: not a loop (LoopQuery.top_kf)

        def eligible_of(ids: Tensor, scores: Tensor) -> list[tuple[int, float]]:
            pairs = ((self._kf_of_id[int(c)], float(s)) for c, s in zip(ids.tolist(), scores.tolist()))
            return [(k, s) for k, s in pairs if k not in joined]

        top = eligible_of(cands.top_ids, cands.top_scores)
        eligible = eligible_of(cands.ids, cands.scores)[: self.config.max_candidates]
        top_kf, top_score = top[0] if top else (-1, float("-inf"))
        query = LoopQuery(kf.id, top_kf, top_score, float(cands.threshold), [c for c, _ in eligible], [])
        self._queries.append(query)
        return desc, query, eligible

    def _follow(self, kf: Keyframe, graph: KeyframeGraph, did: int) -> Optional[int]:
        """The keyframe to verify ``kf`` against first when its odometry parent was a revisit (:meth:`close`):
        of the database's keyframes within two edges of the one repeated, outside the detector's window and not
        joined to ``kf``, the nearest to ``kf``'s estimate (translation and turn, each over its view limit)."""
        joined = graph.joined(kf.id)
        if self._place is None or self._place[0] not in joined:
            return None
        near = {self._place[1]} | graph.joined(self._place[1])
        near = near.union(*(graph.joined(k) for k in near))
        window = self.detector.config.window
        ids = sorted(k for k in near if k in self._id_of_kf and k not in joined and k != kf.id
                     and did - self._id_of_kf[k] >= window)
        if not ids:
            return None
        rel = se3_between(torch.stack([graph.estimate(k) for k in ids]), graph.estimate(kf.id).expand(len(ids), 7))
        cost = (rel[:, :3].norm(dim=1) / self.config.max_translation
                + quat_angle(rel[:, 3:]) / math.radians(self.config.max_rotation_deg))
        return ids[int(torch.argmin(cost))]

    def _verify(self, kf: Keyframe, keyframes: Sequence[Keyframe], graph: KeyframeGraph, query: LoopQuery,
                eligible: list[tuple[int, float]], through_loops: bool, min_loop_weight: float,
                repeats: Optional[Callable[[LoopClosure], bool]], seen: Dict[int, Optional[Verification]],
                follow: bool = False) -> LoopUpdate:
        """Verify ``eligible`` (``(keyframe id, similarity)``, most similar first) in order for :meth:`close`,
        recording the outcome in ``query``; the loops in a :class:`LoopUpdate`.

        ``seen``: this query keyframe's verifications so far, by candidate (None: already a hypothesis), reused
        and added to. ``follow``: only a loop that ``repeats`` becomes a hypothesis.
        """
        cfg = self.config
        update = LoopUpdate()
        if not eligible:
            return update
        ids = [c for c, _ in eligible]
        lengths = dict(zip(ids, graph.path_lengths_to(kf.id, ids, through_loops=through_loops,
                                                       min_loop_weight=min_loop_weight).tolist()))
        for rank, (cand_id, score) in enumerate(eligible):
            a = keyframes[cand_id]
            if cand_id in seen and seen[cand_id] is None:
                query.rejections[cand_id] = "a hypothesis already, outside the consistent group (followed)"
                continue
            v = seen.get(cand_id)
            if v is None:
                with self.timer("verification"):
                    estimate = se3_between(graph.estimate(a.id), graph.estimate(kf.id))
                    v = verify_candidate(a.features, kf.features, estimate, self.limits(float(lengths[a.id])), cfg)
                seen[cand_id] = v
            if not v.accepted:
                query.rejections[cand_id] = v.reason
                logger.info("loop candidate %d -> %d rejected: %s", cand_id, kf.id, v.reason)
                continue
            loop = LoopClosure(a.id, kf.id, a.frame_index, kf.frame_index, a.timestamp, kf.timestamp, float(score),
                               v.num_inliers, v.T_ab, v.information, v, id=len(self._loops),
                               path_length=float(lengths[a.id]),
                               settled=(v.disagreement <= cfg.settled_translation
                                        and v.disagreement_deg <= cfg.settled_rotation_deg))
            if follow and not repeats(loop):
                query.rejections[cand_id] = "verified, but it does not repeat that keyframe"
                continue
            seen[cand_id] = None
            query.verified.append(cand_id)
            self._loops.append(loop)
            update.new.append(loop)
            logger.info("loop verified: keyframe %d (frame %d) <-> keyframe %d (frame %d), %d inliers, %.2f m "
                        "travelled", loop.kf_a, loop.frame_a, loop.kf_b, loop.frame_b, loop.num_inliers,
                        loop.path_length)
            with self.timer("loop_consistency"):
                flipped = self.consistency.update(loop.kf_a, loop.kf_b, loop.T_ab, graph)
            loop.consistent = self.consistency.is_kept(loop.id)
            for i in flipped:  # only the loops whose kept state changed are visited
                lp = self._loops[i]
                was, lp.consistent = lp.consistent, self.consistency.is_kept(i)
                if lp is not loop and lp.consistent != was and lp not in update.changed:
                    update.changed.append(lp)
            if not loop.consistent:
                logger.info("loop %d (keyframes %d <-> %d) is outside the largest consistent group", loop.id,
                            loop.kf_a, loop.kf_b)
            elif repeats is not None and repeats(loop):
                for c, _ in eligible[rank + 1:]:
                    query.rejections[c] = f"not verified: the query repeats keyframe {cand_id}"
                break
        return update
