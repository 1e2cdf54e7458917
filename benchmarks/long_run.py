"""Long runs: does the cost per frame stay constant as the run goes on?

A sequence (the building demo scene, rendered once, or any TUM-layout / 7-Scenes folder) is played as N laps,
forward, backward, forward, ... (:class:`slam.io.laps.LapSequence`: continuous motion, increasing timestamps,
no new rendering), and run through :func:`slam.pipeline.run_slam` as ``attnloop-slam --laps N`` runs it
(the loop worker in its thread, features extracted ahead, the map built). Per fifth of the run it reports:

* tracking: wall milliseconds per frame of :meth:`slam.system.RGBDSLAM.track` (what the caller waits,
  the waits for the loop worker included) and of its odometry alone;
* the loop worker's lag: keyframes the front end has made that the loop worker has not yet closed (read
  from the system after each frame: its keyframes minus the loop closer's records, one a keyframe, whether it
  queried the database or followed a revisit; the keyframe in flight counts), the maximum and the mean over
  the fifth;
* loop work per keyframe by stage (``descriptor``, ``loop_detection``, ``verification``,
  ``loop_consistency``, ``online_correction``: milliseconds in the fifth over the keyframes made in it), and
  its total per frame of the fifth; the candidates verified per keyframe;
* resident memory at the end of the fifth (MB, read every 10 frames while tracking: the last fifth's does not
  include :meth:`~slam.system.RGBDSLAM.finish`, the map's merge and the evaluation, which the maximum does);

and at the end keyframes (and those whose features were released: revisits that added nothing,
``LoopClosureConfig.release_revisits``), accepted loops (true / false by ground truth, as ``metrics.json``
judges them) and the ATE. The figures go to stdout and, with ``--json``, to a file.

Usage (figures in docs/results.md)::

    python -m benchmarks.long_run --demo-frames 600 --laps 2 --cache /tmp/building600
    python -m benchmarks.long_run --laps 5 --cache /tmp/building2400        # five tours, 12,000 frames
    python -m benchmarks.long_run --sequence /path/to/tum_folder --laps 3
"""
from __future__ import annotations

import argparse
import json
import os
import resource
import sys
import time
from pathlib import Path

LOOP_STAGES = ("descriptor", "loop_detection", "verification", "loop_consistency", "online_correction")


def _rss_mb() -> float:
    """Resident memory now (MB), from /proc (the maximum so far where /proc is missing)."""
    try:
        with open("/proc/self/statm") as f:
            return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 1e6
    except OSError:
        return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1e3


def building_folder(cache: Path, frames: int, quiet: bool) -> Path:
    """The building demo scene's tour (320 x 240) rendered into ``cache`` once (reused when there)."""
    from slam.synthetic.demo import DEMO_SCENES, generate_demo

    if (cache / "rgb.txt").is_file() and (cache / "groundtruth.txt").is_file():
        return cache
    w, h = DEMO_SCENES["building"].default_size
    cache.parent.mkdir(parents=True, exist_ok=True)
    return Path(generate_demo(cache, scene="building", num_frames=frames, width=w, height=h, progress=not quiet))


