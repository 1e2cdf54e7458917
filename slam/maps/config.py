"""Settings of relocalisation in a saved map (:mod:`slam.maps.relocalise`), every default commented."""
from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class RelocalisationConfig:
    """How a new recording is placed in a saved map.

    Verification itself is the loop closer's (:func:`slam.loop.verify_candidate` with
    ``LoopClosureConfig``'s inlier, ratio and view-distance thresholds): a map link is a loop whose older
    keyframe belongs to the map. The map's keyframes are held fixed in the joint optimisation (not
    given priors): the map is the reference world every later session is reported in, optimised with its
    own loops over a recording that is no longer there; moving it would move the world under the poses
    reported before.
    """

    # Map keyframes verified per keyframe of the new recording (the most similar first). Verification,
    # not the descriptor's similarity, decides: a place the map does not hold has no geometric match.
    max_candidates: int = 5
    # Verified links from this many distinct keyframes of the recording, mutually consistent (the loop
    # closer's pairwise test, slam.loop.pairwise_consistent, with the drift bound of the path between
    # them), before the recording is placed in the map: one link can be an aliased place (a repeated
    # cupboard), two independent views agreeing on one placement rarely are (ORB-SLAM3 asks the same of
    # a map merge: several covisible keyframes).
    min_agreeing: int = 2
    # Localisation only (--localize): the recording is tracked and placed in the map without growing
    # anything: its keyframes serve tracking and the map queries only (no loop closing among them, no
    # index of them, no map.ply), their features and images are released once queried, and no map is
    # saved. Memory then stays flat however long the recording; the map folder is only read.
    localize: bool = False

    def __post_init__(self) -> None:
        if self.max_candidates < 1 or self.min_agreeing < 1:
            raise ValueError(f"RelocalisationConfig: need max_candidates >= 1 and min_agreeing >= 1, got "
                             f"{self.max_candidates}, {self.min_agreeing}")
