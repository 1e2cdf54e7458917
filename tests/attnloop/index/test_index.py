"""Tests of attnloop.index (keyframe database, loop-candidate detector) and attnloop.threshold."""
from __future__ import annotations

import json

import numpy as np
import pytest
import torch
from helpers import unit_rows

from attnloop.index import (
    FaissConfig,
    FlannConfig,
    IndexConfig,
    IndexFileError,
    KeyframeIndex,
    LoopCandidateDetector,
    LoopDetectorConfig,
    exact_search,
    faiss_available,
    fit_pca,
    load_index,
    resolve_backend,
)
from attnloop.index.config import config_from_dict, config_to_dict
from attnloop.threshold import ThresholdConfig, accept_mask, adaptive_threshold


def _unit(x: torch.Tensor) -> torch.Tensor:
    return x / x.norm(dim=-1, keepdim=True)


random_data = unit_rows


def clustered_data(n: int, d: int, clusters: int = 40, spread: float = 0.5, seed: int = 0) -> torch.Tensor:
    """Points around ``clusters`` random centres: like keyframes of a few places seen many times."""
    g = torch.Generator().manual_seed(seed)
    centres = _unit(torch.randn(clusters, d, generator=g))
    labels = torch.randint(0, clusters, (n,), generator=g)
    return _unit(centres[labels] + spread * _unit(torch.randn(n, d, generator=g)))


def brute(db: torch.Tensor, q: torch.Tensor, k: int, max_id: int | None = None):
    """Reference over rows 0..max_id (ids = rows)."""
    m = db.shape[0] if max_id is None else max(0, min(db.shape[0], max_id + 1))
    if m == 0:
        return torch.zeros(0, dtype=torch.long), torch.zeros(0)
    rows, sims = exact_search(db[:m], q[None], k)
    return rows[0], sims[0]


def tree_config(flann: dict | None = None, **kw) -> IndexConfig:
    """FLANN on the full descriptors, exhaustive tree search (exact), synchronous builds."""
    f = {"rebuild_every": 128, "rebuild_fraction": 0.25, "checks": -1}
    f.update(flann or {})
    base = {"backend": "flann", "exact_below": 256, "reduce_dim": None, "background": False, "flann": FlannConfig(**f)}
    base.update(kw)
    return IndexConfig(**base)


# ------------------------------------------------------------------ exact reference
def test_exact_search_matches_sort():
    db = random_data(50, 8)
    q = random_data(3, 8, seed=1)
    rows, sims = exact_search(db, q, 5)
    full = q @ db.t()
    ref = torch.argsort(full, dim=1, descending=True)[:, :5]
    assert torch.equal(rows, ref)
    torch.testing.assert_close(sims, full.gather(1, ref))


# ------------------------------------------------------------------ index == exact search
@pytest.mark.parametrize("kind", ["random", "clustered"])
def test_index_equals_exact_search(kind):
    d = 64
    db = random_data(3000, d) if kind == "random" else clustered_data(3000, d)
    index = KeyframeIndex(tree_config())
    for start in range(0, 3000, 500):  # grows through several rebuilds, leaving an exact tail
        index.add(db[start: start + 500])
    assert index.num_builds >= 2 and 0 < index.n_indexed < len(index) == 3000  # tree + tail both used
    queries = (random_data(20, d, seed=7) if kind == "random"
               else _unit(db[torch.arange(0, 3000, 150)] + 0.1 * random_data(20, d, seed=7)))
    for i, q in enumerate(queries):
        for max_id in (None, 2999 - i, index.n_indexed - 3, index.n_indexed + 40, 100):
            ids, sims = index.search(q, k=10, max_id=max_id)
            ref_ids, ref_sims = brute(db, q, 10, max_id)
            assert torch.equal(ids, ref_ids), (i, max_id)
            torch.testing.assert_close(sims, ref_sims, atol=1e-6, rtol=0)


def test_exact_backend_builds_no_structure_and_matches():
    db = random_data(1000, 32)
    index = KeyframeIndex(IndexConfig(backend="exact", exact_below=10))
    index.add(db)
    assert index.n_indexed == 0 and index.num_builds == 0
    q = random_data(1, 32, seed=3)[0]
    ids, sims = index.search(q, k=7)
    ref_ids, ref_sims = brute(db, q, 7)
    assert torch.equal(ids, ref_ids)
    torch.testing.assert_close(sims, ref_sims)


