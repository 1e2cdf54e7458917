"""Closed-form least-squares alignment of two point sets (Umeyama 1991, as evo's ``geometry.umeyama_alignment``):
``target ~ s * R @ source + t``, rigid by default, Sim(3) with ``with_scale``.

Example:
    >>> src = torch.randn(10, 3, dtype=torch.float64)
    >>> R, t, s = umeyama_alignment(src, src + 1.0)
    >>> R.shape, t.shape, s.shape
    (torch.Size([3, 3]), torch.Size([3]), torch.Size([]))
    >>> torch.allclose(t, torch.ones(3, dtype=torch.float64))
    True
"""
from __future__ import annotations

import torch

from slam.lie import quat_mul, quat_normalize, rotmat_to_quat

__all__ = ["transform_poses", "umeyama_alignment"]


def umeyama_alignment(
    source: torch.Tensor, target: torch.Tensor, with_scale: bool = False
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Best rotation, translation (and scale) mapping ``source`` onto ``target``.

    Args:
        source: ``(..., N, 3)`` points (e.g. estimated camera centres).
        target: ``(..., N, 3)`` corresponding points (e.g. ground-truth camera centres).
        with_scale: also estimate a scale (Sim(3)); otherwise ``s = 1`` (rigid).

    Returns:
        ``R (..., 3, 3)``, ``t (..., 3)``, ``s (...)`` minimising ``sum |target - (s R source + t)|^2``.

    Raises:
        ValueError: mismatched shapes, or a degenerate configuration (fewer than 3 points, or all
            points collinear) where the rotation is not determined.
    """
    if source.shape != target.shape or source.dim() < 2 or source.shape[-1] != 3:
        raise ValueError(
            f"source and target must both have shape (..., N, 3), got {tuple(source.shape)} and {tuple(target.shape)}"
        )
    n = source.shape[-2]
    if n < 3:
        raise ValueError(f"alignment needs at least 3 point pairs, got {n}")
    mean_s = source.mean(dim=-2)
    mean_t = target.mean(dim=-2)
    xs = source - mean_s[..., None, :]
    xt = target - mean_t[..., None, :]
    sigma_s = (xs * xs).sum(dim=(-2, -1)) / n
    cov = xt.transpose(-1, -2) @ xs / n  # (..., 3, 3) = mean of outer(target_i, source_i)
    U, D, Vh = torch.linalg.svd(cov)
    eps = torch.finfo(cov.dtype).eps
    if bool(((D > eps).sum(dim=-1) < 2).any()):
        raise ValueError("degenerate point configuration (collinear or coincident): alignment is not possible")
    S = torch.ones_like(D)
    S[..., 2] = torch.where(torch.det(U) * torch.det(Vh) < 0, -1.0, 1.0).to(D.dtype)
    R = U @ (S[..., :, None] * Vh)
    if with_scale:
        s = (D * S).sum(dim=-1) / sigma_s
    else:
        s = torch.ones(cov.shape[:-2], dtype=cov.dtype, device=cov.device)
    t = mean_t - s[..., None] * (R @ mean_s[..., :, None])[..., 0]
    return R, t, s


def transform_poses(poses: torch.Tensor, R: torch.Tensor, t: torch.Tensor, s=1.0) -> torch.Tensor:
    """Apply a similarity ``x -> s R x + t`` to camera-to-world poses.

    Args:
        poses: ``(N, 7)`` ``[t, q_xyzw]``.
        R: ``(3, 3)`` rotation.
        t: ``(3,)`` translation.
        s: scale (float or 0-d tensor); it scales positions only.

    Returns:
        ``(N, 7)`` poses: positions ``s R p + t``, orientations ``q_R * q``.
    """
    if poses.dim() != 2 or poses.shape[-1] != 7:
        raise ValueError(f"poses must have shape (N, 7), got {tuple(poses.shape)}")
    if R.shape != (3, 3) or t.shape != (3,):
        raise ValueError(f"R must be (3, 3) and t (3,), got {tuple(R.shape)} and {tuple(t.shape)}")
    s = torch.as_tensor(s, dtype=poses.dtype, device=poses.device)
    positions = s * (poses[:, :3] @ R.T) + t
    q = quat_mul(rotmat_to_quat(R).expand(poses.shape[0], 4), poses[:, 3:])
    return torch.cat([positions, quat_normalize(q)], dim=-1)
