"""Build of the optional C kernels of the pose-graph optimiser (everything else is in pyproject.toml).

``slam.graph._kernels`` (slam/graph/_kernels.c) does the per-edge work of :mod:`slam.graph.host` in one
call per step instead of ~150 numpy calls, and the small supernodes of :mod:`slam.graph.cholesky`: it needs
a C compiler and nothing else (no numpy headers). The extension is optional: where it cannot be built the
install still succeeds and the optimiser runs the same math in numpy, LAPACK and torch
(``slam.graph.compiled_kernels()`` says which).
"""
from setuptools import Extension, setup

setup(ext_modules=[Extension("slam.graph._kernels", ["slam/graph/_kernels.c"], optional=True)])
