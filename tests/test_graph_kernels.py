"""The optional C kernels of the accelerator (slam.graph.accel._kernels) against its numpy functions
(slam.graph.accel.host; both are checked against the torch reference in test_graph_host): residuals,
Jacobian products, retraction, measurement terms, dense assembly and re-anchoring, to round-off, on
random edges that include an exact edge, angles near pi and both series branches; their input checks;
and whole optimisations on the shared g2o files against the torch reference."""
import math
import os

import numpy as np
import pytest
import torch

from slam.graph import OptimizerConfig, PoseGraph, compiled_kernels, optimize, read_g2o
from slam.graph.accel import _compiled, host
from slam.lie import se3_between, se3_compose, se3_exp

F64 = torch.float64

needs_c = pytest.mark.skipif(not compiled_kernels(), reason="the C kernels slam.graph.accel._kernels were not built")


def test_the_c_kernels_are_built_in_ci():
    """setup.py builds them where a C compiler is found (optional=True: a failed build does not fail the
    install), so CI checks that it did not fail silently where it could build them."""
    import shutil
    import sysconfig
    from pathlib import Path

    if os.environ.get("CI") != "true":
        pytest.skip("only checked in CI (CI=true)")
    cc = (sysconfig.get_config_var("CC") or "cc").split()[0]
    if shutil.which(cc) is None or not Path(sysconfig.get_paths()["include"], "Python.h").exists():
        pytest.skip(f"no C compiler ({cc}) or no Python.h here: the numpy path runs, as designed")
    assert compiled_kernels()


def _graph(seed=3, N=12, E=40, planar=False):
    """A PoseGraph of random poses and measurements with an exact edge, one near pi, and edges in each
    series branch (below both thresholds, between them)."""
    g = torch.Generator().manual_seed(seed)
    xi = torch.randn(N, 6, generator=g, dtype=F64)
    xi[:, 3:] *= 1.2
    ii = torch.randint(0, N, (E,), generator=g)
    jj = (ii + torch.randint(1, N, (E,), generator=g)) % N
    dz = torch.randn(E, 6, generator=g, dtype=F64) * 0.3
    if planar:
        xi[:, [2, 3, 4]] = 0.0
        dz[:, [2, 3, 4]] = 0.0
    P = se3_exp(xi)
    dz[0] = 0.0  # met exactly: r = 0
    dz[1, 3:] = torch.tensor([0.0, 0.0, math.pi - 1e-3])  # near pi
    dz[2, 3:] = torch.tensor([0.0, 0.0, 1e-7]) if planar else 1e-7  # below both series thresholds
    dz[3, 3:] = torch.tensor([0.0, 0.0, 3e-3]) if planar else 3e-3  # between them (log exact, Q series)
    Z = se3_compose(se3_between(P[ii], P[jj]), se3_exp(dz))
    A = torch.randn(E, 6, 6, generator=g, dtype=F64)
    info = A @ A.transpose(1, 2) + 6 * torch.eye(6, dtype=F64)
    if planar:  # no coupling between (x, y, yaw) and (z, roll, pitch)
        inp, out = torch.tensor([0, 1, 5]), torch.tensor([2, 3, 4])
        info[:, inp[:, None], out] = 0.0
        info[:, out[:, None], inp] = 0.0
    return PoseGraph(P, ii, jj, Z, info)


def _problems(graph, **cfg):
    """The same HostProblem with the numpy functions and with the C kernels."""
    c = OptimizerConfig(**cfg)
    return (host.host_problem(graph, c, None, c.gauge, "auto", compiled=False),
            host.host_problem(graph, c, None, c.gauge, "auto", compiled=True))


@needs_c
def test_measurement_terms_and_residuals_match_numpy():
    graph = _graph()
    a, b = _problems(graph)
    for name in ("zt", "zq", "neg_adz_t"):
        np.testing.assert_allclose(getattr(b, name), getattr(a, name), rtol=0, atol=1e-14, err_msg=name)
    # perturbed poses, so that no residual is exactly that of the generator
    P = host.retract(a.poses, 0.05 * np.random.default_rng(0).standard_normal((graph.num_poses, 6)))
    _, chi2_a, (r_a, t2_a, c_a, _) = a.evaluate(P)
    cost_b, chi2_b, (r_b, t2_b, c_b, _) = b.evaluate(P)
    np.testing.assert_allclose(r_b, r_a, rtol=0, atol=1e-12)
    np.testing.assert_allclose(t2_b, t2_a, rtol=1e-12, atol=1e-20)
    np.testing.assert_allclose(c_b, c_a, rtol=1e-12)
    assert chi2_b == pytest.approx(chi2_a, rel=1e-12) and cost_b == chi2_b
    # at the generating poses the exact edge has r = 0 and the near-pi one an angle just below pi
    _, _, (r0, t20, c0, _) = b.evaluate(a.poses)
    assert np.abs(r0[0]).max() < 1e-14 and t20[0] < 1e-28 and c0[0] == pytest.approx(1 / 12)
    assert math.sqrt(t20[1]) == pytest.approx(math.pi - 1e-3, abs=1e-3)
    assert np.linalg.norm(r0[1, 3:]) <= math.pi


