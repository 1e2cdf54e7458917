"""Gradients of optimised poses with respect to the measurements, the information matrices and the held
poses, by implicit differentiation at the optimum (as theseus' implicit mode, with the exact Hessian).

At an optimum the cost's gradient in the free poses' tangent perturbations is zero, ``G(theta) = 0``, so
``d delta* / d theta = -H^-1 dG / d theta`` with ``H`` the exact Hessian (not Gauss-Newton's: the residuals
are not zero at the optimum). A backward pass with ``dL / dx``: ``b`` the free poses' tangent gradients,
``v = H^-1 b`` (one sparse factorisation), ``dL / d theta = -d (v . G) / d theta`` (one second-order autograd
pass through :mod:`slam.graph.fused`), plus the held poses' direct dependence on their inputs.

The held poses (pose 0 for the free and first gauges, or the ``fixed`` ones) output their inputs. With
``planar=True`` the free poses move in ``(x, y, yaw)`` only. The gradients are exact at a stationary point:
tighten ``rel_tol`` / ``abs_tol`` for precise ones.

Example:
    >>> import dataclasses, torch
    >>> from slam.lie import se3_exp
    >>> from slam.graph import PoseGraph, optimize
    >>> step = se3_exp(torch.tensor([1.0, 0, 0, 0, 0, 0.3], dtype=torch.float64))
    >>> g = PoseGraph.from_lists([se3_exp(torch.zeros(6, dtype=torch.float64))] * 3,
    ...                          [(0, 1, step), (1, 2, step), (0, 2, step)])
    >>> z = g.measurements.clone().requires_grad_(True)
    >>> res = optimize(dataclasses.replace(g, measurements=z), differentiable=True, rel_tol=0.0, abs_tol=0.0)
    >>> res.graph.poses[2, 0].backward()
    >>> z.grad.shape, bool(z.grad[:, 0].abs().sum() > 0)
    (torch.Size([3, 7]), True)
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import List, Optional, Tuple

import numpy as np
import torch

from slam.graph.config import OptimizerConfig
from slam.graph.costs import RobustKernel, edge_chi2
from slam.graph.fused import error_poses, se3_residuals, se3_retract
from slam.graph.initialization import edge_components
from slam.graph.linear import LinearSolverError, assemble_blocks, build_pattern, make_solver
from slam.graph.pose_graph import PoseGraph
from slam.graph.problem import PLANAR_DIMS, held_poses
from slam.lie import se3_ad, se3_adjoint, se3_between, se3_identity, se3_inv, se3_normalize

__all__ = ["attach_gradients", "implicit_vjp"]

Tensor = torch.Tensor


@dataclass
class _Spec:
    """What the backward pass needs besides the tensors: the graph's structure and the cost's settings."""

    ii: Tensor
    jj: Tensor
    chart: str
    kernel: Optional[RobustKernel]
    held: List[int]
    prior_weight: Optional[float]  # the "prior" gauge's weight, or None
    dims: Optional[Tuple[int, ...]]  # the tangent dimensions that move (planar=True), or None: all 6
    solver: object


def attach_gradients(graph: PoseGraph, x: Tensor, cfg: OptimizerConfig, kernel: Optional[RobustKernel], gauge: str,
                     solver) -> Tensor:
    """``x (N, 7)`` (float64, the optimum of ``graph``) with a ``grad_fn`` towards ``graph.measurements``,
    ``graph.information`` and ``graph.poses`` when any of them requires grad (else ``x`` itself)."""
    inputs = (graph.measurements, graph.information, graph.poses)
    if not torch.is_grad_enabled() or not any(t.requires_grad for t in inputs):
        return x
    # the poses whose outputs are their inputs: the held ones, else pose 0 that the free gauge re-anchors on
    held = sorted(set(held_poses(cfg, gauge, graph.num_poses))) or ([0] if gauge == "free" else [])
    spec = _Spec(graph.ii, graph.jj, graph.chart, kernel, held,
                 cfg.prior_weight if gauge == "prior" else None, PLANAR_DIMS if cfg.planar is True else None,
                 solver)
    return _ImplicitOptimum.apply(x.detach(), spec, *inputs)


class _ImplicitOptimum(torch.autograd.Function):
    """Identity on the optimum ``x`` in the forward pass; :func:`implicit_vjp` in the backward pass."""

    @staticmethod
    def forward(ctx, x, spec, measurements, information, poses):
        ctx.spec = spec
        ctx.save_for_backward(x, measurements.detach(), information.detach(), poses.detach())
        return x.clone()

    @staticmethod
    def backward(ctx, grad_x):
        x, meas, info, poses = ctx.saved_tensors
        needs = ctx.needs_input_grad[2:]
        g_meas, g_info, g_poses = implicit_vjp(ctx.spec, x, meas, info, poses, grad_x, needs)
        return None, None, g_meas, g_info, g_poses


def _objective(spec: _Spec, x: Tensor, delta: Tensor, meas: Tensor, info: Tensor, poses: Tensor,
               free: Tensor) -> Tensor:
    """The optimised cost at ``x exp(delta)`` for the free poses and the held poses' inputs (a scalar)."""
    moved = se3_retract(x, delta)
    P = torch.where(free[:, None], moved, se3_normalize(poses, positive_w=False))
    r, _ = se3_residuals(P, spec.ii, spec.jj, se3_inv(se3_normalize(meas, positive_w=False)), spec.chart)
    s = edge_chi2(r, 0.5 * (info + info.transpose(-1, -2)))  # the information as the symmetric matrix it is
    f = (s if spec.kernel is None else spec.kernel(s)[0]).sum()
    if spec.prior_weight is not None:
        f = f + _prior_cost(spec, poses, P[:1])
    return f


