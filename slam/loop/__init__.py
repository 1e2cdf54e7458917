"""Loop closure: place recognition, geometric verification and the acceptance of loops.

* :mod:`slam.loop.closer`: :class:`LoopCloser` (describe -> candidates -> verify -> consistency per
  keyframe) and its records :class:`LoopClosure`, :class:`LoopQuery`, :class:`LoopUpdate`;
* :mod:`slam.loop.verification`: :func:`verify_candidate`, one candidate pair -> :class:`Verification`;
* :mod:`slam.loop.acceptance`: the disagreement bound that grows with the distance travelled;
* :mod:`slam.loop.consistency`: group consistency (the largest set of mutually consistent loops).
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