class Recorder:
    """Per frame: the wall time of ``track``, the odometry's share, the loop worker's lag, the stage totals.

    The rows are one array allocated before the run, so that the benchmark's own bookkeeping does not grow
    the resident memory it reports."""

    # columns of a row: seconds, odometry seconds, keyframes, lag, rss MB, verifications, then LOOP_STAGES
    SECONDS, ODOMETRY, KEYFRAMES, LAG, RSS, VERIFIED = range(6)

    def __init__(self, frames: int):
        import numpy as np

        self.table = np.zeros((frames, 6 + len(LOOP_STAGES)))
        self.count = 0
        self.system = None

    @property
    def rows(self):
        return self.table[: self.count]

    def system_class(self):
        from slam.system import RGBDSLAM

        recorder = self

        class RecordedSLAM(RGBDSLAM):
            def __init__(self, *args, **kwargs):
                super().__init__(*args, **kwargs)
                recorder.system = self

            def track(self, frame, features=None):
                odo = self.timer.seconds["odometry"]
                t0 = time.perf_counter()
                state = super().track(frame, features)
                dt = time.perf_counter() - t0
                kfs = len(self.keyframes)
                queried = len(self.loop_closer.queries) if self.loop_closer is not None else kfs
                n = recorder.count
                row = recorder.table[n]
                row[6:] = [self.timer.seconds.get(s, 0.0) for s in LOOP_STAGES]
                row[Recorder.RSS] = _rss_mb() if n % 10 == 0 else recorder.table[n - 1, Recorder.RSS]
                row[:4] = dt, self.timer.seconds["odometry"] - odo, kfs, kfs - queried
                row[Recorder.VERIFIED] = self.timer.calls.get("verification", 0)
                recorder.count = n + 1
                return state

        return RecordedSLAM

    def fifths(self, parts: int = 5) -> list[dict]:
        rows_all = self.rows
        n = len(rows_all)
        out = []
        prev_kf, prev_stages, prev_verified = 0, [0.0] * len(LOOP_STAGES), 0
        for p in range(parts):
            lo, hi = p * n // parts, (p + 1) * n // parts
            rows = rows_all[lo:hi]
            if not len(rows):
                continue
            kf, stages = int(rows[-1, self.KEYFRAMES]), rows[-1, 6:].tolist()
            new_kf = max(kf - prev_kf, 1)
            by_stage = {s: 1000.0 * (stages[k] - prev_stages[k]) / new_kf for k, s in enumerate(LOOP_STAGES)}
            out.append({
                "frames": [lo, hi],
                "track_ms_per_frame": 1000.0 * float(rows[:, self.SECONDS].mean()),
                "odometry_ms_per_frame": 1000.0 * float(rows[:, self.ODOMETRY].mean()),
                "keyframes": kf - prev_kf,
                "lag_max": int(rows[:, self.LAG].max()),
                "lag_mean": float(rows[:, self.LAG].mean()),
                "loop_ms_per_keyframe": sum(by_stage.values()),
                "loop_ms_per_frame": sum(by_stage.values()) * new_kf / len(rows),
                "loop_ms_per_keyframe_by_stage": by_stage,
                "verified_per_keyframe": (rows[-1, self.VERIFIED] - prev_verified) / new_kf,
                "rss_mb": float(rows[-1, self.RSS]),
            })
            prev_kf, prev_stages, prev_verified = kf, stages, rows[-1, self.VERIFIED]
        return out


