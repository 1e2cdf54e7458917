"""optimize(..., differentiable=True): gradients of the optimised poses by implicit differentiation, against
central finite differences of re-optimised poses (float64, every optimisation run to its lambda limit).

The gauge: the free gauge re-anchors the result on the initial pose 0, so the compared outputs are the
poses with pose 0 held at its input (the "first" gauge gives the same); a gauge-invariant quantity (the
relative translation of two far-apart poses) is compared too."""
import dataclasses

import pytest
import torch

from slam.graph import OptimizerConfig, PoseGraph, make_kernel, optimize, read_g2o
from slam.graph.problem import TorchProblem
from slam.lie import se3_between, se3_compose, se3_exp

F64 = torch.float64
TIGHT = dict(rel_tol=0.0, abs_tol=0.0)  # run to the lambda limit


def _optimum(graph, method="lm", **kw):
    """Optimised poses to round-off: LM to its lambda limit (which stops on the cost, so leaves the poses
    ~sqrt(eps) away), then plain Gauss-Newton steps on the torch problem, taken whatever the cost says (at
    this level the cost cannot tell a better pose from a worse one), holding pose 0 as the free gauge's
    result does."""
    P = optimize(graph, method, **TIGHT, **kw).graph.poses.detach()
    kernel = make_kernel(kw.pop("kernel", None))
    gauge = kw.get("gauge", "free")
    # the free gauge's result is re-anchored on pose 0 only when no pose is fixed; with a fixed pose, pose 0
    # is free and must be polished too (holding it kept its ~sqrt(eps) error: 1.2e-6 relative at h = 1e-5)
    polish_gauge = "first" if gauge == "free" and not kw.get("fixed") else gauge
    prob = TorchProblem(graph.with_poses(P), OptimizerConfig(**kw), kernel, polish_gauge, "auto")
    x = prob.poses
    for _ in range(8):
        H, g = prob.linearize(x, prob.evaluate(x)[2])
        x = prob.retract(x, prob.solve(H, g, 0.0))
    return prob.finish(x, False)


def _chain_graph(n=8, seed=0, planar=False):
    """A noisy loop of n poses with two chords (initial guess = the noisy odometry)."""
    g = torch.Generator().manual_seed(seed)
    xi = torch.zeros(n, 6, dtype=F64)
    xi[:, 0] = torch.arange(n, dtype=F64)
    xi[:, 5] = 0.7 * torch.arange(n, dtype=F64)
    if not planar:
        xi[:, 2:5] = 0.1 * torch.randn(n, 3, generator=g, dtype=F64)
    T = se3_exp(xi)
    ii = torch.tensor(list(range(n - 1)) + [n - 1, 1, 2])
    jj = torch.tensor(list(range(1, n)) + [0, 5, 6])
    E = ii.shape[0]
    noise = 0.05 * torch.randn(E, 6, generator=g, dtype=F64)
    if planar:
        noise[:, 2:5] = 0.0
    Z = se3_compose(se3_between(T[ii], T[jj]), se3_exp(noise))
    A = torch.randn(E, 6, 6, generator=g, dtype=F64) * 0.3
    info = A @ A.mT + torch.eye(6, dtype=F64) * 4
    if planar:
        keep = torch.tensor([0, 1, 5])
        mask = torch.zeros(6, 6, dtype=torch.bool)
        mask[keep[:, None], keep] = True
        mask[2:5, 2:5] = True
        info = info * mask
    init = [T[0]]
    for k in range(n - 1):
        init.append(se3_compose(init[-1], Z[k]))
    return PoseGraph(torch.stack(init), ii, jj, Z, info)


