"""The supernodal sparse Cholesky (slam.graph.cholesky) against dense references on random SPD systems
(LAPACK front by front and torch batched groups)."""
import threading

import numpy as np
import pytest
import torch

import slam.graph.cholesky as chol
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


@pytest.mark.parametrize("d", [1, 2, 3, 4, 5, 6, 7, 8, 36, 37, 99, 100, 601])
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


# the in-place factorisation's edge cases (error paths, threads, NaN, autograd, empty patterns)
def _assert_solves(f, A, b):
    ref = np.linalg.solve(A, b)
    np.testing.assert_allclose(f.solve(b), ref, rtol=0, atol=1e-9 * np.abs(ref).max())


def test_interrupted_factorisation_leaves_earlier_factor_intact(monkeypatch):
    """A factorisation that raises half way (bad input, KeyboardInterrupt) must not stay as the buffer's
    'owner': the earlier factor, already moved to its own copy, would then be moved again at the next
    factorisation, i.e. replaced by the half-done buffer (finite, wrong solutions)."""

    ii, jj, n, k = CASES["loops_k6"]
    A1, pat, vals1 = _system(ii, jj, n, k, seed=1)
    A2, _, vals2 = _system(ii, jj, n, k, seed=2)
    sym = SymbolicCholesky(pat)
    b = np.random.default_rng(6).standard_normal(A1.shape[0])
    f1 = sym.factor(vals1)
    with pytest.raises((IndexError, RuntimeError)):  # values of the wrong length
        sym.factor(vals2[:-2 * k * k])
    calls, saved = [], chol._factor_numpy_group

    def interrupt_fifth(orig):
        def call(*args):
            calls.append(1)
            if len(calls) == 5:
                raise KeyboardInterrupt
            return orig(*args)
        return call

    monkeypatch.setattr(chol, "_factor_numpy_group", interrupt_fifth(chol._factor_numpy_group))
    with pytest.raises(KeyboardInterrupt):
        sym.factor(vals2)
    monkeypatch.setattr(chol, "_factor_numpy_group", saved)
    f2 = sym.factor(vals2)
    _assert_solves(f2, A2, b)
    _assert_solves(f1, A1, b)


def test_failed_factorisation_is_not_copied(monkeypatch):
    """A factorisation that fails its pivots is useless: while its exception is alive (a retry inside the
    handler), the next factorisation must not copy the buffer to keep it."""
    import slam.graph.cholesky as chol

    ii, jj, n, k = CASES["loops_k6"]
    A, pat, vals = _system(ii, jj, n, k, seed=3)
    sym = SymbolicCholesky(pat)
    copies = []
    orig = chol.NumericCholesky._detach
    monkeypatch.setattr(chol.NumericCholesky, "_detach", lambda self: (copies.append(1), orig(self)))
    bad = vals.copy()
    bad[pat.diag_pos.numpy()[:k]] = -1e3
    b = np.ones(A.shape[0])
    try:
        sym.factor(bad)
    except NotPositiveDefiniteError:
        f = sym.factor(vals)  # the LM retry, inside the handler
    assert copies == []
    _assert_solves(f, A, b)


def test_factor_made_in_another_thread_keeps_its_own_values():
    """The factor must hold its views before the lock is released: a factorisation in another thread
    that takes the lock right then moves the first factor to a copy, and the first thread must not
    point it back at the shared buffer afterwards. The lock below widens that window deterministically."""
    ii, jj, n, k = CASES["loops_k6"]
    A1, pat, vals1 = _system(ii, jj, n, k, seed=1)
    A2, _, vals2 = _system(ii, jj, n, k, seed=2)
    sym = SymbolicCholesky(pat)
    ws = sym.workspace(torch.device("cpu"))

    class PausingLock:
        """A lock after whose release thread 'A' waits until thread 'B' has factored."""

        def __init__(self):
            self.lock, self.released, self.resume = threading.Lock(), threading.Event(), threading.Event()

        def __enter__(self):
            self.lock.acquire()
            return self

        def __exit__(self, *exc):
            self.lock.release()
            if threading.current_thread().name == "A" and not self.released.is_set():
                self.released.set()
                self.resume.wait(10)
            return False

    ws.lock = lock = PausingLock()
    out = {}

    def first():
        out[1] = sym.factor(vals1)

    def second():
        lock.released.wait(10)
        out[2] = sym.factor(vals2)
        lock.resume.set()

    threads = [threading.Thread(target=first, name="A"), threading.Thread(target=second, name="B")]
    for t in threads:
        t.start()
    for t in threads:
        t.join(30)
    b = np.random.default_rng(7).standard_normal(A1.shape[0])
    _assert_solves(out[2], A2, b)
    _assert_solves(out[1], A1, b)


