"""Refusals and edge cases of attnloop.index and attnloop.threshold: dot-product indexes, non-finite and
non-integral inputs, the threshold's sample, half-precision thresholds, corrupt or unsupported index files."""
from __future__ import annotations

import json
import re

import numpy as np
import pytest
import torch
from helpers import unit_rows as _data

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
)
from attnloop.index.config import config_to_dict
from attnloop.threshold import ThresholdConfig, accept_mask, adaptive_threshold


def _brute(db: torch.Tensor, q: torch.Tensor, k: int, max_id: int | None = None) -> tuple[list[int], torch.Tensor]:
    """Float64 dot products over rows 0..max_id, rounded to float32, ties to the lower row."""
    m = db.shape[0] if max_id is None else max_id + 1
    s = (db[:m].double() @ q.double()).float()
    order = np.lexsort((np.arange(m), -s.numpy()))[:k]
    return order.tolist(), s[order]


# ------------------------------------------------------------------ 1. files saved with retired settings
def test_a_file_with_retired_settings_loads_at_their_kept_value(tmp_path):
    index = KeyframeIndex(IndexConfig(backend="exact"))
    index.add(_data(50, 16))
    state = index.state_dict()
    meta = state.pop("meta")
    for extra, ok in (({"whiten": False, "normalize": True}, True), ({"normalize": False}, False),
                      ({"whiten": True}, False)):
        meta["config"] = {**config_to_dict(index.config), **extra}
        np.savez(tmp_path / "old.npz", meta=np.array(json.dumps(meta)), **state)
        if ok:
            assert torch.equal(KeyframeIndex.load(tmp_path / "old.npz").search(_data(3, 16), k=5)[0],
                               index.search(_data(3, 16), k=5)[0])
        else:
            with pytest.raises(IndexFileError, match=rf"old\.npz.*{next(iter(extra))}.* no longer supported"):
                KeyframeIndex.load(tmp_path / "old.npz")


# ------------------------------------------------------------------ 3. non-finite queries
def test_non_finite_queries_are_refused_naming_the_rows():
    index = KeyframeIndex(IndexConfig(backend="exact"))
    index.add(_data(300, 16))
    q = _data(4, 16, seed=2)
    q[1, 3] = float("nan")
    q[3, 0] = float("inf")
    with pytest.raises(ValueError, match=r"query rows \[1, 3\] contain NaN or inf"):
        index.search(q, k=3)
    with pytest.raises(ValueError, match="the query contains NaN or inf"):
        index.search(q[1], k=3)
    with pytest.raises(ValueError, match="the query contains NaN or inf"):
        index.similarities(q[3])
    with pytest.raises(ValueError, match="NaN or inf"):
        index.search(torch.full((16,), 1e39, dtype=torch.float64), k=3)  # overflows float32
    det = LoopCandidateDetector(LoopDetectorConfig(window=1))
    det.add_and_query(q[0], keyframe_id=0)
    with pytest.raises(ValueError, match="NaN or inf"):
        det.add_and_query(q[1], keyframe_id=1)
    assert index.search(q[[0, 2]], k=3)[0].shape == (2, 3)  # finite rows still answer


# ------------------------------------------------------------------ 4. the threshold's sample
@pytest.mark.parametrize("m,samples", [(33, 32), (63, 32), (100, 7), (4097, 4096), (10, 1), (5, 5), (4, 9)])
def test_similarities_sample_exactly_max_samples_rows(m, samples):
    db = _data(m, 8, seed=3)
    index = KeyframeIndex(IndexConfig(backend="exact"))
    index.add(db, ids=torch.arange(m) * 2)
    q = _data(1, 8, seed=4)[0]
    ids, sims = index.similarities(q, max_samples=samples)
    rows = ids // 2
    assert rows.numel() == min(m, samples) and bool((rows[1:] > rows[:-1]).all())
    assert rows[0] == 0 and (samples == 1 or rows[-1] == m - 1)
    if samples > 1 and m > samples:  # evenly spread: gaps differ by at most one
        gaps = rows[1:] - rows[:-1]
        assert int(gaps.max() - gaps.min()) <= 1
    torch.testing.assert_close(sims, (db[rows].double() @ q.double()).float(), atol=1e-6, rtol=0)


