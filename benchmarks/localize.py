"""Localisation only in a saved map (``--localize``): accuracy, the map folder untouched, memory over laps.

Saves a map of one part of a sequence (default: 7-Scenes redkitchen frames 0-599), then places another part
(frames 850-999) in it three ways: relocalised as a recording of its own (``--map``, which grows its own
keyframes, index and map.ply), localised only (``--map --localize``), and localised over ``--laps`` laps of
the same frames (forward, backward, ...: continuous motion, a longer recording). Prints the position error
in the map's world without alignment, whether the map folder is byte-identical afterwards, and the resident
memory (VmRSS, sampled every 0.2 s) per fifth of each long run.

    OMP_NUM_THREADS=1 python -m benchmarks.localize
    OMP_NUM_THREADS=1 python -m benchmarks.localize --laps 10 --map /tmp/localize_map   # reuse a saved map
"""
from __future__ import annotations

import argparse
import dataclasses
import hashlib
import sys
import threading
import time
from pathlib import Path

import numpy as np

from benchmarks._common import data_root
from slam.io.laps import LapSequence


def rss_mb() -> float:
    """Resident memory of this process (MB), from /proc/self/status."""
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024.0
    return float("nan")


class RSSSampler:
    """VmRSS every ``period`` seconds in a thread, while in its ``with`` block."""

    def __init__(self, period: float = 0.2):
        self.period, self.samples, self._stop = period, [], threading.Event()

    def __enter__(self):
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()
        return self

    def _run(self):
        while not self._stop.is_set():
            self.samples.append(rss_mb())
            time.sleep(self.period)

    def __exit__(self, *exc):
        self._stop.set()
        self._thread.join()

    def per_fifth(self) -> list[float]:
        return [round(float(np.max(p)), 1) for p in np.array_split(np.array(self.samples), 5) if p.size]


def folder_digest(folder: Path) -> dict:
    return {p.name: (hashlib.sha256(p.read_bytes()).hexdigest(), p.stat().st_mtime_ns)
            for p in sorted(folder.iterdir())}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--data", default=str(data_root() / "7scenes-redkitchen"), help="the sequence folder")
    p.add_argument("--map-frames", default="0:600", help="frames START:END saved as the map")
    p.add_argument("--frames", default="850:1000", help="frames START:END placed in it")
    p.add_argument("--laps", type=int, default=10, help="laps of --frames for the long localisation run")
    p.add_argument("--map", default=None, help="the map folder (made when absent; default: a temporary one)")
    p.add_argument("--skip-mapping-laps", action="store_true",
                   help="do not run the relocalised (map-growing) recording over the laps")
    args = p.parse_args(argv)

    import tempfile

    from slam.io import open_sequence
    from slam.options import frame_range, resolve_settings
    from slam.pipeline import run_slam
    from slam.report import evaluate_run

    seq = open_sequence(args.data)
    cfg = resolve_settings({"map.enabled": False}, None, seq).config
    map_dir = Path(args.map) if args.map else Path(tempfile.mkdtemp()) / "map"
    if not (map_dir / "manifest.json").is_file():
        t = time.perf_counter()
        run_slam(seq, cfg, progress=False, frames=frame_range(args.map_frames), save_map=map_dir)
        print(f"map of frames {args.map_frames} saved into {map_dir} ({time.perf_counter() - t:.0f} s)")
    before = folder_digest(map_dir)
    start, end = frame_range(args.frames)
    local = dataclasses.replace(cfg, relocalisation=dataclasses.replace(cfg.relocalisation, localize=True))

    def report(name, run, sampler=None):
        m = evaluate_run(run).as_dict()
        rel = m["relocalisation"]
        err = rel["map_world_errors"] or {}
        line = (f"{name}: {m['num_frames']} frames, {m['num_keyframes']} keyframes, {m['num_loops']} own loops, "
                f"relocalised {rel['relocalised']} at frame {rel['frame']}, {rel['frames_in_map']} in the map, "
                f"map-world RMSE {err.get('rmse', float('nan')):.4f} m (max {err.get('max', float('nan')):.4f}), "
                f"{m['fps']:.1f} frames/s")
        if sampler is not None:
            line += f", VmRSS max per fifth (MB) {sampler.per_fifth()}"
        print(line, flush=True)

    report("relocalised (--map)", run_slam(seq, cfg, progress=False, frames=(start, end), map_dir=map_dir))
    report("localised (--map --localize)", run_slam(seq, local, progress=False, frames=(start, end), map_dir=map_dir))
    laps = LapSequence(seq[start:end], args.laps)
    with RSSSampler() as s:
        run = run_slam(laps, local, progress=False, map_dir=map_dir)
    report(f"localised, {args.laps} laps", run, s)
    if not args.skip_mapping_laps:
        with RSSSampler() as s:
            run = run_slam(laps, cfg, progress=False, map_dir=map_dir)
        report(f"relocalised, {args.laps} laps", run, s)
    same = folder_digest(map_dir) == before
    print(f"map folder byte-identical (contents and modification times) after the runs: {same}")
    return 0 if same else 1


if __name__ == "__main__":
    sys.exit(main())
