"""The optional C kernels of the accelerator (``slam.graph.accel._kernels``, from ``_kernels.c``), loaded once
for :mod:`slam.graph.accel.host` and :mod:`slam.graph.cholesky`.

``kernels`` is the module, or None when it was not built (no C compiler at install time) or was built from
another version of ``_kernels.c`` (an editable install does not rebuild the extension when the source
changes: a stale build would lack functions this code calls). Either way the callers fall back to numpy,
LAPACK and torch, which compute the same. The kernels take the series thresholds and coefficients of the
torch reference (:mod:`slam.graph.fused`) once, here.
"""
from __future__ import annotations

import warnings

import torch

# the version of the kernels' functions this code calls (the ABI constant of _kernels.c)
ABI = 2

try:
    from slam.graph.accel import _kernels as kernels
except ImportError:  # not built
    kernels = None
else:
    if getattr(kernels, "ABI", None) != ABI:
        warnings.warn(f"slam.graph.accel._kernels ({kernels.__file__}) was built from another version of "
                      f"_kernels.c (ABI {getattr(kernels, 'ABI', None)}, this code needs {ABI}): rebuild it with "
                      "`pip install -e .` (or `python setup.py build_ext --inplace`); using the numpy path "
                      "meanwhile", RuntimeWarning, stacklevel=2)
        kernels = None

if kernels is not None:
    from slam.graph import fused

    kernels.set_constants(fused._SMALL[torch.float64], fused._SMALL_Q[torch.float64],
                          tuple(float(v) for v in fused._Q_SERIES.reshape(-1)))
