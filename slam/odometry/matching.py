"""Descriptor matching with Kornia's matchers, optionally guided by a motion prior.

Binary (ORB) descriptors are compared by Hamming distance: the packed bits are unpacked to ``{0, 1}``
floats and the distance matrix ``|a| + |b| - 2 a.b`` (exact integers in float32) is handed to
``kornia.feature.match_*`` through its ``dm=`` argument; float descriptors use Kornia's own L2 ``cdist``.
A motion prior turns the matcher into a *guided* one: pairs whose predicted position disagrees by more
than a radius get a prohibitive distance before the nearest-neighbour search.

Example:
    >>> a = torch.randint(0, 256, (6, 32), dtype=torch.uint8)
    >>> hamming_distance(a, a).diagonal().tolist()
    [0.0, 0.0, 0.0, 0.0, 0.0, 0.0]
"""
from __future__ import annotations

import kornia.feature as KF
import torch

from slam.odometry.config import MatchConfig
from slam.odometry.features import FrameFeatures
from slam.odometry.geometry import project, transform_points

Tensor = torch.Tensor

__all__ = ["hamming_distance", "match_descriptors", "match_features", "unpack_bits"]

# Distance given to pairs the motion prior forbids: larger than any Hamming (256) or unit-L2 (2) distance
# but finite, so Kornia's ratio test stays well defined.
_FORBIDDEN = 1.0e4


def unpack_bits(desc: Tensor) -> Tensor:
    """Packed uint8 descriptors ``(N, D)`` -> ``(N, 8 D)`` float32 bits in ``{0, 1}``.

    Example:
        >>> unpack_bits(torch.tensor([[1, 128]], dtype=torch.uint8)).nonzero()[:, 1].tolist()
        [0, 15]
    """
    if desc.dim() != 2 or desc.dtype != torch.uint8:
        raise ValueError(f"desc must be (N, D) uint8 packed bits, got {tuple(desc.shape)} {desc.dtype}")
    shifts = torch.arange(8, dtype=torch.uint8, device=desc.device)
    bits = (desc[:, :, None] >> shifts) & 1
    return bits.reshape(desc.shape[0], -1).to(torch.float32)


def _popcount64(x: Tensor) -> Tensor:
    """Number of set bits of each int64 (SWAR; the masks also clear the sign fill of the arithmetic shift)."""
    x = x - ((x >> 1) & 0x5555555555555555)
    x = (x & 0x3333333333333333) + ((x >> 2) & 0x3333333333333333)
    x = (x + (x >> 4)) & 0x0F0F0F0F0F0F0F0F
    return ((x * 0x0101010101010101) >> 56) & 0xFF


def hamming_distance(desc_a: Tensor, desc_b: Tensor, pairs: Tensor | None = None) -> Tensor:
    """Hamming distances between packed binary descriptors ``(N, D)`` and ``(M, D)`` uint8.

    Args:
        desc_a: ``(N, D)`` uint8.
        desc_b: ``(M, D)`` uint8.
        pairs: optional ``(P, 2)`` int64 index pairs: only those distances are computed.

    Returns:
        ``(N, M)`` float32 distance matrix, or ``(P,)`` float32 distances of ``pairs``.

    Example:
        >>> a = torch.tensor([[0, 0, 0, 0, 0, 0, 0, 3]], dtype=torch.uint8)
        >>> hamming_distance(a, torch.zeros(2, 8, dtype=torch.uint8)).tolist()
        [[2.0, 2.0]]
        >>> hamming_distance(a, a, torch.tensor([[0, 0]])).tolist()
        [0.0]
    """
    if pairs is None:
        # dense: a matmul of the {0, 1} bits (exact in float32; runs on any device)
        a, b = unpack_bits(desc_a), unpack_bits(desc_b)
        return a.sum(1, keepdim=True) + b.sum(1)[None] - 2.0 * (a @ b.transpose(0, 1))
    if desc_a.shape[1] % 8 == 0:
        xa = desc_a.contiguous().view(torch.int64)[pairs[:, 0]]
        xb = desc_b.contiguous().view(torch.int64)[pairs[:, 1]]
        return _popcount64(xa ^ xb).sum(-1).to(torch.float32)
    x = unpack_bits(desc_a)[pairs[:, 0]] - unpack_bits(desc_b)[pairs[:, 1]]
    return x.abs().sum(-1)