def _prior_cost(spec: _Spec, poses: Tensor, P0: Tensor) -> Tensor:
    """The ``"prior"`` gauge's term ``w |Log(p0^-1 T_0)|^2`` (``p0`` the input pose 0, ``T_0 = P0 (1, 7)``)."""
    one = torch.zeros(1, dtype=torch.long, device=P0.device)
    r0, _ = se3_residuals(torch.cat([se3_normalize(poses[:1], positive_w=False), P0]), one, one + 1,
                          se3_identity(1, dtype=P0.dtype, device=P0.device))
    return spec.prior_weight * (r0 * r0).sum()


def _edge_hessians(spec: _Spec, x: Tensor, meas: Tensor, info: Tensor, poses: Tensor) -> Tensor:
    """``(E, 12, 12)``: each edge's Hessian of its cost in the right perturbations ``[delta_i, delta_j]`` at ``x``.

    ``D = D0 Exp(-A d_i) Exp(d_j)`` with ``A = Ad(T_j^-1 T_i)``; by BCH, with ``h(e) = cost(D0 Exp e)``, its
    gradient ``g`` and Hessian ``H_h`` at 0, ``M = [-A, I]`` and ``N_mn = g . ad(e_m) e_n / 2``:
    ``H = M^T H_h M`` plus ``-A^T N`` in the ``(i, j)`` block (and its transpose in ``(j, i)``).
    """
    E, dt, dev = spec.ii.shape[0], x.dtype, x.device
    tD, qD = error_poses(x, spec.ii, spec.jj, se3_inv(se3_normalize(meas, positive_w=False)))
    A = se3_adjoint(se3_between(x[spec.jj], x[spec.ii]))
    eye = se3_identity(E, dtype=dt, device=dev)
    ar = torch.arange(E, device=dev)
    with torch.enable_grad():
        e = torch.zeros(E, 6, dtype=dt, device=dev, requires_grad=True)
        D = se3_retract(torch.cat([tD, qD], -1), e)
        r, _ = se3_residuals(torch.cat([eye, D]), ar, ar + E, eye, spec.chart)  # the residual of D itself
        s = edge_chi2(r, 0.5 * (info + info.transpose(-1, -2)))
        f = (s if spec.kernel is None else spec.kernel(s)[0]).sum()
        (g,) = torch.autograd.grad(f, e, create_graph=True)
        Hh = torch.stack([torch.autograd.grad(g[:, c].sum(), e, retain_graph=c < 5)[0] for c in range(6)], 1)
    g = g.detach()
    M = torch.cat([-A, torch.eye(6, dtype=dt, device=dev).expand(E, 6, 6)], -1)  # (E, 6, 12)
    H = M.transpose(1, 2) @ Hh @ M
    N = 0.5 * torch.einsum("ek,mkn->emn", g, se3_ad(torch.eye(6, dtype=dt, device=dev)))  # ad(e_m): (6, 6, 6)
    X = -A.transpose(1, 2) @ N
    H[:, :6, 6:] += X
    H[:, 6:, :6] += X.transpose(1, 2)
    return 0.5 * (H + H.transpose(1, 2))


def _prior_hessian(spec: _Spec, x: Tensor, poses: Tensor) -> Tensor:
    """``(6, 6)``: the Hessian of the prior gauge's term in pose 0's right perturbation."""
    with torch.enable_grad():
        d = torch.zeros(1, 6, dtype=x.dtype, device=x.device, requires_grad=True)
        (g,) = torch.autograd.grad(_prior_cost(spec, poses, se3_retract(x[:1], d)), d, create_graph=True)
        H = torch.stack([torch.autograd.grad(g[0, c], d, retain_graph=c < 5)[0][0] for c in range(6)])
    return 0.5 * (H + H.T)


