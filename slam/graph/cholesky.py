"""Supernodal sparse Cholesky for block-sparse SPD matrices (numpy + LAPACK via scipy; torch has no CPU one).

The symbolic analysis is made once per pattern; the numeric phase is right-looking, in place in the factor's
panels, batched per group of supernodes of one height and shape (small groups front by front through LAPACK).
"""
from __future__ import annotations

import collections
import functools
import itertools
import threading
import weakref
from dataclasses import dataclass

import numpy as np
import torch

_EMPTY = np.zeros(0, dtype=np.int64)

__all__ = ["NotPositiveDefiniteError", "NumericCholesky", "SymbolicCholesky"]


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

    rng = np.random.default_rng(0)  # values only steer SuperLU's pivots
    rows = np.repeat(np.arange(n), np.diff(bptr))
    vals = np.where(rows == bcol, float(n + 1), rng.uniform(0.1, 0.5, size=rows.shape[0]))
    B = sp.csc_matrix((vals, bcol, bptr), shape=(n, n))  # the pattern is symmetric: CSR read as CSC
    # an incomplete LU with every entry dropped: SuperLU's ordering without the factorisation
    ilu = sla.spilu(B, permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.0, drop_tol=1e300, fill_factor=1.0,
                    options={"SymmetricMode": True})
    return np.argsort(ilu.perm_c)


def _etree(n: int, ptr: np.ndarray, col: np.ndarray) -> list[int]:
    """Elimination tree of a symmetric pattern (CSR ``ptr, col``, any numbering); ``-1`` for roots."""
    parent = [-1] * n
    ancestor = [-1] * n
    rows = np.repeat(np.arange(n), np.diff(ptr))
    low = rows > col
    lptr = np.concatenate(([0], np.cumsum(np.bincount(rows[low], minlength=n))))
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


def _postorder(parent: list[int]) -> np.ndarray:
    """A postorder of the forest ``parent`` (``-1`` for roots): children in increasing order, roots too
    (the reverse of scipy's preorder from a virtual root, children visited in decreasing order)."""
    from scipy.sparse import csr_matrix
    from scipy.sparse.csgraph import depth_first_order

    n = len(parent)
    par = np.asarray(parent, dtype=np.int64).reshape(-1)
    par = np.where(par >= 0, par, n)  # the virtual root n
    kids = np.argsort(par * (n + 1) + (n - 1 - np.arange(n)))  # by parent, then decreasing
    indptr = np.searchsorted(par[kids], np.arange(n + 2))
    graph = csr_matrix((np.ones(n), kids, indptr), shape=(n + 1, n + 1))
    pre = depth_first_order(graph, n, directed=True, return_predecessors=False)
    return pre[:0:-1].astype(np.int64)


@dataclass
class _Tree:
    """The supernodal elimination tree of a block pattern, in the order the factor is stored.

    Attributes:
        order: ``(n,)`` position -> original block variable (fill-reducing, postordered, group-major).
        lab: ``(n,)`` position in the postorder -> final position (what the row structures are mapped by).
        first: ``ns + 1`` first postorder column of each supernode (then ``n``).
        ncols, nrows: per supernode its block columns and the block rows below its pivot block.
        groups: ``((height, ncols, nrows), [supernodes])`` sorted: the batches factored together.
        nf: ``(ns,)`` final first column of each supernode.
        struct: per postorder column the set of block rows below the diagonal (postorder labels).
    """

    order: np.ndarray
    lab: np.ndarray
    first: list
    ncols: list
    nrows: list
    groups: list
    nf: np.ndarray
    struct: list


def _permuted(bptr: np.ndarray, bcol: np.ndarray, order: np.ndarray):
    """The pattern (CSR ``bptr, bcol``) with rows and columns renumbered by ``order`` (position -> variable):
    ``(rows, cols)`` sorted by row then column, and the row pointers."""
    n = order.shape[0]
    iperm = np.argsort(order)  # variable -> position
    rows = iperm[np.repeat(np.arange(n), np.diff(bptr))]
    cols = iperm[bcol]
    srt = np.argsort(rows * n + cols)  # the entries are distinct: one key sorts as (row, col)
    pr, pc = rows[srt], cols[srt]
    return pr, pc, np.searchsorted(pr, np.arange(n + 1))


