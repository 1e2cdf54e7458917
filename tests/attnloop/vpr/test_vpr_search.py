"""attnloop.vpr.search: one index per row range, searched and merged, answers as one index does."""
from __future__ import annotations

import numpy as np
import pytest

from attnloop.index import IndexConfig
from attnloop.vpr.search import ShardedIndex, rows_that_fit


def test_sharded_exact_index_returns_the_brute_force_top_k(tmp_path):
    rng = np.random.default_rng(0)
    x = rng.standard_normal((1000, 16)).astype(np.float32)
    x[700] = x[3]  # a duplicate in another shard: the tie goes to the lower id, as in one index
    x /= np.linalg.norm(x, axis=1, keepdims=True)
    q = np.concatenate([x[[3]], rng.standard_normal((20, 16)).astype(np.float32)])
    index = ShardedIndex.build(x, IndexConfig(backend="exact", background=False), max_rows=300)
    assert len(index.indexes) == 4
    ids, sims = index.search(q, k=10)
    qn = q / np.linalg.norm(q, axis=1, keepdims=True)
    brute = np.argsort(-(qn.astype(np.float64) @ x.T.astype(np.float64)), axis=1, kind="stable")[:, :10]
    np.testing.assert_array_equal(ids.numpy(), brute)
    assert ids[0, :2].tolist() == [3, 700]
    np.testing.assert_allclose(sims.numpy(), np.take_along_axis(qn @ x.T, brute, 1), atol=1e-6)
    index.save(tmp_path)
    np.testing.assert_array_equal(ShardedIndex.load(tmp_path).search(q, k=10)[0].numpy(), brute)


def test_rows_that_fit_counts_rows_and_the_structure():
    gib = 2 ** 30
    # half of 8 GiB in 2560-d float32 rows (10 KiB each): 419430 rows; a 128-d code + links add 1 KiB a row
    assert rows_that_fit(2560, IndexConfig(backend="exact"), memory=8 * gib) == 4 * gib // 10240
    assert rows_that_fit(2560, IndexConfig(backend="faiss"), memory=8 * gib) == 4 * gib // (10240 + 1024)


def test_nothing_to_index_is_refused():
    with pytest.raises(ValueError, match=r"shape \(N, D\) with N >= 1, got \(0, 8\)"):
        ShardedIndex.build(np.zeros((0, 8), np.float32))
    with pytest.raises(ValueError, match="at least one index"):
        ShardedIndex([])