def test_max_samples_must_be_a_positive_integer():
    index = KeyframeIndex(IndexConfig(backend="exact"))
    q = torch.rand(8)
    for bad, err in ((0, ValueError), (-1, ValueError), (2.5, TypeError)):
        with pytest.raises(err, match="max_samples"):
            index.similarities(q, max_samples=bad)  # refused on an empty index too
        index.add(torch.rand(3, 8))
        with pytest.raises(err, match="max_samples"):
            index.similarities(q, max_samples=bad)


def test_detector_threshold_uses_threshold_samples_keyframes():
    # window 1, threshold_samples 32 = min_samples: with 33 eligible keyframes the old stride sampled 17
    # (ceil(33 / 32) = 2), below min_samples, so the threshold stayed inf forever.
    db = _data(40, 16, seed=5)
    det = LoopCandidateDetector(LoopDetectorConfig(window=1, threshold_samples=32))
    for i in range(34):
        out = det.add_and_query(db[i], keyframe_id=i)
    out = det.query(db[34], keyframe_id=34)  # 34 eligible keyframes: 0 .. 33
    rows = np.floor(np.arange(32) * 33 / 31 + 0.5).astype(np.int64)
    sims = (db[rows].double() @ db[34].double()).float()
    expected = adaptive_threshold(sims, ThresholdConfig())
    assert np.isfinite(out.threshold)
    assert out.threshold == pytest.approx(float(expected), abs=1e-6)
    with pytest.raises(ValueError, match="threshold_samples must be an integer"):
        LoopDetectorConfig(threshold_samples=64.5)


# ------------------------------------------------------------------ 5. the adaptive threshold
@pytest.mark.parametrize("dtype", [torch.float16, torch.bfloat16])
def test_threshold_half_precision_computed_in_float32(dtype):
    g = torch.Generator().manual_seed(6)
    s = (0.5 + 0.05 * torch.randn(200, generator=g)).to(dtype)
    t = adaptive_threshold(s)
    assert t.dtype == dtype
    ref = adaptive_threshold(s.float())  # float32 on the same (rounded) values
    assert t.item() == ref.to(dtype).item()
    x = s.float()
    med = x.quantile(0.5)
    by_hand = med + 3.0 * 1.4826 * (x - med).abs().quantile(0.5)
    assert abs(t.item() - by_hand.item()) <= 4e-3  # one half-precision ulp at 0.6
    assert accept_mask(s).dtype == torch.bool


def test_threshold_refuses_non_finite_similarities_and_settings():
    s = torch.rand(64)
    s[5] = float("nan")
    with pytest.raises(ValueError, match=r"finite.*\[5\]"):
        adaptive_threshold(s)
    with pytest.raises(ValueError, match="finite"):
        adaptive_threshold(torch.full((40,), float("-inf")))  # e.g. the padding of a batched search
    with pytest.raises(ValueError, match="finite"):
        adaptive_threshold(torch.tensor([0.1, float("nan")]))  # also below min_samples
    for kwargs in ({"k_sigma": float("nan")}, {"k_sigma": float("inf")}, {"min_margin": float("nan")},
                   {"min_similarity": float("nan")}, {"min_similarity": float("inf")}, {"k_sigma": "3"},
                   {"min_samples": 2.5}, {"min_samples": True}, {"min_samples": 1}):
        with pytest.raises(ValueError):
            ThresholdConfig(**kwargs)
    assert ThresholdConfig(min_samples=np.int64(16), k_sigma=np.float32(1.5)).min_samples == 16