def test_default_checks_recall_on_clustered_data():
    # FLANN with its default checks (and the default PCA code, here a rotation of the 128 dimensions):
    # recall@10 on clustered data stays high (stated bound).
    d = 128
    db = clustered_data(4000, d, clusters=60, spread=0.6, seed=2)
    index = KeyframeIndex(IndexConfig(backend="flann", exact_below=1000, background=False))
    index.add(db)
    index.rebuild()
    assert index.n_indexed == 4000
    queries = _unit(db[torch.arange(0, 4000, 40)] + 0.3 * random_data(100, d, seed=5))
    ids, _ = index.search(queries, k=10)
    ref, _ = exact_search(db, queries, 10)
    recall = np.mean([len(set(a.tolist()) & set(b.tolist())) / 10 for a, b in zip(ids, ref)])
    assert recall >= 0.95, recall


# ------------------------------------------------------------------ growth
def test_rebuild_keeps_answers_equal():
    db = clustered_data(1500, 32, seed=4)
    index = KeyframeIndex(tree_config(flann={"rebuild_every": 10_000}))  # no automatic rebuild
    index.add(db[:600])
    index.rebuild()
    index.add(db[600:])
    before_n = index.n_indexed
    assert before_n == 600
    queries = random_data(10, 32, seed=9)
    before = [index.search(q, k=8, max_id=1200) for q in queries]
    index.rebuild()
    assert index.n_indexed == 1500 > before_n
    for q, (ids0, sims0) in zip(queries, before):
        ids1, sims1 = index.search(q, k=8, max_id=1200)
        assert torch.equal(ids0, ids1)
        torch.testing.assert_close(sims0, sims1)


def test_tail_is_searched():
    db = random_data(600, 32)
    index = KeyframeIndex(tree_config(flann={"rebuild_every": 10_000}))
    index.add(db)
    index.rebuild()
    assert index.n_indexed == 600
    target = random_data(1, 32, seed=11)[0]
    index.add(target[None], ids=[1000])
    assert index.n_indexed == 600 and len(index) == 601
    ids, sims = index.search(target, k=3)
    assert ids[0].item() == 1000 and sims[0].item() == pytest.approx(1.0, abs=1e-6)


def test_background_build_and_buffer_growth():
    d = 48
    db = clustered_data(5000, d, seed=6)
    index = KeyframeIndex(tree_config(background=True, exact_below=512, flann={"rebuild_every": 256}))
    q = db[123]
    for start in range(0, 5000, 100):
        index.add(db[start: start + 100], ids=torch.arange(start, start + 100) * 2)  # ids 0, 2, 4, ...
        # Whatever the state of the background build, answers stay exact.
        ids, _ = index.search(q, k=5)
        ref, _ = brute(db[: start + 100], q, 5)
        assert torch.equal(ids, ref * 2)
    index.wait()
    # How many builds overlapped the adds depends on timing; at least the first one finished.
    assert not index.building and index.num_builds >= 1 and index.n_indexed >= 512
    index.rebuild()
    assert index.n_indexed == 5000
    ids, _ = index.search(q, k=5, max_id=2 * 3000)
    ref, _ = brute(db, q, 5, 3000)
    assert torch.equal(ids, ref * 2)


def test_same_seed_same_tree():
    db = random_data(2000, 32, seed=12)
    q = random_data(30, 32, seed=13)
    results = []
    for _ in range(2):
        index = KeyframeIndex(IndexConfig(backend="flann", exact_below=100, background=False,
                                          flann=FlannConfig(checks=16)))
        index.add(db)
        index.rebuild()
        results.append(index.search(q, k=5)[0])
    assert torch.equal(results[0], results[1])


# ------------------------------------------------------------------ exclusion window, batches, edges
def test_exclusion_window_and_batch_padding():
    db = random_data(400, 16)
    index = KeyframeIndex(tree_config(exact_below=200))
    index.add(db, ids=torch.arange(400) + 100)  # ids 100..499
    q = db[[350, 10, 200]]
    ids, sims = index.search(q, k=4, max_id=torch.tensor([430, 102, 99]))
    assert ids.shape == (3, 4) and sims.shape == (3, 4)
    assert (ids[0] <= 430).all() and 450 not in ids[0].tolist()
    ref0, _ = brute(db, q[0], 4, 330)
    assert torch.equal(ids[0], ref0 + 100)
    assert sorted(ids[1, :3].tolist()) == [100, 101, 102] and ids[1, 3] == -1 and sims[1, 3] == -np.inf
    assert (ids[2] == -1).all() and torch.isinf(sims[2]).all()
    # Nothing eligible for a single query: empty tensors of the right shape.
    e_ids, e_sims = index.search(q[0], k=4, max_id=50)
    assert e_ids.shape == (0,) and e_sims.shape == (0,) and e_ids.dtype == torch.long
    b_ids, b_sims = index.search(q, k=4, max_id=50)
    assert b_ids.shape == (3, 0) and b_sims.shape == (3, 0)