def implicit_vjp(spec: _Spec, x: Tensor, meas: Tensor, info: Tensor, poses: Tensor, grad_x: Tensor,
                 needs: Tuple[bool, bool, bool] = (True, True, True)):
    """The gradients of ``L`` w.r.t. the measurements ``(E, 7)``, the information ``(E, 6, 6)`` and the input
    poses ``(N, 7)`` (each None unless ``needs`` says so), given ``grad_x = dL / dx (N, 7)`` at the optimum
    ``x (N, 7)`` (see the module docstring); in the inputs' dtypes."""
    dt, dev = torch.float64, x.device
    x = x.to(dt)
    m64, i64, p64 = (t.to(dt) for t in (meas, info, poses))
    N = x.shape[0]
    free = torch.ones(N, dtype=torch.bool, device=dev)
    free[spec.held] = False
    dims = list(spec.dims) if spec.dims is not None else list(range(6))
    k = len(dims)
    # 1. the free poses' tangent gradients b
    with torch.enable_grad():
        d0 = torch.zeros(N, 6, dtype=dt, device=dev, requires_grad=True)
        # a vector-Jacobian product as the gradient of a scalar (grad_outputs imports sympy on first use)
        (b,) = torch.autograd.grad((se3_retract(x, d0) * grad_x.to(dt)).sum(), d0)
    # 2. v = H^-1 b on the block pattern of the free poses
    pattern = build_pattern(spec.ii, spec.jj, free, k)
    He = _edge_hessians(spec, x, m64, i64, p64)
    sel = dims + [6 + d for d in dims]
    He = He[:, sel][:, :, sel]
    E = He.shape[0]
    blocks = He.reshape(E, 2, k, 2, k).permute(0, 1, 3, 2, 4).reshape(E, 4, k, k)
    H, _ = assemble_blocks(pattern, blocks, He.new_zeros(E, 2, k))
    if spec.prior_weight is not None and bool(free[0]):
        H0 = _prior_hessian(spec, x, p64)[dims][:, dims]
        pos = int(pattern.diag_blocks[int(pattern.var_index[0])]) * k * k
        H = H.index_add(0, torch.arange(pos, pos + k * k, device=dev), H0.reshape(-1))
    rhs = b[free][:, dims].reshape(-1)
    grads = [None, None, None]
    if pattern.size:
        try:
            v = make_solver(spec.solver, pattern.size).solve(pattern, H, rhs)
        except LinearSolverError as exc:
            # the first pose of each component of the edges that holds no pose
            count, label = edge_components(spec.ii, spec.jj, N)
            anchored = {int(label[h]) for h in spec.held}
            if spec.prior_weight is not None:  # the gauge's prior holds pose 0
                anchored.add(int(label[0]))
            _, first = np.unique(label, return_index=True)  # labels 0 .. count - 1
            loose = sorted(p for c, p in enumerate(first.tolist()) if c not in anchored)
            if loose:  # each such component can move as a whole at the same cost: no minimum is strict
                hold = sorted(set(int(h) for h in spec.held) | set(loose))
                raise RuntimeError(
                    f"implicit differentiation: the graph has {count} separate components, and {len(loose)} of them "
                    f"hold no pose (their first poses: {', '.join(str(c) for c in loose[:5])}), so each can move as "
                    f"a whole at the same cost; hold a pose in every component (fixed={tuple(hold[:8])})") from None
            raise RuntimeError("implicit differentiation: the cost's Hessian at the optimised poses is not "
                               f"positive definite ({exc}); they are not a strict local minimum (optimise to "
                               "convergence, or hold poses that no edge constrains)") from None
        vfull = torch.zeros(N, 6, dtype=dt, device=dev)
        vfull[torch.nonzero(free)[:, 0][:, None], torch.tensor(dims, device=dev)] = v.view(-1, k)
        # 3. -d (v . G) / d theta, G the cost's gradient in the tangent perturbations at delta = 0
        with torch.enable_grad():
            theta = [t.detach().requires_grad_(True) for t in (m64, i64, p64)]
            d0 = torch.zeros(N, 6, dtype=dt, device=dev, requires_grad=True)
            f = _objective(spec, x, d0, *theta, free)
            (G,) = torch.autograd.grad(f, d0, create_graph=True)
            grads = list(torch.autograd.grad(-(G * vfull).sum(), theta, allow_unused=True))
    if needs[2]:  # the held poses' outputs are their inputs (unit quaternions)
        with torch.enable_grad():
            p = p64.detach().requires_grad_(True)
            held = ~free
            unit = se3_normalize(p, positive_w=False)
            (direct,) = torch.autograd.grad((unit[held] * grad_x.to(dt)[held]).sum(), p)
        grads[2] = direct if grads[2] is None else grads[2] + direct
    out = []
    for need, g, ref in zip(needs, grads, (meas, info, poses)):
        out.append(None if not need else (torch.zeros_like(ref) if g is None else g.to(ref.dtype)))
    return tuple(out)
