"""Wall time of the kitchen command on an idle machine and with cores kept busy by another process.

    python -m benchmarks.threads [--data ../shared/data] [--frames 150] [--rounds 3] [--threads 2 4]
    python -m benchmarks.threads --command [--rounds 2] [--frames N] [--compare OTHER_CHECKOUT]

``--command`` times the whole command of docs/results.md's kitchen figure, ``python -m slam.cli
../shared/data/7scenes-redkitchen --out DIR --quiet`` (every frame unless ``--frames``), in a fresh process
each time with no OMP/MKL/OpenBLAS thread variable set (its own thread limit is all it has), idle then busy in
each round, and prints each run's wall time, frames/s, ATE, loops and the load average, then the median of the
busy/idle ratios (the goal: <= 1.5). ``--compare DIR`` runs the same command from another checkout of the
repository in the same rounds (another version of the code under the same load).

Runs what ``attnloop-slam ../shared/data/7scenes-redkitchen --max-frames 150 --out DIR`` runs (its config
from :func:`slam.options.resolve_settings`, the map on; outputs not written) with each thread setting, idle
and busy, interleaved in one process: every round runs every setting idle, then starts ``--busy`` spinning
subprocesses (``while True: pass``, one core each) and runs every setting again, then stops them. Settings:
the config's default (``SLAMConfig.threads``), then each ``--threads N`` (default: torch's own count in this
process, what a run used before the setting existed). Prints the median wall time of each setting idle and
busy and the median over rounds of the busy/idle ratio (the default's goal: <= 1.5), and
checks that the caller's torch/OpenCV thread counts are the same after every run.

Timings are only comparable within one run of this script; on a machine that other work also loads, the
"idle" column is not idle: re-run it quietly for the figures of docs/results.md.
"""
from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import torch

from benchmarks._common import add_data_argument
from slam.config import SLAMConfig
from slam.io import open_sequence
from slam.options import resolve_settings
from slam.pipeline import run_slam
from slam.threads import thread_counts


def _spinners(n: int) -> list[subprocess.Popen]:
    procs = [subprocess.Popen([sys.executable, "-c", "while True: pass"]) for _ in range(n)]
    time.sleep(0.5)  # let them be scheduled before the timed run starts
    return procs


def _stop(procs: list[subprocess.Popen]) -> None:
    for p in procs:
        p.kill()
    for p in procs:
        p.wait()


def _run(seq, threads, frames: int) -> tuple[float, dict]:
    # what attnloop-slam builds for this folder with --threads only
    cfg = resolve_settings({"threads": threads}, sequence=seq).config
    before = thread_counts()
    t0 = time.perf_counter()
    run = run_slam(seq, cfg, max_frames=frames, progress=False)
    wall = time.perf_counter() - t0
    after = thread_counts()
    if after != before:
        raise AssertionError(f"run_slam changed the caller's thread counts: {before} -> {after}")
    stages = {k: v["ms_per_call"] for k, v in run.result.timings.items() if "ms_per_call" in v}
    return wall, stages


_THREAD_VARIABLES = ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS")


def _command(folder: Path, frames: int | None, out: Path, code: Path) -> dict:
    """One run of the kitchen command in its own process: wall time and what its metrics.json says."""
    env = {k: v for k, v in os.environ.items() if k not in _THREAD_VARIABLES}
    argv = [sys.executable, "-m", "slam.cli", str(folder), "--out", str(out), "--quiet"]
    if frames is not None:
        argv += ["--max-frames", str(frames)]
    load = os.getloadavg()[0]
    t0 = time.perf_counter()
    subprocess.run(argv, env=env, check=True, stdout=subprocess.DEVNULL, cwd=code)
    wall = time.perf_counter() - t0
    m = json.loads((out / "metrics.json").read_text())
    return {"wall": wall, "fps": m["fps"], "ate": m["ate_rmse"], "loops": m["num_loops"], "load": load}


