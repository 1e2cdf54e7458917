"""attnloop.vpr.evaluate: recall@k, the best-match PR curve, VPR-Bench's AUC-PR, the readers."""
from __future__ import annotations

import io
import math

import cv2
import numpy as np
import pytest
import torch

from attnloop.vpr.evaluate import (
    GroundTruthFormatError,
    ShapeMismatchError,
    evaluate,
    ground_truth_from_poses,
    plot_place_recognition,
    read_ground_truth,
    read_ground_truth_matrix,
    read_vpr_bench_ground_truth,
    sequence_candidates,
    sequence_similarity,
)
from slam.eval.loops import LoopGroundTruthConfig, ground_truth_loops
from slam.lie import so3_exp


def test_perfect_ranking():
    n = 6
    sim = torch.eye(n) + 0.1 * torch.rand(n, n)  # the diagonal (the true match) is always best
    r = evaluate(sim, torch.eye(n, dtype=torch.bool))
    assert [r.recall_at(k) for k in (1, 5, 10)] == [1.0, 1.0, 1.0]
    assert r.recall_at_full_precision == 1.0
    assert r.auc_pr == pytest.approx(1.0, abs=1e-12)
    assert r.accuracy == 1.0 and r.best.tolist() == list(range(n))


def test_reversed_ranking():
    # every true match ranks last among 4 candidates
    n = 4
    sim = 1.0 - torch.eye(n) + 0.01 * torch.arange(n)
    r = evaluate(sim, torch.eye(n, dtype=torch.bool))
    assert [r.recall_at(k) for k in (1, 2, 3, 4, 10)] == [0.0, 0.0, 0.0, 1.0, 1.0]
    assert r.first_true_rank.tolist() == [3, 3, 3, 3]
    assert r.recall_at_full_precision == 0.0 and r.threshold_at_full_precision == math.inf
    assert r.auc_pr == 0.0 and r.accuracy == 0.0


def test_random_ranking_recall_is_k_over_r():
    g = torch.Generator().manual_seed(3)
    q, n = 4000, 50
    gt = torch.zeros(q, n, dtype=torch.bool)
    gt[torch.arange(q), torch.randint(0, n, (q,), generator=g)] = True
    r = evaluate(torch.rand(q, n, generator=g), gt)
    for k in (1, 5, 10):
        p = k / n
        assert abs(r.recall_at(k) - p) < 4 * math.sqrt(p * (1 - p) / q), (k, r.recall_at(k))
    # random scores: precision stays at the chance level 1/50, the area is that plus the first step
    assert r.auc_pr < 0.06
    assert r.recall_at_full_precision < 0.01


