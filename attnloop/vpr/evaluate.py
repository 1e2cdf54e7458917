"""Place-recognition evaluation: recall@k, the best-match precision/recall curve, AUC-PR, R@P100.

Each query ranks its candidates by similarity, ties in database order; in the best-match PR curve every query
proposes its best candidate, and an accepted query without a true match is a false positive.

Example:
    >>> sim = torch.tensor([[0.9, 0.1, 0.2], [0.3, 0.8, 0.1], [0.2, 0.7, 0.4]])
    >>> gt = torch.tensor([[True, False, False], [False, True, False], [False, False, True]])
    >>> r = evaluate(sim, gt)
    >>> r.recall_at(1), r.recall_at(2), round(r.recall_at_full_precision, 3)
    (0.6666666666666666, 1.0, 0.667)
"""
from __future__ import annotations

import io
import math
import os
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import IO, Union

import cv2
import numpy as np
import torch

from slam.eval.loops import LoopGroundTruthConfig, PRCurve, plot_pr_curves, poses_close, precision_recall_curve
from slam.input_checks import source_name

__all__ = [
    "GroundTruthFormatError",
    "PlaceRecognitionResult",
    "ShapeMismatchError",
    "evaluate",
    "ground_truth_from_poses",
    "plot_place_recognition",
    "read_ground_truth",
    "read_ground_truth_matrix",
    "read_vpr_bench_ground_truth",
    "sequence_candidates",
    "sequence_similarity",
]

PathOrFile = Union[str, os.PathLike, IO[bytes]]


class GroundTruthFormatError(ValueError):
    """A ground-truth file that cannot be read or does not hold a ground truth.

    Attributes:
        path: the file name (``"<stream>"`` for an unnamed file object).
        reason: a short explanation (also in the message).
    """

    def __init__(self, path: str, reason: str):
        self.path = str(path)
        self.reason = reason
        super().__init__(f"{self.path}: {reason}")


class ShapeMismatchError(ValueError):
    """Similarity, ground truth and candidate mask of different shapes (the message gives them)."""


def _read_bytes(source: PathOrFile) -> tuple[str, bytes]:
    """The name of ``source`` in messages, and its bytes."""
    name = source_name(source)
    if isinstance(source, (str, os.PathLike)):
        try:
            with open(name, "rb") as f:
                return name, f.read()
        except FileNotFoundError:
            raise GroundTruthFormatError(name, "file does not exist") from None
        except OSError as e:
            raise GroundTruthFormatError(name, f"cannot read file ({type(e).__name__}: {e})") from None
    if hasattr(source, "read"):
        data = source.read()
        if isinstance(data, str):
            raise TypeError(f"{name}: open the ground-truth file in binary mode ('rb'), not text")
        return name, bytes(data)
    raise TypeError(f"expected a path or a binary file object, got {type(source).__name__}")


def _load_npy(data: bytes, name: str, allow_pickle: bool) -> np.ndarray:
    try:
        return np.load(io.BytesIO(data), allow_pickle=allow_pickle)
    except ValueError as e:
        if not allow_pickle and "allow_pickle" in str(e):
            raise GroundTruthFormatError(name, "holds Python objects (a VPR-Bench list?): read it with "
                                               "read_vpr_bench_ground_truth") from None
        raise GroundTruthFormatError(name, f"not a readable .npy file ({e})") from None
    except Exception as e:  # noqa: BLE001  (truncated or foreign data: numpy raises several kinds)
        raise GroundTruthFormatError(name, f"not a readable .npy file ({type(e).__name__}: {e})") from None


def _is_npy(data: bytes) -> bool:
    return data[:6] == b"\x93NUMPY"


def _matrix_from_array(arr: np.ndarray, name: str) -> torch.Tensor:
    if arr.ndim == 3 and arr.shape[2] in (3, 4):
        if not all(np.array_equal(arr[..., 0], arr[..., c]) for c in (1, 2)):
            raise GroundTruthFormatError(name, f"a colour image of shape {arr.shape}: a ground-truth matrix "
                                               "image must be grey (or have equal colour channels)")
        arr = arr[..., 0]
    if arr.ndim != 2:
        raise GroundTruthFormatError(name, f"a ground-truth matrix must be 2-D (queries, references), got shape "
                                           f"{arr.shape}")
    if not (arr.dtype == bool or np.issubdtype(arr.dtype, np.integer) or np.issubdtype(arr.dtype, np.floating)):
        raise GroundTruthFormatError(name, f"a ground-truth matrix must be boolean or real, got dtype {arr.dtype}")
    if np.issubdtype(arr.dtype, np.floating) and not np.isfinite(arr).all():
        r, c = np.argwhere(~np.isfinite(arr))[0]
        raise GroundTruthFormatError(name, f"non-finite entry at (row {r}, column {c})")
    if arr.dtype != bool:
        _check_binary(arr, name)
    return torch.from_numpy(np.ascontiguousarray(arr != 0))