def test_empty_index():
    index = KeyframeIndex()
    ids, sims = index.search(torch.rand(8), k=5)
    assert ids.shape == (0,) and sims.shape == (0,) and ids.dtype == torch.long
    assert index.search(torch.rand(2, 8), k=5)[0].shape == (2, 0)
    s_ids, s = index.similarities(torch.rand(8))
    assert s_ids.shape == (0,) and s.shape == (0,)
    assert len(index) == 0 and index.dim is None and index.last_id is None
    index.add(torch.rand(2, 8), ids=[4, 9])
    index.add(torch.rand(1, 8))  # the next id after the largest
    assert index.last_id == 10 and index.ids.tolist() == [4, 9, 10]


def test_errors():
    index = KeyframeIndex()
    index.add(torch.rand(5, 8))
    with pytest.raises(ValueError, match="dimension 7"):
        index.add(torch.rand(2, 7))
    with pytest.raises(ValueError, match="dimension 9"):
        index.search(torch.rand(9), k=2)
    with pytest.raises(ValueError, match="strictly increasing"):
        index.add(torch.rand(1, 8), ids=[3])
    with pytest.raises(ValueError, match="strictly increasing"):
        index.add(torch.rand(2, 8), ids=[10, 10])
    with pytest.raises(ValueError, match=r"\(D,\) or \(N, D\)"):
        index.add(torch.rand(1, 2, 8))
    with pytest.raises(ValueError, match="NaN"):
        index.add(torch.full((1, 8), float("nan")))
    with pytest.raises(ValueError, match="max_id must be"):
        index.search(torch.rand(3, 8), k=2, max_id=[1, 2])
    with pytest.raises(ValueError, match="k must be"):
        index.search(torch.rand(8), k=0)
    with pytest.raises(ValueError, match="unknown keyframe id"):
        index.rows_of([77])
    assert index.rows_of([0, 4]).tolist() == [0, 4]


def test_devices_and_dtypes_follow_query():
    index = KeyframeIndex()
    db = random_data(20, 8).double()
    index.add(db)
    ids, sims = index.search(db[3], k=2)
    assert ids.dtype == torch.long and sims.dtype == torch.float32 and ids[0].item() == 3
    assert index.descriptors.dtype == torch.float32


def test_similarities_exact_and_sampled():
    db = random_data(300, 16)
    index = KeyframeIndex(tree_config(exact_below=100))
    index.add(db, ids=torch.arange(300) * 3)
    ids, sims = index.similarities(db[5], max_id=3 * 199)
    assert torch.equal(ids, torch.arange(200) * 3)
    torch.testing.assert_close(sims, db[:200] @ db[5])
    s_ids, s_sims = index.similarities(db[5], max_samples=31)  # exactly 31 rows, from the first to the last
    rows = torch.from_numpy(np.floor(np.arange(31) * 299 / 30 + 0.5).astype(np.int64))
    assert torch.equal(s_ids, rows * 3) and s_ids[0] == 0 and s_ids[-1] == 3 * 299
    torch.testing.assert_close(s_sims, db[rows] @ db[5])


# ------------------------------------------------------------------ adaptive threshold
def test_threshold_outlier_accepted():
    g = torch.Generator().manual_seed(0)
    s = 0.6 + 0.02 * torch.randn(500, generator=g)
    s = torch.cat([s, torch.tensor([0.85])])
    mask = accept_mask(s, ThresholdConfig(k_sigma=5.0))
    assert mask.nonzero().flatten().tolist() == [500]
    # MAD threshold by hand (odd count: the medians are plain middle values): median + 5 * 1.4826 * MAD
    med = s.sort().values[250]
    mad = (s - med).abs().sort().values[250]
    torch.testing.assert_close(adaptive_threshold(s, ThresholdConfig(k_sigma=5.0)), med + 5.0 * 1.4826 * mad)
    # Even count: interpolated medians.
    e = torch.tensor([0.0, 1.0, 2.0, 10.0] * 4)  # median 1.5, |dev| = 1.5, .5, .5, 8.5 -> MAD 1.0
    expected = torch.tensor(1.5 + 2 * 1.4826)
    torch.testing.assert_close(adaptive_threshold(e, ThresholdConfig(k_sigma=2.0, min_samples=8)), expected)


def test_threshold_flat_distribution_gives_nothing():
    flat = torch.full((100,), 0.8)
    assert not accept_mask(flat).any()
    noisy = 0.8 + 1e-4 * torch.randn(100)
    assert not accept_mask(noisy).any()  # min_margin above the centre
    assert adaptive_threshold(flat, ThresholdConfig(min_margin=0.05)).item() == pytest.approx(0.85)