def _column_structures(n: int, parent: list, pr: np.ndarray, pc: np.ndarray) -> list:
    """Per column the set of rows strictly below the diagonal in the factor (its entries of the pattern and
    its children's structures: the fill)."""
    children: list[list[int]] = [[] for _ in range(n)]
    for j in range(n):
        if parent[j] >= 0:
            children[parent[j]].append(j)
    up = pc > pr
    uptr = np.concatenate(([0], np.cumsum(np.bincount(pr[up], minlength=n))))
    ucol, up_ = pc[up].tolist(), uptr.tolist()
    struct: list[set] = [None] * n  # type: ignore[list-item]
    for j in range(n):
        s = set(ucol[up_[j]:up_[j + 1]])
        for c in children[j]:
            s |= struct[c]
        s.discard(j)
        struct[j] = s
    return struct


# CHOLMOD-style amalgamation ``(max_cols, max_zero_fraction)``: a column joins its child supernode when a rule
# allows the merged size and fraction of explicit zeros (merging more than CHOLMOD: each front has a fixed cost)
_RELAX = ((2, 1.0), (6, 0.8), (16, 0.2), (10 ** 9, 0.05))


def _relaxed_supernodes(n: int, parent: list, struct: list) -> list:
    """First columns of the relaxed supernodes (:data:`_RELAX`), runs of consecutive columns along etree
    chains (then ``n``)."""
    first = [0] if n else []  # no variables (every pose fixed): no supernode
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
            if any(nc <= mc and frac <= mz for mc, mz in _RELAX):
                zeros = nz
                continue
        first.append(j)
        zeros = 0
    first.append(n)
    return first


def _supernode_tree(pattern) -> _Tree:
    """Ordering, elimination tree, column structures, relaxed supernodes and their level schedule, and the
    final group-major numbering of the columns."""
    n = pattern.num_vars
    bptr, bcol = _block_graph(pattern)
    # the elimination tree in the minimum-degree order, then postordered (order: position -> variable)
    order = _mmd_order(n, bptr, bcol)
    _, pc, ptr = _permuted(bptr, bcol, order)
    parent0 = _etree(n, ptr, pc)
    post = _postorder(parent0)  # post[q] = node (in the first numbering)
    newpos = np.argsort(post)
    par0 = np.asarray(parent0, dtype=np.int64)[post]
    order, parent = order[post], np.where(par0 >= 0, newpos[par0], -1).tolist()
    pr, pc, _ = _permuted(bptr, bcol, order)
    struct = _column_structures(n, parent, pr, pc)
    first = _relaxed_supernodes(n, parent, struct)
    ns = len(first) - 1
    sn_of = np.repeat(np.arange(ns), np.diff(first))
    sn_parent = [int(sn_of[parent[first[s + 1] - 1]]) if parent[first[s + 1] - 1] >= 0 else -1
                 for s in range(ns)]
    ncols = [first[s + 1] - first[s] for s in range(ns)]
    nrows = [len(struct[first[s + 1] - 1]) for s in range(ns)]
    # supernodes of one height are independent; those of one front shape are one batch ("group")
    height = [0] * ns
    for s in range(ns):  # children come before parents (postorder)
        if sn_parent[s] >= 0:
            height[sn_parent[s]] = max(height[sn_parent[s]], height[s] + 1)
    groups: dict = {}
    for s in range(ns):
        groups.setdefault((height[s], ncols[s], nrows[s]), []).append(s)
    group_list = sorted(groups.items())
    # relabel the columns so that every group is one contiguous run (height-major is topological: same fill)
    gorder = np.fromiter(itertools.chain.from_iterable(sns for _, sns in group_list), dtype=np.int64, count=ns)
    nc = np.asarray(ncols, dtype=np.int64)
    nf = np.empty(ns, dtype=np.int64)  # new first column of each supernode
    nf[gorder] = np.cumsum(nc[gorder]) - nc[gorder]
    lab = np.repeat(nf - np.asarray(first[:-1], dtype=np.int64), nc) + np.arange(n)
    final = np.empty(n, dtype=np.int64)
    final[lab] = order
    return _Tree(final, lab, first, ncols, nrows, group_list, nf, struct)