# ------------------------------------------------------------------ 8. ids, k and max_id must be integers
def test_non_integral_ids_and_max_ids_are_refused():
    index = KeyframeIndex(IndexConfig(backend="exact"))
    with pytest.raises(ValueError, match=r"ids must be integers, got \[0.5, 1.7\]"):
        index.add(torch.rand(2, 8), ids=[0.5, 1.7])
    with pytest.raises(ValueError, match="ids must be integers"):
        index.add(torch.rand(2, 8), ids=torch.tensor([1.0, float("nan")]))
    assert len(index) == 0
    index.add(torch.rand(2, 8), ids=np.array([3.0, 7.0]))  # integral floats are ids
    index.add(torch.rand(1, 8), ids=torch.tensor([9]))
    assert index.ids.tolist() == [3, 7, 9]
    with pytest.raises(ValueError, match="max_id must be integers"):
        index.search(torch.rand(8), k=2, max_id=7.5)
    assert index.search(torch.rand(8), k=5, max_id=7.0)[0].numel() == 2
    with pytest.raises(TypeError, match="k must be an integer"):
        index.search(torch.rand(8), k=2.7)
    with pytest.raises(ValueError, match="ids must be integers"):
        index.rows_of([3.5])


# ------------------------------------------------------------------ minor: exact_search
def test_exact_search_promotes_dtypes_and_checks_k():
    db = _data(50, 6, seed=7)
    q = _data(3, 6, seed=8).double()
    rows, sims = exact_search(db, q, 4)
    assert sims.dtype == torch.float64
    full = q @ db.double().t()
    assert rows.tolist() == torch.argsort(full, dim=1, descending=True)[:, :4].tolist()
    torch.testing.assert_close(sims, full.gather(1, rows))
    assert exact_search(db, q, 0)[0].shape == (3, 0)
    with pytest.raises(ValueError, match="k must be >= 0"):
        exact_search(db, q, -1)
    with pytest.raises(TypeError, match="k must be an integer"):
        exact_search(db, q, 2.5)


# ------------------------------------------------------------------ 6, 7. index files
def _structure_configs():
    out = [("flann", IndexConfig(backend="flann", exact_below=100, reduce_dim=8, background=False,
                                 flann=FlannConfig(checks=32)))]
    if faiss_available():
        out.append(("faiss", IndexConfig(backend="faiss", exact_below=100, reduce_dim=8, background=False,
                                         faiss=FaissConfig(m=8))))
    return out