@needs_c
@pytest.mark.parametrize("planar", [False, True])
@pytest.mark.parametrize("weighted", [False, True])
def test_normal_equations_match_numpy(planar, weighted):
    """H and g of the dense path (C assembly) and of the block-sparse path (C products, torch scatter)."""
    graph = _graph(planar=planar)
    for dense_max in (400, 0):
        # fixed poses 2 and 5: their rows and columns are dropped by both assemblies
        a, b = _problems(graph, fixed=(2, 5), dense_max=dense_max, planar=planar)
        assert a.dense == b.dense == (dense_max > 0) and a.k == b.k == (3 if planar else 6)
        P = host.retract(a.poses, 0.05 * np.random.default_rng(1).standard_normal((graph.num_poses, 6)))
        cache = list(a.evaluate(P)[2])
        if weighted:
            cache[3] = np.random.default_rng(2).uniform(0.1, 1.0, graph.num_edges)
        Ha, ga = (x.copy() for x in a.linearize(P, tuple(cache)))
        Hb, gb = b.linearize(P, tuple(cache))
        assert Hb.shape == Ha.shape and gb.shape == ga.shape
        scale = np.abs(Ha).max()
        np.testing.assert_allclose(Hb, Ha, rtol=0, atol=1e-12 * scale)
        np.testing.assert_allclose(gb, ga, rtol=0, atol=1e-12 * scale)
        # and the same step out of them
        np.testing.assert_allclose(b.solve(Hb, gb, 1e-3), a.solve(Ha, ga, 1e-3), rtol=0, atol=1e-10)


@needs_c
def test_retraction_matches_numpy_and_the_identity():
    P = _graph().poses.numpy()
    rng = np.random.default_rng(3)
    xi = rng.standard_normal((P.shape[0], 6))
    xi[0] = 0.0  # no step: P itself
    xi[1, 3:] = 1e-9  # series branch of b
    xi[2, 3:] = [0.0, 0.0, math.pi - 1e-6]  # near pi
    out = np.empty_like(P)
    host.host_kernels().retract(P, xi, out)
    np.testing.assert_allclose(out, host.retract(P, xi), rtol=0, atol=1e-14)
    np.testing.assert_array_equal(out[0], P[0])


@needs_c
def test_reanchoring_matches_numpy():
    graph = _graph()
    a, b = _problems(graph)
    P = host.retract(a.poses, 0.3 * np.random.default_rng(4).standard_normal((graph.num_poses, 6)))
    out_a, out_b = a.finish(P.copy(), True), b.finish(P.copy(), True)
    torch.testing.assert_close(out_b, out_a, rtol=0, atol=1e-13)
    assert torch.equal(out_b[0], torch.from_numpy(a.poses[0]))  # pose 0 back at its initial value exactly


