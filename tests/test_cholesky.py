"""The supernodal sparse Cholesky (slam.graph.cholesky) against dense references on random SPD systems."""
import numpy as np
import pytest
import torch

from slam.graph.cholesky import NotPositiveDefiniteError, SymbolicCholesky
from slam.graph.linear import build_pattern


def _chain(n):
    i = np.arange(n - 1)
    return i, i + 1


def _star(n):
    return np.zeros(n - 1, dtype=np.int64), np.arange(1, n)


def _grid(r, c, diagonal=False):
    idx = np.arange(r * c).reshape(r, c)
    pairs = [(idx[:, :-1], idx[:, 1:]), (idx[:-1, :], idx[1:, :])]
    if diagonal:
        pairs.append((idx[:-1, :-1], idx[1:, 1:]))
    ii = np.concatenate([a.ravel() for a, _ in pairs])
    jj = np.concatenate([b.ravel() for _, b in pairs])
    return ii, jj


def _loops(n, extra, seed):
    """A chain with ``extra`` random loop closures (duplicates and both directions included)."""
    rng = np.random.default_rng(seed)
    ii, jj = _chain(n)
    a, b = rng.integers(0, n, extra), rng.integers(0, n, extra)
    keep = a != b
    return np.concatenate([ii, a[keep]]), np.concatenate([jj, b[keep]])


def _system(ii, jj, n, k, seed, free=None):
    """A random SPD ``A (m, m)`` with the block pattern of the edges (as ``J^T J`` of random edge
    Jacobians plus a small diagonal), the pattern and its block-major values."""
    rng = np.random.default_rng(seed)
    free = np.ones(n, dtype=bool) if free is None else free
    pat = build_pattern(torch.as_tensor(ii, dtype=torch.int64), torch.as_tensor(jj, dtype=torch.int64),
                        torch.from_numpy(free), k)
    var = pat.var_index.numpy()
    m = pat.num_vars * k
    A = np.zeros((m, m))
    for a, b in zip(ii, jj):
        J = rng.standard_normal((k + 2, 2 * k))
        blocks = [v for v in (var[a], var[b])]
        cols = np.concatenate([np.arange(v * k, (v + 1) * k) if v >= 0 else np.full(k, -1) for v in blocks])
        ok = cols >= 0
        A[np.ix_(cols[ok], cols[ok])] += (J.T @ J)[np.ix_(ok, ok)]
    A += np.diag(rng.uniform(0.5, 2.0, m))  # SPD also where a pose has no edge
    nv = pat.num_vars
    vals = A.reshape(nv, k, nv, k).transpose(0, 2, 1, 3)[pat.block_rows.numpy(), pat.block_cols.numpy()].reshape(-1)
    return A, pat, vals


CASES = {
    "single_pose": (np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64), 1, 6),
    "single_edge": (np.array([0]), np.array([1]), 2, 6),
    "chain": (*_chain(40), 40, 6),
    "star": (*_star(30), 30, 6),
    "grid": (*_grid(8, 9), 72, 6),
    "grid_diagonal": (*_grid(7, 7, True), 49, 6),
    "planar_grid_k3": (*_grid(10, 12), 120, 3),
    "planar_loops_k3": (*_loops(150, 40, 3), 150, 3),
    "loops_k6": (*_loops(80, 25, 4), 80, 6),
    "disconnected": (np.array([0, 2, 4, 5]), np.array([1, 3, 5, 6]), 8, 6),
}


@pytest.mark.parametrize("name", sorted(CASES))
def test_solve_matches_dense(name):
    ii, jj, n, k = CASES[name]
    A, pat, vals = _system(ii, jj, n, k, seed=len(name))
    sym = SymbolicCholesky(pat)
    rng = np.random.default_rng(1)
    b = rng.standard_normal(A.shape[0])
    x = sym.factor(vals).solve(b)
    ref = np.linalg.solve(A, b)
    assert x.shape == (n * k,)
    np.testing.assert_allclose(x, ref, rtol=0, atol=1e-9 * np.abs(ref).max())
    # against torch's dense Cholesky, with torch tensors in and out
    Lt = torch.linalg.cholesky(torch.from_numpy(A))
    ref_t = torch.cholesky_solve(torch.from_numpy(b)[:, None], Lt)[:, 0]
    xt = sym.factor(torch.from_numpy(vals)).solve(torch.from_numpy(b))
    assert isinstance(xt, torch.Tensor) and xt.dtype == torch.float64
    torch.testing.assert_close(xt, ref_t, rtol=0, atol=1e-9 * float(ref_t.abs().max()))
    # the residual itself, relative to the scale of A and x
    assert np.abs(A @ x - b).max() <= 1e-10 * np.abs(A).max() * np.abs(x).max()


