"""Loop closure: place recognition, geometric verification and the acceptance of loops.

* :mod:`slam.loop.closer`: :class:`LoopCloser` (describe -> candidates -> verify -> consistency per
  keyframe) and its records :class:`LoopClosure`, :class:`LoopQuery`;
* :mod:`slam.loop.verification`: :func:`verify_candidate`, one candidate pair -> :class:`Verification`.
"""
from slam.loop.closer import LoopCloser, LoopClosure, LoopQuery, build_descriptor
from slam.loop.verification import DriftLimits, Verification, verify_candidate

__all__ = [
    "DriftLimits",
    "LoopCloser",
    "LoopClosure",
    "LoopQuery",
    "Verification",
    "build_descriptor",
    "verify_candidate",
]