@needs_c
def test_kernels_check_their_inputs():
    C = host.host_kernels()
    P, ii, jj = np.zeros((3, 7)), np.array([0, 1]), np.array([1, 2])
    P[:, 6] = 1.0
    zt, zq, L = np.zeros((2, 3)), np.tile([0.0, 0, 0, 1], (2, 1)), np.tile(np.eye(6), (2, 1, 1))
    r, t2, c, s = np.empty((2, 6)), np.empty(2), np.empty(2), np.empty(2)
    assert C.residuals(P, ii, jj, zt, zq, L, r, t2, c, s) == 0.0
    with pytest.raises(ValueError, match=r"zq: expected 8 values, got 4"):
        C.residuals(P, ii, jj, zt, zq[:1], L, r, t2, c, s)
    with pytest.raises(ValueError, match="P: expected float64"):
        C.residuals(P.astype(np.float32), ii, jj, zt, zq, L, r, t2, c, s)
    with pytest.raises(ValueError, match="ii: expected int64"):
        C.residuals(P, ii.astype(np.int32), jj, zt, zq, L, r, t2, c, s)
    with pytest.raises(ValueError, match="P: expected a C-contiguous array"):
        C.residuals(np.zeros((3, 14))[:, ::2], ii, jj, zt, zq, L, r, t2, c, s)
    with pytest.raises(ValueError, match=r"edge 1: pose index \(1, 3\) out of range \[0, 3\)"):
        C.residuals(P, ii, np.array([1, 3]), zt, zq, L, r, t2, c, s)
    with pytest.raises(ValueError, match="P: expected \\(N, 7\\) values, got 20"):
        C.residuals(np.zeros(20), ii, jj, zt, zq, L, r, t2, c, s)
    ro = r.copy()
    ro.flags.writeable = False
    with pytest.raises(ValueError, match="r: expected a C-contiguous writable array"):
        C.residuals(P, ii, jj, zt, zq, L, ro, t2, c, s)
    with pytest.raises(TypeError, match=r"takes 10 arguments \(9 given\)"):
        C.residuals(P, ii, jj, zt, zq, L, r, t2, c)
    F = np.empty((2, 13, 13))
    with pytest.raises(ValueError, match=r"rows\[0\] = 13 is out of range"):
        C.linearize(r, t2, c, np.zeros((2, 6, 6)), L, None, np.array([13]), np.arange(6), F)
    with pytest.raises(ValueError, match=r"F: expected 338 values, got 288"):
        C.linearize(r, t2, c, np.zeros((2, 6, 6)), L, None, np.arange(13), np.arange(6), np.empty((2, 12, 12)))
    with pytest.raises(ValueError, match=r"edge 0: variable \(0, 5\) out of range for 12 unknowns"):
        C.assemble_dense(F, ii, jj, np.array([0, 5, 1]), np.zeros(144), np.zeros(12))
    with pytest.raises(ValueError, match="out: expected 21 values, got 14"):
        C.retract(P, np.zeros((3, 6)), np.empty((2, 7)))


def test_backend_c_says_when_the_kernels_are_missing(monkeypatch):
    graph = _graph(N=4, E=6)
    monkeypatch.setattr(_compiled, "kernels", None)
    assert not compiled_kernels()
    with pytest.raises(ValueError, match="backend 'c' needs the C kernels slam.graph.accel._kernels"):
        optimize(graph, backend="c")
    res = optimize(graph, backend="auto")  # falls back to numpy
    assert res.status == "converged"
    with pytest.raises(RuntimeError, match="were not built"):
        host.host_problem(graph, OptimizerConfig(), None, "free", "auto", compiled=True)


@needs_c
@pytest.mark.parametrize("name", ["tinyGrid3D", "smallGrid3D", "parking-garage"])
def test_whole_optimisations_match_numpy_and_the_torch_reference(posegraph_dir, name):
    graph = read_g2o(posegraph_dir / f"{name}.g2o")
    ref = optimize(graph, backend="torch")
    for other in (optimize(graph, backend="numpy"), optimize(graph, backend="c")):
        assert other.iterations == ref.iterations and other.status == ref.status == "converged"
        assert other.chi2 == pytest.approx(ref.chi2, rel=1e-9)
        np.testing.assert_allclose(other.cost_history, ref.cost_history, rtol=1e-8)  # round-off of the early steps
        torch.testing.assert_close(other.graph.poses, ref.graph.poses, rtol=0, atol=1e-8)


@needs_c
def test_robust_planar_and_held_optimisations_match_numpy():
    graph = _graph(seed=5, N=20, E=60, planar=True)
    for kw in ({"kernel": "cauchy"}, {"fixed": (0, 7)}, {"method": "gn"}):
        a, b = optimize(graph, backend="numpy", **kw), optimize(graph, backend="c", **kw)
        assert a.iterations == b.iterations, kw
        assert b.chi2 == pytest.approx(a.chi2, rel=1e-9), kw
        torch.testing.assert_close(b.graph.poses, a.graph.poses, rtol=0, atol=1e-8)
        torch.testing.assert_close(b.weights, a.weights, rtol=1e-7, atol=0)