_BINARY_ONES = (1, 255, 65535)  # a 0/1 array, an 8-bit and a 16-bit black/white image


def _check_binary(arr: np.ndarray, name: str) -> None:
    """Refuse a matrix whose values are not 0 and one of 1, 255, 65535 (the first non-zero value sets which)."""
    nonzero = arr != 0
    if not nonzero.any():
        return
    first = arr.flat[int(np.flatnonzero(nonzero)[0])]
    one = next((v for v in _BINARY_ONES if first == v), None)
    bad = nonzero if one is None else nonzero & (arr != one)
    if not bad.any():
        return
    r, c = (int(x) for x in np.argwhere(bad)[0])
    hint = ("; a (Q, 2) array of [query, reference] rows is read by read_vpr_bench_ground_truth"
            if arr.shape[1] == 2 else "")
    raise GroundTruthFormatError(name, f"entry at (row {r}, column {c}) is {arr[r, c].item()!r}: a ground-truth "
                                       f"matrix must be binary (0 and 1, 0 and 255, or 0 and 65535; a lossy "
                                       f"JPEG is not){hint}")


def read_ground_truth_matrix(source: PathOrFile) -> torch.Tensor:
    """Read a binary ground-truth matrix: an image (non-zero pixel = match) or a 2-D ``.npy`` array.

    Args:
        source: a path or a binary file object (the format is told from the content, not the name).

    Returns:
        ``(Q, R)`` bool; entry (q, r) is True when reference r shows the place of query q.

    Raises:
        GroundTruthFormatError: missing, undecodable, not 2-D, not real, non-finite or not binary (bool, or 0
            and one of 1, 255, 65535), naming the file and the first bad entry.
    """
    name, data = _read_bytes(source)
    if not data:
        raise GroundTruthFormatError(name, "empty file")
    if _is_npy(data):
        return _matrix_from_array(_load_npy(data, name, allow_pickle=False), name)
    image = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
    if image is None:
        raise GroundTruthFormatError(name, "neither a .npy array nor an image OpenCV can decode")
    return _matrix_from_array(image, name)


# Without num_references, a (Q, R) matrix implied by the largest index has at most this many entries (1 GiB).
_MAX_IMPLIED_ENTRIES = 2 ** 30


def _check_num_references(num_references) -> int | None:
    if num_references is None:
        return None
    if isinstance(num_references, (bool, np.bool_)) or not isinstance(num_references, (int, np.integer)):
        raise TypeError(f"num_references must be a non-negative integer, got {num_references!r}")
    if num_references < 0:
        raise ValueError(f"num_references must be a non-negative integer, got {num_references!r}")
    return int(num_references)


def _index_of(value, name: str, q: int, what: str) -> int:
    """One index: an int (or numpy integer), or an integral finite float; never a bool or a string."""
    integer = isinstance(value, (int, np.integer)) and not isinstance(value, (bool, np.bool_))
    integral = isinstance(value, (float, np.floating)) and math.isfinite(value) and value == math.floor(value)
    v = int(value) if integer or integral else None
    if v is None or v < 0:
        raise GroundTruthFormatError(name, f"row {q}: {what} must be a non-negative integer, got {value!r} "
                                           f"({type(value).__name__})")
    return v


def _reference_indices(refs, name: str, q: int) -> list[int]:
    if isinstance(refs, np.ndarray):
        if refs.ndim > 1:
            raise GroundTruthFormatError(name, f"row {q}: references of shape {refs.shape}; expected a list")
        items = refs.reshape(-1).tolist() if refs.dtype != object else list(refs.reshape(-1))
    elif isinstance(refs, (list, tuple, range)):
        items = list(refs)
    else:
        items = [refs]  # a single index (a string, a dict ... is refused there)
    return [_index_of(x, name, q, "reference index") for x in items]