def _command_rounds(folder: Path, frames: int | None, rounds: int, busy: int, compare: Path | None) -> int:
    codes = {"this": Path(__file__).resolve().parents[1]}
    if compare is not None:
        codes[str(compare)] = compare.resolve()
    print(f"# threads.py --command: python -m slam.cli {folder} --quiet"
          + (f" --max-frames {frames}" if frames else "") + f"; {rounds} round(s), busy = {busy} spinning "
          f"process(es); {os.cpu_count()} CPUs, torch {torch.__version__}; "
          f"{time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}", flush=True)
    ratios: dict[str, list[float]] = {name: [] for name in codes}
    with tempfile.TemporaryDirectory() as tmp:
        for r in range(rounds):
            for name, code in codes.items():
                walls = {}
                for cond in ("idle", "busy"):
                    procs = _spinners(busy) if cond == "busy" else []
                    try:
                        m = _command(folder, frames, Path(tmp) / cond, code)
                    finally:
                        _stop(procs)
                    walls[cond] = m["wall"]
                    print(f"round {r + 1} {name} {cond}: {m['wall']:.1f} s wall, {m['fps']:.1f} frames/s, ATE "
                          f"{m['ate']:.4f} m, {m['loops']} loops (load average before it {m['load']:.2f})", flush=True)
                ratios[name].append(walls["busy"] / walls["idle"])
                print(f"round {r + 1} {name}: busy / idle {ratios[name][-1]:.2f}", flush=True)
    for name, rs in ratios.items():
        print(f"\nthe command ({name}): busy/idle wall-time ratio, median of {rounds} round(s): "
              f"{statistics.median(rs):.2f} (goal <= 1.5)")
    return 0


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_data_argument(p)
    p.add_argument("--frames", type=int, default=None,
                   help="input frames per run (default 150; with --command every frame)")
    p.add_argument("--command", action="store_true",
                   help="time the whole kitchen command, each run in its own process (python -m slam.cli)")
    p.add_argument("--compare", type=Path, default=None, metavar="DIR",
                   help="with --command: also run the command from this other checkout, in the same rounds")
    p.add_argument("--rounds", type=int, default=3, help="idle/busy rounds (default 3)")
    p.add_argument("--busy", type=int, default=1, help="spinning processes in the busy runs (default 1)")
    p.add_argument("--threads", type=int, nargs="*", default=None,
                   help="thread counts to compare with the default (default: torch's own count here)")
    args = p.parse_args(argv)

    folder = Path(args.data) / "7scenes-redkitchen"
    if not folder.is_dir():
        print(f"threads.py: {folder} not found (set --data or ATTNLOOP_DATA)", file=sys.stderr)
        return 2
    if args.command:
        return _command_rounds(folder, args.frames, args.rounds, args.busy, args.compare)
    args.frames = 150 if args.frames is None else args.frames
    seq = open_sequence(folder)
    default = SLAMConfig().threads
    extra = args.threads if args.threads is not None else [torch.get_num_threads()]
    settings = [default] + [t for t in extra if t != default]
    label = {t: (f"default ({t})" if t == default else f"{t}") for t in settings}
    print(f"# threads.py: {args.frames} frames of {folder}, {args.rounds} round(s), busy = {args.busy} spinning "
          f"process(es); {os.cpu_count()} CPUs, torch {torch.__version__} (own count {torch.get_num_threads()}), "
          f"caller's counts {thread_counts()}; {time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}", flush=True)
    _run(seq, default, 5)  # warm-up: imports, the backbone's weights read once from disk

    walls = {(t, c): [] for t in settings for c in ("idle", "busy")}
    stages = {}
    for r in range(args.rounds):
        for cond in ("idle", "busy"):
            procs = _spinners(args.busy) if cond == "busy" else []
            try:
                for t in settings:
                    w, st = _run(seq, t, args.frames)
                    walls[(t, cond)].append(w)
                    stages[(t, cond)] = st
                    print(f"round {r + 1} {cond} threads={label[t]}: {w:.2f} s "
                          f"(odometry {st.get('odometry', float('nan')):.1f} ms/frame, descriptor "
                          f"{st.get('descriptor', float('nan')):.1f} ms/keyframe)", flush=True)
            finally:
                _stop(procs)

    print("\n| threads | idle wall (s) | busy wall (s) | busy / idle | odometry ms/frame idle / busy |")
    print("|---|---|---|---|---|")
    for t in settings:
        idle, busy = walls[(t, "idle")], walls[(t, "busy")]
        ratio = statistics.median(b / i for b, i in zip(busy, idle))
        print(f"| {label[t]} | {statistics.median(idle):.2f} | {statistics.median(busy):.2f} | {ratio:.2f} | "
              f"{stages[(t, 'idle')].get('odometry', float('nan')):.1f} / "
              f"{stages[(t, 'busy')].get('odometry', float('nan')):.1f} |")
    ratio = statistics.median(b / i for b, i in zip(walls[(default, "busy")], walls[(default, "idle")]))
    print(f"\ndefault threads ({default}): busy/idle wall-time ratio {ratio:.2f} (target <= 1.5)")
    for t in settings:
        if t != default:
            rel = statistics.median(a / b for a, b in zip(walls[(t, "idle")], walls[(default, "idle")]))
            print(f"threads={t} idle / default idle: {rel:.2f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
