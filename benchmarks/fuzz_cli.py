"""The outcome of every case of the command-line fuzz test (tests/test_fuzz_cli.py), as a table.

Runs each case's mutation and ``attnloop-slam`` exactly as the test does, and prints one row per case:
the exit code and what came of it (the ATE or why there is none, or the error's one line), then the
counts. The test asserts the invariants; this shows what each case does.

    python benchmarks/fuzz_cli.py [--out FILE.md]
"""
from __future__ import annotations

import argparse
import contextlib
import io
import json
import os
import random
import shutil
import sys
import tempfile
from collections import Counter
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "tests"))

import test_fuzz_cli as T  # the cases themselves

from slam.io import Trajectory
from slam.synthetic import generate_sequence, make_trajectory


def _run(argv, out: Path):
    err, dev_null = io.StringIO(), io.StringIO()
    with contextlib.redirect_stderr(err), contextlib.redirect_stdout(dev_null):
        rc = T._exit_code(argv)
    if rc == 0:
        m = json.loads((out / "metrics.json").read_text())
        what = (f"ATE {m['ate_rmse']:.4f} m ({m['num_lost']} lost, {m['num_skipped']} unreadable)"
                if m["ate_rmse"] is not None else f"no ATE: {m['ate_unavailable']}")
    else:
        lines = [ln for ln in err.getvalue().splitlines() if ln.startswith("attnloop-slam")]
        what = lines[-1] if lines else err.getvalue().strip().splitlines()[-1]
    return rc, what


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out", type=Path, default=None, help="also write the table here")
    args = p.parse_args()
    os.environ["ATTNLOOP_OFFLINE"] = "1"
    tmp = Path(tempfile.mkdtemp(prefix="fuzz_cli."))
    os.environ["TORCH_HOME"] = str(tmp / "torch_home")  # no VGG16 weights, as in the test
    loop = make_trajectory("loop", 300)
    n = T.N
    base = generate_sequence(tmp / "base", width=160, height=120,
                             trajectory=Trajectory(loop.timestamps[:2 * n:2], loop.poses[:2 * n:2]))
    rows, counts = [], Counter()
    try:
        cases = [(name, mutate, extra) for name, mutate, extra, _, _ in T.CASES]
        for name, mutate, extra in cases:
            d = tmp / name
            folder = shutil.copytree(base, d / "seq")
            seq = mutate(folder) if mutate is not None else folder
            rc, what = _run([str(seq), "--out", str(d / "out"), "--quiet", *extra], d / "out")
            rows.append((name, rc, what))
        for name, extra, _ in T.DEMO_CASES:
            rc, what = _run(["--demo", "--demo-size", "160", "120", "--out", str(tmp / name), *extra], tmp / name)
            rows.append((name, rc, what))
        for kind, fname, seed in T.FILE_CASES:
            name = f"{fname}-{kind}-{seed}"
            folder = shutil.copytree(base, tmp / name / "seq")
            path = folder / fname
            path.write_bytes(T.mutate(path.read_bytes(), kind, random.Random(seed)))
            rc, what = _run([str(folder), "--out", str(tmp / name / "out"), "--quiet", "--no-loop"], tmp / name / "out")
            rows.append((name, rc, what))
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    lines = ["| case | exit | outcome |", "|---|---|---|"]
    for name, rc, what in rows:
        counts["finished (0)" if rc == 0 else "named error (2)" if rc == 2 else f"other ({rc})"] += 1
        lines.append(f"| {name} | {rc} | {what.replace(str(tmp), '...').replace('|', '/')[:160]} |")
    lines += ["", f"{len(rows)} cases: " + ", ".join(f"{v} {k}" for k, v in sorted(counts.items()))]
    text = "\n".join(lines) + "\n"
    print(text)
    if args.out:
        args.out.write_text(text)


if __name__ == "__main__":
    main()
