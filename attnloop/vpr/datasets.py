"""Place-recognition sets as image paths and a ground truth."""
from __future__ import annotations

import csv
from pathlib import Path
from typing import NamedTuple

import torch

from attnloop.vpr.describe import VPRInputError


class VPRSet(NamedTuple):
    """Query and reference images and what counts as a match.

    Attributes:
        query: Q image paths.
        reference: R image paths, or None: the queries against themselves.
        ground_truth: ``(Q, R)`` bool (``(Q, Q)`` without references): reference r shows query q's place.
        candidates: ``(Q, R)`` bool, the pairs a query may return (None: all).
    """

    query: list
    reference: list | None
    ground_truth: torch.Tensor
    candidates: torch.Tensor | None = None


def aligned_ground_truth(query_index, reference_index, tolerance: int) -> torch.Tensor:
    """Index-aligned ground truth: query q matches reference r when their frame numbers differ by at most
    ``tolerance``. ``(Q,)``, ``(R,)`` integers -> ``(Q, R)`` bool."""
    if isinstance(tolerance, bool) or int(tolerance) != tolerance or tolerance < 0:
        raise VPRInputError(f"tolerance must be a non-negative integer, got {tolerance!r}")
    q, r = torch.as_tensor(query_index), torch.as_tensor(reference_index)
    return (q[:, None] - r[None, :]).abs() <= int(tolerance)


def nordland(root, step: int = 1, tolerance: int = 1) -> VPRSet:
    """Nordland (the SeqSLAM trim, ``nordland-64x32``): winter queries against summer references.

    The seasons are frame-synchronised; ``gt_index_aligned.csv`` pairs them (query_idx, ref_idx,
    query_file, ref_file). A match is a reference within ``tolerance`` frames of the query's (frames of
    the trimmed set, every 10th of the ride); ``step`` keeps every ``step``-th pair.

    Args:
        root: the folder holding ``gt_index_aligned.csv``, ``winter/`` and ``summer/``.
        step: subsampling (``--step 10``: 358 of the 3576 pairs).
        tolerance: frames either side counted as the same place.

    Returns:
        a :class:`VPRSet` (``ground_truth`` ``(Q, Q)``).
    """
    root = Path(root)
    try:
        with open(root / "gt_index_aligned.csv", newline="") as f:
            rows = list(csv.DictReader(f))
    except OSError as e:
        raise VPRInputError(f"{root / 'gt_index_aligned.csv'}: {e.strerror or e}") from None
    rows.sort(key=lambda r: int(r["query_idx"]))
    if any(int(r["query_idx"]) != int(r["ref_idx"]) or int(r["query_idx"]) != i for i, r in enumerate(rows)):
        raise VPRInputError(f"{root / 'gt_index_aligned.csv'}: not index-aligned pairs 0, 1, 2, ...")
    if isinstance(step, bool) or int(step) != step or step < 1:
        raise VPRInputError(f"step must be a positive integer, got {step!r}")
    keep = list(range(0, len(rows), int(step)))  # tolerance counts frames of the full sequence
    return VPRSet([str(root / rows[i]["query_file"]) for i in keep], [str(root / rows[i]["ref_file"]) for i in keep],
                  aligned_ground_truth(keep, keep, tolerance))


def rtabmap(root, min_gap: int = 10) -> VPRSet:
    """RTAB-Map's samples: 84 corridor images against themselves, each against those at least ``min_gap``
    earlier, RTAB-Map's ``samples_GT.bmp`` as the ground truth."""
    from attnloop.vpr.evaluate import read_ground_truth, sequence_candidates

    root = Path(root)
    return VPRSet([str(root / f"{i}.jpg") for i in range(1, 85)], None, read_ground_truth(root / "samples_GT.bmp"),
                  sequence_candidates(84, min_gap))
