"""Supernodal multifrontal sparse Cholesky for block-sparse SPD matrices (numpy + LAPACK via scipy).

Why: torch has no CPU sparse Cholesky, and scipy's SuperLU (an LU) is 5-10x slower than a Cholesky on
pose-graph normal equations. The pattern of ``H`` is fixed during an optimisation, so the symbolic work
(ordering, elimination tree, supernodes, index maps) is done once per pattern at the level of pose
blocks, and each numeric factorisation is a loop over supernodes doing dense LAPACK/BLAS work.

Steps of the symbolic analysis (all on the ``n``-node block graph, not on the ``n k`` scalars):

1. fill-reducing ordering: multiple minimum degree on the block graph (SuperLU's ``MMD_AT_PLUS_A``
   applied to the tiny ``n x n`` block matrix, ~ms);
2. elimination tree (Liu's algorithm with path compression), then a postorder so that every
   supernode is a run of consecutive columns;
3. column structures and relaxed supernode amalgamation (as CHOLMOD: merge a column into its child
   supernode when the merged block has few columns or few explicit zeros);
4. per supernode: where its entries of ``H`` come from and where its update matrix goes in its parent.

The numeric phase assembles each frontal matrix (entries of ``H`` + children's update matrices),
factors its pivot block with ``potrf``, its rows with ``trsm``, and passes ``F22 - L21 L21^T`` up.

Example:
    >>> import torch
    >>> from slam.graph.linear import build_pattern
    >>> ii, jj = torch.tensor([0, 1, 2]), torch.tensor([1, 2, 0])
    >>> pat = build_pattern(ii, jj, torch.ones(3, dtype=torch.bool), 2)
    >>> sym = SymbolicCholesky(pat)
    >>> A = torch.eye(6, dtype=torch.float64) * 4 + 1
    >>> vals = A.view(3, 2, 3, 2).transpose(1, 2)[pat.block_rows, pat.block_cols].reshape(-1)  # block-major
    >>> x = sym.factor(vals.numpy()).solve(torch.ones(6, dtype=torch.float64).numpy())
    >>> bool(abs(A.numpy() @ x - 1).max() < 1e-12)
    True
"""
from __future__ import annotations

import itertools
import threading

import numpy as np

_EMPTY = np.zeros(0, dtype=np.int64)

__all__ = ["NotPositiveDefiniteError", "NumericCholesky", "SymbolicCholesky", "limit_blas_threads"]

_OPENBLAS = None  # (get, set) thread functions of the OpenBLAS builds loaded in this process


def _openblas_thread_functions():
    """Find the loaded OpenBLAS libraries (numpy's and scipy's wheels each bundle one) by their path in
    ``/proc/self/maps`` and return their ``(get_num_threads, set_num_threads)`` (Linux only; [] else)."""
    global _OPENBLAS
    if _OPENBLAS is not None:
        return _OPENBLAS
    import ctypes

    import scipy.linalg.blas  # noqa: F401  (load scipy's BLAS before looking)

    found = []
    try:
        with open("/proc/self/maps") as fh:
            paths = sorted({ln.split()[-1] for ln in fh if "openblas" in ln.lower() and "/" in ln})
    except OSError:
        paths = []
    for path in paths:
        try:
            lib = ctypes.CDLL(path)
        except OSError:
            continue
        for prefix, suffix in (("scipy_openblas", "64_"), ("scipy_openblas", ""), ("openblas", "64_"),
                               ("openblas", "")):
            try:
                get = getattr(lib, f"{prefix}_get_num_threads{suffix}")
                put = getattr(lib, f"{prefix}_set_num_threads{suffix}")
            except AttributeError:
                continue
            found.append((get, put))
            break
    _OPENBLAS = found
    return found


class limit_blas_threads:
    """Context manager: OpenBLAS (numpy's and scipy's) uses ``n`` threads inside, the old count after.

    The factorisation makes many small BLAS calls; OpenBLAS threads some of them (e.g. a 60 x 18
    ``trsm``), which on a busy CPU took 16 ms instead of 3 us. ``n=None`` changes nothing.
    """

    def __init__(self, n):
        self.n = n
        self.saved = []

    def __enter__(self):
        if self.n is not None:
            for get, put in _openblas_thread_functions():
                old = get()
                if old != self.n:
                    put(int(self.n))
                    self.saved.append((put, old))
        return self

    def __exit__(self, *exc):
        for put, old in self.saved:
            put(old)
        self.saved = []
        return False