class _Layout:
    """Where each supernode's front lives: its row structure ``R_s`` (new labels, sorted) and its panel's
    offset in the factor's buffer; :meth:`local` places a block row in a front."""

    def __init__(self, tree: _Tree, k: int):
        n, ns = tree.order.shape[0], len(tree.ncols)
        self.n, self.k = n, k
        self.nrows = np.asarray(tree.nrows, dtype=np.int64)
        self.ncols = np.asarray(tree.ncols, dtype=np.int64)
        self.nf = tree.nf
        # row structures R_s, concatenated
        self.roff = np.concatenate(([0], np.cumsum(self.nrows)))
        seg = np.repeat(np.arange(ns), self.nrows)
        first = tree.first
        rcat = tree.lab[np.fromiter(itertools.chain.from_iterable(tree.struct[first[s + 1] - 1] for s in range(ns)),
                                    dtype=np.int64, count=int(self.roff[-1]))]
        self.rcat = rcat[np.lexsort((rcat, seg))]
        self.rkeys = seg * n + self.rcat  # sorted: (supernode, row)
        # a group's panels one after the other (m x p row-major each, F11 above F21): a (B, m, p) view
        self.off = np.zeros(ns, dtype=np.int64)
        pos = 0
        for (_, c, r), sns in tree.groups:
            self.off[sns] = pos + k * k * (c + r) * c * np.arange(len(sns))
            pos += k * k * (c + r) * c * len(sns)
        self.buffer_size = int(pos)
        # the supernode owning each final column
        by_first = np.argsort(self.nf)
        self.owner = np.repeat(np.arange(ns)[by_first], self.ncols[by_first])

    def local(self, sn: np.ndarray, blk: np.ndarray) -> np.ndarray:
        """Position of block ``blk`` in the front of supernode ``sn`` (its columns, then R_sn)."""
        inside = blk < self.nf[sn] + self.ncols[sn]
        pos_r = np.searchsorted(self.rkeys, sn * self.n + blk) - self.roff[sn]
        return np.where(inside, blk - self.nf[sn], self.ncols[sn] + pos_r)


def _gather_map(pattern, tree: _Tree, lay: _Layout):
    """``(src, dst)``: run indices (runs of ``k`` values, one row of a ``k x k`` block) moving H's block-major
    values to the panels. Entry ``(row, col)``, ``row >= col`` (new labels), belongs to the panel of col's
    supernode at local ``(row, col)``."""
    k, nb = lay.k, pattern.num_blocks
    iperm = np.argsort(tree.order)  # variable -> position
    bpos = np.arange(nb * k * k, dtype=np.int64).reshape(nb, k, k)  # block-major value positions
    prow, pcol = iperm[pattern.block_rows.cpu().numpy()], iperm[pattern.block_cols.cpu().numpy()]
    keep = np.nonzero(prow >= pcol)[0]
    prow, pcol, bpos = prow[keep], pcol[keep], bpos[keep]
    sn_blk = lay.owner[pcol]
    lr = lay.local(sn_blk, prow)
    lc = pcol - lay.nf[sn_blk]
    p_blk = k * lay.ncols[sn_blk]  # row stride of the panel
    ar = np.arange(k)
    dst = lay.off[sn_blk][:, None] + (lr[:, None] * k + ar) * p_blk[:, None] + lc[:, None] * k
    return bpos[:, :, 0].reshape(-1) // k, dst.reshape(-1) // k


# supernodes of one height and one front shape (p pivots, m rows), factored as one batch: B = size of them, their
# scalar rows (B d,) and update positions (B d (d + 1) / 2,) int32
_Group = collections.namedtuple("_Group", "size p m offset col0 rows upd")


