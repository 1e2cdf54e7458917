"""Descriptor matching with Kornia's ``match_*`` (Hamming distances of binary descriptors passed as ``dm=``,
L2 for float ones), optionally guided by a motion prior (pairs farther than a radius apart are forbidden).

Example:
    >>> a = torch.randint(0, 256, (6, 32), dtype=torch.uint8)
    >>> hamming_distance(a, a).diagonal().tolist()
    [0.0, 0.0, 0.0, 0.0, 0.0, 0.0]
"""
from __future__ import annotations

import kornia.feature as KF
import numpy as np
import torch

from slam.odometry.config import MatchConfig
from slam.odometry.features import FrameFeatures
from slam.odometry.geometry import project, transform_points

Tensor = torch.Tensor

__all__ = ["guided_pairs", "hamming_distance", "match_descriptors", "match_features", "unpack_bits"]

# Distance of pairs the motion prior forbids: above any Hamming (256) or unit-L2 (2) one, finite for the ratio test
_FORBIDDEN = 1.0e4

_NP_POPCOUNT = getattr(np, "bitwise_count", None)  # numpy >= 2.0


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
    """Number of set bits of each int64 (numpy's popcount on the CPU, else SWAR; the masks also clear the
    sign fill of the arithmetic shift)."""
    if x.device.type == "cpu" and _NP_POPCOUNT is not None:  # on unsigned bits: numpy counts a signed value's |x|
        return torch.from_numpy(_NP_POPCOUNT(x.contiguous().numpy().view(np.uint64)).astype(np.int64))
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
        # dense: one matmul of the bits as +-1, whose dot product is D - 2 h (exact in float32, any device)
        a, b = unpack_bits(desc_a).mul_(2).sub_(1), unpack_bits(desc_b).mul_(2).sub_(1)
        return torch.addmm(a.new_tensor(a.shape[1] / 2), a, b.transpose(0, 1), alpha=-0.5)
    if desc_a.shape[1] % 8 == 0:
        xa = desc_a.contiguous().view(torch.int64)[pairs[:, 0]]
        xb = desc_b.contiguous().view(torch.int64)[pairs[:, 1]]
        return _popcount64(xa ^ xb).sum(-1).to(torch.float32)
    x = unpack_bits(desc_a)[pairs[:, 0]] - unpack_bits(desc_b)[pairs[:, 1]]
    return x.abs().sum(-1)


def match_descriptors(desc_a: Tensor, desc_b: Tensor, binary: bool, config: MatchConfig | None = None, *,
                      allowed_pairs: Tensor | None = None) -> tuple[Tensor, Tensor]:
    """Match two descriptor sets with Kornia's ``match_{mnn,snn,smnn}``.

    Args:
        desc_a: ``(N, D)`` descriptors (uint8 packed bits when ``binary``, else float).
        desc_b: ``(M, D)``.
        binary: Hamming distance on packed bits instead of L2.
        config: matcher settings.
        allowed_pairs: optional ``(P, 2)`` int64 ``(i_a, i_b)``, the only pairs that may match (guided matching;
            no duplicates).

    Returns:
        ``(K, 2)`` int64 index pairs ``(i_a, i_b)`` and ``(K,)`` descriptor distances (Hamming bits or L2).
    """
    config = config or MatchConfig()
    if desc_a.dim() != 2 or desc_b.dim() != 2 or desc_a.shape[1] != desc_b.shape[1]:
        raise ValueError(f"descriptors must be (N, D) and (M, D), got {tuple(desc_a.shape)} and "
                         f"{tuple(desc_b.shape)}")
    n_a, n_b = desc_a.shape[0], desc_b.shape[0]
    # only the ratio test needs a second column (snn: per row of a; smnn: both ways); Kornia returns nothing
    if (n_a == 0 or n_b == 0 or (config.method == "snn" and n_b < 2)
            or (config.method == "smnn" and min(n_a, n_b) < 2)):
        return torch.zeros(0, 2, dtype=torch.long, device=desc_a.device), torch.zeros(0, device=desc_a.device)
    allowed = None  # (N, M) bool, False where a pair is ruled out
    if allowed_pairs is not None:
        if allowed_pairs.dim() != 2 or allowed_pairs.shape[1] != 2:
            raise ValueError(f"allowed_pairs must have shape (P, 2), got {tuple(allowed_pairs.shape)}")
        if (binary and config.method in ("smnn", "snn") and config.ratio < 1.0
                and allowed_pairs.shape[0] < 0.25 * n_a * n_b):
            return _match_pairs(desc_a, desc_b, allowed_pairs, config)
        allowed = torch.zeros(n_a, n_b, dtype=torch.bool, device=desc_a.device)
        allowed[allowed_pairs[:, 0], allowed_pairs[:, 1]] = True
    fa, fb = (desc_a, desc_b) if binary else (desc_a.float(), desc_b.float())  # given dm, Kornia checks only shapes
    dm = hamming_distance(fa, fb) if binary else torch.cdist(fa, fb)
    max_dist = config.max_hamming if binary else config.max_l2
    if allowed is not None:
        dm = torch.where(allowed, dm, torch.full_like(dm, _FORBIDDEN))
    if config.method == "smnn":
        _, idx = KF.match_smnn(fa, fb, config.ratio, dm=dm)
    elif config.method == "snn":
        _, idx = KF.match_snn(fa, fb, config.ratio, dm=dm)
    else:  # "mnn" (MatchConfig checks the name)
        _, idx = KF.match_mnn(fa, fb, dm=dm)
    dist = dm[idx[:, 0], idx[:, 1]]
    keep = dist <= max_dist
    return idx[keep], dist[keep]