class NotPositiveDefiniteError(RuntimeError):
    """The matrix is not (numerically) positive definite."""


def _block_graph(pattern):
    """CSR adjacency (including the diagonal) of the ``n``-node block graph: (indptr, indices)."""
    rows = pattern.block_rows.cpu().numpy()
    return np.searchsorted(rows, np.arange(pattern.num_vars + 1)), pattern.block_cols.cpu().numpy()


def _mmd_order(n: int, bptr: np.ndarray, bcol: np.ndarray) -> np.ndarray:
    """Minimum-degree ordering of the block graph: ``order[p]`` = the node eliminated p-th."""
    if n <= 2:
        return np.arange(n)
    import scipy.sparse as sp
    import scipy.sparse.linalg as sla

    rng = np.random.default_rng(0)  # values only steer SuperLU's pivots; the ordering uses the pattern
    rows = np.repeat(np.arange(n), np.diff(bptr))
    vals = np.where(rows == bcol, float(n + 1), rng.uniform(0.1, 0.5, size=rows.shape[0]))
    # the block pattern is symmetric with its diagonal (build_pattern stores (i, j) and (j, i)), so this
    # CSR-as-CSC matrix is the transpose of the same pattern: MMD_AT_PLUS_A orders A^T + A alike
    B = sp.csc_matrix((vals, bcol, bptr), shape=(n, n))
    lu = sla.splu(B, permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.0, options={"SymmetricMode": True})
    return np.argsort(lu.perm_c)


def _etree(n: int, ptr: np.ndarray, col: np.ndarray) -> list[int]:
    """Elimination tree of a symmetric pattern (CSR ``ptr, col``, any numbering); ``-1`` for roots."""
    parent = [-1] * n
    ancestor = [-1] * n
    # only the entries left of the diagonal matter: select them once (vectorised) instead of testing
    # every entry in the Python loop
    rows = np.repeat(np.arange(n), np.diff(ptr))
    low = rows > col
    lptr = np.zeros(n + 1, dtype=np.int64)
    np.cumsum(np.bincount(rows[low], minlength=n), out=lptr[1:])
    colist, lp = col[low].tolist(), lptr.tolist()
    for j in range(n):
        for i in colist[lp[j]:lp[j + 1]]:
            while True:  # walk from i to the root of its current subtree, compressing the path to j
                nxt = ancestor[i]
                if nxt == j:
                    break
                ancestor[i] = j
                if nxt == -1:
                    parent[i] = j
                    break
                i = nxt
    return parent


def _postorder(parent: list[int]) -> list[int]:
    n = len(parent)
    children: list[list[int]] = [[] for _ in range(n)]
    roots = []
    for j in range(n):
        (children[parent[j]] if parent[j] >= 0 else roots).append(j)
    post: list[int] = []
    stack = [(r, False) for r in reversed(roots)]
    while stack:
        v, done = stack.pop()
        if done:
            post.append(v)
            continue
        stack.append((v, True))
        for c in reversed(children[v]):
            stack.append((c, False))
    return post


class _Ticker:
    def __init__(self):
        import time

        self.clock = time.perf_counter
        self.last = self.clock()
        self.times = {}

    def __call__(self, name: str) -> None:
        now = self.clock()
        self.times[name] = now - self.last
        self.last = now


