"""Descriptor sets for benchmarks/index.py: deterministic, generated in chunks (10^6 x 1024 is never held twice).

* :class:`Clustered`: ``n / views`` random unit "places", each keyframe = place + noise of norm ``spread``
  (cosine between two views of a place ~``1 / (1 + spread^2)``: 0.5 at spread 1.0, 0.31 at 1.5; between
  places ~0), normalised. The structure of a SLAM database on isotropic data; at every size a place has
  ``views`` keyframes on average (5,000 places at 10^5, 50,000 at 10^6).
* :class:`RealStatistics`: the same places-and-views structure with the statistics of real descriptors: places
  drawn from a Gaussian with the mean and covariance of real keyframe descriptors (7-Scenes redkitchen +
  rtabmap-samples, EfficientNet-Lite0 + DAM), views = place + Gaussian noise with the covariance of the
  kitchen's descriptor changes over 10 frames (1/3 s; cosine 0.83 between such frames), normalised.
  Real descriptors are far from isotropic (a large common component: median cosine 0.40 between kitchen
  frames; 94% of the variance in 128 principal directions), which is what PCA codes and graphs exploit.

Queries are new views of stored places (revisits); keyframe ids are row numbers.
"""
from __future__ import annotations

import numpy as np
import torch

from benchmarks._common import data_root

CHUNK = 65536  # rows generated (and added to an index) at a time


def _unit(x: torch.Tensor) -> torch.Tensor:
    return x / x.norm(dim=-1, keepdim=True).clamp_min(1e-12)


class _Places:
    """Common part: place labels per chunk and queries, all seeded (chunk c uses seed (seed, c))."""

    n: int
    dim: int
    n_places: int
    seed: int

    def _views(self, labels: torch.Tensor, g: torch.Generator) -> torch.Tensor:
        raise NotImplementedError

    def chunk(self, start: int, stop: int) -> np.ndarray:
        """Rows ``[start, stop)`` (must be whole chunks but the last) as unit float32 ``(stop - start, D)``."""
        c = start // CHUNK
        g = torch.Generator().manual_seed(self.seed * 1_000_003 + c + 1)
        labels = torch.randint(0, self.n_places, (stop - start,), generator=g)
        return _unit(self._views(labels, g)).numpy()

    def chunks(self):
        """``(start, rows)`` over the whole set, ``CHUNK`` rows at a time."""
        for start in range(0, self.n, CHUNK):
            yield start, self.chunk(start, min(start + CHUNK, self.n))

    def queries(self, nq: int, seed: int = 12345) -> np.ndarray:
        """``nq`` new unit views ``(nq, D)`` of random stored places."""
        g = torch.Generator().manual_seed(seed)
        labels = torch.randint(0, self.n_places, (nq,), generator=g)
        return _unit(self._views(labels, g)).numpy()


