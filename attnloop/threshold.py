"""Adaptive acceptance threshold for loop-closure candidates, relative to the query's own similarities ``s``.

``max(min_similarity, median(s) + max(k_sigma * 1.4826 * MAD(s), min_margin))`` (interpolated medians, the MAD
scaled to a Gaussian standard deviation), ``+inf`` below ``min_samples`` similarities; a candidate strictly
above it is accepted.

Example:
    >>> s = torch.cat([torch.linspace(0.40, 0.60, 200), torch.tensor([0.95])])
    >>> t = adaptive_threshold(s, ThresholdConfig())
    >>> bool(0.60 < t < 0.95)
    True
    >>> accept_mask(s, ThresholdConfig()).nonzero().flatten().tolist()
    [200]
"""
from __future__ import annotations

import math
import numbers
from dataclasses import dataclass

import torch

Tensor = torch.Tensor

__all__ = ["ThresholdConfig", "accept_mask", "adaptive_threshold"]

_MAD_TO_SIGMA = 1.4826  # MAD of a Gaussian = 0.6745 sigma


@dataclass(frozen=True)
class ThresholdConfig:
    """Parameters of :func:`adaptive_threshold` (see the module docstring for the rule)."""

    k_sigma: float = 3.0  # robust standard deviations above the centre (docs/results.md)
    min_margin: float = 0.02  # the threshold is at least this far above the centre (flat -> nothing)
    min_similarity: float = 0.0  # absolute cosine floor (0 = off: the relative rule alone decides)
    min_samples: int = 32  # fewer eligible keyframes -> threshold +inf: the MAD of fewer is too noisy

    def __post_init__(self) -> None:
        for name in ("k_sigma", "min_margin", "min_similarity"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, numbers.Real) or not math.isfinite(value):
                raise ValueError(f"ThresholdConfig.{name} must be a finite number, got {value!r}")
        if self.k_sigma < 0 or self.min_margin < 0:
            raise ValueError(f"k_sigma and min_margin must be >= 0, got {self.k_sigma}, {self.min_margin}")
        if isinstance(self.min_samples, bool) or not isinstance(self.min_samples, numbers.Integral):
            raise ValueError(f"ThresholdConfig.min_samples must be an integer, got {self.min_samples!r}")
        if self.min_samples < 2:
            raise ValueError(f"min_samples must be >= 2, got {self.min_samples}")


def adaptive_threshold(similarities: Tensor, config: ThresholdConfig | None = None) -> Tensor:
    """The acceptance threshold for one query, from its similarities to the eligible keyframes.

    Args:
        similarities: the query's similarities to the eligible keyframes ``(N,)`` (all of them, or an
            unbiased sample of them).
        config: the rule's parameters (default :class:`ThresholdConfig`).

    Returns:
        threshold, a 0-d tensor in ``similarities``' dtype (float32 for integers) on its device; ``+inf``
        when ``N < config.min_samples``.

    Raises:
        ValueError: NaN or infinite similarities (naming the first positions), a shape other than ``(N,)``.
    """
    cfg = config or ThresholdConfig()
    if not isinstance(similarities, Tensor):
        raise TypeError(f"similarities must be a torch.Tensor, got {type(similarities).__name__}")
    if similarities.dim() != 1:
        raise ValueError(f"similarities must have shape (N,), got {tuple(similarities.shape)}")
    out_dtype = similarities.dtype if similarities.is_floating_point() else torch.float32
    # quantile takes float32 and float64 only: half precisions are widened (and the result rounded back).
    s = similarities.to(torch.float64 if out_dtype == torch.float64 else torch.float32)
    finite = torch.isfinite(s)
    if not bool(finite.all()):
        where = (~finite).nonzero().flatten()[:5].tolist()
        raise ValueError(f"similarities must be finite: NaN or inf at positions {where}")
    if s.numel() < cfg.min_samples:
        return torch.tensor(float("inf"), dtype=out_dtype, device=s.device)
    centre = s.quantile(0.5)
    spread = _MAD_TO_SIGMA * (s - centre).abs().quantile(0.5)
    margin = torch.clamp(cfg.k_sigma * spread, min=cfg.min_margin)
    return torch.clamp(centre + margin, min=cfg.min_similarity).to(out_dtype)


def accept_mask(similarities: Tensor, config: ThresholdConfig | None = None) -> Tensor:
    """Boolean mask ``(N,)``: which ``similarities (N,)`` exceed their adaptive threshold (strictly)."""
    return similarities > adaptive_threshold(similarities, config)