def test_refactor_reuses_symbolic_with_new_values():
    """The same symbolic object factors other values (LM retries): each solve matches its own dense one."""
    ii, jj, n, k = CASES["grid"]
    _, pat, _ = _system(ii, jj, n, k, seed=0)
    sym = SymbolicCholesky(pat)
    for seed in range(3):
        A, _, vals = _system(ii, jj, n, k, seed=seed)
        A_damped = A + 10.0 ** -seed * np.eye(A.shape[0])
        vals = vals.copy()
        vals[pat.diag_pos.numpy()] += 10.0 ** -seed  # lambda on the diagonal, as the LM loop adds it
        b = np.random.default_rng(seed).standard_normal(A.shape[0])
        ref = np.linalg.solve(A_damped, b)
        np.testing.assert_allclose(sym.factor(vals).solve(b), ref, rtol=0, atol=1e-9 * np.abs(ref).max())


def test_fixed_poses_reduce_the_system():
    ii, jj = _loops(60, 15, 7)
    free = np.ones(60, dtype=bool)
    free[[0, 17, 33]] = False
    A, pat, vals = _system(ii, jj, 60, 6, seed=5, free=free)
    assert A.shape == (57 * 6, 57 * 6)
    b = np.random.default_rng(2).standard_normal(A.shape[0])
    ref = np.linalg.solve(A, b)
    np.testing.assert_allclose(SymbolicCholesky(pat).factor(vals).solve(b), ref, rtol=0,
                               atol=1e-9 * np.abs(ref).max())


def test_many_equal_fronts_take_the_batched_path():
    """A star's leaves are many equal fronts of one height: they are factored as batches (groups of more
    than a few fronts), and the result still matches the dense solve."""
    ii, jj = _star(200)
    A, pat, vals = _system(ii, jj, 200, 6, seed=11)
    sym = SymbolicCholesky(pat)
    assert max(g.size for g in sym.groups) > 3
    b = np.random.default_rng(3).standard_normal(A.shape[0])
    ref = np.linalg.solve(A, b)
    np.testing.assert_allclose(sym.factor(vals).solve(b), ref, rtol=0, atol=1e-9 * np.abs(ref).max())