@needs_c
def test_review_cases_are_refused_or_harmless():
    """Found in review: indices that alias an output (or change in another thread) while the loop runs
    without the GIL, a variable index whose bound check overflowed, misaligned and foreign-endian
    buffers. Each must raise or give (unspecified) values, never read or write out of bounds."""
    C = host.host_kernels()
    E, N = 4, 3
    P = np.zeros((N, 7))
    P[:, 6] = 1.0
    P[1, :3] = [1.0, 1.5, 2.0]
    r = np.zeros((E, 6))
    ii = r.reshape(-1).view(np.int64)[:E]  # the memory of r[0, :4]: valid when checked, overwritten by edge 0
    ii[:] = [0, 1, 2, 0]
    zt, zq, L = np.zeros((E, 3)), np.tile([0.0, 0, 0, 1], (E, 1)), np.tile(np.eye(6), (E, 1, 1))
    with pytest.raises(ValueError, match=r"edge 1: pose index \(\d+, 2\) out of range \[0, 3\)"):
        C.residuals(P, ii, np.array([1, 2, 0, 2]), zt, zq, L, r, np.empty(E), np.empty(E), np.empty(E))
    # rows aliasing F: read once before the loop, so the loop's writes cannot move them out of range
    F = np.zeros((3, 13, 13))
    rows = F.reshape(-1).view(np.int64)[:13]
    rows[:] = np.arange(13)
    rr = np.random.default_rng(0).standard_normal((3, 6))
    C.linearize(rr, (rr[:, 3:] ** 2).sum(1), np.full(3, 1 / 12), np.tile(-np.eye(6), (3, 1, 1)), L[:3], None, rows,
                np.arange(6), F)
    for big in (2 * 10 ** 18, np.iinfo(np.int64).max):  # (v + 1) * k overflowed past the check
        with pytest.raises(ValueError, match=r"edge 0: variable \(0, \d+\) out of range for 12 unknowns"):
            C.assemble_dense(np.ones((1, 13, 13)), np.array([0]), np.array([1]), np.array([0, big]), np.zeros(144),
                             np.zeros(12))
    raw = np.zeros(7 * N * 8 + 1, dtype=np.uint8)
    with pytest.raises(ValueError, match="P: expected an 8-byte aligned array"):
        C.retract(np.frombuffer(raw.data, dtype=np.float64, count=7 * N, offset=1), np.zeros((N, 6)), np.empty((N, 7)))
    with pytest.raises(ValueError, match="P: expected float64"):
        C.retract(P.astype(P.dtype.newbyteorder()), np.zeros((N, 6)), np.empty((N, 7)))
    # relocate with the anchor inside the output: the copy of the anchor overlaps it
    out = np.empty((N, 7))
    out[0] = P[1]
    C.relocate(P, out[0], out)
    np.testing.assert_array_equal(out[0], P[1])


@needs_c
def test_host_problem_inputs_the_kernels_would_refuse_are_converted():
    """Review: a PoseGraph keeps edge-index views as given (non-contiguous), numpy < 2 on Windows makes
    int32 index arrays, and a caller of HostProblem may pass any square root L of the information (not
    the lower Cholesky factor): the C path gives what the numpy path gives."""
    graph = _graph(seed=11, N=8, E=20)
    edges = torch.stack([graph.ii, graph.jj], 1)  # (E, 2): its columns are strided views
    strided = PoseGraph(graph.poses, edges[:, 0], edges[:, 1], graph.measurements, graph.information)
    assert not strided.ii.is_contiguous()
    ref = optimize(graph, backend="numpy")
    for backend in ("auto", "c"):
        res = optimize(strided, backend=backend)
        assert res.iterations == ref.iterations and res.chi2 == pytest.approx(ref.chi2, rel=1e-9)
    a, _ = _problems(graph)
    w, V = np.linalg.eigh(a.L @ a.L.transpose(0, 2, 1))
    sym_root = V @ (np.sqrt(w)[:, :, None] * V.transpose(0, 2, 1))  # symmetric: L L^T = info, not triangular
    args = (a.poses, a.ii.astype(np.int32), a.jj.astype(np.int32), graph.measurements.numpy(), None, sym_root,
            np.ones(graph.num_poses, dtype=bool))
    num, cc = host.HostProblem(*args, compiled=False), host.HostProblem(*args, compiled=True)
    P = host.retract(a.poses, 0.1 * np.random.default_rng(5).standard_normal((graph.num_poses, 6)))
    assert cc.evaluate(P)[1] == pytest.approx(num.evaluate(P)[1], rel=1e-12)
    cache = num.evaluate(P)[2]
    Hn, gn = (x.copy() for x in num.linearize(P, cache))
    Hc, gc = cc.linearize(P, cache)
    np.testing.assert_allclose(Hc, Hn, rtol=0, atol=1e-12 * np.abs(Hn).max())
    np.testing.assert_allclose(gc, gn, rtol=0, atol=1e-12 * np.abs(Hn).max())