def match_descriptors(desc_a: Tensor, desc_b: Tensor, binary: bool, config: MatchConfig | None = None,
                      allowed: Tensor | None = None) -> tuple[Tensor, Tensor]:
    """Match two descriptor sets with Kornia's ``match_{mnn,snn,smnn}``.

    Args:
        desc_a: ``(N, D)`` descriptors (uint8 packed bits when ``binary``, else float).
        desc_b: ``(M, D)``.
        binary: Hamming distance on packed bits instead of L2.
        config: matcher settings.
        allowed: optional ``(N, M)`` bool, False where a pair is ruled out (guided matching).

    Returns:
        ``(K, 2)`` int64 index pairs ``(i_a, i_b)`` and ``(K,)`` descriptor distances (Hamming bits or L2).
    """
    config = config or MatchConfig()
    if desc_a.dim() != 2 or desc_b.dim() != 2 or desc_a.shape[1] != desc_b.shape[1]:
        raise ValueError(f"descriptors must be (N, D) and (M, D), got {tuple(desc_a.shape)} and "
                         f"{tuple(desc_b.shape)}")
    empty = (torch.zeros(0, 2, dtype=torch.long, device=desc_a.device),
             torch.zeros(0, device=desc_a.device))
    if desc_a.shape[0] < 2 or desc_b.shape[0] < 2:
        return empty
    shape = (desc_a.shape[0], desc_b.shape[0])
    if allowed is not None and allowed.shape != shape:
        raise ValueError(f"allowed must have shape {shape}, got {tuple(allowed.shape)}")
    if binary:
        fa, fb = desc_a, desc_b  # Kornia only checks their shapes when dm is given
        max_dist = config.max_hamming
        if allowed is not None and int(allowed.sum()) < 0.25 * allowed.numel():
            # guided: only the allowed pairs (a few percent) are worth a distance
            pairs = allowed.nonzero()
            dm = torch.full(shape, _FORBIDDEN, dtype=torch.float32, device=desc_a.device)
            dm[pairs[:, 0], pairs[:, 1]] = hamming_distance(desc_a, desc_b, pairs)
            allowed = None
        else:
            dm = hamming_distance(desc_a, desc_b)
    else:
        fa, fb = desc_a.float(), desc_b.float()
        dm = torch.cdist(fa, fb)
        max_dist = config.max_l2
    if allowed is not None:
        dm = torch.where(allowed, dm, torch.full_like(dm, _FORBIDDEN))
    if config.method == "smnn":
        _, idx = KF.match_smnn(fa, fb, config.ratio, dm=dm)
    elif config.method == "snn":
        _, idx = KF.match_snn(fa, fb, config.ratio, dm=dm)
    elif config.method == "mnn":
        _, idx = KF.match_mnn(fa, fb, dm=dm)
    else:
        raise ValueError(f"unknown matching method {config.method!r}: expected 'smnn', 'snn' or 'mnn'")
    if idx.shape[0] == 0:
        return empty
    dist = dm[idx[:, 0], idx[:, 1]]
    keep = dist <= max_dist
    return idx[keep], dist[keep]


def match_features(fa: FrameFeatures, fb: FrameFeatures, config: MatchConfig | None = None,
                   prior_ab: Tensor | None = None, only_valid: bool = True) -> tuple[Tensor, Tensor]:
    """Match the keypoints of two frames.

    Args:
        fa: features of frame a.
        fb: features of frame b.
        config: matcher settings.
        prior_ab: optional ``(7,)`` predicted pose of frame b in frame a (``p_a = T_ab p_b``): b's 3D points
            are projected into a and may only match a's keypoints within ``config.guided_radius_px``.
        only_valid: match only keypoints that have a 3D point in both frames (what 3D-3D RANSAC needs).

    Returns:
        ``(K, 2)`` int64 indices into ``fa`` and ``fb`` and ``(K,)`` descriptor distances.
    """
    config = config or MatchConfig()
    if fa.binary != fb.binary:
        raise ValueError("cannot match binary descriptors with float ones (different detectors)")
    ia = torch.nonzero(fa.valid).squeeze(1) if only_valid else torch.arange(len(fa))
    ib = torch.nonzero(fb.valid).squeeze(1) if only_valid else torch.arange(len(fb))
    allowed = None
    if prior_ab is not None and config.guided_radius_px > 0 and ia.numel() and ib.numel():
        pts_b = fb.points[ib].to(torch.float64)
        uv = project(transform_points(prior_ab.to(torch.float64), pts_b), fa.K.to(torch.float64))
        radius = config.guided_radius_px * fa.image_size[1] / 640.0
        kp = fa.keypoints[ia].to(torch.float32)
        uv = uv.to(torch.float32)
        # separate x / y differences: a reduction over a last dimension of 2 is slow on the CPU
        dx = kp[:, 0:1] - uv[None, :, 0]
        dy = kp[:, 1:2] - uv[None, :, 1]
        allowed = dx * dx + dy * dy <= radius * radius  # (Na, Nb)
    idx, dist = match_descriptors(fa.descriptors[ia], fb.descriptors[ib], fa.binary, config, allowed)
    if idx.shape[0] == 0:
        return idx, dist
    return torch.stack([ia[idx[:, 0]], ib[idx[:, 1]]], dim=1), dist
