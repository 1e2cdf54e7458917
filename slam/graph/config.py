"""The settings of the pose-graph optimiser (:func:`slam.graph.optimize`)."""
from __future__ import annotations

from dataclasses import dataclass
from numbers import Integral
from typing import Optional, Tuple

import numpy as np

__all__ = ["OptimizerConfig"]


@dataclass
class OptimizerConfig:
    """Settings of :func:`optimize` (all thresholds in chi2 units, i.e. 2x GTSAM's error)."""

    max_iterations: int = 100  # outer iterations (accepted or GN steps); GTSAM's default is 100
    rel_tol: float = 1e-5  # converged when (cost - new_cost) < rel_tol * cost  (GTSAM relativeErrorTol)
    abs_tol: float = 2e-5  # converged when cost - new_cost < abs_tol  (GTSAM absoluteErrorTol 1e-5 x 2)
    lambda_init: float = 1e-5  # initial LM damping (GTSAM's default)
    lambda_factor: float = 10.0  # lambda /= factor after a good step, *= factor after a bad one
    lambda_max: float = 1e10  # LM gives up (status lambda_limit) beyond this damping
    damping: str = "identity"  # "identity": H + lambda I (GTSAM's default); "diagonal": H + lambda diag(H)
    # how lambda moves (LM only): "gtsam" (/= lambda_factor after a good step, *= after a bad one) or
    # "nielsen" (the gain-ratio rule of g2o and Ceres)
    lambda_update: str = "gtsam"
    # "free": LM damping, then re-anchored on pose 0; "first": hold pose 0; "prior": a prior on pose 0
    gauge: str = "free"
    prior_weight: float = 1e8  # information of the "prior" gauge (rotation and translation alike)
    fixed: Tuple[int, ...] = ()  # further pose indices held constant (e.g. an already-optimised map)
    kernel_width: Optional[float] = None  # width of a kernel given by name (default sqrt(chi2_0.95(6)))
    planar: Optional[bool] = None  # solve only (x, y, yaw); None: auto-detect with PoseGraph.is_planar()
    check_information: bool = True  # check every information matrix is SPD before optimising
    # the optimised poses carry a grad_fn when the measurements, information matrices or held poses require
    # grad (implicit differentiation at the optimum: slam.graph.implicit; first order only)
    differentiable: bool = False
    verbose: bool = False  # print one line per iteration

    def validate(self, method: str = "lm") -> OptimizerConfig:
        """Check the settings for ``method`` (``"lm"`` or ``"gn"``: GN has no damping to check); a
        ``ValueError`` names the first bad one. Returns ``self``."""
        for name in ("differentiable", "check_information", "verbose"):
            # bool("no") is True: a string or a number here is a mistake (numpy's bool is a bool)
            if not isinstance(getattr(self, name), (bool, np.bool_)):
                raise ValueError(f"{name} must be True or False, got {getattr(self, name)!r}")
        it = self.max_iterations
        if isinstance(it, (bool, np.bool_)) or not isinstance(it, Integral) or it < 0:
            raise ValueError(f"max_iterations must be an integer >= 0, got {it!r}")
        choices = (("damping", ("identity", "diagonal")), ("lambda_update", ("gtsam", "nielsen")),
                   ("gauge", ("free", "first", "prior")))
        for name, allowed in choices:
            value = getattr(self, name)
            if value not in allowed:
                listed = ", ".join(repr(a) for a in allowed[:-1]) + f" or {allowed[-1]!r}"
                raise ValueError(f"{name} must be {listed}, got {value!r}")
        lm_ok = self.lambda_init > 0 and self.lambda_factor > 1 and self.lambda_max > self.lambda_init
        if method == "lm" and not lm_ok:
            raise ValueError("LM needs lambda_init > 0, lambda_factor > 1 and lambda_max > lambda_init, got "
                             f"{self.lambda_init}, {self.lambda_factor}, {self.lambda_max}")
        return self