@needs_c
def test_setup_kernels_match_numpy_and_flag_bad_information():
    """unit_poses = the numpy normalisation; information_factors = numpy's Cholesky (zeros above the
    diagonal), and -1 or the first bad edge by the rule of slam.graph.optimizer._information_factor."""
    from slam.graph.problem import SYMMETRY_RTOL as _SYMMETRY_RTOL
    from slam.graph.problem import unit_quaternions as _unit_quaternions

    C = host.host_kernels()
    graph = _graph(seed=13, N=10, E=30)
    Z = graph.measurements.numpy().copy()
    Z[:, 3:] *= np.linspace(0.999, 1.001, Z.shape[0])[:, None]  # within the graph's 1e-3 validation
    out = np.empty_like(Z)
    C.unit_poses(Z, out)
    np.testing.assert_allclose(out, _unit_quaternions(Z), rtol=0, atol=2e-16)
    info = graph.information.numpy().copy()
    L = np.empty_like(info)
    assert C.information_factors(info, L, True, _SYMMETRY_RTOL) == -1
    np.testing.assert_allclose(L, np.linalg.cholesky(info), rtol=0, atol=1e-13 * np.abs(info).max())
    assert not L[:, np.triu_indices(6, 1)[0], np.triu_indices(6, 1)[1]].any()
    bad = info.copy()
    bad[7, 0, 1] += 1e-3 * bad[7].diagonal().max()  # not symmetric (flagged only when checked)
    bad[12] = -np.eye(6)  # not positive definite
    bad[20, 2, 2] = np.nan
    assert C.information_factors(bad, L, True, _SYMMETRY_RTOL) == 7
    assert C.information_factors(bad, L, False, _SYMMETRY_RTOL) == 12  # the lower triangle is still SPD
    bad[12] = info[12]
    assert C.information_factors(bad, L, False, _SYMMETRY_RTOL) == 20
    bad[7, 0, 1] = info[7, 0, 1] + 1e-8 * info[7].diagonal().max()  # within the tolerance: accepted
    bad[20] = info[20]
    assert C.information_factors(bad, L, True, _SYMMETRY_RTOL) == -1
    # through optimize: the torch factor names the edge, as on the numpy path
    bad[7, 0, 1] += 1e-3 * bad[7].diagonal().max()
    g = PoseGraph(graph.poses, graph.ii, graph.jj, graph.measurements, graph.information)
    g.information = torch.from_numpy(bad)  # after validation, as a caller mutating the tensors would
    for backend in ("c", "numpy"):
        with pytest.raises(ValueError, match=r"information\[7\] \(edge \d+ -> \d+\) is not symmetric positive"):
            optimize(g, backend=backend)


def test_planar_rule_on_arrays_equals_the_graph_method():
    from slam.graph.pose_graph import planar_arrays

    for planar in (False, True):
        graph = _graph(seed=2, planar=planar)
        args = (graph.poses.numpy(), graph.measurements.numpy(), graph.information.numpy())
        assert planar_arrays(*args) == graph.is_planar() == planar
    info = graph.information.clone()
    info[3, 1, 4] = info[3, 4, 1] = 1e-3  # y coupled with pitch
    coupled = PoseGraph(graph.poses, graph.ii, graph.jj, graph.measurements, info)
    assert not coupled.is_planar() and coupled.is_planar(tol=1.0)


