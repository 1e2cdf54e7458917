"""The optional C kernels of the pose-graph optimiser (``slam.graph._kernels``, from ``_kernels.c``), loaded
once for :mod:`slam.graph.host` and :mod:`slam.graph.cholesky`.

``kernels`` is the module, or None when it was not built (no C compiler at install time) or was built from
another version of ``_kernels.c`` (an editable install does not rebuild the extension when the source
changes: a stale build would lack functions this code calls). Either way the callers fall back to numpy,
LAPACK and torch, which compute the same.
"""
from __future__ import annotations

import warnings

# the version of the kernels' functions this code calls (the ABI constant of _kernels.c)
ABI = 2

try:
    from slam.graph import _kernels as kernels
except ImportError:  # not built
    kernels = None
else:
    if getattr(kernels, "ABI", None) != ABI:
        warnings.warn(f"slam.graph._kernels ({kernels.__file__}) was built from another version of _kernels.c "
                      f"(ABI {getattr(kernels, 'ABI', None)}, this code needs {ABI}): rebuild it with "
                      "`pip install -e .`; using the numpy path meanwhile", RuntimeWarning, stacklevel=2)
        kernels = None