@pytest.mark.parametrize("batched", [False, True])
@pytest.mark.parametrize("where", ["first", "middle", "last"])
def test_nan_values_raise_on_both_paths(where, batched, monkeypatch):
    """A NaN in H (on a diagonal or below it in a diagonal block) is not positive definite on both paths:
    OpenBLAS's dpotrf (the front-by-front path) returns info 0 for a NaN pivot, torch's cholesky_ex
    (the batched path) reports it. A later good factorisation of the same symbolic object is right."""
    import slam.graph.cholesky as chol

    if batched:
        monkeypatch.setattr(chol, "_NUMPY_MAX_BATCH", 0)
    ii, jj, n, k = CASES["loops_k6"]
    A, pat, vals = _system(ii, jj, n, k, seed=3)
    sym = SymbolicCholesky(pat)
    var = sym.order[{"first": 0, "middle": pat.num_vars // 2, "last": -1}[where]]
    start = pat.diag_pos.numpy()[var * k]  # entry (0, 0) of the variable's diagonal block
    for pos in (start + k + 1, start + k):  # entry (1, 1), then (1, 0)
        bad = vals.copy()
        bad[pos] = np.nan
        with pytest.raises(NotPositiveDefiniteError):
            sym.factor(bad)
    _assert_solves(sym.factor(vals), A, np.ones(A.shape[0]))


@pytest.mark.parametrize("batched", [False, True])
@pytest.mark.parametrize("bad", ["inf_diagonal", "nan_off_diagonal_block"])
def test_non_finite_values_raise_on_both_paths(bad, batched, monkeypatch):
    """An infinite pivot (it stays on the diagonal: later rows divide by it and stay finite) and a NaN in an
    off-diagonal block (it reaches an ancestor's pivot through the update) are not positive definite on
    both paths, wherever the bad entry sits in the elimination order."""
    import slam.graph.cholesky as chol

    if batched:
        monkeypatch.setattr(chol, "_NUMPY_MAX_BATCH", 0)
    ii, jj, n, k = CASES["loops_k6"]
    A, pat, vals = _system(ii, jj, n, k, seed=5)
    sym = SymbolicCholesky(pat)
    rows, cols = pat.block_rows.numpy(), pat.block_cols.numpy()
    if bad == "inf_diagonal":
        targets = [[pat.diag_pos.numpy()[sym.order[q] * k + 2]] for q in (0, pat.num_vars // 2, pat.num_vars - 1)]
    else:  # entry (1, 2) of an off-diagonal block and (2, 1) of its mirror (the factor reads one triangle)
        key = rows * n + cols
        off = np.flatnonzero(rows != cols)
        targets = [[q * k * k + k + 2, np.searchsorted(key, cols[q] * n + rows[q]) * k * k + 2 * k + 1]
                   for q in (off[0], off[len(off) // 2], off[-1])]
    for pos in targets:
        worse = vals.copy()
        worse[pos] = np.inf if bad == "inf_diagonal" else np.nan
        with pytest.raises(NotPositiveDefiniteError):
            sym.factor(worse)
    _assert_solves(sym.factor(vals), A, np.ones(A.shape[0]))


@pytest.mark.parametrize("k", [3, 6])
@pytest.mark.parametrize("r", [1, 2, 5, 13])
def test_update_positions_follow_their_definition(k, r):
    """Entry ``(a, b)`` of a supernode's packed update lands at ``base[pair] + (a % k) * pt[pair] + b % k``
    with ``pair`` the block pair ``(a // k, b // k)``: checked entry by entry (a Python loop over the
    packed order) on random bases and strides."""
    from slam.graph.cholesky import _rfp_rows_cols, _update_positions

    rng = np.random.default_rng(r * k)
    B, d = 3, k * r
    npair = r * (r + 1) // 2
    base, pt = rng.integers(0, 10 ** 6, (B, npair)), rng.integers(1, 500, (B, npair))
    pair_of = {(al, be): q for q, (al, be) in enumerate((al, be) for al in range(r) for be in range(al + 1))}
    a, b = _rfp_rows_cols(d)
    want = [[base[s, pair_of[x // k, y // k]] + (x % k) * pt[s, pair_of[x // k, y // k]] + y % k
             for x, y in zip(a.tolist(), b.tolist())] for s in range(B)]
    got = _update_positions(base, pt, d, k)
    assert got.dtype == np.int32 and np.array_equal(got, np.asarray(want).reshape(-1))


@pytest.mark.parametrize("batched", [False, True])
@pytest.mark.parametrize("where", ["first", "middle", "last"])
def test_not_positive_definite_in_any_supernode_then_good_values(where, batched, monkeypatch):
    """A failing pivot in the first, a middle or the last supernode raises on both paths; a factor made
    before it still solves its system, and a later good factorisation of the reused buffer is right."""
    import slam.graph.cholesky as chol

    if batched:
        monkeypatch.setattr(chol, "_NUMPY_MAX_BATCH", 0)
    ii, jj, n, k = CASES["planar_loops_k3"]
    A, pat, vals = _system(ii, jj, n, k, seed=3)
    A0, _, vals0 = _system(ii, jj, n, k, seed=4)
    sym = SymbolicCholesky(pat)
    f0 = sym.factor(vals0)
    var = sym.order[{"first": 0, "middle": pat.num_vars // 2, "last": -1}[where]]
    bad = vals.copy()
    bad[pat.diag_pos.numpy()[var * k:(var + 1) * k]] = -1e3
    with pytest.raises(NotPositiveDefiniteError):
        sym.factor(bad)
    b = np.random.default_rng(8).standard_normal(A.shape[0])
    _assert_solves(sym.factor(vals), A, b)
    _assert_solves(f0, A0, b)


def test_values_that_require_grad_do_not_poison_the_workspace():
    """The workspace buffer is shared: values that require grad must not make it require grad (a later
    factorisation then failed in numpy() when it moved the earlier factor to a copy)."""
    ii, jj, n, k = CASES["loops_k6"]
    A, pat, vals = _system(ii, jj, n, k, seed=1)
    sym = SymbolicCholesky(pat)
    b = np.random.default_rng(0).standard_normal(A.shape[0])
    f1 = sym.factor(torch.from_numpy(vals.copy()).requires_grad_(True))
    assert not sym.workspace(torch.device("cpu")).buf.requires_grad
    f2 = sym.factor(vals)
    _assert_solves(f2, A, b)
    _assert_solves(f1, A, b)


@pytest.mark.parametrize("k", [3, 6])
def test_pattern_without_variables(k):
    """Every pose fixed: an empty system, no supernode (it raised IndexError in the analysis)."""
    pat = build_pattern(torch.tensor([0]), torch.tensor([1]), torch.zeros(2, dtype=torch.bool), k)
    sym = SymbolicCholesky(pat)
    assert sym.num_supernodes == 0 and sym.size == 0
    assert sym.factor(np.zeros(0)).solve(np.zeros(0)).shape == (0,)


@pytest.mark.parametrize("seed", range(5))
def test_postorder_is_the_recursive_one(seed):
    """The postorder of a random forest (parents above their children, as in an elimination tree) equals a
    recursive depth-first search that visits roots and children in increasing order."""
    import sys

    from slam.graph.cholesky import _postorder

    rng = np.random.default_rng(seed)
    n = int(rng.integers(1, 400))
    parent = [int(rng.integers(j + 1, n)) if j < n - 1 and rng.random() < 0.9 else -1 for j in range(n)]
    children = {j: [c for c in range(n) if parent[c] == j] for j in range(n)}
    out = []

    def visit(v):
        for c in children[v]:
            visit(c)
        out.append(v)

    limit = sys.getrecursionlimit()
    sys.setrecursionlimit(max(limit, 2 * n + 100))
    try:
        for r in (j for j in range(n) if parent[j] < 0):
            visit(r)
    finally:
        sys.setrecursionlimit(limit)
    assert _postorder(parent).tolist() == out
    assert _postorder([]).tolist() == []


def test_symbolic_analysis_is_shared_by_equal_patterns_across_calls():
    """Two problems of the same edges (the same graph optimised twice) share one analysis, which still
    solves each one's values exactly; another pattern gets its own; the least recent is dropped."""
    import slam.graph.linear as lin

    solver = lin.SparseCholeskySolver()
    ii, jj = _loops(30, 8, seed=3)
    systems = [_system(ii, jj, 30, 3, seed) for seed in (0, 1)]  # equal patterns, built apart, other values
    first = solver.symbolic(systems[0][1])
    assert solver.symbolic(systems[1][1]) is first
    held = _system(ii, jj, 30, 3, 0, free=np.arange(30) > 0)[1]  # pose 0 held: another pattern
    assert solver.symbolic(held) is not first
    b = np.random.default_rng(2).standard_normal(90)
    for A, pat, vals in systems:
        x = solver.solve(pat, torch.from_numpy(vals), torch.from_numpy(b))
        np.testing.assert_allclose(x.numpy(), np.linalg.solve(A, b), rtol=0, atol=1e-9)
    for n in range(lin.SYMBOLIC_CACHE_SIZE):  # as many newer patterns as the cache holds
        solver.symbolic(_system(*_chain(5 + n), 5 + n, 3, 0)[1])
    assert solver.symbolic(_system(ii, jj, 30, 3, 0)[1]) is not first
