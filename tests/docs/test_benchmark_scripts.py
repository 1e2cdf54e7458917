"""Every benchmark script runs as ``python -m benchmarks.NAME`` from the repository's root: ``--help`` exits 0."""
from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]


def benchmark_scripts() -> list[str]:
    """The modules of benchmarks/ with a ``__main__`` guard (the others are helpers)."""
    return [p.stem for p in sorted((ROOT / "benchmarks").glob("*.py"))
            if re.search(r"^if __name__ == .__main__.:", p.read_text(encoding="utf-8"), flags=re.MULTILINE)]


def test_the_scripts_are_found():
    names = benchmark_scripts()
    assert {"slam_pipeline", "descriptor", "index", "place_recognition"} <= set(names)
    assert "_common" not in names and "index_data" not in names


@pytest.mark.parametrize("name", benchmark_scripts())
def test_help_runs_as_a_module(name):
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}  # nothing but the working folder
    env["OMP_NUM_THREADS"] = "1"
    r = subprocess.run([sys.executable, "-m", f"benchmarks.{name}", "--help"], cwd=ROOT, env=env,
                       capture_output=True, text=True, timeout=300, check=False)
    assert r.returncode == 0, f"python -m benchmarks.{name} --help: exit {r.returncode}\n{r.stderr[-2000:]}"
    assert r.stdout.startswith("usage: "), r.stdout[:200]