class SymbolicCholesky:
    """Symbolic analysis of a :class:`~slam.graph.linear.BlockPattern` (done once per pattern).

    Args:
        pattern: the block pattern of the SPD matrix.
        relax: CHOLMOD-style amalgamation as ``((max_cols, max_zero_fraction), ...)`` in block columns:
            a column joins its child supernode if the merged supernode has at most ``max_cols`` block
            columns and at most that fraction of explicit zeros (first rule that applies). The
            default merges more than CHOLMOD's: every front costs a few batched calls of fixed
            overhead, and fewer, larger fronts were 5-20% faster per factorisation on the benchmark
            graphs (smallGrid3D, parking-garage, M3500) and neutral on sphere2500.
    """

    def __init__(self, pattern, relax=((2, 1.0), (6, 0.8), (16, 0.2), (10 ** 9, 0.05))):
        n, k = pattern.num_vars, pattern.k
        self.n, self.k, self.size = n, k, n * k
        tick = _Ticker()
        bptr, bcol = _block_graph(pattern)
        order = _mmd_order(n, bptr, bcol)
        iperm = np.empty(n, dtype=np.int64)
        iperm[order] = np.arange(n)
        # permuted adjacency (CSR, rows by new index)
        rows_new = np.repeat(iperm, np.diff(bptr))
        cols_new = iperm[bcol]
        srt = np.lexsort((cols_new, rows_new))
        pr, pc = rows_new[srt], cols_new[srt]
        ptr = np.searchsorted(pr, np.arange(n + 1))
        tick("order")
        parent0 = _etree(n, ptr, pc)
        post = np.asarray(_postorder(parent0), dtype=np.int64)  # post[q] = node (in MMD numbering)
        newpos = np.empty(n, dtype=np.int64)
        newpos[post] = np.arange(n)
        par0 = np.asarray(parent0, dtype=np.int64)[post]
        parent = np.where(par0 >= 0, newpos[par0], -1).tolist()
        self.order = order[post]  # final: position -> original block variable
        iperm = np.empty(n, dtype=np.int64)
        iperm[self.order] = np.arange(n)
        rows_f = iperm[np.repeat(np.arange(n), np.diff(bptr))]
        cols_f = iperm[bcol]
        srt = np.lexsort((cols_f, rows_f))
        pr, pc = rows_f[srt], cols_f[srt]
        ptr = np.searchsorted(pr, np.arange(n + 1))
        tick("etree")
        # column structures (strictly below the diagonal), children lists
        children: list[list[int]] = [[] for _ in range(n)]
        for j in range(n):
            if parent[j] >= 0:
                children[parent[j]].append(j)
        # the entries right of the diagonal, selected once (vectorised) rather than tested in the loop
        up = pc > pr
        uptr = np.zeros(n + 1, dtype=np.int64)
        np.cumsum(np.bincount(pr[up], minlength=n), out=uptr[1:])
        ucol, up_ = pc[up].tolist(), uptr.tolist()
        struct: list[set] = [None] * n  # type: ignore[list-item]
        for j in range(n):
            s = set(ucol[up_[j]:up_[j + 1]])
            for c in children[j]:
                s |= struct[c]
            s.discard(j)
            struct[j] = s
        tick("struct")
        # relaxed supernodes: runs [first, last] of consecutive columns along etree chains
        first = [0]
        zeros = 0  # explicit zeros (in blocks) of the current supernode
        for j in range(1, n):
            f = first[-1]
            if parent[j - 1] == j:
                nc = j - f + 1  # merged number of block columns
                r_prev, r_new = len(struct[j - 1]), len(struct[j])
                extra = (j - f) * (1 + r_new - r_prev)
                nz = zeros + extra
                total = nc * (nc + 1) // 2 + nc * r_new
                frac = nz / total
                if any(nc <= mc and frac <= mz for mc, mz in relax):
                    zeros = nz
                    continue
            first.append(j)
            zeros = 0
        first.append(n)
        ns = len(first) - 1
        self.num_supernodes = ns
        sn_of = np.empty(n, dtype=np.int64)
        for s in range(ns):
            sn_of[first[s]:first[s + 1]] = s
        sn_parent = [int(sn_of[parent[first[s + 1] - 1]]) if parent[first[s + 1] - 1] >= 0 else -1
                     for s in range(ns)]
        ncols = [first[s + 1] - first[s] for s in range(ns)]
        nrows = [len(struct[first[s + 1] - 1]) for s in range(ns)]
        tick("supernodes")
        # level schedule: a supernode's height is 1 + the largest height of its children; supernodes of one
        # height are independent, and those of one front shape are factored as one batch ("group")
        height = [0] * ns
        for s in range(ns):  # children come before parents (postorder)
            if sn_parent[s] >= 0:
                height[sn_parent[s]] = max(height[sn_parent[s]], height[s] + 1)
        groups = {}
        for s in range(ns):
            groups.setdefault((height[s], ncols[s], nrows[s]), []).append(s)
        group_list = sorted(groups.items())
        # relabel the columns so that every group is one contiguous run: a height-major order is a
        # topological order of the elimination tree, so the fill is unchanged, and the solves can take
        # each group's unknowns as a slice
        lab = np.empty(n, dtype=np.int64)
        nf = np.empty(ns, dtype=np.int64)  # new first column of each supernode
        pos = 0
        for _, sns in group_list:
            for s in sns:
                nf[s] = pos
                lab[first[s]:first[s + 1]] = np.arange(pos, pos + ncols[s])
                pos += ncols[s]
        order = np.empty(n, dtype=np.int64)
        order[lab] = self.order
        self.order = order  # position -> original block variable
        iperm = np.empty(n, dtype=np.int64)
        iperm[order] = np.arange(n)
        tick("relabel")
        # row structures R_s (blocks below the pivot block, new labels, sorted), concatenated
        nrows_a = np.asarray(nrows, dtype=np.int64)
        ncols_a = np.asarray(ncols, dtype=np.int64)
        roff = np.zeros(ns + 1, dtype=np.int64)
        roff[1:] = np.cumsum(nrows_a)
        seg = np.repeat(np.arange(ns), nrows_a)
        rcat = lab[np.fromiter(itertools.chain.from_iterable(struct[first[s + 1] - 1] for s in range(ns)),
                               dtype=np.int64, count=int(roff[-1]))]
        rcat = rcat[np.lexsort((rcat, seg))]
        rkeys = seg * n + rcat  # sorted: (supernode, row)

        def local(sn: np.ndarray, blk: np.ndarray) -> np.ndarray:
            """Position of block ``blk`` in the front of supernode ``sn`` (its columns, then R_sn)."""
            inside = blk < nf[sn] + ncols_a[sn]
            pos_r = np.searchsorted(rkeys, sn * n + blk) - roff[sn]
            return np.where(inside, blk - nf[sn], ncols_a[sn] + pos_r)

        self.p = [k * c for c in ncols]
        self.m = [k * (c + r) for c, r in zip(ncols, nrows)]
        m_a = k * (ncols_a + nrows_a)
        self.height = height
        self.sn_parent = sn_parent
        # front storage: the fronts of a group one after the other (m * m values each), so a group is a
        # (B, m * m) view. A front is stored by columns split at p: its left ``m x p`` panel [F11; F21]
        # (row-major), then its right ``m x d`` columns [F12; F22] (row-major), so that F22 is one
        # contiguous row-major block: LAPACK's syrk then updates it in place (no copy of it per front),
        # and F11, F21 are contiguous too. Local entry (i, j) of a front lies at ``i p + j`` (j < p) or
        # ``m p + i d + j - p`` (j >= p) from its offset.
        off = np.zeros(ns, dtype=np.int64)
        pos = 0
        for (_, c, r), sns in group_list:
            m = k * (c + r)
            off[sns] = pos + m * m * np.arange(len(sns))
            pos += m * m * len(sns)
        self.buffer_size = int(pos)
        ar = np.arange(k)
        tick("rows")
        # gather map from the value array of H into the fronts: entry (row, col) with row >= col (new
        # labels) belongs to the front of col's supernode, at local (row, col)
        sn_new = np.repeat(np.arange(ns)[np.argsort(nf)], ncols_a[np.argsort(nf)])
        nb = pattern.num_blocks
        bpos = np.arange(nb * k * k, dtype=np.int64).reshape(nb, k, k)  # block-major value positions
        prow, pcol = iperm[pattern.block_rows.cpu().numpy()], iperm[pattern.block_cols.cpu().numpy()]
        keep = np.nonzero(prow >= pcol)[0]
        prow, pcol, bpos = prow[keep], pcol[keep], bpos[keep]
        sn_blk = sn_new[pcol]
        lr = local(sn_blk, prow)
        lc = pcol - nf[sn_blk]
        p_blk = k * ncols_a[sn_blk]  # H's entries lie in the left panel (row stride p) of their front
        dst = (off[sn_blk][:, None, None] + (lr[:, None, None] * k + ar[None, :, None]) * p_blk[:, None, None]
               + lc[:, None, None] * k + ar[None, None, :])  # entry (a, c) of block = H[row*k + a, col*k + c]
        self.src = bpos.reshape(-1)
        self.dst = dst.reshape(-1)
        tick("gather")
        parent_a = np.asarray(sn_parent, dtype=np.int64)
        # where each row of R_s lands in the front of s's parent (block local index), for all s at once
        loc_all = local(np.repeat(parent_a, nrows_a), rcat) if roff[-1] else rcat
        # every supernode's scalar rows and their local positions in its parent's front, made for all
        # supernodes at once in group order (per group only slices and one broadcast remain: the groups
        # stage was ~20 numpy calls per group)
        gorder = np.fromiter(itertools.chain.from_iterable(sns for _, sns in group_list), dtype=np.int64,
                             count=ns)
        glen = nrows_a[gorder]
        gstart = np.zeros(ns + 1, dtype=np.int64)
        gstart[1:] = np.cumsum(glen)
        at = np.repeat(roff[gorder] - gstart[:-1], glen) + np.arange(int(gstart[-1]))
        rows_all = (rcat[at][:, None] * k + ar).reshape(-1)  # block rows -> scalar rows
        rel_all = (loc_all[at][:, None] * k + ar).reshape(-1)
        gstart *= k
        ext_base = off[parent_a[gorder]]  # parent's front offset and size per supernode (group order)
        ext_m = m_a[parent_a[gorder]]
        ext_p = k * ncols_a[parent_a[gorder]]
        self.groups = []
        i0 = 0
        for (_, c, r), sns in group_list:
            p, m = k * c, k * (c + r)
            B = len(sns)
            s0 = sns[0]
            if r:
                d = k * r
                rows = rows_all[gstart[i0]:gstart[i0 + B]]
                rel = rows_rel = rel_all[gstart[i0]:gstart[i0 + B]].reshape(B, d)
                # where each child's update matrix lands in its parent's front (scalar local indices)
                # entry (a, b) of the update lands at local (rel[a], rel[b]) of the parent's front
                pp, mp = ext_p[i0:i0 + B, None, None], ext_m[i0:i0 + B, None, None]
                ra, rb = rel[:, :, None], rows_rel[:, None, :]
                ext_idx = (ext_base[i0:i0 + B, None, None]
                           + np.where(rb < pp, ra * pp + rb, mp * pp + ra * (mp - pp) + rb - pp)).reshape(-1)
            else:
                rows = ext_idx = _EMPTY
            self.groups.append(_Group(B, p, m, int(off[s0]), int(k * nf[s0]), rows, ext_idx))
            i0 += B
        tick("groups")
        self.perm_scalar = (self.order[:, None] * k + ar).reshape(-1)  # permuted scalar -> original scalar
        self.nnz_L = int(sum(p * (p + 1) // 2 + (m - p) * p for p, m in zip(self.p, self.m)))
        self._torch_cache = {}
        tick("done")
        self.timings = tick.times  # seconds per stage of the analysis (for profiling)

    def workspace(self, device) -> _Workspace:
        """Index tensors, the front buffer and the solve vector on ``device``, with every per-group view
        made once (cached): a factorisation then only launches the numeric kernels."""
        key = str(device)
        if key not in self._torch_cache:
            self._torch_cache[key] = _Workspace(self, device)
        return self._torch_cache[key]

    def factor(self, values) -> NumericCholesky:
        """Numeric factorisation for the values ``(nnz,)`` (torch tensor or numpy array) of the pattern;
        raises :class:`NotPositiveDefiniteError` when a pivot block is not positive definite."""
        return NumericCholesky(self, values)


# On the CPU, groups of at most this many fronts are factored front by front with direct LAPACK/BLAS
# calls (a few us each) instead of batched torch calls (10-20 us each whatever the batch size).
_NUMPY_MAX_BATCH = 3


class _Workspace:
    """Per-device state of a :class:`SymbolicCholesky`: index tensors, the buffer holding every frontal
    matrix, the permuted right-hand side, and views into both for every group.

    On the CPU, groups of a single supernode (most groups near the root) run through numpy views of the
    same memory and direct LAPACK/BLAS calls (scipy), whose call overhead is a few microseconds against
    ten or more for a batched torch call.
    """

    def __init__(self, sym: SymbolicCholesky, device):
        import torch

        def t(a):
            return torch.from_numpy(np.ascontiguousarray(a)).to(device)

        self.lock = threading.Lock()  # the buffers are shared by the factorisations of this pattern
        k = sym.k
        # H's entries go to the fronts in runs of k (one row of a k x k block, contiguous in both; every
        # front offset and row stride is a multiple of k): copying rows of k values takes k times fewer
        # indices than copying scalars (parking-garage: the fill 1.2 -> 0.6 ms)
        self.src, self.dst = t(sym.src[::k] // k), t(sym.dst[::k] // k)
        self.perm = t(sym.perm_scalar)
        self.buf = torch.zeros(sym.buffer_size, dtype=torch.float64, device=device)
        self.buf_rows = self.buf.view(-1, k)
        self.y = torch.zeros(sym.size, dtype=torch.float64, device=device)
        cpu = self.buf.device.type == "cpu"
        self.bufnp = self.buf.numpy() if cpu else None
        self.ynp = self.y.numpy() if cpu else None
        self.groups = []
        for g in sym.groups:
            B, p, m = g.size, g.p, g.m
            d = m - p
            if cpu and B <= _NUMPY_MAX_BATCH:  # front by front: see _NUMPY_MAX_BATCH
                for b in range(B):
                    o = g.offset + b * m * m
                    left = self.bufnp[o:o + m * p].reshape(m, p)  # see SymbolicCholesky: the front layout
                    F22 = self.bufnp[o + m * p + p * d:o + m * m].reshape(d, d)
                    self.groups.append(_NumpyGroup(p, d, left[:p], left[p:], F22, g.col0 + b * p,
                                                   g.rows[b * d:(b + 1) * d], t(g.ext_idx[b * d * d:(b + 1) * d * d]),
                                                   torch.from_numpy(F22.reshape(-1))))
                continue
            F = self.buf[g.offset:g.offset + B * m * m].view(B, m * m)
            left = F[:, :m * p].view(B, m, p)
            yc = self.y[g.col0:g.col0 + B * p].view(B, p, 1)
            self.groups.append((B, p, d, left[:, :p], left[:, p:], F[:, m * p + p * d:].view(B, d, d), yc,
                                t(g.rows) if d else None, t(g.ext_idx) if d else None))


_SYRK_IN_PLACE = []


def _syrk_in_place() -> bool:
    """Whether scipy's ``dsyrk(..., c=C, overwrite_c=1)`` writes into a Fortran-contiguous ``C`` (f2py
    does, for an array of the right type and order; checked once on a 2 x 2 probe)."""
    if not _SYRK_IN_PLACE:
        from scipy.linalg.blas import dsyrk

        c = np.zeros((2, 2))
        dsyrk(1.0, np.ones((2, 1)), beta=1.0, c=c.T, trans=0, lower=0, overwrite_c=1)
        _SYRK_IN_PLACE.append(bool(c[1, 0] == 1.0))  # c^T's upper triangle (lower=0) is c's lower one
    return _SYRK_IN_PLACE[0]


class _NumpyGroup:
    """A one-supernode group on the CPU: numpy views of its front and its index arrays."""

    __slots__ = ("F11", "F21", "F22", "F22_flat", "c0", "c1", "d", "ext", "p", "rows")

    def __init__(self, p, d, F11, F21, F22, c0, rows, ext, F22_flat):
        self.p, self.d, self.F11, self.F21, self.F22 = p, d, F11, F21, F22
        self.c0, self.c1, self.rows, self.ext = c0, c0 + p, rows, ext
        # a torch tensor over F22's memory, made once (torch.from_numpy: ~1 us per call). It has its own
        # storage object, so index_add_ into the buffer accepts it: the memory really is disjoint from the
        # parent's front it is added to.
        self.F22_flat = F22_flat


class NumericCholesky:
    """``P H P^T = L L^T`` stored per group as batched dense panels; :meth:`solve` applies ``H^-1``.

    Works on torch tensors (float64) on the device of ``values``; numpy arrays are accepted too.
    """

    def __init__(self, sym: SymbolicCholesky, values):
        import torch
        from scipy.linalg.blas import dsyrk, dtrsm
        from scipy.linalg.lapack import dpotrf

        self.sym = sym
        v = torch.from_numpy(values) if isinstance(values, np.ndarray) else values
        v = v.to(torch.float64)
        ws = self.ws = sym.workspace(v.device)
        self.L11, self.L21, infos = [], [], []
        failed = False
        # numpy's BLAS runs single-threaded here (see limit_blas_threads)
        with ws.lock, limit_blas_threads(1 if ws.bufnp is not None else None):
            buf = ws.buf
            from_numpy = torch.from_numpy
            in_place = _syrk_in_place()
            buf.zero_()
            # rows of k values (see _Workspace); faster than buf[dst] = v[src]
            ws.buf_rows.index_copy_(0, ws.dst, torch.index_select(v.reshape(-1, ws.buf_rows.shape[1]), 0, ws.src))
            for grp in ws.groups:
                if type(grp) is _NumpyGroup:
                    L11, info = dpotrf(grp.F11, lower=1, clean=0)
                    failed |= info != 0
                    self.L11.append(L11)
                    if grp.d:
                        L21 = dtrsm(1.0, L11, grp.F21, side=1, lower=1, trans_a=1)
                        self.L21.append(L21)
                        # F22 - L21 L21^T on one triangle only (syrk: half the flops of a product), in
                        # place: the Fortran view F22^T (contiguous) is F22 itself, and its upper triangle
                        # is F22's lower one; the other triangle keeps stale values and lands in the
                        # parent's upper triangle, which is never read. torch's index_add_ adds the same
                        # values as numpy's buffered ``bufnp[ext] += U`` (one addition per entry: the
                        # indices of one update matrix are distinct) in ~60% of its time.
                        U = dsyrk(-1.0, L21, beta=1.0, c=grp.F22.T, trans=0, lower=0, overwrite_c=1)
                        if in_place:  # U is F22^T: F22 read row-major is the row-major update
                            buf.index_add_(0, grp.ext, grp.F22_flat)
                        else:  # a copy: read it in Fortran order (the row-major update)
                            buf.index_add_(0, grp.ext, from_numpy(U.ravel(order="F")))
                    else:
                        self.L21.append(None)
                    continue
                _, _, d, F11, F21, F22, _, _, ext_idx = grp
                L11, info = torch.linalg.cholesky_ex(F11)
                infos.append(info)
                self.L11.append(L11)
                if d:
                    L21 = torch.linalg.solve_triangular(L11.mT, F21, upper=True, left=False)
                    self.L21.append(L21)
                    # the whole update matrix goes up: its upper triangle lands in the parent's upper
                    # triangle, which is never read (cheaper than extracting the lower triangle first)
                    buf.index_add_(0, ext_idx, torch.baddbmm(F22, L21, L21.mT, alpha=-1.0).view(-1))
                else:
                    self.L21.append(None)
        if failed or (infos and bool(torch.cat(infos).any())):
            raise NotPositiveDefiniteError("the matrix is not positive definite (a pivot block failed)")

    def solve(self, b):
        """``x = H^-1 b`` for ``b (n k,)`` (numpy array or torch tensor; returns the same kind)."""
        import torch
        from scipy.linalg.blas import dtrsv

        is_np = isinstance(b, np.ndarray)
        bt = torch.from_numpy(b) if is_np else b
        ws = self.ws
        with ws.lock, limit_blas_threads(1 if ws.ynp is not None else None):
            y, ynp = ws.y, ws.ynp
            torch.index_select(bt.to(torch.float64), 0, ws.perm, out=y)
            groups = ws.groups
            for g, grp in enumerate(groups):
                if type(grp) is _NumpyGroup:
                    # in place on the (contiguous) slice: no copy back
                    z = dtrsv(self.L11[g], ynp[grp.c0:grp.c1], lower=1, overwrite_x=1)
                    if grp.d:
                        ynp[grp.rows] -= self.L21[g] @ z
                    continue
                _, _, d, _, _, _, yc, rows, _ = grp
                z = torch.linalg.solve_triangular(self.L11[g], yc, upper=False)
                yc.copy_(z)
                if d:
                    y.index_add_(0, rows, (self.L21[g] @ z).view(-1), alpha=-1.0)
            for g in range(len(groups) - 1, -1, -1):
                grp = groups[g]
                if type(grp) is _NumpyGroup:
                    yc = ynp[grp.c0:grp.c1]
                    if grp.d:
                        yc -= self.L21[g].T @ ynp[grp.rows]
                    dtrsv(self.L11[g], yc, lower=1, trans=1, overwrite_x=1)
                    continue
                B, _, d, _, _, _, yc, rows, _ = grp
                rhs = yc
                if d:
                    rhs = torch.baddbmm(yc, self.L21[g].mT, y[rows].view(B, d, 1), alpha=-1.0)
                yc.copy_(torch.linalg.solve_triangular(self.L11[g].mT, rhs, upper=True))
            x = torch.empty_like(y)
            x[ws.perm] = y
        return x.numpy() if is_np else x.to(bt.dtype)


class _Group:
    """Supernodes of one height and one front shape ``(p pivots, m rows)``, factored as one batch."""

    __slots__ = ("col0", "ext_idx", "m", "offset", "p", "rows", "size")

    def __init__(self, size, p, m, offset, col0, rows, ext_idx):
        self.size, self.p, self.m, self.offset, self.col0 = size, p, m, offset, col0
        self.rows, self.ext_idx = rows, ext_idx