def _factor_groups(tree: _Tree, lay: _Layout) -> list:
    """The :class:`_Group` objects: per batch its scalar rows (for the solves) and the int32 positions its
    updates go to, made for all supernodes at once in group order."""
    k, ns = lay.k, len(tree.ncols)
    ar = np.arange(k)
    gorder = np.fromiter(itertools.chain.from_iterable(sns for _, sns in tree.groups), dtype=np.int64, count=ns)
    glen = lay.nrows[gorder]
    gstart = np.concatenate(([0], np.cumsum(glen)))
    at = np.repeat(lay.roff[gorder] - gstart[:-1], glen) + np.arange(int(gstart[-1]))
    rows_all = (lay.rcat[at][:, None] * k + ar).reshape(-1)  # block rows -> scalar rows
    gstart *= k
    # per block pair (alpha >= beta) of R_s: where its entry (alpha k, beta k) lands (``base``, in the panel
    # of the owner of column block beta) and that panel's row stride ``pt`` (see _update_positions)
    npair = glen * (glen + 1) // 2
    pstart = np.concatenate(([0], np.cumsum(npair)))
    AL, BE = np.tril_indices(int(glen.max()) if ns else 0)
    q = np.arange(int(pstart[-1])) - np.repeat(pstart[:-1], npair)
    s_pair = np.repeat(gorder, npair)
    a_blk = lay.rcat[lay.roff[s_pair] + AL[q]]
    b_blk = lay.rcat[lay.roff[s_pair] + BE[q]]
    own = lay.owner[b_blk]
    pair_pt = k * lay.ncols[own]
    pair_base = lay.off[own] + lay.local(own, a_blk) * k * pair_pt + (b_blk - lay.nf[own]) * k
    # the update positions of all the groups with the same number of rows r in one call, then split per group
    sizes = np.array([len(sns) for _, sns in tree.groups], dtype=np.int64)
    i0s = np.concatenate(([0], np.cumsum(sizes)))
    by_r: dict = {}
    for gi, ((_, _, r), _) in enumerate(tree.groups):
        if r:
            by_r.setdefault(r, []).append(gi)
    upd_of = {}
    for r, gis in by_r.items():
        sel = np.concatenate([np.arange(pstart[i0s[gi]], pstart[i0s[gi + 1]]) for gi in gis])
        npr = r * (r + 1) // 2
        upd = _update_positions(pair_base[sel].reshape(-1, npr), pair_pt[sel].reshape(-1, npr), k * r, k)
        nl = k * r * (k * r + 1) // 2
        cuts = np.cumsum(sizes[gis]) * nl
        upd_of.update(zip(gis, np.split(upd, cuts[:-1])))
    groups = []
    for gi, ((_, c, r), sns) in enumerate(tree.groups):
        p, m = k * c, k * (c + r)
        B, i0 = len(sns), i0s[gi]
        if r:
            rows, upd = rows_all[gstart[i0]:gstart[i0 + B]], upd_of[gi]
        else:
            rows, upd = _EMPTY, _EMPTY.astype(np.int32)
        groups.append(_Group(B, p, m, int(lay.off[sns[0]]), int(k * tree.nf[sns[0]]), rows, upd))
    return groups