def test_threshold_floor_and_few_samples():
    s = torch.tensor([0.1, 0.2, 0.3, 0.4, 0.5, 0.6, 0.7, 0.8, 0.9, 1.0], dtype=torch.float64)
    cfg = ThresholdConfig(k_sigma=1.0, min_margin=0.0, min_samples=8)
    # median 0.55, |s - 0.55| has median 0.25: 0.55 + 1.4826 * 0.25
    torch.testing.assert_close(adaptive_threshold(s, cfg), torch.tensor(0.55 + 1.4826 * 0.25, dtype=torch.float64))
    floored = ThresholdConfig(k_sigma=0.0, min_margin=0.0, min_similarity=0.95, min_samples=8)
    assert adaptive_threshold(s, floored).item() == pytest.approx(0.95)
    assert adaptive_threshold(s[:7], cfg).item() == float("inf")  # fewer than min_samples
    assert adaptive_threshold(torch.zeros(0)).item() == float("inf")
    with pytest.raises(ValueError, match=r"\(N,\)"):
        adaptive_threshold(torch.rand(2, 5))


# ------------------------------------------------------------------ detector
def _trajectory(n_places: int, d: int = 256, seed: int = 0):
    """Descriptors of a walk through n_places distinct places; keyframe descriptors = place + noise."""
    g = torch.Generator().manual_seed(seed)
    places = _unit(torch.randn(n_places, d, generator=g))

    def view(p):
        return _unit(places[p] + 0.15 * _unit(torch.randn(d, generator=g)))

    return view


def test_detector_finds_revisit_outside_window_only():
    view = _trajectory(60)
    # Unrelated random places have cosine ~ N(0, 1/256); k_sigma 5 keeps chance peaks out of this test.
    strict = ThresholdConfig(k_sigma=5.0)
    det = LoopCandidateDetector(LoopDetectorConfig(window=10, top_k=3, threshold=strict))
    for i in range(60):  # first pass: no revisits
        out = det.add_and_query(view(i), keyframe_id=i, timestamp=0.1 * i)
        assert len(out) == 0, i
        assert out.ids.shape == (0,) and out.scores.shape == (0,)
    out = det.add_and_query(view(20), keyframe_id=60)  # back at place 20
    assert out.ids.tolist() == [20] and out.scores[0] > out.threshold
    assert out.top_ids.shape == (3,) and out.top_ids[0] == 20
    # The place just seen is inside the window: not a candidate.
    out = det.add_and_query(view(20), keyframe_id=61)
    assert 60 not in out.ids.tolist() and out.ids.tolist() == [20]
    assert det.index.timestamps[5].item() == pytest.approx(0.5)


def test_detector_few_keyframes_give_nothing():
    det = LoopCandidateDetector(LoopDetectorConfig(window=2))
    v = random_data(1, 16)[0]
    for i in range(33):  # eligible keyframes stay below min_samples = 32: threshold inf
        out = det.add_and_query(v, keyframe_id=i)
        assert len(out) == 0 and out.threshold == float("inf")


def test_detector_accepts_a_revisit_above_the_threshold():
    view = _trajectory(80, seed=1)
    strict = ThresholdConfig(k_sigma=5.0)
    det = LoopCandidateDetector(LoopDetectorConfig(window=10, top_k=3, threshold=strict))
    for i in range(50):
        det.add_and_query(view(i), keyframe_id=i)
    assert det.add_and_query(view(20), keyframe_id=50).ids.tolist() == [20]
    assert len(det.add_and_query(view(70), keyframe_id=51)) == 0  # a new place


def test_detector_errors():
    det = LoopCandidateDetector()
    det.add_and_query(torch.rand(8), keyframe_id=5)
    with pytest.raises(ValueError, match=r"strictly increasing; got \[5\]\.\.\. after last id 5"):
        det.add_and_query(torch.rand(8), keyframe_id=5)
    with pytest.raises(ValueError, match=r"\(D,\)"):
        det.add_and_query(torch.rand(2, 8), keyframe_id=6)
    with pytest.raises(ValueError, match="dimension"):
        det.add_and_query(torch.rand(9), keyframe_id=6)
    with pytest.raises(ValueError):
        LoopDetectorConfig(top_k=0)


# ------------------------------------------------------------------ backends: auto, faiss, PCA codes
needs_faiss = pytest.mark.skipif(not faiss_available(), reason="faiss not installed (pip install attnloop[faiss])")


def recall_at(ids: torch.Tensor, ref: torch.Tensor) -> float:
    k = ref.shape[1]
    return float(np.mean([len(set(a.tolist()) & set(b.tolist())) / k for a, b in zip(ids, ref)]))