@needs_c
def test_supernode_kernels_check_their_inputs():
    """factor_group / solve_group (the small fronts of slam.graph.cholesky; their results are tested in
    tests/test_cholesky.py, which runs with and without them) refuse what would read or write outside
    their buffers."""
    C = host.host_kernels()
    buf = np.zeros(100)
    upd = np.zeros(3, dtype=np.int32)  # one supernode, p = 2, m = 4: d = 2, 3 packed update entries
    buf[[0, 3]] = 4.0  # F11 = 4 I: L11 = 2 I
    assert C.factor_group(buf, 0, 1, 2, 4, upd) == 0 and buf[0] == buf[3] == 2.0
    with pytest.raises(ValueError, match="do not fit a buffer of 100 values"):
        C.factor_group(buf, 95, 1, 2, 4, upd)
    with pytest.raises(ValueError, match="do not fit"):
        C.factor_group(buf, 0, 2 ** 61, 2, 4, upd)  # B m p overflows
    with pytest.raises(ValueError, match=r"upd\[1\] = 100 is out of range \[0, 100\)"):
        C.factor_group(buf, 0, 1, 2, 4, np.array([0, 100, 0], dtype=np.int32))
    with pytest.raises(ValueError, match="upd: expected int32"):
        C.factor_group(buf, 0, 1, 2, 4, upd.astype(np.int64))
    with pytest.raises(ValueError, match="upd: expected 3 values, got 2"):
        C.factor_group(buf, 0, 1, 2, 4, upd[:2])
    bad = np.zeros(100)
    bad[0], bad[3] = 4.0, -1.0  # second pivot negative
    assert C.factor_group(bad, 0, 1, 2, 4, upd) == 1
    y = np.ones(6)
    C.solve_group(buf, 0, 1, 2, 4, 0, np.array([4, 5]), y, True)
    np.testing.assert_allclose(y[:2], 0.5)  # L11 = 2 I
    with pytest.raises(ValueError, match=r"rows\[1\] = 6 is out of range \[0, 6\)"):
        C.solve_group(buf, 0, 1, 2, 4, 0, np.array([4, 6]), y, False)
    with pytest.raises(ValueError, match="rows/col0"):
        C.solve_group(buf, 0, 1, 2, 4, 5, np.array([4, 5]), y, False)
    # review: sums that overflowed past the checks, index arrays inside the array written, numpy ints
    with pytest.raises(ValueError, match="do not fit"):
        C.factor_group(buf, 2 ** 63 - 4, 1, 2, 4, upd)
    with pytest.raises(ValueError, match="rows/col0"):
        C.solve_group(buf, 0, 1, 2, 4, 2 ** 63 - 2, np.array([4, 5]), y, True)
    alias = np.zeros(100)
    with pytest.raises(ValueError, match="upd: shares memory with buf"):
        C.factor_group(alias, 0, 1, 2, 4, alias[96:98].view(np.int32)[:3])
    with pytest.raises(ValueError, match="rows: shares memory with y"):
        C.solve_group(buf, 0, 1, 2, 4, 0, y[4:6].view(np.int64), y, True)
    fresh = np.zeros(100)
    fresh[[0, 3]] = 4.0
    assert C.factor_group(fresh, np.int64(0), np.int32(1), 2, 4, upd) == 0 and fresh[3] == 2.0


def test_a_build_of_another_version_is_not_used(monkeypatch):
    """An editable install does not rebuild _kernels when _kernels.c changes: a build of another ABI
    (missing functions this code calls) is refused with a warning, and the numpy path runs."""
    import importlib
    import sys
    import types

    import slam.graph.accel

    stale = types.ModuleType("slam.graph.accel._kernels")
    stale.ABI = _compiled.ABI - 1
    stale.__file__ = "stale.so"
    monkeypatch.setitem(sys.modules, "slam.graph.accel._kernels", stale)
    monkeypatch.setattr(slam.graph.accel, "_kernels", stale, raising=False)
    try:
        with pytest.warns(RuntimeWarning, match=r"built from another version of _kernels.c .*pip install -e \."):
            reloaded = importlib.reload(_compiled)
        assert reloaded.kernels is None
    finally:
        monkeypatch.undo()
        importlib.reload(_compiled)  # back to the real build for the other tests
    assert (_compiled.kernels is not None) == compiled_kernels()


@needs_c
def test_backend_numpy_runs_no_compiled_code(monkeypatch):
    """backend="numpy" is what runs without the build: neither the per-edge kernels nor the sparse
    Cholesky's small fronts go through slam.graph.accel._kernels (here made to fail if called)."""
    from slam.graph.simulate import manhattan_world

    graph = manhattan_world(120, seed=1).graph  # 720 unknowns: the sparse path
    ref = optimize(graph, backend="c")

    class Refuse:
        def __getattr__(self, name):
            raise AssertionError(f"_kernels.{name} called under backend='numpy'")

    monkeypatch.setattr(_compiled, "kernels", Refuse())
    res = optimize(graph, backend="numpy")
    assert res.iterations == ref.iterations and res.chi2 == pytest.approx(ref.chi2, rel=1e-9)
    with pytest.raises(AssertionError, match="called under backend='numpy'"):
        optimize(graph, backend="auto")  # the C path does call them
