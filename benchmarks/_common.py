"""What the benchmark scripts share: where the data is, test frames, timing and table helpers."""
from __future__ import annotations

import argparse
import os
import time
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

#: the repository's root folder
ROOT = Path(__file__).resolve().parents[1]

DATA_HELP = "the shared data folder (default: ATTNLOOP_DATA or ../shared/data)"


def data_root() -> Path:
    """The shared data folder: env ``ATTNLOOP_DATA``, else ``../shared/data`` beside the repository."""
    return Path(os.environ.get("ATTNLOOP_DATA", ROOT.parent / "shared" / "data"))


def add_data_argument(parser: argparse.ArgumentParser) -> None:
    """The ``--data`` option every script that reads the shared data takes."""
    parser.add_argument("--data", type=Path, default=data_root(), help=DATA_HELP)


def test_frames(batch: int, seed: int = 0, uint8: bool = True) -> torch.Tensor:
    """Smooth random 640 x 480 RGB frames ``(B, 3, 480, 640)``: uint8 in channels-last memory, as a decoded
    image comes from numpy, or (``uint8=False``) float in [0, 1], as a training loop feeds them."""
    g = torch.Generator().manual_seed(seed)
    small = torch.rand(batch, 3, 30, 40, generator=g)
    big = F.interpolate(small, size=(480, 640), mode="bilinear", align_corners=False)
    img = (big + 0.05 * torch.rand(batch, 3, 480, 640, generator=g)).clamp(0, 1)
    if not uint8:
        return img
    return (img * 255).round().to(torch.uint8).permute(0, 2, 3, 1).contiguous().permute(0, 3, 1, 2)


def time_call(fn) -> float:
    """Seconds ``fn()`` takes."""
    t0 = time.perf_counter()
    fn()
    return time.perf_counter() - t0


def quartiles(values: list[float]) -> tuple[float, float, float]:
    """25th, 50th and 75th percentiles of ``values``."""
    q = np.percentile(values, [25, 50, 75])
    return float(q[0]), float(q[1]), float(q[2])


def table(header: list[str], rows: list[list]) -> str:
    """A markdown table of ``rows`` (cells formatted with ``str``) under ``header``."""
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    lines += ["| " + " | ".join(str(c) for c in row) + " |" for row in rows]
    return "\n".join(lines)
