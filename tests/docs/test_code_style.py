"""The repository's Python keeps lines to 120 characters and passes pyflakes' checks (names defined, imports used),
as ruff reads them with nothing but these rules: a trimmed module that lost a name it still uses fails here, not
at run time in a path no other test takes."""
from __future__ import annotations

import importlib.util
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
FOLDERS = ("attnloop", "slam", "benchmarks", "examples", "tests")


@pytest.mark.skipif(importlib.util.find_spec("ruff") is None, reason="needs ruff (attnloop[dev])")
def test_lines_fit_120_and_pyflakes_finds_nothing():
    r = subprocess.run([sys.executable, "-m", "ruff", "check", "--isolated", "--line-length", "120", "--select",
                        "E501,E9,F", "--output-format", "concise", "--no-cache", *FOLDERS],
                       cwd=ROOT, capture_output=True, text=True, timeout=300, check=False)
    assert r.returncode == 0, r.stdout[-4000:] + r.stderr[-2000:]