def _ratio_nn_of_pairs(rows: Tensor, cols: Tensor, dist: Tensor, n_rows: int, ratio: float):
    """Kornia's ``match_snn`` on a distance matrix that is ``_FORBIDDEN`` except at the given pairs.

    Per row ``v1 / v2 <= ratio`` (float32, as Kornia) with the two smallest distances (``v2 = v1`` when it
    occurs twice); with ``ratio < 1`` a passing row's nearest column is unique, so it is Kornia's.

    Returns:
        ``(n_rows,)`` bool: passes, ``(n_rows,)`` int64: the nearest column (-1 for a row without pairs),
        ``(n_rows,)`` the nearest distance.
    """
    forbidden = torch.full((n_rows,), _FORBIDDEN, dtype=dist.dtype, device=dist.device)
    v1 = forbidden.scatter_reduce(0, rows, dist, reduce="amin")
    is_min = dist == v1[rows]
    n_min = torch.zeros(n_rows, dtype=torch.long, device=dist.device).scatter_add_(0, rows, is_min.long())
    v2 = forbidden.scatter_reduce(0, rows, torch.where(is_min, forbidden[0], dist), reduce="amin")
    v2 = torch.where(n_min >= 2, v1, v2)
    nearest = torch.full((n_rows,), -1, dtype=torch.long, device=dist.device)
    nearest[rows[is_min]] = cols[is_min]  # several only where v1 == v2, a row that fails
    return v1 / v2 <= ratio, nearest, v1


def _match_pairs(desc_a: Tensor, desc_b: Tensor, pairs: Tensor, config: MatchConfig):
    """``smnn`` / ``snn`` of binary descriptors on the allowed pairs only (the result of the dense
    matrix with ``_FORBIDDEN`` elsewhere, in Kornia's order: by ``i_a``)."""
    n, m = desc_a.shape[0], desc_b.shape[0]
    rows, cols = pairs[:, 0], pairs[:, 1]
    dist = hamming_distance(desc_a, desc_b, pairs)
    ok_a, nn_a, d_a = _ratio_nn_of_pairs(rows, cols, dist, n, config.ratio)
    if config.method == "smnn":
        ok_b, nn_b, _ = _ratio_nn_of_pairs(cols, rows, dist, m, config.ratio)
        j = nn_a.clamp_min(0)
        ok_a = ok_a & ok_b[j] & (nn_b[j] == torch.arange(n, device=pairs.device))
    ia = torch.nonzero(ok_a).squeeze(1)
    idx, d = torch.stack([ia, nn_a[ia]], dim=1), d_a[ia]
    keep = d <= config.max_hamming
    return idx[keep], d[keep]