def test_hand_computed_curve_with_a_query_without_match():
    #            q0 correct 0.9, q1 no true match 0.8 (a false positive when accepted), q2 correct 0.7,
    #            q3 wrong 0.6 (its true match ranks second), q4 correct 0.5
    sim = torch.tensor([
        [0.9, 0.1, 0.0],
        [0.2, 0.8, 0.3],
        [0.7, 0.0, 0.1],
        [0.6, 0.5, 0.0],
        [0.0, 0.1, 0.5],
    ])
    gt = torch.tensor([[1, 0, 0], [0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], dtype=torch.bool)
    r = evaluate(sim, gt)
    assert r.num_queries == 5 and r.num_with_match == 4
    assert r.correct.tolist() == [True, False, True, False, True]
    assert r.recall_at(1) == 0.75 and r.recall_at(2) == 1.0
    # loop-closure curve: recall over the 4 queries with a match
    c = r.curve
    assert c.recall.tolist() == pytest.approx([0, 0.25, 0.25, 0.5, 0.5, 0.75])
    assert c.precision.tolist() == pytest.approx([1, 1, 0.5, 2 / 3, 0.5, 0.6])
    assert r.recall_at_full_precision == 0.25 and r.threshold_at_full_precision == pytest.approx(0.9)
    # VPR-Bench: recall over the 3 correct best matches, trapezoids from (0, 1)
    assert r.vpr_bench_curve.recall.tolist() == pytest.approx([0, 1 / 3, 1 / 3, 2 / 3, 2 / 3, 1])
    assert r.auc_pr == pytest.approx(1 / 3 + (1 / 3) * (0.5 + 2 / 3) / 2 + (1 / 3) * (0.5 + 0.6) / 2)
    assert r.auc_pr == pytest.approx(128 / 180)
    assert r.accuracy == 0.6
    d = r.to_dict()
    assert d["recall@1"] == 0.75 and d["auc_pr"] == pytest.approx(128 / 180)


def test_candidates_mask_and_non_finite_entries():
    # a sequence of 4 frames, each against those at least 2 earlier: frames 0 and 1 have no candidate
    sim = torch.tensor([
        [1.0, 0.9, 0.8, 0.7],
        [0.9, 1.0, 0.9, 0.1],
        [0.95, 0.2, 1.0, 0.9],
        [0.1, 0.3, float("nan"), 1.0],
    ])
    gt = torch.tensor([[0, 0, 0, 0], [1, 0, 0, 0], [1, 0, 0, 0], [0, 0, 1, 0]], dtype=torch.bool)
    cand = sequence_candidates(4, 2)
    assert cand.tolist() == [[False] * 4, [False] * 4, [True, False, False, False], [True, True, False, False]]
    r = evaluate(sim, gt, candidates=cand)
    # frame 1's match (0) is not a candidate, frame 3's (2) is NaN: neither counts
    assert r.has_match.tolist() == [False, False, True, False]
    assert r.best.tolist() == [-1, -1, 0, 1]
    assert r.best_score[:2].tolist() == [-math.inf, -math.inf]
    assert r.recall_at(1) == 1.0
    # frame 3 is accepted at 0.3 with a wrong match: a false positive below frame 2's 0.95
    assert r.curve.precision.tolist() == pytest.approx([1.0, 1.0, 0.5])
    assert r.recall_at_full_precision == 1.0


def test_ties_rank_in_database_order():
    sim = torch.tensor([[0.5, 0.5, 0.5], [0.5, 0.5, 0.5]])
    gt = torch.tensor([[1, 0, 0], [0, 0, 1]], dtype=torch.bool)
    r = evaluate(sim, gt)
    assert r.best.tolist() == [0, 0]
    assert r.first_true_rank.tolist() == [0, 2]
    assert r.recall_at(1) == 0.5 and r.recall_at(3) == 1.0


def test_no_query_with_a_match_and_empty_inputs():
    r = evaluate(torch.rand(3, 4), torch.zeros(3, 4, dtype=torch.bool))
    assert math.isnan(r.recall_at(1)) and math.isnan(r.recall_at_full_precision)
    assert r.auc_pr == 0.0
    assert r.to_dict()["recall@1"] is None
    r = evaluate(torch.zeros(2, 0), torch.zeros(2, 0, dtype=torch.bool))
    assert r.best.tolist() == [-1, -1] and r.num_with_match == 0
    r = evaluate(np.zeros((0, 3)), np.zeros((0, 3), dtype=bool))
    assert r.num_queries == 0 and r.best.shape == (0,)


def test_evaluate_errors():
    with pytest.raises(ShapeMismatchError, match=r"\(3, 4\) and ground_truth \(4, 3\)"):
        evaluate(torch.rand(3, 4), torch.zeros(4, 3, dtype=torch.bool))
    with pytest.raises(ShapeMismatchError, match=r"candidates \(3, 3\)"):
        evaluate(torch.rand(3, 4), torch.zeros(3, 4, dtype=torch.bool), candidates=torch.ones(3, 3, dtype=torch.bool))
    with pytest.raises(ShapeMismatchError, match=r"\(Q, R\), got \(12,\)"):
        evaluate(torch.rand(12), torch.zeros(12, dtype=torch.bool))
    with pytest.raises(TypeError):
        evaluate([[0.1]], [[True]])
    r = evaluate(torch.rand(2, 2), torch.eye(2, dtype=torch.bool))
    for bad in (0, -1, 1.5, True):
        with pytest.raises(ValueError, match="k must be a positive integer"):
            r.recall_at(bad)
    with pytest.raises(ValueError, match="min_gap"):
        sequence_candidates(5, 0)


# ---------------------------------------------------------------------------------------------------
# Readers


def test_read_matrix_image_and_npy(tmp_path):
    m = np.zeros((5, 4), np.uint8)
    m[2, 1] = m[4, 0] = 255
    cv2.imwrite(str(tmp_path / "gt.bmp"), m)
    cv2.imwrite(str(tmp_path / "gt.png"), cv2.cvtColor(m, cv2.COLOR_GRAY2BGR))  # equal channels are fine
    np.save(tmp_path / "gt.npy", m > 0)
    np.save(tmp_path / "gt_float.npy", m.astype(np.float32) / 255)
    want = torch.from_numpy(m > 0)
    for name in ("gt.bmp", "gt.png", "gt.npy", "gt_float.npy"):
        got = read_ground_truth_matrix(tmp_path / name)
        assert got.dtype == torch.bool and torch.equal(got, want), name
        assert torch.equal(read_ground_truth(str(tmp_path / name)), want)
    with open(tmp_path / "gt.bmp", "rb") as f:  # a binary file object
        assert torch.equal(read_ground_truth_matrix(f), want)
    assert torch.equal(evaluate(torch.rand(5, 4), tmp_path / "gt.bmp").has_match, want.any(1))


def test_read_matrix_errors(tmp_path):
    with pytest.raises(GroundTruthFormatError, match="does not exist") as e:
        read_ground_truth_matrix(tmp_path / "missing.bmp")
    assert e.value.path.endswith("missing.bmp")
    (tmp_path / "empty.bmp").write_bytes(b"")
    with pytest.raises(GroundTruthFormatError, match="empty file"):
        read_ground_truth_matrix(tmp_path / "empty.bmp")
    (tmp_path / "junk.bmp").write_bytes(b"not an image at all")
    with pytest.raises(GroundTruthFormatError, match="junk.bmp: neither a .npy array nor an image"):
        read_ground_truth_matrix(tmp_path / "junk.bmp")
    colour = np.zeros((3, 3, 3), np.uint8)
    colour[0, 0, 2] = 255
    cv2.imwrite(str(tmp_path / "colour.png"), colour)
    with pytest.raises(GroundTruthFormatError, match="must be grey"):
        read_ground_truth_matrix(tmp_path / "colour.png")
    np.save(tmp_path / "vec.npy", np.ones(4))
    with pytest.raises(GroundTruthFormatError, match=r"2-D .* got shape \(4,\)"):
        read_ground_truth_matrix(tmp_path / "vec.npy")
    bad = np.zeros((2, 2))
    bad[1, 0] = np.nan
    np.save(tmp_path / "nan.npy", bad)
    with pytest.raises(GroundTruthFormatError, match=r"non-finite entry at \(row 1, column 0\)"):
        read_ground_truth_matrix(tmp_path / "nan.npy")
    data = (tmp_path / "vec.npy").read_bytes()
    (tmp_path / "cut.npy").write_bytes(data[: len(data) - 8])
    with pytest.raises(GroundTruthFormatError, match="cut.npy: not a readable .npy"):
        read_ground_truth_matrix(tmp_path / "cut.npy")
    np.save(tmp_path / "obj.npy", np.array([[0, [1]]], dtype=object))
    with pytest.raises(GroundTruthFormatError, match="read_vpr_bench_ground_truth"):
        read_ground_truth_matrix(tmp_path / "obj.npy")
    with pytest.raises(TypeError, match="binary mode"):
        read_ground_truth_matrix(io.StringIO("0 1"))
    with pytest.raises(ShapeMismatchError, match="4 columns, expected num_references=5"):
        read_ground_truth(_saved(tmp_path, "m.npy", np.eye(4)), num_references=5)


def _saved(tmp_path, name, arr):
    np.save(tmp_path / name, arr, allow_pickle=True)
    return tmp_path / name


def _vpr_rows(rows):
    arr = np.empty((len(rows), 2), dtype=object)
    for i, (q, refs) in enumerate(rows):
        arr[i, 0], arr[i, 1] = q, refs
    return arr


def test_read_vpr_bench(tmp_path):
    # the layout of VPR-Bench's ground_truth_new.npy: row q = [q, list of matching references]
    rows = [(0, [0, 1]), (1, np.array([1, 2])), (2, range(2, 4)), (3, []), (4, 5)]
    path = _saved(tmp_path, "ground_truth_new.npy", _vpr_rows(rows))
    gt = read_vpr_bench_ground_truth(path)
    assert gt.shape == (5, 6)
    assert [torch.nonzero(g).flatten().tolist() for g in gt] == [[0, 1], [1, 2], [2, 3], [], [5]]
    assert read_vpr_bench_ground_truth(path, num_references=9).shape == (5, 9)
    assert torch.equal(read_ground_truth(path), gt)  # told from the object dtype
    with open(path, "rb") as f:
        assert torch.equal(read_vpr_bench_ground_truth(f), gt)
    # an object array holding floats (integral) and single indices
    assert read_vpr_bench_ground_truth(_saved(tmp_path, "o.npy", _vpr_rows([(0.0, 1.0), (1.0, 0.0)]))).tolist() == [
        [False, True], [True, False]]
    # a real float (and int) array of [query, reference] rows, one reference per query
    for dtype in (np.float64, np.float32, np.int64):
        arr = np.array([[0.0, 2.0], [1.0, 0.0]], dtype=dtype)
        assert arr.dtype != object
        got = read_vpr_bench_ground_truth(_saved(tmp_path, "f.npy", arr))
        assert got.tolist() == [[False, False, True], [True, False, False]], dtype


def test_numeric_q_by_2_arrays_are_matrices_for_read_ground_truth(tmp_path):
    """One reading per function, whatever the values: read_ground_truth -> a binary matrix,
    read_vpr_bench_ground_truth -> [query, reference] rows."""
    path = _saved(tmp_path, "amb.npy", np.array([[0.0, 0.0], [1.0, 1.0]]))
    assert read_ground_truth(path).tolist() == [[False, False], [True, True]]
    assert read_ground_truth_matrix(path).tolist() == [[False, False], [True, True]]
    assert read_vpr_bench_ground_truth(path).tolist() == [[True, False], [False, True]]
    rows = _saved(tmp_path, "rows.npy", np.array([[0, 5], [1, 6]]))
    with pytest.raises(GroundTruthFormatError, match=r"rows.npy: entry at \(row 0, column 1\) is 5: .*binary.*"
                                                     r"read_vpr_bench_ground_truth"):
        read_ground_truth(rows)
    assert read_vpr_bench_ground_truth(rows).shape == (2, 7)
    with pytest.raises(GroundTruthFormatError, match="bool.*read_ground_truth_matrix"):
        read_vpr_bench_ground_truth(_saved(tmp_path, "b.npy", np.array([[True, False]])))
    with pytest.raises(GroundTruthFormatError, match="dtype complex128"):
        read_vpr_bench_ground_truth(_saved(tmp_path, "c.npy", np.array([[0, 1]], dtype=complex)))


def test_read_vpr_bench_errors(tmp_path):
    with pytest.raises(GroundTruthFormatError, match=r"row 1: holds query 5"):
        read_vpr_bench_ground_truth(_saved(tmp_path, "a.npy", _vpr_rows([(0, [0]), (5, [1])])))
    with pytest.raises(GroundTruthFormatError, match=r"row 0: reference index must be a non-negative integer, got -1"):
        read_vpr_bench_ground_truth(_saved(tmp_path, "b.npy", _vpr_rows([(0, [-1])])))
    with pytest.raises(GroundTruthFormatError, match=r"row 0: reference index must be a non-negative integer, got 1.5"):
        read_vpr_bench_ground_truth(_saved(tmp_path, "c.npy", _vpr_rows([(0, [1.5])])))
    with pytest.raises(GroundTruthFormatError, match=r"row 0: reference index must be .* got 'x' \(str\)"):
        read_vpr_bench_ground_truth(_saved(tmp_path, "d.npy", _vpr_rows([(0, ["x"])])))
    with pytest.raises(GroundTruthFormatError, match=r"row 1: reference index 7 is not below num_references=4"):
        read_vpr_bench_ground_truth(_saved(tmp_path, "e.npy", _vpr_rows([(0, [0]), (1, [7])])), num_references=4)
    with pytest.raises(GroundTruthFormatError, match=r"shape \(3,\)"):
        read_vpr_bench_ground_truth(_saved(tmp_path, "g.npy", np.arange(3)))
    (tmp_path / "h.npy").write_bytes(b"GARBAGE")
    with pytest.raises(GroundTruthFormatError, match="h.npy: not a .npy file"):
        read_vpr_bench_ground_truth(tmp_path / "h.npy")
    with pytest.raises(GroundTruthFormatError, match="does not exist"):
        read_vpr_bench_ground_truth(tmp_path / "none.npy")


def test_read_vpr_bench_validates_indices_and_num_references(tmp_path):
    """No StopIteration, overflow or huge allocation; no bool, string or fractional index."""
    no_match = _saved(tmp_path, "n.npy", _vpr_rows([(0, []), (1, [])]))
    for bad in (-1, 2.7, 3.0, True, "3"):
        with pytest.raises((TypeError, ValueError), match="num_references must be a non-negative integer"):
            read_vpr_bench_ground_truth(no_match, num_references=bad)
        with pytest.raises((TypeError, ValueError), match="num_references must be a non-negative integer"):
            read_ground_truth(no_match, num_references=bad)
    assert read_vpr_bench_ground_truth(no_match, num_references=np.int64(0)).shape == (2, 0)
    assert read_vpr_bench_ground_truth(no_match).shape == (2, 0)
    cases = [
        ("huge.npy", [(0, [0]), (1, [2 ** 70])], r"row 1: reference index 1180591620717411303424 is not below"),
        ("big.npy", [(0, [0]), (1, [10 ** 15])], r"row 1: reference index 1000000000000000 is not below \d+ .*num_ref"),
        ("bool.npy", [(0, True), (1, [1])], r"row 0: reference index must be a non-negative integer, got True"),
        ("boolarr.npy", [(0, np.array([True]))], r"row 0: reference index .* got True \(bool\)"),
        ("str.npy", [(0, "12"), (1, [1])], r"row 0: reference index .* got '12' \(str\)"),
        ("strq.npy", [("0", [0])], r"row 0: the query index must be a non-negative integer, got '0'"),
        ("boolq.npy", [(0, [0]), (True, [1])], r"row 1: the query index .* got True"),
        ("dict.npy", [(0, {3: 1})], r"row 0: reference index .* \(dict\)"),
        ("nan.npy", [(0, [float("nan")])], r"row 0: reference index .* got nan"),
        ("2d.npy", [(0, np.zeros((2, 2), int))], r"row 0: references of shape \(2, 2\)"),
    ]
    for name, rows, pattern in cases:
        with pytest.raises(GroundTruthFormatError, match=pattern) as e:
            read_vpr_bench_ground_truth(_saved(tmp_path, name, _vpr_rows(rows)))
        assert e.value.path.endswith(name)
    with pytest.raises(GroundTruthFormatError, match=r"row 1: reference index 1000000000000000 is not below "
                                                     r"num_references=5"):
        read_vpr_bench_ground_truth(_saved(tmp_path, "big.npy", _vpr_rows([(0, [0]), (1, [10 ** 15])])),
                                    num_references=5)
    # numpy integers and integral floats are indices; the matrix bound leaves room for real reference sets
    rows = [(np.int32(0), np.array([1, 2], np.uint8)), (1.0, 4.0), (2, [50_000])]
    gt = read_vpr_bench_ground_truth(_saved(tmp_path, "ok.npy", _vpr_rows(rows)))
    assert gt.shape == (3, 50_001) and gt.sum() == 4


def test_read_matrix_refuses_non_binary_values(tmp_path):
    """A grey level, a JPEG's artefacts, -1 or 0.5 are refused (named file, first (row, column), value)."""
    img = np.zeros((4, 4), np.uint8)
    img[1, 0] = 255
    img[2, 1] = 128
    img[3, 3] = 1
    cv2.imwrite(str(tmp_path / "grey.png"), img)
    with pytest.raises(GroundTruthFormatError, match=r"grey.png: entry at \(row 2, column 1\) is 128: .*binary"):
        read_ground_truth_matrix(tmp_path / "grey.png")
    cv2.imwrite(str(tmp_path / "grey16.png"), img.astype(np.uint16) * 257)
    with pytest.raises(GroundTruthFormatError, match=r"grey16.png: entry at \(row 2, column 1\) is 32896"):
        read_ground_truth(tmp_path / "grey16.png")
    mixed = np.zeros((3, 3))
    mixed[0, 2], mixed[1, 1] = 1.0, 255.0  # 0/1 from the first non-zero entry: 255 is then the odd one
    for arr, pattern in ((mixed, r"\(row 1, column 1\) is 255.0"),
                         (np.array([[0.0, 0.5], [0.0, 0.0]], np.float32), r"\(row 0, column 1\) is 0.5"),
                         (np.array([[0, 0, 0], [0, -1, 0]], np.int8), r"\(row 1, column 1\) is -1"),
                         (np.array([[0, 3, 0]], np.int64), r"\(row 0, column 1\) is 3")):
        with pytest.raises(GroundTruthFormatError, match=r"m.npy: entry at " + pattern):
            read_ground_truth_matrix(_saved(tmp_path, "m.npy", arr))
    with pytest.raises(GroundTruthFormatError, match=r"c.npy: .*dtype complex128"):
        read_ground_truth_matrix(_saved(tmp_path, "c.npy", np.array([[complex(np.nan, 0), 0]])))
    with pytest.raises(GroundTruthFormatError, match=r"c.npy: .*dtype complex64"):
        read_ground_truth(_saved(tmp_path, "c.npy", np.eye(2, dtype=np.complex64)))
    # binary in every accepted form reads as before
    want = [[False, True], [True, False]]
    for ones, dtype in ((1, np.float64), (1, np.int32), (255, np.uint8), (255, np.float32), (65535, np.uint16),
                        (65535, np.int64)):
        arr = np.array([[0, ones], [ones, 0]], dtype=dtype)
        assert read_ground_truth_matrix(_saved(tmp_path, "ok.npy", arr)).tolist() == want, (ones, dtype)
    assert read_ground_truth_matrix(_saved(tmp_path, "ok.npy", np.array(want))).tolist() == want
    assert read_ground_truth_matrix(_saved(tmp_path, "zero.npy", np.zeros((2, 3)))).sum() == 0
    cv2.imwrite(str(tmp_path / "w16.png"), np.array(want, np.uint16) * 65535)
    assert read_ground_truth_matrix(tmp_path / "w16.png").tolist() == want


def test_rtabmap_ground_truth_image(data_dir):
    path = data_dir / "rtabmap-samples" / "samples_GT.bmp"
    if not path.is_file():
        pytest.skip(f"{path} not found")
    assert np.unique(cv2.imread(str(path), cv2.IMREAD_UNCHANGED)).tolist() == [0, 255]  # binary: still read
    gt = read_ground_truth(path)
    assert gt.shape == (84, 84) and int(gt.sum()) == 228
    assert not gt[:40].any() and gt[40:].any(dim=1).all()  # images 41-84 revisit, 1-40 do not
    assert not torch.triu(gt).any()  # only earlier images are marked
    assert torch.nonzero(gt[40]).flatten().tolist() == [0, 1, 2]  # 41 revisits 1, 2, 3


# ---------------------------------------------------------------------------------------------------
# Ground truth from poses


def _pose(x=0.0, yaw_deg=0.0):
    q = so3_exp(torch.tensor([0.0, math.radians(yaw_deg), 0.0], dtype=torch.float64))
    return torch.cat([torch.tensor([x, 0.0, 0.0], dtype=torch.float64), q])


def test_ground_truth_from_poses_equals_the_loop_pairs():
    g = torch.Generator().manual_seed(1)
    n = 120
    poses = torch.stack([_pose(float(x), float(a)) for x, a in zip(torch.rand(n, generator=g) * 2,
                                                                    torch.rand(n, generator=g) * 90)])
    poses[7] = float("nan")
    cfg = LoopGroundTruthConfig(max_distance=0.3, max_angle_deg=30.0, min_frame_gap=10)
    gt = ground_truth_from_poses(poses, config=cfg)
    pairs = ground_truth_loops(poses, cfg)
    assert gt.shape == (n, n) and int(gt.sum()) == pairs.shape[0] > 50
    assert torch.equal(torch.nonzero(gt), pairs)
    assert not gt[7].any() and not gt[:, 7].any()


def test_ground_truth_from_two_pose_sets():
    queries = torch.stack([_pose(0.0), _pose(1.0), _pose(0.0, 50.0)])
    refs = torch.stack([_pose(0.45), _pose(0.55), _pose(1.2, 10.0)])
    gt = ground_truth_from_poses(queries, refs)  # 0.5 m, 45 degrees, no frame gap between two sets
    assert gt.tolist() == [[True, False, False], [False, True, True], [False, False, False]]
    with pytest.raises(ShapeMismatchError, match=r"reference_poses must have shape \(N, 7\), got \(3, 6\)"):
        ground_truth_from_poses(queries, refs[:, :6])


def test_sequence_similarity_hand_computed():
    s = torch.tensor([[0.1, 0.2, 0.3], [0.4, 0.5, 0.6], [0.7, 0.8, 0.9]])
    assert torch.equal(sequence_similarity(s, 1), s.double())
    # (i, j) -> mean of s[max(i - k, 0), max(j - k, 0)], k = 0, 1, 2
    want = torch.tensor([[0.1 + 0.1 + 0.1, 0.2 + 0.1 + 0.1, 0.3 + 0.2 + 0.1],
                         [0.4 + 0.1 + 0.1, 0.5 + 0.1 + 0.1, 0.6 + 0.2 + 0.1],
                         [0.7 + 0.4 + 0.1, 0.8 + 0.4 + 0.1, 0.9 + 0.5 + 0.1]], dtype=torch.float64) / 3
    assert torch.allclose(sequence_similarity(s, 3), want, atol=1e-15)
    assert torch.allclose(sequence_similarity(s.numpy(), 3), want, atol=1e-15)
    # a length beyond the sequence repeats the first frames: a constant stays that constant
    assert torch.allclose(sequence_similarity(torch.full((3, 4), 0.7), 6), torch.full((3, 4), 0.7, dtype=torch.float64))
    assert sequence_similarity(torch.zeros(0, 4), 3).shape == (0, 4)
    assert sequence_similarity(torch.zeros(3, 0), 3).shape == (3, 0)


def test_sequence_similarity_outvotes_a_one_frame_look_alike():
    # query 5 looks most like reference 0 (a blank wall seen elsewhere); its predecessors agree on the
    # diagonal through reference 3, so the sequence of 3 finds it
    s = torch.full((6, 6), 0.2)
    s[4, 2], s[3, 1] = 0.9, 0.9
    s[5, 3], s[5, 0] = 0.6, 0.95
    gt = torch.zeros(6, 6, dtype=torch.bool)
    gt[5, 3] = True
    assert evaluate(s, gt).recall_at(1) == 0.0
    assert evaluate(sequence_similarity(s, 3), gt).recall_at(1) == 1.0
    # a non-finite entry poisons every sequence through it, so evaluate never proposes one
    s[4, 2] = float("nan")
    out = sequence_similarity(s, 2)
    assert torch.isnan(out[4, 2]) and torch.isnan(out[5, 3]) and torch.isfinite(out[5, 2])


def test_sequence_similarity_errors():
    with pytest.raises(ShapeMismatchError, match=r"\(Q, R\), got \(3,\)"):
        sequence_similarity(torch.zeros(3), 2)
    for bad in (0, -1, 1.5, True):
        with pytest.raises(ValueError, match="positive integer"):
            sequence_similarity(torch.zeros(2, 2), bad)


def test_plot(tmp_path):
    r = evaluate(torch.eye(4) + 0.1 * torch.rand(4, 4), torch.eye(4, dtype=torch.bool))
    img = plot_place_recognition(tmp_path / "pr.png", {"a": r, "b": r}, size=(320, 260))
    assert img.shape == (260, 320, 3)
    assert cv2.imread(str(tmp_path / "pr.png")).shape == (260, 320, 3)


def test_evaluate_reads_a_vpr_bench_file_with_unmatched_trailing_references(tmp_path):
    # Tokyo 24/7-style distractors: references 3 and 4 match no query, so the file alone says 3 columns; the
    # similarity's 5 columns are the reference set
    rows = np.empty((2, 2), dtype=object)
    rows[0, 0], rows[0, 1] = 0, [1]
    rows[1, 0], rows[1, 1] = 1, [2]
    np.save(tmp_path / "gt.npy", rows, allow_pickle=True)
    sim = torch.tensor([[0.1, 0.9, 0.2, 0.3, 0.0], [0.1, 0.2, 0.3, 0.9, 0.0]])  # query 1: distractor 3 first
    r = evaluate(sim, tmp_path / "gt.npy")
    assert r.recall_at(1) == 0.5 and r.recall_at(2) == 1.0
    with pytest.raises(TypeError, match="pass the file's path"):
        evaluate(sim, np.load(tmp_path / "gt.npy", allow_pickle=True))