def read_vpr_bench_ground_truth(source: PathOrFile, num_references: int | None = None) -> torch.Tensor:
    """Read a VPR-Bench ``ground_truth_new.npy``: row q is ``[q, matching reference indices]``.

    An object array ``(Q, 2)`` or ``(Q,)`` of ``[q, matches]`` (a list, range or array of indices, or one
    index), or a numeric ``(Q, 2)`` array of ``[query, reference]`` rows. Row q must hold query q (VPR-Bench
    looks matches up by position). The file is a pickled object array: load only files you trust.

    Args:
        source: a path or a binary file object.
        num_references: the size R of the reference set (default: the largest index + 1, at most a 2^30
            entry matrix).

    Returns:
        ``(Q, R)`` bool matrix.

    Raises:
        GroundTruthFormatError: unreadable file, a malformed row or index (naming the file and the row).
        TypeError, ValueError: ``num_references`` is not a non-negative int.
    """
    num_references = _check_num_references(num_references)
    name, data = _read_bytes(source)
    if not _is_npy(data):
        raise GroundTruthFormatError(name, "not a .npy file")
    arr = _load_npy(data, name, allow_pickle=True)
    if arr.dtype != object and not (np.issubdtype(arr.dtype, np.integer) or np.issubdtype(arr.dtype, np.floating)):
        what = "a boolean matrix: read it with read_ground_truth_matrix" if arr.dtype == bool else "not indices"
        raise GroundTruthFormatError(name, f"dtype {arr.dtype} is {what}")
    lists = arr.dtype == object and arr.ndim == 1 and all(isinstance(x, (list, tuple, np.ndarray)) for x in arr)
    if not (lists or (arr.ndim == 2 and arr.shape[1] == 2) or arr.size == 0):
        raise GroundTruthFormatError(name, f"expected rows [query, [references]] (shape (Q, 2)), got shape "
                                           f"{arr.shape} dtype {arr.dtype}")
    rows = list(arr) if arr.size else []
    matches: list[list[int]] = []
    for q, row in enumerate(rows):
        if len(row) != 2:
            raise GroundTruthFormatError(name, f"row {q}: expected [query, [references]], got {len(row)} entries")
        index = _index_of(row[0], name, q, "the query index")
        if index != q:
            raise GroundTruthFormatError(name, f"row {q}: holds query {row[0]!r}; VPR-Bench reads row q as query q")
        matches.append(_reference_indices(row[1], name, q))
    if num_references is None:
        bound = max(_MAX_IMPLIED_ENTRIES // max(len(matches), 1), 1)
        limit = (f"{bound} (a matrix of at most 2^30 entries for {len(matches)} queries); give num_references if "
                 "the reference set is that large")
    else:
        bound, limit = num_references, f"num_references={num_references}"
    for q, m in enumerate(matches):
        if m and max(m) >= bound:
            raise GroundTruthFormatError(name, f"row {q}: reference index {max(m)} is not below {limit}")
    if num_references is None:
        num_references = max((max(m) + 1 for m in matches if m), default=0)
    gt = torch.zeros(len(matches), num_references, dtype=torch.bool)
    for q, m in enumerate(matches):
        gt[q, torch.tensor(m, dtype=torch.long)] = True
    return gt


def read_ground_truth(source: PathOrFile, num_references: int | None = None) -> torch.Tensor:
    """Read a VPR-Bench object ``.npy`` (:func:`read_vpr_bench_ground_truth`), else a binary matrix, whatever its shape.

    Args:
        source: a path or a binary file object.
        num_references: the size of the reference set; a matrix must then have that many columns.

    Returns:
        ``(Q, R)`` bool matrix.
    """
    num_references = _check_num_references(num_references)
    name, data = _read_bytes(source)
    buf = io.BytesIO(data)
    buf.name = name
    if _is_npy(data) and _npy_dtype(data, name) == np.dtype(object):
        return read_vpr_bench_ground_truth(buf, num_references)
    gt = read_ground_truth_matrix(buf)
    if num_references is not None and gt.shape[1] != num_references:
        raise ShapeMismatchError(f"{name}: the ground-truth matrix has {gt.shape[1]} columns, expected "
                                 f"num_references={num_references}")
    return gt


def _npy_dtype(data: bytes, name: str) -> np.dtype:
    stream = io.BytesIO(data)
    try:
        major, _ = np.lib.format.read_magic(stream)
        read = np.lib.format.read_array_header_1_0 if major == 1 else np.lib.format.read_array_header_2_0
        return read(stream)[2]
    except Exception as e:  # noqa: BLE001  (a damaged header: numpy raises several kinds)
        raise GroundTruthFormatError(name, f"not a readable .npy file ({type(e).__name__}: {e})") from None


def ground_truth_from_poses(
    query_poses: torch.Tensor,
    reference_poses: torch.Tensor | None = None,
    config: LoopGroundTruthConfig | None = None,
) -> torch.Tensor:
    """Ground truth from camera poses: closer than ``config.max_distance`` and ``config.max_angle_deg``.

    With one sequence (``reference_poses`` None) frame i's database is the frames at least
    ``config.min_frame_gap`` earlier; NaN rows match nothing.

    Args:
        query_poses: ``(Q, 7)`` ``[tx, ty, tz, qx, qy, qz, qw]`` (a :class:`slam.io.Trajectory`'s poses).
        reference_poses: ``(R, 7)``, or None for a single sequence.
        config: the thresholds (default :class:`LoopGroundTruthConfig`: 0.5 m, 45 degrees, 100 frames).

    Returns:
        ``(Q, R)`` bool (``(Q, Q)`` for one sequence).
    """
    config = LoopGroundTruthConfig() if config is None else config
    def check(p, what):
        p = torch.as_tensor(np.asarray(p) if not isinstance(p, torch.Tensor) else p).to("cpu", torch.float64)
        if p.dim() != 2 or p.shape[-1] != 7:
            raise ShapeMismatchError(f"{what} must have shape (N, 7), got {tuple(p.shape)}")
        return p

    q = check(query_poses, "query_poses")
    r = q if reference_poses is None else check(reference_poses, "reference_poses")
    out = poses_close(q[:, None, :], r[None, :, :], config)
    if reference_poses is None:
        out &= sequence_candidates(q.shape[0], config.min_frame_gap)
    return out


def sequence_candidates(n: int, min_gap: int) -> torch.Tensor:
    """The candidates of a single sequence: frame i against the frames at least ``min_gap`` earlier.

    Args:
        n: number of frames.
        min_gap: the minimum index difference (``>= 1``).

    Returns:
        ``(n, n)`` bool, entry (i, j) True when ``j <= i - min_gap``.
    """
    if int(min_gap) != min_gap or min_gap < 1:
        raise ValueError(f"min_gap must be a positive integer, got {min_gap!r}")
    idx = torch.arange(int(n))
    return (idx[:, None] - idx[None, :]) >= int(min_gap)


def sequence_similarity(similarity: torch.Tensor | np.ndarray, length: int) -> torch.Tensor:
    """Similarity of short sequences: each pair scored with the ``length - 1`` pairs before it.

    SeqSLAM's causal diagonal at speed 1: entry (i, j) is the mean of ``similarity[i - k, j - k]`` for
    ``k = 0 .. length - 1``, an index below 0 clamped to 0.

    Args:
        similarity: ``(Q, R)``; a non-finite entry makes every sequence through it non-finite.
        length: frames per sequence (``>= 1``; 1 returns the similarity unchanged, as float64).

    Returns:
        ``(Q, R)`` float64 on the input's device.
    """
    sim = similarity if isinstance(similarity, torch.Tensor) else torch.from_numpy(np.asarray(similarity))
    if sim.dim() != 2:
        raise ShapeMismatchError(f"similarity must have shape (Q, R), got {tuple(sim.shape)}")
    if isinstance(length, bool) or int(length) != length or length < 1:
        raise ValueError(f"length must be a positive integer, got {length!r}")
    sim = sim.detach().to(torch.float64)
    q, r = sim.shape
    rows, cols = torch.arange(q, device=sim.device), torch.arange(r, device=sim.device)
    out = torch.zeros_like(sim)
    for k in range(int(length)):  # length is a handful of frames: one gather of the (Q, R) matrix each
        out += sim[(rows - k).clamp_min(0)][:, (cols - k).clamp_min(0)]
    return out / int(length)


@dataclass
class PlaceRecognitionResult:
    """What :func:`evaluate` measured. All tensors are on the CPU.

    Attributes:
        best: ``(Q,)`` int64 index of each query's best candidate (-1: no candidate).
        best_score: ``(Q,)`` float64 its similarity (-inf: no candidate).
        correct: ``(Q,)`` bool: the best candidate is a true match.
        has_match: ``(Q,)`` bool: the query has at least one true match among its candidates.
        first_true_rank: ``(Q,)`` int64 0-based rank of the best-ranked true match (-1: none).
        curve: the best-match precision/recall curve, recall relative to the queries with a match.
        vpr_bench_curve: the same ranking with VPR-Bench's recall (relative to the correct best matches).
    """

    best: torch.Tensor = field(repr=False)
    best_score: torch.Tensor = field(repr=False)
    correct: torch.Tensor = field(repr=False)
    has_match: torch.Tensor = field(repr=False)
    first_true_rank: torch.Tensor = field(repr=False)
    curve: PRCurve = field(repr=False)
    vpr_bench_curve: PRCurve = field(repr=False)

    @property
    def num_queries(self) -> int:
        """Q, the number of queries (rows of the similarity)."""
        return int(self.best.shape[0])

    @property
    def num_with_match(self) -> int:
        """The number of queries with at least one true match: the recall denominator."""
        return int(self.has_match.sum())

    def recall_at(self, k: int) -> float:
        """Fraction of the queries with a true match that have one among their ``k`` best candidates.

        Args:
            k: a positive integer.

        Returns:
            recall@k in [0, 1]; NaN when no query has a true match.
        """
        if isinstance(k, bool) or int(k) != k or k < 1:
            raise ValueError(f"k must be a positive integer, got {k!r}")
        n = self.num_with_match
        if n == 0:
            return math.nan
        hit = self.has_match & (self.first_true_rank >= 0) & (self.first_true_rank < int(k))
        return float(hit.sum()) / n

    @property
    def recall_at_full_precision(self) -> float:
        """The largest recall of :attr:`curve` with no false positive (NaN when no query has a match)."""
        return self.curve.max_recall_at_full_precision if self.num_with_match else math.nan

    @property
    def threshold_at_full_precision(self) -> float:
        """The similarity threshold reaching :attr:`recall_at_full_precision` (+inf when that is 0)."""
        return self.curve.threshold_at_full_precision

    @property
    def auc_pr(self) -> float:
        """Area under VPR-Bench's best-match PR curve (trapezoidal, from (0, 1)); 0 when none is correct."""
        c = self.vpr_bench_curve
        if c.num_positives == 0:
            return 0.0
        r, p = c.recall.numpy(), c.precision.numpy()
        return float(np.sum((r[1:] - r[:-1]) * (p[1:] + p[:-1]) / 2))

    @property
    def accuracy(self) -> float:
        """Fraction of all queries whose best candidate is a true match (VPR-Bench's "accuracy")."""
        return float(self.correct.sum()) / self.num_queries if self.num_queries else math.nan

    def to_dict(self) -> dict[str, object]:
        """The scalars as strict JSON (NaN and infinite values become None)."""
        def clean(v):
            return v if isinstance(v, int) or math.isfinite(v) else None
        return {"num_queries": self.num_queries, "num_with_match": self.num_with_match,
                "recall@1": clean(self.recall_at(1)), "recall@5": clean(self.recall_at(5)),
                "recall@10": clean(self.recall_at(10)), "auc_pr": clean(self.auc_pr),
                "recall_at_full_precision": clean(self.recall_at_full_precision),
                "threshold_at_full_precision": clean(self.threshold_at_full_precision),
                "accuracy": clean(self.accuracy)}


def _as_matrix(x, what: str) -> torch.Tensor:
    if isinstance(x, np.ndarray):
        if x.dtype == object:  # np.load of a VPR-Bench ground_truth_new.npy: rows, not a matrix
            raise TypeError(f"{what} is a numpy object array (a VPR-Bench ground_truth_new.npy as np.load gives "
                            "it?): pass the file's path, or read it with read_ground_truth(path, num_references)")
        x = torch.from_numpy(x)
    if not isinstance(x, torch.Tensor):
        raise TypeError(f"{what} must be a tensor or array (Q, R), got {type(x).__name__}")
    if x.dim() != 2:
        raise ShapeMismatchError(f"{what} must have shape (Q, R), got {tuple(x.shape)}")
    return x.detach().cpu()


def evaluate(
    similarity: torch.Tensor | np.ndarray,
    ground_truth: torch.Tensor | np.ndarray | str | os.PathLike,
    candidates: torch.Tensor | np.ndarray | None = None,
) -> PlaceRecognitionResult:
    """Evaluate a query x database similarity against the ground truth (:class:`PlaceRecognitionResult`).

    Args:
        similarity: ``(Q, R)`` higher = more alike (e.g. the cosine of unit descriptors). Non-finite
            entries are not candidates.
        ground_truth: ``(Q, R)`` bool (non-zero = match), or a path read by :func:`read_ground_truth`
            with ``num_references`` R (a VPR-Bench file's unmatched trailing references count).
        candidates: ``(Q, R)`` bool mask of the pairs a query may return (e.g.
            :func:`sequence_candidates` for "each image against those at least 10 earlier"); default all.

    Returns:
        a :class:`PlaceRecognitionResult` (``.recall_at(k)``, ``.auc_pr``, ``.recall_at_full_precision``,
        ``.curve``).

    Raises:
        ShapeMismatchError: the three matrices differ in shape.
    """
    sim = _as_matrix(similarity, "similarity")
    if not (sim.is_floating_point() or sim.dtype in (torch.int8, torch.int16, torch.int32, torch.int64,
                                                     torch.uint8)):
        raise TypeError(f"similarity must be numeric, got dtype {sim.dtype}")
    sim = sim.to(torch.float64)
    if isinstance(ground_truth, (str, os.PathLike)):
        # the similarity's columns are the reference set (a VPR-Bench file omits unmatched trailing ones)
        ground_truth = read_ground_truth(ground_truth, num_references=sim.shape[1])
    gt = _as_matrix(ground_truth, "ground_truth") != 0
    if gt.shape != sim.shape:
        raise ShapeMismatchError(f"similarity {tuple(sim.shape)} and ground_truth {tuple(gt.shape)} must have the "
                                 "same shape (queries, references)")
    valid = torch.isfinite(sim)
    if candidates is not None:
        cand = _as_matrix(candidates, "candidates")
        if cand.shape != sim.shape:
            raise ShapeMismatchError(f"candidates {tuple(cand.shape)} must have the shape of similarity "
                                     f"{tuple(sim.shape)}")
        valid &= cand != 0
    gt = gt & valid
    q = sim.shape[0]
    none = torch.full((q,), -1, dtype=torch.long)
    # One ordering for everything: by similarity, descending, ties in database order; non-candidates last.
    key = torch.where(valid, sim, torch.full_like(sim, -math.inf))
    order = torch.argsort(key, dim=1, descending=True, stable=True)
    padded = torch.cat([order, none[:, None]], dim=1)  # column 0 exists even without references
    any_valid = valid.any(dim=1)
    has_match = gt.any(dim=1)
    gt_sorted = torch.cat([torch.gather(gt, 1, order), has_match[:, None]], dim=1)
    first = torch.where(has_match, gt_sorted.to(torch.int8).argmax(dim=1), none)
    best = torch.where(any_valid, padded[:, 0], none)
    best_score = torch.cat([key, key.new_full((q, 1), -math.inf)], dim=1).amax(dim=1)  # the best's, -inf: none
    correct = any_valid & (first == 0)
    # Queries without a candidate propose nothing: a -inf score is never accepted (loops' convention).
    curve = precision_recall_curve(best_score, correct, num_positives=int(has_match.sum()))
    vpr = precision_recall_curve(best_score, correct, num_positives=int(correct.sum()))
    return PlaceRecognitionResult(best, best_score, correct, has_match, first, curve, vpr)


def plot_place_recognition(
    path: str | os.PathLike | None,
    results: Mapping[str, PlaceRecognitionResult] | Sequence[tuple[str, PlaceRecognitionResult]],
    title: str = "Place recognition: best-match precision / recall",
    size: tuple[int, int] = (640, 520),
) -> np.ndarray:
    """Draw the best-match PR curves (:attr:`PlaceRecognitionResult.curve`) of several methods to a PNG.

    Args:
        path: PNG to write, or None.
        results: ``{label: result}`` or ``[(label, result), ...]``.
        title: figure title.
        size: ``(W, H)`` pixels.

    Returns:
        the ``(H, W, 3)`` uint8 BGR image.
    """
    items = list(results.items()) if isinstance(results, Mapping) else list(results)
    return plot_pr_curves(path, [(label, res.curve) for label, res in items], title=title, size=size)