def guided_pairs(kp: Tensor, uv: Tensor, radius: float) -> Tensor:
    """Every pair ``(i, j)`` with ``|kp_i - uv_j|^2 <= radius^2`` (float32, as the dense mask would test it),
    from the 3 x 3 grid cells around ``kp_i``'s. NaN or huge ``uv`` (points behind the camera) pair with nothing.

    Args:
        kp: ``(N, 2)`` float32 keypoints (finite).
        uv: ``(M, 2)`` float32 predicted positions.
        radius: in pixels (> 0).

    Returns:
        ``(P, 2)`` int64 ``(i, j)``, ordered by ``i`` (and by cell, then ``j``, for one ``i``).

    Example:
        >>> guided_pairs(torch.tensor([[0., 0.], [10., 0.]]), torch.tensor([[3., 4.], [30., 0.]]), 5.0).tolist()
        [[0, 0]]
    """
    dev = kp.device
    n, m = kp.shape[0], uv.shape[0]
    if n == 0 or m == 0:
        return torch.zeros(0, 2, dtype=torch.long, device=dev)
    cell = 1.01 * float(radius)
    a = torch.floor(kp.to(torch.float64) / cell).long()
    lo = a.amin(dim=0)
    a = a - lo  # kp's cells: [0, ncol) x [0, nrow)
    ncol, nrow = int(a[:, 0].max()) + 1, int(a[:, 1].max()) + 1
    width = ncol + 2  # the grid's columns -1 .. ncol: every neighbour of a keypoint's cell
    # uv's cells; the ones no keypoint cell touches (far, or not finite) get key -1, which no query asks for
    bf = torch.nan_to_num(uv.to(torch.float64) / cell, nan=-1e9, posinf=1e9, neginf=-1e9)
    bx = bf[:, 0].clamp(-1e9, 1e9).floor().long() - lo[0]
    by = bf[:, 1].clamp(-1e9, 1e9).floor().long() - lo[1]
    near_grid = (bx >= -1) & (bx <= ncol) & (by >= -1) & (by <= nrow)
    key = torch.where(near_grid, (by + 1) * width + (bx + 1), -1)
    order = torch.argsort(key, stable=True)  # by cell, then j
    sorted_key = key[order]
    off = torch.tensor([-1, 0, 1], device=dev)
    qx = a[:, 0:1] + off.repeat(3)[None, :]  # (N, 9): i-major, so the pairs come out ordered by i
    qy = a[:, 1:2] + off.repeat_interleave(3)[None, :]
    query = ((qy + 1) * width + (qx + 1)).reshape(-1)
    start = torch.searchsorted(sorted_key, query)
    count = torch.searchsorted(sorted_key, query, right=True) - start
    total = int(count.sum())
    i = torch.arange(n, device=dev).repeat_interleave(9).repeat_interleave(count)
    shift = (start - (torch.cumsum(count, 0) - count)).repeat_interleave(count)
    j = order[torch.arange(total, device=dev) + shift]
    dx = kp[i, 0] - uv[j, 0]
    dy = kp[i, 1] - uv[j, 1]
    near = dx * dx + dy * dy <= radius * radius
    return torch.stack([i[near], j[near]], dim=1)

def match_features(fa: FrameFeatures, fb: FrameFeatures, config: MatchConfig | None = None,
                   prior_ab: Tensor | None = None) -> tuple[Tensor, Tensor]:
    """Match the keypoints of two frames that have a 3D point (what 3D-3D RANSAC needs).

    Args:
        fa: features of frame a.
        fb: features of frame b.
        config: matcher settings.
        prior_ab: optional ``(7,)`` predicted pose of frame b in frame a (``p_a = T_ab p_b``): b's 3D points
            are projected into a and may only match a's keypoints within ``config.guided_radius_px``.

    Returns:
        ``(K, 2)`` int64 indices into ``fa`` and ``fb`` and ``(K,)`` descriptor distances.
    """
    config = config or MatchConfig()
    if fa.binary != fb.binary:
        raise ValueError("cannot match binary descriptors with float ones (different detectors)")
    ia = torch.nonzero(fa.valid).squeeze(1)
    ib = torch.nonzero(fb.valid).squeeze(1)
    allowed = None
    if prior_ab is not None and config.guided_radius_px > 0 and ia.numel() and ib.numel():
        pts_b = fb.points[ib].to(torch.float64)
        uv = project(transform_points(prior_ab.to(torch.float64), pts_b), fa.K.to(torch.float64))
        radius = config.guided_radius_px * fa.image_size[1] / 640.0
        allowed = guided_pairs(fa.keypoints[ia].to(torch.float32), uv.to(torch.float32), radius)
    idx, dist = match_descriptors(fa.descriptors[ia], fb.descriptors[ib], fa.binary, config,
                                  allowed_pairs=allowed)
    return torch.stack([ia[idx[:, 0]], ib[idx[:, 1]]], dim=1), dist