def _directional(graph, field, u, w, h, richardson=False, **kw):
    """(autograd, central difference) of <w, optimised poses> along ``u`` added to ``graph.<field>``; with
    ``richardson``, the differences of steps ``h`` and ``2 h`` combined to cancel their ``h^2`` error, so
    that a larger step can average out the re-optimised poses' round-off."""
    warm = graph.with_poses(_optimum(graph, **kw))
    if field == "poses":  # only pose 0 (the anchor) matters: keep the others warm
        warm = warm.with_poses(torch.cat([graph.poses[:1], warm.poses[1:]]))
    leaf = getattr(warm, field).clone().requires_grad_(True)
    res = optimize(dataclasses.replace(warm, **{field: leaf}), differentiable=True, **TIGHT, **kw)
    assert res.graph.poses.grad_fn is not None
    (res.graph.poses * w).sum().backward()
    ad = float((leaf.grad * u).sum())

    def value(s):
        moved = dataclasses.replace(warm, **{field: getattr(warm, field) + s * u})
        return float((_optimum(moved, **kw) * w).sum())

    d1 = (value(h) - value(-h)) / (2 * h)
    if not richardson:
        return ad, d1
    d2 = (value(2 * h) - value(-2 * h)) / (4 * h)
    return ad, (4 * d1 - d2) / 3


def _rel(a, b):
    return abs(a - b) / max(abs(b), 1e-12)


@pytest.mark.slow
def test_gradient_wrt_measurement_translations_matches_finite_differences_on_smallgrid3d(posegraph_dir):
    """smallGrid3D, float64, d(optimised poses)/d(measurements' translations) against
    central differences of re-optimised poses (Richardson-extrapolated), pose 0 held by the free gauge's
    re-anchoring, and a gauge-invariant relative translation."""
    graph = read_g2o(posegraph_dir / "smallGrid3D.g2o")
    gen = torch.Generator().manual_seed(0)
    E, N = graph.num_edges, graph.num_poses
    for trial in range(2):
        u = torch.zeros(E, 7, dtype=F64)
        u[:, :3] = torch.randn(E, 3, generator=gen, dtype=F64)
        w = torch.randn(N, 7, generator=gen, dtype=F64)
        # the re-optimised poses carry 1e-10 - 1e-9 of round-off (the conditioning of H), which a small step
        # amplifies (h = 1e-5: errors up to 3e-3, h = 1e-4: 4e-5); h = 1 mm has an h^2 error of 4e-5, which
        # Richardson's combination of h and 2 h cancels (measured: ~2e-6 and below)
        ad, fd = _directional(graph, "measurements", u, w, 1e-3, richardson=True)
        assert _rel(ad, fd) <= 1e-6, (trial, ad, fd)  # required <= 1e-4; measured <= 6e-10
    # gauge-invariant: the translation of the last pose seen from the first (autograd vs differences)
    warm = graph.with_poses(_optimum(graph))
    z = warm.measurements.clone().requires_grad_(True)
    res = optimize(dataclasses.replace(warm, measurements=z), differentiable=True, **TIGHT)
    rel = se3_between(res.graph.poses[:1], res.graph.poses[-1:])[0, :3]
    rel.sum().backward()
    ad = float((z.grad * u).sum())

    def value(s):
        P = _optimum(dataclasses.replace(warm, measurements=warm.measurements + s * u))
        return float(se3_between(P[:1], P[-1:])[0, :3].sum())

    h = 1e-3
    fd = (4 * (value(h) - value(-h)) / (2 * h) - (value(2 * h) - value(-2 * h)) / (4 * h)) / 3
    assert _rel(ad, fd) <= 1e-6, (ad, fd)


@pytest.mark.parametrize("case", [
    dict(field="measurements"),  # all seven entries (the quaternion through its normalisation)
    dict(field="information"),
    dict(field="measurements", kernel="cauchy"),
    dict(field="measurements", gauge="first", method="gn"),
    dict(field="measurements", gauge="prior"),
    dict(field="measurements", fixed=(3,)),
    dict(field="poses", fixed=(3,)),  # a fixed pose's value moves the others
    dict(field="poses"),  # pose 0 anchors the free gauge: a rigid motion of the result
])
def test_gradients_match_finite_differences_on_a_small_graph(case):
    case = dict(case)
    field = case.pop("field")
    graph = _chain_graph()
    gen = torch.Generator().manual_seed(1)
    shape = getattr(graph, field).shape
    u = torch.randn(shape, generator=gen, dtype=F64)
    if field == "information":
        u = u + u.mT  # symmetric: the information matrices are
    if field == "poses":
        held = [0] if "fixed" not in case else list(case["fixed"])
        mask = torch.zeros(shape[0], 1, dtype=F64)
        mask[held] = 1.0
        u = u * mask  # the free poses' initial guesses do not matter (checked below)
    w = torch.randn(graph.num_poses, 7, generator=gen, dtype=F64)
    ad, fd = _directional(graph, field, u, w, 1e-5, **case)
    assert _rel(ad, fd) <= 1e-6, (ad, fd)  # measured 4e-11 - 2e-8