class Clustered(_Places):
    def __init__(self, n: int, dim: int = 1024, spread: float = 1.0, views: int = 20, seed: int = 0) -> None:
        self.n, self.dim, self.spread, self.seed = int(n), int(dim), float(spread), int(seed)
        self.n_places = max(self.n // views, 1)
        g = torch.Generator().manual_seed(seed)
        self.places = _unit(torch.randn(self.n_places, self.dim, generator=g))

    def _views(self, labels, g):
        noise = _unit(torch.randn(labels.shape[0], self.dim, generator=g))
        return self.places[labels] + self.spread * noise


def _sqrt_cov(x: torch.Tensor) -> torch.Tensor:
    """``L (D, D)`` with ``L L^T = cov(x)`` (symmetric square root, float32)."""
    xc = x.double() - x.double().mean(0)
    cov = xc.t() @ xc / max(x.shape[0] - 1, 1)
    evals, evecs = torch.linalg.eigh(cov)
    return (evecs * evals.clamp_min(0).sqrt()).float()


class RealStatistics(_Places):
    def __init__(self, n: int, descriptors: torch.Tensor, sequence: torch.Tensor, gap: int = 10,
                 views: int = 20, seed: int = 0) -> None:
        """``descriptors (M, D)``: real keyframe descriptors (places); ``sequence (T, D)``: consecutive frames
        of one recording, whose changes over ``gap`` frames give the view noise."""
        self.n, self.dim, self.seed = int(n), int(descriptors.shape[1]), int(seed)
        self.n_places = max(self.n // views, 1)
        self.mean = descriptors.double().mean(0).float()
        self.l_places = _sqrt_cov(descriptors)
        # Two views of a place differ by the change over `gap` frames: noise covariance = cov(diff) / 2.
        self.l_views = _sqrt_cov((sequence[gap:] - sequence[:-gap]) / np.sqrt(2.0))
        g = torch.Generator().manual_seed(seed)
        self.places = self.mean + torch.randn(self.n_places, self.dim, generator=g) @ self.l_places.t()

    def _views(self, labels, g):
        return self.places[labels] + torch.randn(labels.shape[0], self.dim, generator=g) @ self.l_views.t()


def exact_reference(data: _Places, queries: np.ndarray, k: int, storage: str = "float32"):
    """Exact top-``k`` rows and similarities ``(Q, k)`` of every query over the whole set, as stored
    (float16-rounded for ``storage="float16"``), by a batched scan of the chunks."""
    q = torch.from_numpy(queries)
    best_s = torch.full((q.shape[0], k), -float("inf"))
    best_i = torch.full((q.shape[0], k), -1, dtype=torch.long)
    for start, rows in data.chunks():
        x = torch.from_numpy(rows)
        if storage == "float16":
            x = x.half().float()
        s = q @ x.t()
        s_all = torch.cat([best_s, s], dim=1)
        i_all = torch.cat([best_i, torch.arange(start, start + x.shape[0]).expand(q.shape[0], -1)], dim=1)
        best_s, pos = torch.topk(s_all, k, dim=1)
        best_i = i_all.gather(1, pos)
    return best_i.numpy(), best_s.numpy()


# ----------------------------------------------------------------------------------------------
# Real descriptors (cached: computing them takes minutes on a busy CPU)
# ----------------------------------------------------------------------------------------------
def _image_descriptors(files, backbone: str, fusion: str) -> torch.Tensor:
    import cv2

    from attnloop import AttentionDescriptor

    model = AttentionDescriptor(backbone=backbone, fusion=fusion, pretrained=True).eval()
    out = []
    for s in range(0, len(files), 8):
        imgs = [cv2.cvtColor(cv2.imread(str(f)), cv2.COLOR_BGR2RGB) for f in files[s: s + 8]]
        out.append(model(torch.from_numpy(np.stack(imgs)).permute(0, 3, 1, 2).contiguous()).detach())
    return torch.cat(out)


def descriptor_version(backbone: str = "efficientnet_lite0") -> str:
    """A short tag of the default descriptor's configuration (its recipe and the backbone's default
    settings), part of every cache name of described images: a cache made by another default is not reused."""
    import hashlib

    from attnloop.descriptor import DescriptorRecipe
    from attnloop.presets import DEFAULT_BACKBONE_SETTINGS

    key = repr((DescriptorRecipe(), sorted(DEFAULT_BACKBONE_SETTINGS.get(backbone, {}).items())))
    return hashlib.sha1(key.encode()).hexdigest()[:8]


def real_descriptors(backbone: str = "efficientnet_lite0", fusion: str = "dam", cache_dir=None) -> dict:
    """Descriptors of every 7-Scenes redkitchen frame and every rtabmap-samples image, and the kitchen's poses.

    Returns:
        ``{"kitchen": (1000, D), "rtabmap": (84, D), "kitchen_poses": (1000, 4, 4)}``, cached in
        ``cache_dir`` (default ``out/``) as ``index_real_<backbone>_<fusion>_<descriptor_version>.pt``.
    """
    from pathlib import Path

    cache = Path(cache_dir or "out") / f"index_real_{backbone}_{fusion}_{descriptor_version(backbone)}.pt"
    if cache.is_file():
        return torch.load(cache)
    root = data_root()
    kitchen = sorted((root / "7scenes-redkitchen").glob("frame-*.color.jpg"))
    rtab = sorted((root / "rtabmap-samples").glob("*.jpg"), key=lambda p: int(p.stem))
    if not kitchen or not rtab:
        raise SystemExit(f"7scenes-redkitchen / rtabmap-samples not found under {root} (set ATTNLOOP_DATA)")
    poses = torch.from_numpy(np.stack([np.loadtxt(str(f).replace("color.jpg", "pose.txt")) for f in kitchen]))
    out = {"kitchen": _image_descriptors(kitchen, backbone, fusion),
           "rtabmap": _image_descriptors(rtab, backbone, fusion), "kitchen_poses": poses}
    cache.parent.mkdir(parents=True, exist_ok=True)
    torch.save(out, cache)
    return out
