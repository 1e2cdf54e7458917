"""benchmarks/place_recognition.py's ORB bag of words: an exact, deterministic vocabulary (DBoW2's k-majority)."""
from __future__ import annotations

import sys

import numpy as np
import pytest

from slam.threads import limit_threads


@pytest.fixture(scope="module")
def pr(load_script):
    return load_script("benchmarks/place_recognition.py")


@pytest.fixture(scope="module")
def images():
    # textured frames with ORB corners: random rectangles on noise, one seed each
    out = []
    for i in range(6):
        rng = np.random.default_rng(i)
        im = rng.integers(0, 60, (240, 320, 3), dtype=np.uint8)
        for _ in range(40):
            y, x = rng.integers(0, 220), rng.integers(0, 300)
            im[y:y + rng.integers(8, 30), x:x + rng.integers(8, 30)] = rng.integers(80, 256, 3)
        out.append(im)
    return out


def _popcount_hamming(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    # an independent reference: packed bytes, XOR, a popcount table
    table = np.array([bin(i).count("1") for i in range(256)], np.int32)
    return table[np.bitwise_xor(a[:, None, :], b[None, :, :])].sum(2)


def test_hamming_is_exact(pr):
    rng = np.random.default_rng(0)
    a, b = rng.integers(0, 256, (50, 32), dtype=np.uint8), rng.integers(0, 256, (7, 32), dtype=np.uint8)
    got = pr.hamming(np.unpackbits(a, axis=1).astype(np.float32), np.unpackbits(b, axis=1).astype(np.float32))
    assert got.dtype == np.int32 and np.array_equal(got, _popcount_hamming(a, b))


def test_nearest_word_ties_go_to_the_lowest_index(pr):
    words = np.array([[1, 1, 0, 0], [0, 0, 1, 1], [1, 1, 0, 0]], np.float32)  # word 2 duplicates word 0
    codes = np.array([[1, 0, 0, 0], [1, 0, 1, 0], [0, 0, 0, 1]], np.float32)  # distances 1/3/1, 2/2/2, 3/1/3
    assert pr.nearest_word(codes, words, chunk=2).tolist() == [0, 0, 1]


def test_k_majority_hand_computed(pr):
    # two clusters of 4-bit codes from two given words. Pass 1: codes 0, 1, 2 and 6 (a tie, to the lower
    # index) go to word 0, whose bits 1 and 2 are then ties (2 of 4), which set the bit: [1, 1, 1, 0];
    # codes 3-5 give [0, 0, 0, 1]. Pass 2 moves code 6 to word 1; the words stay; pass 3 changes nothing.
    bits = np.array([[1, 1, 1, 0], [1, 1, 0, 0], [1, 0, 1, 0],
                     [0, 0, 0, 1], [0, 0, 1, 1], [0, 1, 0, 1], [0, 0, 0, 0]], np.float32)
    words = pr.k_majority(bits, 2, init=np.array([[1, 0, 0, 0], [0, 0, 0, 1]]))
    assert words.astype(int).tolist() == [[1, 1, 1, 0], [0, 0, 0, 1]]
    # a duplicate word loses every tie, so its cluster stays empty and it keeps its value
    dup = pr.k_majority(bits, 3, init=np.array([[1, 0, 0, 0], [0, 0, 0, 1], [1, 0, 0, 0]]))
    assert dup.astype(int).tolist() == [[1, 1, 1, 0], [0, 0, 0, 1], [1, 0, 0, 0]]
    with pytest.raises(pr.VocabularyTooSmall, match="7 distinct ORB descriptors for a vocabulary of 8 words"):
        pr.k_majority(bits, 8)
    with pytest.raises(ValueError, match=r"init must have shape \(2, 4\)"):
        pr.k_majority(bits, 2, init=np.zeros((2, 3)))


def _fit(pr, images, threads):
    with limit_threads(threads):
        faiss = sys.modules.get("faiss")
        if faiss is not None:
            faiss.omp_set_num_threads(threads)
        return pr.OrbBagOfWords(words=64).fit(images)


def test_vocabulary_is_the_same_at_any_thread_count_and_without_faiss(pr, images, monkeypatch):
    one = _fit(pr, images, 1)
    four = _fit(pr, images, 4)
    assert np.array_equal(one.vocab, four.vocab) and np.array_equal(one.idf, four.idf)
    # the vocabulary no longer depends on an optional package (faiss's k-means, or OpenCV's without it)
    monkeypatch.setitem(sys.modules, "faiss", None)
    without = pr.OrbBagOfWords(words=64).fit(images)
    assert np.array_equal(one.vocab, without.vocab) and np.array_equal(one.idf, without.idf)
    # each descriptor goes to its nearest word by the independent reference; idf = log(N / images with the word)
    descs = [one._describe(im) for im in images]
    for d in descs:
        ref = _popcount_hamming(d, one.vocab)
        assert np.array_equal(ref[np.arange(len(d)), one._assign(d)], ref.min(1))
    seen = np.stack([np.isin(np.arange(64), _popcount_hamming(d, one.vocab).argmin(1)) for d in descs]).sum(0)
    assert np.allclose(one.idf, np.log(len(images) / np.maximum(seen, 1)))


def test_benchmark_reports_orb_bow_it_cannot_train(pr, capsys):
    # images too small for ORB (it keeps 31 pixels from every border): no vocabulary; the anchor is
    # reported as not measured, and the benchmark goes on (no crash, no row of made-up figures)
    tiny = [np.random.default_rng(i).integers(0, 256, (24, 32, 3), dtype=np.uint8) for i in range(3)]
    with pytest.raises(pr.VocabularyTooSmall):
        pr.OrbBagOfWords(words=8).fit(tiny)
    sims = pr.all_methods(tiny, None, tiny, methods=("orb",))
    assert sims == {}
    assert "ORB-BoW: not measured: 0 distinct ORB descriptors" in capsys.readouterr().out