def test_planar_forced_graphs():
    graph = _chain_graph(planar=True)
    gen = torch.Generator().manual_seed(2)
    u = torch.randn(graph.num_edges, 7, generator=gen, dtype=F64)
    u[:, [2, 3, 4]] = 0.0  # stay in the plane: planar=True solves (x, y, yaw) only
    w = torch.randn(graph.num_poses, 7, generator=gen, dtype=F64)
    ad, fd = _directional(graph, "measurements", u, w, 1e-5, planar=True)
    assert _rel(ad, fd) <= 1e-6, (ad, fd)


def test_interface_dtypes_and_what_carries_no_gradient():
    graph = _chain_graph()
    z = graph.measurements.clone().requires_grad_(True)
    info = graph.information.clone().requires_grad_(True)
    g2 = dataclasses.replace(graph, measurements=z, information=info)  # PoseGraph stays a dataclass
    assert g2.measurements is not graph.measurements and g2.measurements.requires_grad
    res = optimize(g2, differentiable=True)
    assert res.graph.poses.requires_grad and res.graph.poses.grad_fn is not None
    res.graph.poses[:, :3].sum().backward()
    assert z.grad.shape == (graph.num_edges, 7) and info.grad.shape == (graph.num_edges, 6, 6)
    assert torch.allclose(info.grad, info.grad.mT)  # the gradient of a symmetric argument
    assert optimize(g2).graph.poses.grad_fn is None  # differentiable=False (the default): detached
    with torch.no_grad():
        assert optimize(g2, differentiable=True).graph.poses.grad_fn is None
    plain = optimize(graph, differentiable=True)  # nothing requires grad: nothing to attach
    assert plain.graph.poses.grad_fn is None
    # the free poses' initial guesses: no gradient (the optimum does not depend on them)
    p = graph.poses.clone().requires_grad_(True)
    optimize(dataclasses.replace(graph, poses=p), differentiable=True).graph.poses.sum().backward()
    assert float(p.grad[1:].abs().max()) == 0.0 and float(p.grad[0].abs().max()) > 0
    # float32 graphs: float32 gradients
    z32 = graph.measurements.float().requires_grad_(True)
    g32 = dataclasses.replace(graph.to(dtype=torch.float32), measurements=z32)
    out = optimize(g32, differentiable=True).graph.poses
    assert out.dtype == torch.float32
    out.sum().backward()
    assert z32.grad.dtype == torch.float32 and torch.isfinite(z32.grad).all()


def test_an_unconstrained_pose_is_reported_in_the_backward_pass():
    graph = _chain_graph()
    P = torch.cat([graph.poses, se3_exp(torch.ones(1, 6, dtype=F64))])  # pose 8 is in no edge
    z = graph.measurements.clone().requires_grad_(True)
    lonely = PoseGraph(P, graph.ii, graph.jj, z, graph.information)
    res = optimize(lonely, differentiable=True)
    with pytest.raises(RuntimeError, match=r"2 separate components, and 1 of them hold no pose \(their first poses: 8\)"
                                           r".*fixed=\(0, 8\)"):
        res.graph.poses.sum().backward()
    held = optimize(lonely, differentiable=True, fixed=(0, 8))  # holding it is the remedy the message names
    held.graph.poses.sum().backward()
    assert torch.isfinite(z.grad).all()


