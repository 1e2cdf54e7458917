"""Settings of relocalisation in a saved map (:mod:`slam.maps.relocalise`), every default commented."""
from __future__ import annotations

from dataclasses import dataclass

from slam.odometry.config import check_bool, check_int


@dataclass(frozen=True)
class RelocalisationConfig:
    """How a new recording is placed in a saved map.

    Verification itself is the loop closer's (:func:`slam.loop.verify_candidate` with ``LoopClosureConfig``'s
    thresholds). The map's keyframes are held fixed in the joint optimisation: the map is the reference world
    every later session is reported in.
    """

    # Map keyframes verified per keyframe of the new recording (the most similar first).
    max_candidates: int = 5
    # Verified links from this many distinct keyframes of the recording, mutually consistent (the loop
    # closer's pairwise test with the drift bound of the path between them), before the recording is placed
    # in the map: one link can be an aliased place, two independent views agreeing rarely are.
    min_agreeing: int = 2
    # Localisation only (--localize): the recording is placed in the map without growing anything (no loop
    # closing, no index of its keyframes, no map.ply, no map saved); its keyframes' features and images are
    # released once queried, so memory stays flat however long the recording.
    localize: bool = False

    def __post_init__(self) -> None:
        check_int("RelocalisationConfig", "max_candidates", self.max_candidates, 1)
        check_int("RelocalisationConfig", "min_agreeing", self.min_agreeing, 1)
        check_bool("RelocalisationConfig", "localize", self.localize)
