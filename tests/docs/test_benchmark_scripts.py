"""Every benchmark script runs as ``python -m benchmarks.NAME`` from the repository's root: ``--help`` exits 0.

All of them run in one interpreter (``runpy``, as ``-m`` runs a module), so the suite imports torch and the
library once rather than once a script.
"""
from __future__ import annotations

import json
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]

_RUN_ALL = """
import contextlib, io, json, runpy, sys, traceback
out = {}
for name in sys.argv[1:]:
    stdout, stderr = io.StringIO(), io.StringIO()
    code = 0
    sys.argv = [f"benchmarks/{name}.py", "--help"]
    with contextlib.redirect_stdout(stdout), contextlib.redirect_stderr(stderr):
        try:
            runpy.run_module(f"benchmarks.{name}", run_name="__main__", alter_sys=True)
        except SystemExit as e:
            code = e.code if isinstance(e.code, int) else (0 if e.code is None else 1)
        except BaseException:
            traceback.print_exc()
            code = 1
    out[name] = [code, stdout.getvalue()[:400], stderr.getvalue()[-2000:]]
print(json.dumps(out))
"""


def benchmark_scripts() -> list[str]:
    """The modules of benchmarks/ with a ``__main__`` guard (the others are helpers)."""
    return [p.stem for p in sorted((ROOT / "benchmarks").glob("*.py"))
            if re.search(r"^if __name__ == .__main__.:", p.read_text(encoding="utf-8"), flags=re.MULTILINE)]


@pytest.fixture(scope="module")
def help_outputs() -> dict:
    """``{name: [exit code, stdout, stderr]}`` of every script's ``--help``."""
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}  # nothing but the working folder
    env["OMP_NUM_THREADS"] = "1"
    r = subprocess.run([sys.executable, "-c", _RUN_ALL, *benchmark_scripts()], cwd=ROOT, env=env,
                       capture_output=True, text=True, timeout=600, check=False)
    assert r.returncode == 0, r.stderr[-3000:]
    return json.loads(r.stdout.strip().splitlines()[-1])


def test_the_scripts_are_found():
    names = benchmark_scripts()
    assert {"slam_pipeline", "descriptor", "index", "place_recognition"} <= set(names)
    assert "_common" not in names and "index_data" not in names


@pytest.mark.parametrize("name", benchmark_scripts())
def test_help_runs_as_a_module(name, help_outputs):
    code, stdout, stderr = help_outputs[name]
    assert code == 0, f"python -m benchmarks.{name} --help: exit {code}\n{stderr}"
    assert stdout.startswith("usage: "), stdout[:200]
