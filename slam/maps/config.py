"""Settings of relocalisation in a saved map (:mod:`slam.maps.relocalise`), every default commented."""
from __future__ import annotations

from dataclasses import dataclass

from slam.odometry.config import check_bool, check_int


@dataclass(frozen=True)
class RelocalisationConfig:
    """How a new recording is placed in a saved map (verification is the loop closer's, with its thresholds)."""

    # Map keyframes verified per keyframe of the new recording (the most similar first).
    max_candidates: int = 5
    # Distinct keyframes of the recording whose verified links agree pairwise (drift-bounded) before it is
    # placed in the map: one link can be an aliased place, two independent views agreeing rarely are.
    min_agreeing: int = 2
    # Localisation only (--localize): placed in the map without growing anything (no loops, index, map.ply or
    # saved map); keyframes' features and images are released once queried, so memory stays flat.
    localize: bool = False

    def __post_init__(self) -> None:
        check_int("RelocalisationConfig", "max_candidates", self.max_candidates, 1)
        check_int("RelocalisationConfig", "min_agreeing", self.min_agreeing, 1)
        check_bool("RelocalisationConfig", "localize", self.localize)
