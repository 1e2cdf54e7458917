"""Tests of attnloop.index (keyframe database, loop-candidate detector) and attnloop.threshold."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from attnloop.index import (
    IndexConfig,
    KeyframeIndex,
    LoopCandidateDetector,
    LoopDetectorConfig,
    exact_search,
)
from attnloop.threshold import ThresholdConfig, accept_mask, adaptive_threshold


def _unit(x: torch.Tensor) -> torch.Tensor:
    return x / x.norm(dim=-1, keepdim=True)


def random_data(n: int, d: int, seed: int = 0) -> torch.Tensor:
    return _unit(torch.randn(n, d, generator=torch.Generator().manual_seed(seed)))


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


def tree_config(**kw) -> IndexConfig:
    base = dict(min_tree_size=256, rebuild_every=128, rebuild_fraction=0.25, background=False, checks=-1)
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


def test_exact_mode_builds_no_tree_and_matches():
    db = random_data(1000, 32)
    index = KeyframeIndex(IndexConfig(exact=True, min_tree_size=10))
    index.add(db)
    assert index.n_indexed == 0 and index.num_builds == 0
    q = random_data(1, 32, seed=3)[0]
    ids, sims = index.search(q, k=7)
    ref_ids, ref_sims = brute(db, q, 7)
    assert torch.equal(ids, ref_ids)
    torch.testing.assert_close(sims, ref_sims)


def test_default_checks_recall_on_clustered_data():
    # Approximate search with the default checks: recall@10 on clustered data stays high (stated bound).
    d = 128
    db = clustered_data(4000, d, clusters=60, spread=0.6, seed=2)
    index = KeyframeIndex(IndexConfig(min_tree_size=1000, background=False))
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
    index = KeyframeIndex(tree_config(rebuild_every=10_000))  # no automatic rebuild
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
    index = KeyframeIndex(tree_config(rebuild_every=10_000))
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
    index = KeyframeIndex(tree_config(background=True, min_tree_size=512, rebuild_every=256))
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
        index = KeyframeIndex(IndexConfig(min_tree_size=100, checks=16, background=False))
        index.add(db)
        index.rebuild()
        results.append(index.search(q, k=5)[0])
    assert torch.equal(results[0], results[1])


# ------------------------------------------------------------------ exclusion window, batches, edges
def test_exclusion_window_and_batch_padding():
    db = random_data(400, 16)
    index = KeyframeIndex(tree_config(min_tree_size=200))
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
    assert len(index) == 0 and index.dim is None


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
    index = KeyframeIndex(tree_config(min_tree_size=100))
    index.add(db, ids=torch.arange(300) * 3)
    ids, sims = index.similarities(db[5], max_id=3 * 199)
    assert torch.equal(ids, torch.arange(200) * 3)
    torch.testing.assert_close(sims, db[:200] @ db[5])
    s_ids, s_sims = index.similarities(db[5], max_samples=31)  # every ceil(300 / 31) = 10th keyframe
    assert torch.equal(s_ids, torch.arange(0, 300, 10) * 3)
    torch.testing.assert_close(s_sims, db[s_ids // 3] @ db[5])


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


def test_threshold_std_method_floor_and_few_samples():
    s = torch.tensor([0.1, 0.2, 0.3, 0.4, 0.5, 0.6, 0.7, 0.8, 0.9, 1.0], dtype=torch.float64)
    cfg = ThresholdConfig(method="std", k_sigma=1.0, min_margin=0.0, min_samples=8)
    torch.testing.assert_close(adaptive_threshold(s, cfg), s.mean() + s.std(unbiased=False))
    floored = ThresholdConfig(method="std", k_sigma=0.0, min_margin=0.0, min_similarity=0.95, min_samples=8)
    assert adaptive_threshold(s, floored).item() == pytest.approx(0.95)
    assert adaptive_threshold(s[:7], cfg).item() == float("inf")  # fewer than min_samples
    assert adaptive_threshold(torch.zeros(0)).item() == float("inf")
    with pytest.raises(ValueError, match=r"\(N,\)"):
        adaptive_threshold(torch.rand(2, 5))
    with pytest.raises(ValueError, match="method"):
        ThresholdConfig(method="median")


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
    # Evaluation hook: exact similarities against all earlier keyframes.
    ids, sims = det.similarities(61, window=1)
    assert torch.equal(ids, torch.arange(61))
    torch.testing.assert_close(sims, det.index.descriptors[:61] @ det.index.descriptors[61])
    assert det.similarities(61)[0].shape == (52,)  # default window 10: ids <= 51


def test_detector_few_keyframes_give_nothing():
    det = LoopCandidateDetector(LoopDetectorConfig(window=2))
    v = random_data(1, 16)[0]
    for i in range(33):  # eligible keyframes stay below min_samples = 32: threshold inf
        out = det.add_and_query(v, keyframe_id=i)
        assert len(out) == 0 and out.threshold == float("inf")


def test_detector_temporal_consistency():
    view = _trajectory(80, seed=1)
    strict = ThresholdConfig(k_sigma=5.0)
    cfg = LoopDetectorConfig(window=10, top_k=3, consistency=3, consistency_radius=2, threshold=strict)
    det = LoopCandidateDetector(cfg)
    for i in range(50):
        det.add_and_query(view(i), keyframe_id=i)
    # A single isolated revisit of place 5, then new places: rejected by consistency.
    assert len(det.add_and_query(view(5), keyframe_id=50)) == 0
    assert len(det.add_and_query(view(70), keyframe_id=51)) == 0
    # A revisit that goes on: places 20, 21, 22, 23 -> accepted from the third consecutive query on.
    accepted = [det.add_and_query(view(p), keyframe_id=52 + j).ids.tolist()
                for j, p in enumerate(range(20, 24))]
    assert accepted == [[], [], [22], [23]]
    # Without consistency the same revisit is accepted at once.
    det1 = LoopCandidateDetector(LoopDetectorConfig(window=10, top_k=3, threshold=strict))
    for i in range(50):
        det1.add_and_query(view(i), keyframe_id=i)
    assert det1.add_and_query(view(20), keyframe_id=50).ids.tolist() == [20]


def test_detector_errors():
    det = LoopCandidateDetector()
    det.add_and_query(torch.rand(8), keyframe_id=5)
    with pytest.raises(ValueError, match="larger than the last"):
        det.add_and_query(torch.rand(8), keyframe_id=5)
    with pytest.raises(ValueError, match=r"\(D,\)"):
        det.add_and_query(torch.rand(2, 8), keyframe_id=6)
    with pytest.raises(ValueError, match="dimension"):
        det.add_and_query(torch.rand(9), keyframe_id=6)
    with pytest.raises(ValueError, match="unknown keyframe id"):
        det.similarities(3)
    with pytest.raises(ValueError):
        LoopDetectorConfig(top_k=0)
