"""Wall-clock time per pipeline stage."""
from __future__ import annotations

import time
from collections import defaultdict
from contextlib import contextmanager
from typing import Dict, Iterator


class StageTimer:
    """Accumulates seconds and call counts per named stage.

    Example:
        >>> timer = StageTimer()
        >>> with timer("odometry"):
        ...     pass
        >>> sorted(timer.summary())
        ['odometry']
    """

    def __init__(self) -> None:
        self.seconds: Dict[str, float] = defaultdict(float)
        self.calls: Dict[str, int] = defaultdict(int)

    @contextmanager
    def __call__(self, stage: str) -> Iterator[None]:
        start = time.perf_counter()
        try:
            yield
        finally:
            self.seconds[stage] += time.perf_counter() - start
            self.calls[stage] += 1

    def summary(self) -> Dict[str, Dict[str, float]]:
        """``{stage: {"total_s": ..., "calls": ..., "ms_per_call": ...}}``."""
        return {
            k: {"total_s": round(v, 4), "calls": self.calls[k],
                "ms_per_call": round(1000.0 * v / max(self.calls[k], 1), 3)}
            for k, v in self.seconds.items()
        }
