"""PCA codes of descriptors: what an approximate structure is built on when ``IndexConfig.reduce_dim`` is set.

The structure ranks by L2 between the codes ``z = P^T (x - mean)``; the index re-scores with the full descriptors.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

__all__ = ["PCACode", "fit_pca"]

_CHUNK = 16384  # rows encoded at a time (bounds the float32 temporaries of a float16 input)
_FEW = 16  # up to this many rows (queries) are encoded with numpy
_MAX_FIT_ROWS = 65536  # rows the PCA is fitted on at most (a seeded sample): the covariance is D x D anyway


@dataclass
class PCACode:
    """A fitted PCA code.

    Attributes:
        mean: ``(D,)`` mean of the fitting rows.
        components: ``(D, d)`` orthonormal principal directions, largest variance first.
        kept: share of the fitting rows' centred energy the ``d`` components keep (in-sample: rows it was
            not fitted on keep less).
    """

    mean: np.ndarray
    components: np.ndarray
    kept: float

    @property
    def dim(self) -> int:
        """Code size ``d``."""
        return int(self.components.shape[1])

    def encode(self, x: np.ndarray) -> np.ndarray:
        """Codes ``(M, d)`` (float32) of descriptors ``x (M, D)`` (float32 or float16)."""
        if x.ndim != 2 or x.shape[1] != self.mean.shape[0]:
            raise ValueError(f"PCA code of dimension {self.mean.shape[0]} got descriptors {tuple(x.shape)}")
        if x.shape[0] <= _FEW:  # a query: numpy directly (torch's conversions cost more here)
            z = (np.asarray(x, dtype=np.float32) - self.mean) @ self.components
            return z.astype(np.float32, copy=False)
        out = np.empty((x.shape[0], self.dim), dtype=np.float32)
        mean, comp = torch.from_numpy(self.mean), torch.from_numpy(self.components)
        for lo in range(0, x.shape[0], _CHUNK):
            z = (torch.from_numpy(np.asarray(x[lo: lo + _CHUNK], dtype=np.float32)) - mean) @ comp
            out[lo: lo + z.shape[0]] = z.numpy()
        return out

    def state(self) -> dict:
        """Arrays and numbers that :meth:`from_state` restores."""
        return {"mean": self.mean, "components": self.components, "kept": np.float64(self.kept)}

    @classmethod
    def from_state(cls, state: dict, dim: int | None = None) -> PCACode:
        """The code :meth:`state` describes; ValueError naming a missing, misshapen or non-finite entry.

        Args:
            state: ``mean``, ``components`` and ``kept``.
            dim: the descriptor size ``D`` the code must take (``None``: the one ``mean`` has).
        """
        arrays = {}
        for key in ("mean", "components", "kept"):
            if key not in state:
                raise ValueError(f"the PCA code lacks its {key!r}")
            a = np.asarray(state[key])
            if a.dtype.kind not in "fiu" or not np.all(np.isfinite(a)):
                raise ValueError(f"the PCA code's {key!r} must hold finite numbers (dtype {a.dtype})")
            arrays[key] = a
        mean, comp, kept = arrays["mean"], arrays["components"], arrays["kept"]
        d_in = mean.shape[0] if mean.ndim == 1 else -1
        if mean.ndim != 1 or (dim is not None and d_in != int(dim)):
            raise ValueError(f"the PCA code's mean has shape {tuple(mean.shape)}, the descriptors have "
                             f"dimension {dim if dim is not None else '?'}")
        if comp.ndim != 2 or comp.shape[0] != d_in or not 1 <= comp.shape[1] <= d_in:
            raise ValueError(f"the PCA code's components have shape {tuple(comp.shape)}, need ({d_in}, d) "
                             f"with 1 <= d <= {d_in}")
        if kept.size != 1:
            raise ValueError(f"the PCA code's 'kept' must be one number, got shape {tuple(kept.shape)}")
        return cls(np.ascontiguousarray(mean, np.float32), np.ascontiguousarray(comp, np.float32),
                   float(kept.reshape(())))


def fit_pca(x: np.ndarray, dim: int, seed: int = 0) -> PCACode:
    """Fit a PCA code of ``dim`` components to descriptors ``x (N, D)`` (float32 or float16).

    Fitted on at most 65536 rows (a seeded sample). The code keeps ``min(dim, D, rows - 1)`` components:
    directions without variance in the rows carry no information about them.

    Args:
        x: ``(N, D)`` descriptors, ``N >= 2``.
        dim: requested code size.
        seed: seed of the fitting sample.

    Returns:
        :class:`PCACode`.
    """
    if x.ndim != 2 or x.shape[0] < 2:
        raise ValueError(f"fit_pca needs descriptors (N, D) with N >= 2, got {tuple(x.shape)}")
    n, d_in = x.shape
    if n > _MAX_FIT_ROWS:
        x = x[np.sort(np.random.default_rng(seed).choice(n, _MAX_FIT_ROWS, replace=False))]
    xs = torch.from_numpy(np.asarray(x, dtype=np.float32))
    mean = xs.double().mean(0)
    xc = xs - mean.float()  # centred first: real descriptors share a large common component
    cov = (xc.t() @ xc).double() / xs.shape[0]  # float32 product (the cost), float64 eigen-decomposition
    evals, evecs = torch.linalg.eigh(cov)
    evals, evecs = evals.flip(0).clamp(min=0.0), evecs.flip(1)
    keep = max(1, min(int(dim), d_in, xs.shape[0] - 1))
    total = float(evals.sum())
    kept = float(evals[:keep].sum()) / total if total > 0 else 1.0
    return PCACode(mean.float().numpy(), np.ascontiguousarray(evecs[:, :keep].float().numpy()), kept)
