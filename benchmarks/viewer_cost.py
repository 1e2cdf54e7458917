"""What recording a run for the rerun viewer costs (``attnloop-slam --rrd FILE``, slam.viewer): frames/s with and
without it, side by side on the 7-Scenes kitchen.

    python -m benchmarks.viewer_cost [--data ../shared/data] [--rounds 2] [--max-frames N] [--out runs/viewer_cost]

Each round runs ``python -m slam.cli KITCHEN --out ... --quiet`` (the default run: loops, online correction,
map.ply; ``OMP_NUM_THREADS=1``) once without and once with ``--rrd``, in fresh processes, the order alternating
between rounds so that the machine's load hits both alike. Printed per run: the frames/s of ``metrics.json``
(the run loop, the recording's logging and its final poses included), the process's wall seconds (start-up and
the recording's last flush included) and CPU ms per frame (every thread), the ``.rrd`` size; then the median of
the per-round ratios (with / without): of frames/s, the figure that must stay >= 0.9, and of CPU per frame, which
a machine loaded by other processes blurs least.
"""
from __future__ import annotations

import argparse
import json
import os
import resource
import statistics
import subprocess
import sys
import time
from pathlib import Path

from benchmarks._common import ROOT, add_data_argument


def _run(seq: Path, out: Path, rrd: Path | None, max_frames: int | None) -> dict:
    cmd = [sys.executable, "-m", "slam.cli", str(seq), "--out", str(out), "--quiet"]
    cmd += ["--rrd", str(rrd)] if rrd is not None else []
    cmd += ["--max-frames", str(max_frames)] if max_frames else []
    env = {**os.environ, "PYTHONPATH": str(ROOT), "OMP_NUM_THREADS": "1"}
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    start = time.perf_counter()
    subprocess.run(cmd, env=env, cwd=str(ROOT), check=True, stdout=subprocess.DEVNULL)
    wall = time.perf_counter() - start
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    m = json.loads((out / "metrics.json").read_text())
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    return {"fps": m["fps"], "wall_s": wall, "cpu_ms_per_frame": 1000 * cpu / m["num_frames"],
            "frames": m["num_frames"], "loops": m["num_loops"], "rrd_mb": rrd.stat().st_size / 1e6 if rrd else None,
            "load": os.getloadavg()[0]}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m benchmarks.viewer_cost", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    add_data_argument(p)
    p.add_argument("--rounds", type=int, default=2, help="pairs of runs, with and without --rrd (default: 2)")
    p.add_argument("--max-frames", type=int, default=None, metavar="N", help="only the first N frames (default: all)")
    p.add_argument("--out", type=Path, default=Path("runs/viewer_cost"),
                   help="output folder (default: runs/viewer_cost)")
    args = p.parse_args(argv)
    seq = (args.data / "7scenes-redkitchen").resolve()
    if not (seq / "frame-000000.color.jpg").is_file():
        raise SystemExit(f"no 7-Scenes redkitchen sequence at {seq} (--data or ATTNLOOP_DATA)")
    out = args.out.resolve()
    runs: dict[str, list] = {"without": [], "with --rrd": []}
    for r in range(args.rounds):
        order = ("without", "with --rrd") if r % 2 == 0 else ("with --rrd", "without")
        for name in order:
            rrd = out / "run.rrd" if name != "without" else None
            if rrd is not None and rrd.exists():
                rrd.unlink()
            res = _run(seq, out / name.replace(" ", "").replace("-", ""), rrd, args.max_frames)
            runs[name].append(res)
            size = f", .rrd {res['rrd_mb']:.0f} MB" if rrd else ""
            print(f"round {r + 1} {name}: {res['fps']:.2f} frames/s, {res['wall_s']:.1f} s wall, "
                  f"{res['cpu_ms_per_frame']:.1f} CPU ms/frame, {res['loops']} loops{size}, load {res['load']:.1f}",
                  flush=True)
    ratios = [a["fps"] / b["fps"] for a, b in zip(runs["with --rrd"], runs["without"])]
    walls = [b["wall_s"] / a["wall_s"] for a, b in zip(runs["with --rrd"], runs["without"])]
    cpu = [a["cpu_ms_per_frame"] / b["cpu_ms_per_frame"] for a, b in zip(runs["with --rrd"], runs["without"])]
    print(f"{runs['without'][0]['frames']} kitchen frames, {args.rounds} rounds: frames/s with --rrd / without, per "
          f"round {[round(x, 3) for x in ratios]}, median {statistics.median(ratios):.3f} (process wall time ratio "
          f"{statistics.median(walls):.3f}); CPU per frame with / without, median {statistics.median(cpu):.3f} "
          "(what the load of other processes changes least)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
