"""benchmarks/index.py and its data generators: identities of the generators, the tie-aware recall, a smoke run."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from attnloop.index import exact_search, faiss_available

BENCH = Path(__file__).resolve().parents[1] / "benchmarks"


@pytest.fixture
def index_data(monkeypatch):
    monkeypatch.syspath_prepend(str(BENCH))
    import index_data

    return index_data


@pytest.fixture
def bench(index_data, load_script):
    return load_script("benchmarks/index.py")


def test_clustered_views_have_the_stated_cosines(index_data):
    data = index_data.Clustered(4000, 512, spread=1.0, views=20)
    rows = data.chunk(0, 4000)
    again = data.chunk(0, 4000)
    assert rows.shape == (4000, 512) and np.array_equal(rows, again)  # deterministic
    np.testing.assert_allclose(np.linalg.norm(rows, axis=1), 1.0, rtol=1e-5)
    # Two views of a place: (p + s n1).(p + s n2) / (1 + s^2) = 1 / (1 + s^2) = 0.5 (noise ~ orthogonal).
    q = data.queries(200)
    sims = q @ rows.T
    assert 0.45 < np.median(sims.max(axis=1)) < 0.6  # the best match is a view of the same place
    assert abs(float(np.median(sims))) < 0.02  # other places: ~0
    assert np.array_equal(q, data.queries(200))


def test_real_statistics_keep_the_mean_and_the_view_changes(index_data):
    g = torch.Generator().manual_seed(0)
    base = torch.randn(1024, 16, generator=g) * 0.2 + 1.0  # a strong common component, like real descriptors
    seq = base[:300] + 0.05 * torch.cumsum(torch.randn(300, 16, generator=g), 0)
    data = index_data.RealStatistics(4000, base, seq, gap=10, views=20)
    torch.testing.assert_close(data.places.mean(0), base.mean(0), atol=0.06, rtol=0)
    rows = data.chunk(0, 4000)
    assert rows.shape == (4000, 16)
    np.testing.assert_allclose(np.linalg.norm(rows, axis=1), 1.0, rtol=1e-5)


def test_exact_reference_merges_chunks(index_data, monkeypatch):
    monkeypatch.setattr(index_data, "CHUNK", 700)
    data = index_data.Clustered(3000, 32, spread=1.0)
    q = data.queries(15)
    rows, sims = index_data.exact_reference(data, q, 10)
    full = np.concatenate([data.chunk(s, min(s + 700, 3000)) for s in range(0, 3000, 700)])
    ref_rows, ref_sims = exact_search(torch.from_numpy(full), torch.from_numpy(q), 10)
    assert np.array_equal(rows, ref_rows.numpy())
    np.testing.assert_allclose(sims, ref_sims.numpy(), atol=1e-6)


def test_recall_counts_ties(bench):
    ref = np.array([[0.9, 0.8, 0.7]])
    assert bench.recall([np.array([0.9, 0.8, 0.7])], ref) == (1.0, 1.0)
    # A returned keyframe tied with the 3rd exact one counts (duplicate frames); a weaker one does not.
    assert bench.recall([np.array([0.9, 0.7, 0.6])], ref)[0] == pytest.approx(2 / 3)
    assert bench.recall([np.array([0.8, 0.7])], ref) == (pytest.approx(2 / 3), 0.0)


def test_smoke_run(bench, capsys):
    variants = ["exact", "flann-pca128"] + (["faiss-pca128"] if faiss_available() else [])
    threads = torch.get_num_threads()
    try:
        bench.main(["--sizes", "3000", "--dim", "64", "--data", "clustered", "--queries", "20", "--rounds", "2",
                    "--stream", "20", "--variants", *variants])
    finally:
        torch.set_num_threads(threads)
    out = capsys.readouterr().out
    rows = [line for line in out.splitlines() if line.startswith("| exact |")]
    assert rows and rows[0].split("|")[6].strip() == "1.000"  # the exact scan's recall@10
    assert "| flann-pca128 | 3000 | 20 |" in out  # the stream table
    for name in variants[1:]:
        recalls = [float(line.split("|")[6]) for line in out.splitlines()
                   if line.startswith(f"| {name} ") and ("checks" in line or "ef_search" in line)]
        assert len(recalls) == 3 and max(recalls) >= 0.9, (name, recalls)


@pytest.mark.skipif(not faiss_available(), reason="faiss not installed")
def test_diagnosis_splits_the_code_from_the_graph(bench, capsys):
    threads = torch.get_num_threads()
    try:
        bench.main(["--diagnose", "--sizes", "500", "--dim", "64", "--data", "clustered", "--queries", "20",
                    "--diagnose-queries", "20", "--graphs", "8:40", "--ef-sweep", "16", "64"])
    finally:
        torch.set_num_threads(threads)
    out = capsys.readouterr().out
    code = [(int(line.split("|")[2]), float(line.split("|")[3])) for line in out.splitlines()
            if line.startswith("| exact search on the code |")]
    assert [r for r, _ in code] == [80, 160, 320, 640]
    # Nested candidate sets re-scored exactly: recall cannot fall as R grows, and R >= the 500 rows
    # re-scores every row: the exact answer.
    assert all(a <= b for (_, a), (_, b) in zip(code, code[1:])) and code[-1][1] == 1.0
    graph = [line for line in out.splitlines() if line.startswith("| HNSW M 8, ef_construction 40")]
    assert len(graph) == 2 and all("ef_search" in line and "graph proposes" in line for line in graph)
