"""Loop closure: :mod:`~slam.loop.closer` (per keyframe: describe -> candidates -> verify -> consistency),
:mod:`~slam.loop.verification` (one candidate pair), :mod:`~slam.loop.acceptance` (the disagreement bound that
grows with the distance travelled), :mod:`~slam.loop.consistency` (the largest set of mutually consistent loops).
"""
from slam.loop.acceptance import DriftBoundConfig, drift_limits, pairwise_consistent
from slam.loop.closer import LoopCloser, LoopClosure, LoopQuery, LoopUpdate, build_descriptor
from slam.loop.consistency import ConsistencyConfig, GroupConsistency, maximum_clique
from slam.loop.verification import DriftLimits, Verification, verify_candidate

__all__ = [
    "ConsistencyConfig",
    "DriftBoundConfig",
    "DriftLimits",
    "GroupConsistency",
    "LoopCloser",
    "LoopClosure",
    "LoopQuery",
    "LoopUpdate",
    "Verification",
    "build_descriptor",
    "drift_limits",
    "maximum_clique",
    "pairwise_consistent",
    "verify_candidate",
]