@pytest.mark.parametrize("chart,kernel", [("se3", None), ("se3", "cauchy"), ("r3so3", "huber")])
def test_edge_hessians_equal_direct_second_order_autograd(chart, kernel):
    """The per-edge Hessians (through the error pose, the adjoint and the BCH bracket) against autograd's
    Hessian in both poses' perturbations directly."""
    from slam.graph import edge_chi2, make_kernel
    from slam.graph.fused import se3_residuals, se3_retract
    from slam.graph.implicit import _edge_hessians, _Spec
    from slam.lie import se3_inv

    graph = _chain_graph(seed=3)
    x = _optimum(graph, kernel=kernel).clone()
    x[1:] = se3_compose(x[1:], se3_exp(0.05 * torch.randn(x.shape[0] - 1, 6, generator=torch.Generator().manual_seed(5),
                                                               dtype=F64)))  # away from the optimum: g != 0
    kern = make_kernel(kernel)
    spec = _Spec(graph.ii, graph.jj, chart, kern, [0], None, None, "auto")
    H = _edge_hessians(spec, x, graph.measurements, graph.information, graph.poses)
    E = graph.num_edges
    d = torch.zeros(E, 12, dtype=F64, requires_grad=True)
    P = torch.cat([se3_retract(x[graph.ii], d[:, :6]), se3_retract(x[graph.jj], d[:, 6:])])
    r, _ = se3_residuals(P, torch.arange(E), torch.arange(E) + E, se3_inv(graph.measurements), chart)
    s = edge_chi2(r, graph.information)
    f = (s if kern is None else kern(s)[0]).sum()
    (g,) = torch.autograd.grad(f, d, create_graph=True)
    ref = torch.stack([torch.autograd.grad(g[:, c].sum(), d, retain_graph=True)[0] for c in range(12)], 1)
    assert torch.allclose(H, ref, atol=1e-10 * float(ref.abs().max()), rtol=0)


def test_two_components_name_the_one_that_holds_no_pose():
    # it converged, and every pose is constrained: the second loop moves as a whole at the same cost
    a, b = _chain_graph(8, seed=1), _chain_graph(8, seed=2)
    z = torch.cat([a.measurements, b.measurements]).requires_grad_(True)
    two = PoseGraph(torch.cat([a.poses, b.poses]), torch.cat([a.ii, b.ii + 8]), torch.cat([a.jj, b.jj + 8]), z,
                    torch.cat([a.information, b.information]))
    res = optimize(two, differentiable=True)
    assert res.status == "converged"
    with pytest.raises(RuntimeError, match=r"2 separate components.*first poses: 8\).*fixed=\(0, 8\)"):
        res.graph.poses.sum().backward()
    optimize(two, differentiable=True, fixed=(0, 8)).graph.poses.sum().backward()
    assert torch.isfinite(z.grad).all()


def test_gradients_of_a_run_stopped_early_warn():
    graph = _chain_graph()
    z = graph.measurements.clone().requires_grad_(True)
    with pytest.warns(RuntimeWarning, match="status max_iterations after 1 iteration.*those of the optimum"):
        optimize(dataclasses.replace(graph, measurements=z), differentiable=True, max_iterations=1)
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("error")
        optimize(dataclasses.replace(graph, measurements=z), differentiable=True)  # converged: no warning
        optimize(graph, max_iterations=1)  # not differentiable: nothing to warn about


@pytest.mark.parametrize("init", ["chordal", "spanning_tree"])
def test_an_initial_guess_keeps_the_gradient_towards_the_anchor(init):
    # the result is anchored on the input pose 0 whatever the initial guess: its gradient must survive the
    # initialisation (it was None), and equal the one without it
    graph = _chain_graph()
    w = torch.randn(graph.num_poses, 7, dtype=F64, generator=torch.Generator().manual_seed(3))
    w[:, 3:] = 0.0  # positions only: an initial guess may end at the same poses with some quaternions q -> -q
    grads = []
    for how in ("none", init):
        P = graph.poses.clone().requires_grad_(True)
        (optimize(dataclasses.replace(graph, poses=P), differentiable=True, initialization=how, **TIGHT)
         .graph.poses * w).sum().backward()
        grads.append(P.grad)
    assert grads[1] is not None and float(grads[0][0].abs().sum()) > 0
    assert float((grads[1] - grads[0]).abs().max()) < 1e-6 * float(grads[0].abs().max())


@pytest.mark.parametrize("field,value", [("differentiable", "no"), ("verbose", 1), ("max_iterations", "3"),
                                         ("max_iterations", -1), ("max_iterations", True)])
def test_flags_and_counts_are_type_checked(field, value):
    with pytest.raises(ValueError, match=field):
        optimize(_chain_graph(), **{field: value})


def test_numpy_integers_and_booleans_are_integers_and_booleans():
    import numpy as np

    assert optimize(_chain_graph(), max_iterations=np.int64(3), differentiable=np.bool_(False)).iterations <= 3