def test_auto_backend_is_exact_below_the_size_then_a_structure(monkeypatch):
    db = clustered_data(1500, 32, seed=3)
    index = KeyframeIndex(IndexConfig(exact_below=1000, background=False))
    assert index.backend == ("faiss" if faiss_available() else "flann")
    index.add(db[:999])
    assert index.n_indexed == 0 and index.num_builds == 0
    q = _unit(db[5] + 0.1 * random_data(1, 32, seed=4)[0])
    ids, sims = index.search(q, k=10)
    ref_ids, ref_sims = brute(db[:999], q, 10)
    assert torch.equal(ids, ref_ids)
    torch.testing.assert_close(sims, ref_sims)
    index.add(db[999:])
    assert index.num_builds == 1 and index.n_indexed > 0
    # Without faiss, "auto" is the FLANN tree; asking for faiss then says how to install it.
    monkeypatch.setattr("attnloop.index.config.faiss_available", lambda: False)
    assert resolve_backend("auto") == "flann" and KeyframeIndex().backend == "flann"
    with pytest.raises(ImportError, match="attnloop\\[faiss\\]"):
        KeyframeIndex(IndexConfig(backend="faiss"))
    with pytest.raises(ValueError, match="backend"):
        IndexConfig(backend="hnsw")


@needs_faiss
@pytest.mark.parametrize("reduce_dim", [None, 32])
def test_faiss_recall_window_and_growth(reduce_dim):
    d = 128
    db = clustered_data(4000, d, clusters=100, spread=0.6, seed=2)
    cfg = IndexConfig(backend="faiss", exact_below=1000, reduce_dim=reduce_dim, background=False)
    index = KeyframeIndex(cfg)
    for start in range(0, 4000, 400):
        index.add(db[start: start + 400], ids=torch.arange(start, start + 400) * 2)
        assert index.n_indexed == len(index) or len(index) < 1000  # every add extends the graph
    assert index.num_builds >= 1
    queries = _unit(db[torch.arange(0, 4000, 40)] + 0.3 * random_data(100, d, seed=5))
    for max_row in (None, 3969, 1600):  # no window, a SLAM-like window of 30 rows, a deep cut
        ids, _ = index.search(queries, k=10, max_id=None if max_row is None else 2 * max_row)
        ref, _ = exact_search(db[: (4000 if max_row is None else max_row + 1)], queries, 10)
        assert (ids % 2 == 0).all() and (max_row is None or (ids <= 2 * max_row).all())
        assert recall_at(ids // 2, ref) >= 0.95, (max_row, recall_at(ids // 2, ref))


@needs_faiss
def test_faiss_streaming_one_keyframe_at_a_time():
    # The SLAM use: query (window 30) then add, one keyframe at a time, across the exact -> graph switch.
    d = 64
    view = _trajectory(150, d=d, seed=3)
    index = KeyframeIndex(IndexConfig(backend="faiss", exact_below=300, reduce_dim=16, background=False))
    found = hits = 0
    for i in range(900):
        q = view(i % 150)
        ids, _sims = index.search(q, k=3, max_id=i - 30)
        assert (ids <= i - 30).all()
        if 0 < i - 29 < 300:  # fewer eligible rows than exact_below: a scan
            ref_ids, _ = brute(index.descriptors, _unit(q), 3, i - 30)
            assert torch.equal(ids, ref_ids)
        if i >= 300 and ids.numel():
            found += 1
            hits += int(ids[0]) % 150 == i % 150  # the same place on an earlier lap
        index.add(q, ids=[i])
    assert index.num_builds >= 1 and index.n_indexed == 900
    assert found == 600 and hits == found


def test_pca_code_identities():
    g = torch.Generator().manual_seed(0)
    basis = torch.linalg.qr(torch.randn(32, 5, generator=g))[0]  # a 5-d subspace of R^32
    x = (torch.randn(600, 5, generator=g) @ basis.t() + 0.3).numpy().astype(np.float32)
    code = fit_pca(x, dim=5)
    assert code.dim == 5 and code.kept == pytest.approx(1.0, abs=1e-5)
    np.testing.assert_allclose(code.components.T @ code.components, np.eye(5), atol=1e-5)
    z = code.encode(x[:50])
    np.testing.assert_allclose(np.linalg.norm(z[:, None] - z[None], axis=-1),  # an isometry on the data
                               np.linalg.norm(x[:50, None] - x[None, :50], axis=-1), atol=1e-4)
    # Two components of five keep the share of the two largest variances.
    x2 = (torch.randn(4000, 5, generator=g) * torch.tensor([5.0, 4.0, 1.0, 1.0, 1.0])) @ basis.t()
    two = fit_pca(x2.numpy(), dim=2)
    assert two.kept == pytest.approx(41.0 / 44.0, abs=0.01)
    # More components than the fitting rows support: only those with variance are kept.
    assert fit_pca(x[:20], dim=64).dim == 19  # 20 rows span at most 19 directions about their mean
    with pytest.raises(ValueError, match="dimension 32"):
        code.encode(np.zeros((2, 31), np.float32))


def _energy(code, x):
    """Squared norms of the rows' centred projections and of the centred rows: how much the code keeps."""
    return (code.encode(x).astype(np.float64) ** 2).sum(1), ((x - code.mean).astype(np.float64) ** 2).sum(1)


@needs_faiss
def test_faiss_code_is_refit_as_the_rows_grow():
    g = torch.Generator().manual_seed(1)
    q_all = torch.linalg.qr(torch.randn(64, 16, generator=g))[0]
    area_a, area_b = q_all[:, :8], q_all[:, 8:]  # two orthogonal 8-d subspaces: two unlike places
    a = _unit(torch.randn(600, 8, generator=g) @ area_a.t())
    b = _unit(torch.randn(600, 8, generator=g) @ area_b.t())
    for growth, builds in ((1.0, 2), (float("inf"), 1)):
        cfg = IndexConfig(backend="faiss", exact_below=500, reduce_dim=8, background=False,
                          faiss=FaissConfig(retrain_growth=growth))
        index = KeyframeIndex(cfg)
        index.add(a[:500])
        code = index._structure.code
        assert index.num_builds == 1 and code.kept > 0.99
        kept, total = _energy(code, b.numpy())
        assert kept.sum() / total.sum() < 0.2  # the second place is nearly invisible to the first fit
        index.add(a[500:])
        index.add(b[:399])
        assert index.num_builds == 1  # 999 rows: not yet twice the 500 it was fitted on
        index.add(b[399:])
        assert index.num_builds == builds, growth
        assert index.n_indexed == 1200 and index._structure.n_trained == (1200 if builds == 2 else 500)
        # After the refit the code represents the second place (8 of the 16 directions were fitted).
        kept, total = _energy(index._structure.code, b.numpy())
        assert (kept.sum() / total.sum() > 0.3) == (builds == 2)
        ids, _ = index.search(b[-1], k=1, max_id=1198)
        assert ids.numel() == 1


@needs_faiss
def test_faiss_links_reach_the_graph_and_hold_recall_among_many_places():
    # The 10^6 loss was the graph's degree (docs/scale.md): on many
    # isotropic places the same search (ef_search 10, no wider re-rank) finds more of the exact top-10
    # with more links. Measured here: m = 8 -> 0.64, m = 32 -> 0.87 (one faiss thread: a reproducible graph).
    import faiss

    db = clustered_data(6000, 64, clusters=600, spread=1.0, seed=1)
    q = _unit(db[torch.arange(0, 6000, 30)] + random_data(200, 64, seed=2))
    ref, _ = exact_search(db, q, 10)
    threads = faiss.omp_get_max_threads()
    faiss.omp_set_num_threads(1)
    try:
        recalls = {}
        for m in (8, 32):
            cfg = IndexConfig(backend="faiss", exact_below=6000, reduce_dim=None, rerank=1, background=False,
                              faiss=FaissConfig(m=m, ef_construction=40, ef_search=10))
            index = KeyframeIndex(cfg)
            index.add(db)
            assert index._structure.index.hnsw.nb_neighbors(0) == 2 * m  # the bottom layer's links
            recalls[m] = recall_at(index.search(q, k=10)[0], ref)
    finally:
        faiss.omp_set_num_threads(threads)
    assert recalls[32] >= 0.8 and recalls[32] >= recalls[8] + 0.15, recalls
    assert FaissConfig().m == 64


def test_float16_storage_halves_memory_and_scans_exactly():
    db = random_data(20000, 8, seed=21)  # more rows than one float16 chunk (16384)
    i16 = KeyframeIndex(IndexConfig(backend="exact", storage="float16"))
    i32 = KeyframeIndex(IndexConfig(backend="exact"))
    i16.add(db)
    i32.add(db)
    assert i16._store.nbytes - 16 * 20000 == (i32._store.nbytes - 16 * 20000) // 2
    rounded = db.half().float()
    q = random_data(1, 8, seed=22)[0]
    ids, sims = i16.search(q, k=5)
    ref_ids, ref_sims = brute(rounded, q, 5)
    assert torch.equal(ids, ref_ids)
    torch.testing.assert_close(sims, ref_sims, atol=1e-6, rtol=0)
    stored = i16.descriptors  # the float16 rows (normalised in float32 first: a few differ from rounded by an ulp)
    s_ids, s = i16.similarities(q, max_id=19_000)  # the scan across the float16 chunk boundary
    assert s_ids.tolist() == list(range(19_001))
    torch.testing.assert_close(s, stored[:19_001] @ q, atol=1e-6, rtol=0)
    s_ids, s = i16.similarities(q, max_id=19_000, max_samples=3000)  # exactly 3000, first to last row
    assert s_ids.tolist() == np.floor(np.arange(3000) * 19_000 / 2999 + 0.5).astype(int).tolist()
    torch.testing.assert_close(s, stored[s_ids] @ q, atol=1e-6, rtol=0)
    torch.testing.assert_close(i16.descriptors_of([3, 19_999]), rounded[[3, 19_999]])


# ------------------------------------------------------------------ persistence
def _persist_configs():
    out = [
        ("exact", IndexConfig(backend="exact")),
        ("flann+tail", tree_config(reduce_dim=16, flann={"rebuild_every": 10_000, "checks": 32})),
        ("flann-float16", tree_config(storage="float16", flann={"checks": 32})),
    ]
    if faiss_available():
        out += [("faiss", IndexConfig(backend="faiss", exact_below=256, reduce_dim=None, background=False)),
                ("faiss+pca", IndexConfig(backend="faiss", exact_below=256, reduce_dim=16,
                                          background=False))]
    return out


@pytest.mark.parametrize("name,cfg", _persist_configs(), ids=[n for n, _ in _persist_configs()])
def test_save_load_round_trip_gives_identical_answers(tmp_path, name, cfg):
    import io

    db = clustered_data(1200, 48, seed=8)
    index = KeyframeIndex(cfg)
    index.add(db[:700], ids=torch.arange(700) * 3, timestamps=torch.arange(700) * 0.5)
    if name == "flann+tail":
        index.rebuild()
    index.add(db[700:], ids=torch.arange(700, 1200) * 3)  # a tail for FLANN, graph extension for faiss
    path = tmp_path / "index.npz"
    index.save(path)
    buf = io.BytesIO()
    index.save(buf)
    buf.seek(0)
    for loaded in (KeyframeIndex.load(path), KeyframeIndex.load(buf)):
        assert loaded.backend == index.backend and loaded.config == index.config
        assert loaded.n_indexed == index.n_indexed and len(loaded) == 1200
        assert torch.equal(loaded.ids, index.ids)
        torch.testing.assert_close(loaded.timestamps, index.timestamps, equal_nan=True)
        queries = _unit(db[::60] + 0.2 * random_data(20, 48, seed=9))
        for max_id in (None, 3 * 1100, 3 * 650, 3 * 100):
            a, sa = index.search(queries, k=10, max_id=max_id)
            b, sb = loaded.search(queries, k=10, max_id=max_id)
            assert torch.equal(a, b), (name, max_id)
            assert torch.equal(sa, sb)
        assert torch.equal(index.similarities(queries[0], max_samples=100)[1],
                           loaded.similarities(queries[0], max_samples=100)[1])
    # Growing on after a reload works as before (and the reloaded index builds like the original).
    loaded.add(db[:300], ids=torch.arange(3600, 3900))
    assert len(loaded) == 1500 and loaded.search(db[0], k=1)[0].item() in (0, 3600)


def test_load_with_another_config_rebuilds(tmp_path):
    db = clustered_data(1500, 32, seed=10)
    index = KeyframeIndex(tree_config(flann={"checks": 8}))
    index.add(db)
    index.save(tmp_path / "i.npz")
    loaded = KeyframeIndex.load(tmp_path / "i.npz", config=IndexConfig(backend="exact"))
    assert loaded.backend == "exact" and loaded.n_indexed == 0 and len(loaded) == 1500
    q = random_data(1, 32, seed=11)[0]
    assert torch.equal(loaded.search(q, k=5)[0], brute(db, q, 5)[0])


def test_index_file_errors_name_the_file(tmp_path):
    good = KeyframeIndex(IndexConfig(backend="exact"))
    good.add(random_data(10, 4))
    with pytest.raises(FileNotFoundError):
        KeyframeIndex.load(tmp_path / "missing.npz")
    junk = tmp_path / "junk.npz"
    junk.write_bytes(b"not a zip file")
    with pytest.raises(IndexFileError, match="junk.npz"):
        KeyframeIndex.load(junk)
    state = good.state_dict()
    meta = state.pop("meta")

    def write(name, meta_obj, **arrays):
        path = tmp_path / name
        np.savez(path, **({} if meta_obj is None else {"meta": np.array(json.dumps(meta_obj))}),
                 **{**state, **arrays})
        return path

    with pytest.raises(IndexFileError, match="nometa.npz: no 'meta'"):
        KeyframeIndex.load(write("nometa.npz", None))
    with pytest.raises(IndexFileError, match="format"):
        KeyframeIndex.load(write("other.npz", {**meta, "format": "something else"}))
    with pytest.raises(IndexFileError, match="version 99"):
        KeyframeIndex.load(write("newer.npz", {**meta, "version": 99}))
    with pytest.raises(IndexFileError, match=r"shape \(9, 4\)"):
        KeyframeIndex.load(write("shape.npz", meta, descriptors=state["descriptors"][:9]))
    with pytest.raises(IndexFileError, match="increasing"):
        KeyframeIndex.load(write("ids.npz", meta, ids=state["ids"][::-1].copy()))
    with pytest.raises(IndexFileError, match="no setting"):
        KeyframeIndex.load(write("cfg.npz", {**meta, "config": {**meta["config"], "checks": 5}}))
    (tmp_path / "bad.npz").write_bytes(b"")
    with pytest.raises(IndexFileError, match="bad.npz"):
        load_index(tmp_path / "bad.npz")


def test_config_dict_round_trip():
    cfg = IndexConfig(backend="flann", reduce_dim=None, flann=FlannConfig(checks=-1),
                      faiss=FaissConfig(retrain_growth=float("inf")))
    d = config_to_dict(cfg)
    assert json.loads(json.dumps(d)) == d and d["faiss"]["retrain_growth"] == "inf"
    assert config_from_dict(d) == cfg


def brute_ties(db: torch.Tensor, q: torch.Tensor, k: int, max_id: int | None = None) -> list[int]:
    """Float64 reference over rows 0..max_id (ids = rows), similarities rounded to float32 as the index
    reports them, ties to the lower id."""
    m = db.shape[0] if max_id is None else max(0, min(db.shape[0], max_id + 1))
    s = (db[:m].double() @ q.double()).float().numpy()
    return np.lexsort((np.arange(m), -s))[:k].tolist()


def test_ties_go_to_the_lower_id_in_every_backend():
    # Duplicate frames (identical descriptors, as in the kitchen; a camera standing still) tie exactly: every
    # backend and every path must order them alike (lower id first), or a detector's candidate list would
    # depend on the backend. 100 copies of one row: far more than the 2k rows a scan used to keep and the
    # rerank * k = 48 rows a structure proposes.
    base = clustered_data(600, 32, clusters=30, seed=14)
    db = torch.cat([base, base[0].repeat(100, 1), base[::3]])  # rows 600..699 = row 0; 700.. = rows 0, 3, ...
    k = 6
    configs = {
        "exact": IndexConfig(backend="exact"),
        "flann, scan below exact_below": tree_config(exact_below=10_000),
        "flann tree": tree_config(exact_below=100),
        "flann tree + tail": tree_config(exact_below=100, flann={"rebuild_every": 10_000}),
        "flann rerank 1": tree_config(exact_below=100, rerank=1),
    }
    if faiss_available():
        configs["faiss"] = IndexConfig(backend="faiss", exact_below=100, reduce_dim=None, background=False,
                                       faiss=FaissConfig(ef_search=200))
    queries = db[[0, 30, 300, 650]]
    for name, cfg in configs.items():
        index = KeyframeIndex(cfg)
        if name == "flann tree + tail":
            index.add(db[:640])  # the tree covers 100 ... 639 lie in it, the rest of the copies in the tail
            index.add(db[640:])
            assert 0 < index.n_indexed < len(index)
        else:
            index.add(db)
        stored = index.descriptors
        # max_id: all; the copies cut by the window; a window so deep that the tree is not asked (a scan).
        for max_id in (None, 650, 620, 400):
            ids, sims = index.search(queries, k=k, max_id=max_id)
            for j in range(queries.shape[0]):
                q = queries[j] / queries[j].norm()
                ref = brute_ties(stored, q, k, max_id)
                assert ids[j].tolist() == ref, (name, max_id, j)
                assert torch.equal(sims[j], (stored[ref].double() @ q.double()).float()), (name, max_id, j)
        assert index.search(db[0], k=k)[0].tolist() == [0, 600, 601, 602, 603, 604], name
        assert index.search(db[30], k=2)[0].tolist() == [30, 710], name
    # A zero query ties with every row: the k lowest ids.
    index = KeyframeIndex(IndexConfig(backend="exact"))
    index.add(db)
    assert index.search(torch.zeros(32), k=4)[0].tolist() == [0, 1, 2, 3]
    # The reference search breaks ties alike.
    rows, _ = exact_search(db, db[[0, 30]], k)
    assert rows.tolist() == [[0, 600, 601, 602, 603, 604], brute_ties(db, db[30], k)]