@pytest.mark.parametrize("name", ["chain", "star", "planar_grid_k3", "single_pose"])
def test_not_positive_definite_raises(name):
    ii, jj, n, k = CASES[name]
    A, pat, vals = _system(ii, jj, n, k, seed=9)
    sym = SymbolicCholesky(pat)
    bad = vals.copy()
    last = pat.diag_pos.numpy()[-k:]  # a negative diagonal entry: not PD, so some pivot must fail
    bad[last] = -1e3
    with pytest.raises(NotPositiveDefiniteError):
        sym.factor(bad)
    # an indefinite but symmetric matrix: the middle pose's diagonal block made negative definite
    mid = pat.diag_pos.numpy()[(n // 2) * k:(n // 2 + 1) * k]
    bad = vals.copy()
    bad[mid] = -1e3
    with pytest.raises(NotPositiveDefiniteError):
        sym.factor(bad)
    # and the symbolic object still works with good values afterwards
    b = np.ones(A.shape[0])
    ref = np.linalg.solve(A, b)
    np.testing.assert_allclose(sym.factor(vals).solve(b), ref, rtol=0, atol=1e-9 * np.abs(ref).max())


@pytest.mark.parametrize("name", ["loops_k6", "planar_loops_k3", "grid_diagonal"])
def test_batched_path_and_copying_syrk_match_dense(name, monkeypatch):
    """Every group through the batched torch calls (as on a GPU), and the front-by-front path with LAPACK
    calls that return copies instead of writing into the panels: both match the dense solve, and the
    copying path gives the in-place result bit for bit."""
    import slam.graph.cholesky as chol

    ii, jj, n, k = CASES[name]
    A, pat, vals = _system(ii, jj, n, k, seed=21)
    b = np.random.default_rng(4).standard_normal(A.shape[0])
    ref = np.linalg.solve(A, b)
    x_in_place = SymbolicCholesky(pat).factor(vals).solve(b)
    monkeypatch.setattr(chol, "_IN_PLACE", {"all": False})
    x_copy = SymbolicCholesky(pat).factor(vals).solve(b)
    assert np.array_equal(x_copy, x_in_place)
    monkeypatch.setattr(chol, "_NUMPY_MAX_BATCH", 0)
    sym = SymbolicCholesky(pat)
    assert all(isinstance(g, tuple) for g in sym.workspace(torch.device("cpu")).groups)
    for x in (x_in_place, sym.factor(vals).solve(b)):
        np.testing.assert_allclose(x, ref, rtol=0, atol=1e-9 * np.abs(ref).max())


def test_factorisation_survives_a_later_one():
    """The fronts are one buffer per pattern, rewritten by every factorisation: an earlier factorisation
    of the same symbolic object still solves its own system after a later one."""
    ii, jj, n, k = CASES["loops_k6"]
    A1, pat, vals1 = _system(ii, jj, n, k, seed=1)
    A2, _, vals2 = _system(ii, jj, n, k, seed=2)
    sym = SymbolicCholesky(pat)
    f1 = sym.factor(vals1)
    f2 = sym.factor(vals2)
    b = np.random.default_rng(5).standard_normal(A1.shape[0])
    for f, A in ((f1, A1), (f2, A2)):
        ref = np.linalg.solve(A, b)
        np.testing.assert_allclose(f.solve(b), ref, rtol=0, atol=1e-9 * np.abs(ref).max())


def test_factor_is_stored_in_panels_only():
    """The numeric factor lives in the panels [L11; L21] of the supernodes (no update matrices kept): the
    buffer is the factor's size (a full p x p pivot block per supernode: less than twice nnz(L)), and the
    factor read back from it is the dense Cholesky factor of the permuted matrix."""
    ii, jj = _loops(150, 40, 3)
    A, pat, vals = _system(ii, jj, 150, 6, seed=8)
    sym = SymbolicCholesky(pat)
    p, m = np.array(sym.p), np.array(sym.m)
    assert sym.buffer_size == int((m * p).sum())
    assert sym.nnz_L <= sym.buffer_size < 2 * sym.nnz_L
    f = sym.factor(vals)
    # rebuild L (permuted order) from the panels and compare with numpy's Cholesky of P A P^T
    perm = sym.perm_scalar
    L_ref = np.linalg.cholesky(A[np.ix_(perm, perm)])
    L = np.zeros_like(A)
    buf = f.buf.numpy()
    for g in sym.groups:
        d = g.m - g.p
        for b in range(g.size):
            panel = buf[g.offset + b * g.m * g.p:g.offset + (b + 1) * g.m * g.p].reshape(g.m, g.p)
            c0 = g.col0 + b * g.p
            cols = np.arange(c0, c0 + g.p)
            L[np.ix_(cols, cols)] = np.tril(panel[:g.p])
            if d:
                L[np.ix_(g.rows[b * d:(b + 1) * d], cols)] = panel[g.p:]
    np.testing.assert_allclose(L, L_ref, rtol=0, atol=1e-10 * np.abs(L_ref).max())


@pytest.mark.parametrize("d", [1, 2, 5, 6, 7, 36, 37])
def test_packed_update_order_is_lapacks(d):
    """The packed order (a closed form of LAPACK's rectangular full packed layout) is exactly the lower
    triangle, equals what LAPACK's own dtrttf produces, and dsfrk writes -Y^T Y in it (what the scatter of
    every update relies on)."""
    from scipy.linalg.lapack import dsfrk, dtrttf

    from slam.graph.cholesky import _rfp_order

    order = _rfp_order(d)
    a, b = np.divmod(order, d)
    assert order.shape == (d * (d + 1) // 2,) and np.all(a >= b) and len(set(order.tolist())) == order.size
    arf, info = dtrttf(np.arange(d * d, dtype=np.float64).reshape(d, d).T, transr="N", uplo="U")
    assert info == 0 and np.array_equal(arf.astype(np.int64), order)
    Y = np.asfortranarray(np.random.default_rng(d).standard_normal((4, d)))
    packed = dsfrk(d, 4, -1.0, Y, 0.0, np.zeros(order.size), transr="N", uplo="U", trans="T")
    np.testing.assert_allclose(packed, (-Y.T @ Y).reshape(-1)[order], rtol=1e-13, atol=1e-13)


@pytest.mark.parametrize("name", ["loops_k6", "grid_diagonal", "star"])
def test_ordering_is_superlus_minimum_degree(name):
    """The ordering comes from SuperLU's incomplete LU with everything dropped (no factorisation): the
    same column ordering as its full LU (the pattern alone decides it)."""
    import scipy.sparse as sp
    import scipy.sparse.linalg as sla

    from slam.graph.cholesky import _block_graph, _mmd_order

    ii, jj, n, k = CASES[name]
    _, pat, _ = _system(ii, jj, n, k, seed=0)
    bptr, bcol = _block_graph(pat)
    nv = pat.num_vars
    rows = np.repeat(np.arange(nv), np.diff(bptr))
    vals = np.where(rows == bcol, float(nv + 1), np.random.default_rng(0).uniform(0.1, 0.5, rows.shape[0]))
    lu = sla.splu(sp.csc_matrix((vals, bcol, bptr), shape=(nv, nv)), permc_spec="MMD_AT_PLUS_A",
                  diag_pivot_thresh=0.0, options={"SymmetricMode": True})
    order = _mmd_order(nv, bptr, bcol)
    assert np.array_equal(order, np.argsort(lu.perm_c))
    assert sorted(order.tolist()) == list(range(nv))
