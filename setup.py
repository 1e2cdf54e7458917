"""Build of the optional C kernels of the pose-graph optimiser (everything else is in pyproject.toml).

``slam.graph.accel._kernels`` (slam/graph/accel/_kernels.c) does the per-edge work of the optimiser's
accelerator (:mod:`slam.graph.accel`) in one call per step, and the small supernodes of the sparse Cholesky
(:mod:`slam.graph.cholesky`): it needs a C compiler and nothing else (no numpy headers). The extension is optional: where it cannot be built the
install still succeeds and the optimiser runs the same math in torch, numpy and LAPACK
(``slam.graph.compiled_kernels()`` says which).
"""
from setuptools import Extension, setup

setup(ext_modules=[Extension("slam.graph.accel._kernels", ["slam/graph/accel/_kernels.c"], optional=True)])