class SymbolicCholesky:
    """Symbolic analysis of a :class:`~slam.graph.linear.BlockPattern`.

    Args:
        pattern: the block pattern of the SPD matrix.
    """

    def __init__(self, pattern):
        n, k = pattern.num_vars, pattern.k
        self.n, self.k, self.size = n, k, n * k
        tree = _supernode_tree(pattern)
        lay = _Layout(tree, k)
        if lay.buffer_size >= 2 ** 31:
            raise ValueError(f"the factor has {lay.buffer_size} entries: more than int32 positions address")
        self.src, self.dst = _gather_map(pattern, tree, lay)
        self.groups = _factor_groups(tree, lay)
        self.order = tree.order  # position -> original block variable
        self.num_supernodes = len(tree.ncols)
        self.p = [k * c for c in tree.ncols]
        self.m = [k * (c + r) for c, r in zip(tree.ncols, tree.nrows)]
        self.buffer_size = lay.buffer_size
        self.perm_scalar = (self.order[:, None] * k + np.arange(k)).reshape(-1)  # permuted scalar -> original
        # the diagonal entries of every pivot block in the panel buffer (a panel is m x p, row-major)
        pw = np.asarray(self.p, dtype=np.int64)
        within = np.arange(int(pw.sum())) - np.repeat(np.cumsum(pw) - pw, pw)  # i = 0 .. p - 1 per supernode
        self.diag = np.repeat(lay.off, pw) + within * (np.repeat(pw, pw) + 1)
        self.nnz_L = int(sum(p * (p + 1) // 2 + (m - p) * p for p, m in zip(self.p, self.m)))
        self._torch_cache = {}

    def workspace(self, device) -> _Workspace:
        """The :class:`_Workspace` on ``device`` (made once)."""
        key = str(device)
        if key not in self._torch_cache:
            self._torch_cache[key] = _Workspace(self, device)
        return self._torch_cache[key]

    def factor(self, values) -> NumericCholesky:
        """Numeric factorisation for the values ``(nnz,)`` (torch tensor or numpy array) of the pattern;
        raises :class:`NotPositiveDefiniteError` when a pivot block is not positive definite."""
        return NumericCholesky(self, values)


def _rfp_rows_cols(d: int):
    """Rows ``a`` and columns ``b`` (``a >= b``) of the ``d (d + 1) / 2`` entries of the lower triangle of a
    row-major ``d x d`` matrix in LAPACK's rectangular full packed order (``transr='N'``, ``uplo='U'`` of the
    Fortran view): the order ``dsfrk`` writes an update in (LAPACK Working Note 199)."""
    h = d // 2
    r = np.arange(d + 1 - d % 2)[:, None]
    c = np.arange(d - h)[None, :]
    top = r <= h + c
    a = np.where(top, h + c, r - h - 1)
    b = np.where(top, r, c)
    return a.T.reshape(-1), b.T.reshape(-1)  # Fortran order: column by column


def _rfp_order(d: int) -> np.ndarray:
    """Flat row-major positions ``a d + b`` of the packed lower triangle (:func:`_rfp_rows_cols`)."""
    a, b = _rfp_rows_cols(d)
    return a * d + b


@functools.lru_cache(maxsize=512)
def _packed_pairs(d: int, k: int):
    """Per entry of the packed lower triangle of a ``d x d`` update (:func:`_rfp_rows_cols`) its block pair
    (row-major lower: ``alpha (alpha + 1) / 2 + beta``) and its row and column inside the ``k x k`` block."""
    a, b = _rfp_rows_cols(d)
    pair, ia, ib = (a // k) * (a // k + 1) // 2 + b // k, (a % k).astype(np.int32), (b % k).astype(np.int32)
    for x in (pair, ia, ib):
        x.flags.writeable = False
    return pair, ia, ib


def _update_positions(base: np.ndarray, pt: np.ndarray, d: int, k: int) -> np.ndarray:
    """Where the update ``L21 L21^T`` of each supernode of a group lands in the panel buffer: ``(B d (d + 1)
    / 2,)`` int32 positions, per supernode in the packed order of :func:`_rfp_rows_cols`.

    Update entry ``(a, b)``, ``a >= b`` (rows of the supernode's structure ``R_s``) belongs to the panel of
    the supernode owning column ``b``, at its row ``a``. ``base, pt (B, npairs)`` give, per lower block pair
    (row-major), the position of its first entry and the owner's row stride.
    """
    pair, ia, ib = _packed_pairs(d, k)
    out = base.astype(np.int32)[:, pair]  # int32 throughout (the layout checks the buffer fits)
    out += ia * pt.astype(np.int32)[:, pair]
    out += ib
    return out.reshape(-1)


# On the CPU, groups of at most this many fronts go front by front through LAPACK (a few us a call) rather
# than batched torch calls (10-20 us each whatever the batch size)
_NUMPY_MAX_BATCH = 16


def _group_views(sym: SymbolicCholesky, buf, device, cpu: bool, scratch=None, index=None):
    """Per-group views of the panel buffer ``buf`` (torch, flat): :class:`_NumpyGroup` objects for the
    groups factored front by front (``cpu``), tuples for the batched ones. ``index``: the index tensors
    already made for another buffer of the same pattern."""
    def t(a):
        return torch.from_numpy(np.ascontiguousarray(a)).to(device)

    bufnp = buf.numpy() if cpu else None
    out, idx = [], []
    for g in sym.groups:
        B, p, m = g.size, g.p, g.m
        d = m - p
        nl = d * (d + 1) // 2  # entries of one packed update
        if cpu and B <= _NUMPY_MAX_BATCH:  # front by front: see _NUMPY_MAX_BATCH
            for b in range(B):
                o = g.offset + b * m * p
                panel = bufnp[o:o + m * p].reshape(m, p)
                if index is None:
                    idx.append((g.rows[b * d:(b + 1) * d], None, t(g.upd[b * nl:(b + 1) * nl])) if d
                               else (None, None, None))
                rows, _, dst = (index or idx)[len(out)]
                S = scratch[:nl]
                out.append(_NumpyGroup(p, d, panel[:p], panel[p:], g.col0 + b * p, rows, dst, S,
                                       torch.from_numpy(S) if d else None))
            continue
        panels = buf[g.offset:g.offset + B * m * p].view(B, m, p)
        if index is None:
            idx.append((t(g.rows), t(_rfp_order(d)), t(g.upd)) if d else (None, None, None))
        rows, packed, dst = (index or idx)[len(out)]
        out.append((B, p, d, panels[:, :p], panels[:, p:], g.col0, rows, packed, dst))
    return out, (index or idx)


class _Workspace:
    """Per-device state of a :class:`SymbolicCholesky`: index tensors, the panel buffer the factor is
    computed in, the permuted right-hand side, and views into both for every group."""

    def __init__(self, sym: SymbolicCholesky, device):
        self.lock = threading.Lock()  # the buffers are shared by the factorisations of this pattern
        self.owner = None  # weak reference to the NumericCholesky whose factor is in ``buf``
        self.src = torch.from_numpy(sym.src).to(device)  # H's values go to the panels in runs of k
        self.dst = torch.from_numpy(sym.dst).to(device)
        self.perm = torch.from_numpy(sym.perm_scalar).to(device)
        self.device = torch.device(device)
        self.cpu = self.device.type == "cpu"
        self.buf = torch.zeros(sym.buffer_size, dtype=torch.float64, device=device)
        self.y = torch.zeros(sym.size, dtype=torch.float64, device=device)
        self.ynp = self.y.numpy() if self.cpu else None
        self.bufnp = self.buf.numpy() if self.cpu else None
        # the packed update of a front-by-front supernode: one scratch vector, as large as the largest one
        d_max = max([g.m - g.p for g in sym.groups if g.size <= _NUMPY_MAX_BATCH] + [0])
        self.scratch = np.zeros(d_max * (d_max + 1) // 2) if self.cpu else None
        # H's rows on their way to the panels (kept: a fresh array costs its page faults each time)
        self.rows = np.empty(sym.src.shape[0], dtype=np.dtype((np.void, 8 * sym.k))) if self.cpu else None
        self.groups, self.index = _group_views(sym, self.buf, device, self.cpu, self.scratch)


_IN_PLACE = {}


def _lapack():
    """scipy's ``(dpotrf, dtrsm, dsfrk, dtrsv)`` (imported here: scipy.linalg takes ~0.4 s to import) and whether
    they write into their Fortran-contiguous argument with ``overwrite_*=1`` (f2py does; checked once)."""
    from scipy.linalg.blas import dtrsm, dtrsv
    from scipy.linalg.lapack import dpotrf, dsfrk

    if "all" not in _IN_PLACE:
        a = np.array([[4.0, 0.0], [2.0, 5.0]]).T  # Fortran, upper triangle [[4, 2], [., 5]]
        dpotrf(a, lower=0, clean=0, overwrite_a=1)
        b = np.ones((2, 1), order="F")
        dtrsm(1.0, a, b, side=0, lower=0, trans_a=1, overwrite_b=1)
        c = np.zeros(1)
        dsfrk(1, 1, 1.0, np.ones((1, 1), order="F"), 0.0, c, transr="N", uplo="U", trans="T", overwrite_c=1)
        x = np.ones(1)
        dtrsv(np.full((1, 1), 2.0, order="F"), x, overwrite_x=1)
        _IN_PLACE["all"] = bool(a[0, 0] == 2.0 and b[0, 0] == 0.5 and c[0] == 1.0 and x[0] == 0.5)
    return (dpotrf, dtrsm, dsfrk, dtrsv), _IN_PLACE["all"]


class _NumpyGroup:
    """A supernode factored front by front on the CPU: numpy views of its panel, its index tensors and
    the scratch vector of its packed update."""

    __slots__ = ("F11", "F21", "S", "S_t", "c0", "c1", "d", "dst", "p", "rows")

    def __init__(self, p, d, F11, F21, c0, rows, dst, S, S_t):
        self.p, self.d, self.F11, self.F21 = p, d, F11, F21
        self.c0, self.c1, self.rows, self.dst = c0, c0 + p, rows, dst
        # the scratch as numpy and as a torch view of the same memory
        self.S, self.S_t = S, S_t


def _factor_numpy_group(grp: _NumpyGroup, buf, in_place: bool, dpotrf, dtrsm, dsfrk) -> int:
    """Factor one supernode in place in its panel (LAPACK on the Fortran views: a row-major ``F11`` is
    the Fortran ``F11^T``) and add its update to the panels that own its columns; returns LAPACK's ``info``.
    """
    # positional arguments: f2py parses keywords at ~0.4 us each
    X = grp.F11.T  # upper: U = L^T
    U, info = dpotrf(X, 0, 0, 1)  # lower=0, clean=0, overwrite_a=1
    if not in_place:
        X[...] = U
    if grp.d and not info:
        Y = grp.F21.T  # (p, d) Fortran: F21^T, becomes L21^T = L^-1 F21^T
        Z = dtrsm(1.0, X, Y, 0, 0, 1, 0, 1)  # side=0, lower=0, trans_a=1, diag=0, overwrite_b=1
        if not in_place:
            Y[...] = Z
        # -L21 L21^T, its lower triangle only and packed, then into the panels
        V = dsfrk(grp.d, grp.p, -1.0, Y, 0.0, grp.S, "N", "U", "T", 1)  # transr, uplo, trans, overwrite_c
        if not in_place:
            grp.S[...] = V
        buf.index_add_(0, grp.dst, grp.S_t)
    return info


class NumericCholesky:
    """``P H P^T = L L^T`` stored per group as batched dense panels; :meth:`solve` applies ``H^-1``.

    Works on float64 torch tensors on the device of ``values`` (numpy arrays too). The factor lives in
    its pattern's workspace buffer, which the next factorisation reuses: if this object is still referenced
    then, it first moves to a copy of the buffer (so both factors stay valid).
    """

    def __init__(self, sym: SymbolicCholesky, values):
        self.sym = sym
        v = torch.from_numpy(values) if isinstance(values, np.ndarray) else values
        # detached: the workspace buffer is shared by every factorisation of the pattern, and in-place ops
        # from a tensor that requires grad would make it require grad (its numpy views then fail)
        v = v.detach().to(torch.float64)
        ws = self.ws = sym.workspace(v.device)
        infos = []
        with ws.lock:
            prev = ws.owner() if ws.owner is not None else None
            if prev is not None:
                prev._detach()
            # no owner until this factor has succeeded (an exception or a failed pivot leaves none to move)
            ws.owner = None
            buf = ws.buf
            k = sym.k
            lapack, in_place = _lapack()
            buf.zero_()
            if ws.cpu:
                # rows of k values as k * 8-byte records: numpy's take and put copy them whole
                rows = np.take(v.contiguous().numpy().view(ws.rows.dtype), sym.src, out=ws.rows)
                np.put(ws.bufnp.view(ws.rows.dtype), sym.dst, rows)
            else:
                buf.view(-1, k).index_copy_(0, ws.dst, torch.index_select(v.reshape(-1, k), 0, ws.src))
            failed = self._factor_groups(ws.groups, buf, infos, in_place, lapack)
            failed = failed or bool(infos and bool(torch.cat(infos).any()))
            # OpenBLAS's dpotrf does not test for NaN: a NaN or an infinity in the input reaches a pivot
            if not failed and ws.cpu and not np.isfinite(np.take(ws.bufnp, sym.diag)).all():
                failed = True
            # set before the lock is released: another thread may detach this factor once it is the owner
            self.buf, self.groups = buf, ws.groups
            if not failed:
                ws.owner = weakref.ref(self)
        if failed:
            raise NotPositiveDefiniteError("the matrix is not positive definite (a pivot block failed)")

    @staticmethod
    def _factor_groups(groups, buf, infos, in_place: bool, lapack) -> bool:
        """Factor the groups through LAPACK (front by front) or torch (batched); True when a pivot failed
        on the LAPACK path (the torch path's infos are collected in ``infos``)."""
        for grp in groups:
            if type(grp) is _NumpyGroup:
                if _factor_numpy_group(grp, buf, in_place, *lapack[:3]) != 0:
                    return True
                continue
            B, _, d, F11, F21, _, _, packed, dst = grp
            L11, info = torch.linalg.cholesky_ex(F11)
            infos.append(info)
            F11.copy_(L11)
            if d:
                L21 = torch.linalg.solve_triangular(L11.mT, F21, upper=True, left=False)
                F21.copy_(L21)
                # the lower triangles of the (B, d, d) updates, packed as dsfrk would, to the panels
                U = torch.bmm(L21, L21.mT).view(B, d * d).index_select(1, packed)
                buf.index_add_(0, dst, U.view(-1), alpha=-1.0)
        return False

    def _detach(self) -> None:
        """Move this factor to a private copy of the buffer (called before the workspace is reused)."""
        ws = self.ws
        self.buf = ws.buf.clone()
        self.groups, _ = _group_views(self.sym, self.buf, ws.device, ws.cpu, ws.scratch, ws.index)

    def solve(self, b):
        """``x = H^-1 b`` for ``b (n k,)`` (numpy array or torch tensor; returns the same kind)."""
        is_np = isinstance(b, np.ndarray)
        bt = torch.from_numpy(b) if is_np else b
        ws = self.ws
        (_, _, _, dtrsv), in_place = _lapack()
        with ws.lock:
            y, ynp = ws.y, ws.ynp
            torch.index_select(bt.detach().to(torch.float64), 0, ws.perm, out=y)
            self._forward(self.groups, y, ynp, in_place, dtrsv)
            self._backward(self.groups, y, ynp, in_place, dtrsv)
            x = torch.empty_like(y)
            x[ws.perm] = y
        return x.numpy() if is_np else x.to(bt.dtype)

    @staticmethod
    def _forward(groups, y, ynp, in_place: bool, dtrsv) -> None:
        """``L z = y`` on the groups' columns of ``y`` (LAPACK front by front, or torch batched)."""
        for grp in groups:
            if type(grp) is _NumpyGroup:
                # L z = y as U^T z = y on the Fortran view (in place on the contiguous slice)
                # incx, offx, lower=0, trans=1, diag, overwrite_x=1 (positional: see _factor_numpy_group)
                z = dtrsv(grp.F11.T, ynp[grp.c0:grp.c1], 1, 0, 0, 1, 0, 1)
                if not in_place:
                    ynp[grp.c0:grp.c1] = z
                if grp.d:
                    ynp[grp.rows] -= grp.F21 @ z
                continue
            B, p, d, L11, L21, c0, rows, _, _ = grp
            yc = y[c0:c0 + B * p].view(B, p, 1)
            yc.copy_(torch.linalg.solve_triangular(L11, yc, upper=False))
            if d:
                y.index_add_(0, rows, (L21 @ yc).view(-1), alpha=-1.0)

    @staticmethod
    def _backward(groups, y, ynp, in_place: bool, dtrsv) -> None:
        """``L^T x = z`` on the groups' columns of ``y``, the groups in reverse order."""
        for grp in reversed(groups):
            if type(grp) is _NumpyGroup:
                yc = ynp[grp.c0:grp.c1]
                if grp.d:
                    yc -= grp.F21.T @ ynp[grp.rows]
                z = dtrsv(grp.F11.T, yc, 1, 0, 0, 0, 0, 1)  # incx, offx, lower=0, trans=0, diag, overwrite_x=1
                if not in_place:
                    yc[...] = z
                continue
            B, p, d, L11, L21, c0, rows, _, _ = grp
            yc = y[c0:c0 + B * p].view(B, p, 1)
            rhs = yc
            if d:
                rhs = torch.baddbmm(yc, L21.mT, y[rows].view(B, d, 1), alpha=-1.0)
            yc.copy_(torch.linalg.solve_triangular(L11.mT, rhs, upper=True))