@pytest.mark.parametrize("name,cfg", _structure_configs(), ids=[n for n, _ in _structure_configs()])
def test_corrupt_or_inconsistent_index_files_raise_index_file_error(tmp_path, name, cfg):
    db = _data(600, 16, seed=9)
    index = KeyframeIndex(cfg)
    index.add(db)
    state = index.state_dict()
    meta = state.pop("meta")
    blob = state["structure.blob"]
    comps = state["structure.pca.components"]

    def write(tag, meta_obj, drop=(), **arrays):
        path = tmp_path / f"{name}_{tag}.npz"
        entries = {k: v for k, v in {**state, **arrays}.items() if k not in drop}
        np.savez(path, meta=np.array(json.dumps(meta_obj)), **entries)
        return path

    garbage = np.random.default_rng(1).integers(0, 255, blob.size).astype(np.uint8)
    smeta = meta["structure"]
    cases = {
        "blob truncated": (write("trunc", meta, **{"structure.blob": blob[: blob.size // 2]}), "structure"),
        "blob garbage": (write("garb", meta, **{"structure.blob": garbage}), "structure|FLANN"),
        "blob missing": (write("noblob", meta, drop=("structure.blob",)), "structure.blob"),
        "blob not bytes": (write("blobf", meta, **{"structure.blob": blob.astype(np.float32)}), "uint8"),
        "config null": (write("cfg", {**meta, "config": None}), "config"),
        "config bad value": (write("cfgv", {**meta, "config": {**meta["config"], "rerank": "x"}}), "config"),
        "structure n missing": (write("sn", {**meta, "structure": {k: v for k, v in smeta.items() if k != "n"}}),
                                "'n'"),
        "structure n smaller": (write("sn2", {**meta, "structure": {**smeta, "n": 300}}), "300"),
        "structure n larger": (write("sn3", {**meta, "structure": {**smeta, "n": 900}}), "900"),
        "structure kind unknown": (write("kind", {**meta, "structure": {**smeta, "kind": "hnsw"}}), "hnsw"),
        "pca components too narrow": (write("pca1", meta, **{"structure.pca.components": comps[:, :4]}),
                                      "dimension|rows"),
        "pca components missing rows": (write("pca2", meta, **{"structure.pca.components": comps[:8]}),
                                        r"components have shape \(8, 8\)"),
        "pca mean missing": (write("pca3", meta, drop=("structure.pca.mean",)), "mean"),
        "pca code absent": (write("pca4", meta, drop=[k for k in state if k.startswith("structure.pca.")]),
                            "PCA code"),
        "num_builds null": (write("nb", {**meta, "num_builds": None}), "num_builds"),
        "dim a string": (write("dim", {**meta, "dim": "16"}), "'dim'"),
        "descriptors int": (write("dint", meta, descriptors=(state["descriptors"] * 100).astype(np.int64)),
                            "dtype int64"),
        "descriptors not unit": (write("x5", meta, descriptors=state["descriptors"] * 5), "norm"),
        "ids float": (write("idf", meta, ids=state["ids"] + 0.5), "ids must be integers"),
    }
    for case, (path, what) in cases.items():
        with pytest.raises(IndexFileError, match=path.name) as info:
            KeyframeIndex.load(path)
        assert re.search(what, str(info.value)), (case, str(info.value))
    # The untouched state still loads and answers as the original.
    ok = write("ok", meta)
    assert torch.equal(KeyframeIndex.load(ok).search(db[:5], k=4)[0], index.search(db[:5], k=4)[0])


@pytest.mark.parametrize("version", [0, -1, None, "1", 1.0, True, 2, "missing"])
def test_index_file_version_must_be_supported(tmp_path, version):
    index = KeyframeIndex(IndexConfig(backend="exact"))
    index.add(_data(10, 4))
    state = index.state_dict()
    meta = state.pop("meta")
    if version == "missing":
        meta.pop("version")
    else:
        meta["version"] = version
    path = tmp_path / "v.npz"
    np.savez(path, meta=np.array(json.dumps(meta)), **state)
    with pytest.raises(IndexFileError) as info:
        KeyframeIndex.load(path)
    msg = str(info.value)
    assert "v.npz" in msg and re.search(r"this library reads (version 1|\(1\))", msg), msg
    if version == "missing":
        assert "no format version" in msg
    else:  # the version found
        assert re.search(rf"version {re.escape(repr(version))} ", msg), msg


def test_save_writes_the_name_given_atomically(tmp_path, monkeypatch):
    from attnloop.index import IndexConfig, IndexFileError, KeyframeIndex, persistence

    index = KeyframeIndex(IndexConfig(backend="exact"))
    index.add(torch.eye(4), ids=[2, 3, 5, 8])
    index.save(tmp_path / "session1.idx")  # numpy would have written session1.idx.npz
    assert sorted(p.name for p in tmp_path.iterdir()) == ["session1.idx"]
    assert KeyframeIndex.load(tmp_path / "session1.idx").search(torch.eye(4)[2], k=1)[0].tolist() == [5]
    # a save that fails half-way leaves the previous file whole (it was truncated in place)
    bigger = KeyframeIndex(IndexConfig(backend="exact"))
    bigger.add(torch.rand(50, 4))

    def failing(f, **arrays):
        f.write(b"PK\x03\x04 half a zip")
        raise OSError("disk full")

    monkeypatch.setattr(persistence.np, "savez", failing)
    with pytest.raises(OSError, match="disk full"):
        bigger.save(tmp_path / "session1.idx")
    monkeypatch.undo()
    assert len(KeyframeIndex.load(tmp_path / "session1.idx")) == 4
    assert sorted(p.name for p in tmp_path.iterdir()) == ["session1.idx"]  # no temporary file left
    np.save(tmp_path / "array.npy", np.zeros(3))
    with pytest.raises(IndexFileError, match="array.npy: a .npy array"):
        KeyframeIndex.load(tmp_path / "array.npy")


def test_descriptors_of_an_empty_index_names_the_id():
    from attnloop.index import IndexConfig, KeyframeIndex

    index = KeyframeIndex(IndexConfig(backend="exact"))
    with pytest.raises(ValueError, match=r"unknown keyframe id\(s\) \[0\]"):
        index.descriptors_of([0])
    assert index.descriptors_of([]).shape[0] == 0