def save_loops(path, system) -> None:
    """The verified loops (keyframe ends, measured pose, kept now) and the odometry chain, for a replay."""
    import numpy as np
    import torch

    hyp = system.loop_closer.hypotheses
    g = system.graph
    odo = [e for e in g.edges if e.kind == 0]
    np.savez_compressed(
        path, loop_ends=np.array([[lp.kf_a, lp.kf_b] for lp in hyp], dtype=np.int64).reshape(-1, 2),
        loop_T=torch.stack([lp.T_ab for lp in hyp]).numpy() if hyp else np.zeros((0, 7)),
        loop_kept=np.array([lp.consistent for lp in hyp], dtype=bool),
        odometry_ij=np.array([[e.i, e.j] for e in odo], dtype=np.int64).reshape(-1, 2),
        odometry_T=torch.stack([e.T_ij for e in odo]).numpy(),
        odometry_weak=np.array([e.weak for e in odo], dtype=bool),
        origin=g.odometry_pose(0).numpy())


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    src = p.add_mutually_exclusive_group()
    src.add_argument("--sequence", default=None, help="a TUM-layout or 7-Scenes folder (default: the building demo)")
    src.add_argument("--demo-frames", type=int, default=2400,
                     help="frames of the building tour rendered (default 2400, the scene's own tour)")
    p.add_argument("--cache", default=None,
                   help="folder of the rendered building (reused when present; default: a temporary one)")
    p.add_argument("--laps", type=int, default=5, help="laps, alternately forward and backward (default 5)")
    p.add_argument("--frame-step", type=int, default=1, help="use every Nth frame of the laps (default 1)")
    p.add_argument("--no-map", action="store_true", help="do not build the map (map.ply's points)")
    p.add_argument("--threads", type=int, default=None, help="SLAMConfig.threads (default: the config's)")
    p.add_argument("--json", default=None, metavar="FILE", help="write the figures here too")
    p.add_argument("--save-loops", default=None, metavar="FILE",
                   help="save the verified loops in order and the keyframes' odometry chain (.npz): a real loop "
                        "set for replaying the group check (tests/slam/loop/test_consistency_vectorised.py)")
    p.add_argument("--quiet", action="store_true", help="no progress bar (the rendering and the run)")
    args = p.parse_args(argv)

    import tempfile

    from slam import pipeline
    from slam.io import open_sequence
    from slam.io.laps import LapSequence
    from slam.options import resolve_settings
    from slam.report import evaluate_run

    if args.sequence is not None:
        source = open_sequence(args.sequence)
    else:
        cache = Path(args.cache) if args.cache else Path(tempfile.mkdtemp(prefix="long_run_")) / "building"
        source = open_sequence(building_folder(cache, args.demo_frames, args.quiet))
    seq = LapSequence(source, args.laps)
    settings = {"map.enabled": False} if args.no_map else {}
    if args.threads is not None:
        settings["threads"] = args.threads
    cfg = resolve_settings(settings, None, seq).config
    rec = Recorder(-(-len(seq) // args.frame_step))
    pipeline.RGBDSLAM = rec.system_class()  # the run's own system, timed per frame
    t0 = time.perf_counter()
    run = pipeline.run_slam(seq, cfg, frame_step=args.frame_step, progress=False if args.quiet else None)
    wall = time.perf_counter() - t0
    m = evaluate_run(run).as_dict()
    fifths = rec.fifths()
    first, last = fifths[0], fifths[-1]
    report = {
        "sequence": str(source.root), "source_frames": len(source), "laps": args.laps, "frames": len(rec.rows),
        "wall_s": wall, "fifths": fifths,
        "ratios_last_over_first": {
            "track_ms_per_frame": last["track_ms_per_frame"] / max(first["track_ms_per_frame"], 1e-9),
            "loop_ms_per_keyframe": last["loop_ms_per_keyframe"] / max(first["loop_ms_per_keyframe"], 1e-9),
            "loop_ms_per_frame": last["loop_ms_per_frame"] / max(first["loop_ms_per_frame"], 1e-9)},
        "lag_max": max(f["lag_max"] for f in fifths),
        "rss_growth_last_four_fifths_mb": last["rss_mb"] - first["rss_mb"],
        "max_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1e3,
        "rss_after_run_mb": _rss_mb(),
        "map_kept_mb": (m.get("map") or {}).get("kept_mb"),  # the map's points as kept during the run
        "keyframes": m["num_keyframes"], "released_keyframes": len(rec.system.released),
        "loops": m["num_loops"], "loops_true": m.get("loops_true"),
        "loops_false": m.get("loops_false"), "loop_hypotheses": m.get("loop_hypotheses"),
        "ate_rmse": m.get("ate_rmse"), "fps": m["fps"],
    }
    print(f"{len(source)} frames x {args.laps} laps = {len(rec.rows)} frames, {wall:.1f} s")
    print(f"{'fifth':>5} {'frames':>13} {'track ms/f':>10} {'odo ms/f':>8} {'kf':>5} {'lag max':>7} {'lag mean':>8} "
          f"{'loop ms/kf':>10} {'loop ms/f':>9}  {'by stage (ms/kf)':<60} {'verif/kf':>8} {'RSS MB':>7}")
    for k, f in enumerate(fifths):
        st = " ".join(f"{s[:6]}={v:.1f}" for s, v in f["loop_ms_per_keyframe_by_stage"].items())
        print(f"{k + 1:>5} {f['frames'][0]:>6}-{f['frames'][1]:<6} {f['track_ms_per_frame']:>10.2f} "
              f"{f['odometry_ms_per_frame']:>8.2f} {f['keyframes']:>5} {f['lag_max']:>7} {f['lag_mean']:>8.2f} "
              f"{f['loop_ms_per_keyframe']:>10.1f} {f['loop_ms_per_frame']:>9.1f}  {st:<60} "
              f"{f['verified_per_keyframe']:>8.2f} {f['rss_mb']:>7.0f}")
    r = report["ratios_last_over_first"]
    print(f"last / first fifth: tracking {r['track_ms_per_frame']:.2f}x, loop work per keyframe "
          f"{r['loop_ms_per_keyframe']:.2f}x (per frame {r['loop_ms_per_frame']:.2f}x); lag at most "
          f"{report['lag_max']} keyframes; RSS +{report['rss_growth_last_four_fifths_mb']:.0f} MB over the last four "
          f"fifths (after the run {report['rss_after_run_mb']:.0f} MB, max {report['max_rss_mb']:.0f} MB; the map's "
          f"points {report['map_kept_mb'] or 0:.1f} MB)")
    ate = report["ate_rmse"]
    print(f"keyframes {report['keyframes']} (features released: {report['released_keyframes']}), loops "
          f"{report['loops']} (true {report['loops_true']}, false "
          f"{report['loops_false']}), ATE {'n/a' if ate is None else f'{ate:.4f} m'}, {report['fps']:.2f} frames/s")
    if args.json:
        Path(args.json).write_text(json.dumps(report, indent=1))
    if args.save_loops:
        save_loops(args.save_loops, rec.system)
    return 0


if __name__ == "__main__":
    sys.exit(main())
