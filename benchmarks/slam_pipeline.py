"""End-to-end SLAM: ATE against odometry alone, loops (true/false, and what the group check and the back end
rejected), recall at 100 % precision, frames/s, for every fusion mode, on real and synthetic sequences.

    python benchmarks/slam_pipeline.py [--data ../shared/data] [--frame-step N] [--out runs/bench_slam]
    python benchmarks/slam_pipeline.py --building runs/building_seq [--modes dam]  # the aliased building
    python benchmarks/slam_pipeline.py --modes dam --fps-ab 3                       # online correction's cost

Sequences: 7-Scenes redkitchen (``--data``; its Kinect v1 rig, as ``attnloop-slam`` sets it) unless
``--no-kitchen``; the building tour when ``--building DIR`` names its folder (generated there first if the
folder does not exist, as ``attnloop-slam --demo --demo-scene building`` does); any other folders with
``--sequence``. Per sequence: one odometry-only run, then one run per fusion mode (slam.ablation), all with
the same options. Prints (and writes to OUT/slam.md, OUT/slam.json) one row per run and the paper's Table 1
layout.

``--fps-ab R``: afterwards, R rounds on the first sequence of the first mode (as ``attnloop-slam`` runs it by
default: with the map) alternating online correction on and off (same process, interleaved, so that the machine's load hits both alike): the median frames/s of
each and the median of the per-round ratios.
"""
import argparse
import json
import os
import statistics
import time
from pathlib import Path

import torch

from slam.ablation import MODES, markdown_table, run_ablation
from slam.io import open_sequence
from slam.options import config_from_args, run_options
from slam.pipeline import evaluate_run, run_slam


def _fmt(x, digits=4):
    return "-" if x is None else f"{x:.{digits}f}"


def _row(label, m, odo_ate):
    det = m.get("loop_detection", {})
    b = det.get("before_verification", {}).get("max_recall_at_full_precision")
    a = det.get("after_verification", {}).get("max_recall_at_full_precision")
    ate = m.get("ate_rmse")
    cut = f"{100 * (1 - ate / odo_ate):+.0f} %" if ate is not None and odo_ate else "-"
    hyp, false = m.get("loop_hypotheses", {}), m.get("loop_hypotheses_false", {})
    rejected = (f"{hyp.get('inconsistent', 0)} ({false.get('inconsistent', 0)} false) / "
                f"{hyp.get('switched_off', 0)} ({false.get('switched_off', 0)} false)") if hyp else "-"
    oc = m.get("online_corrections", {})
    corr = f"{oc['count']} x {oc['total_ms'] / max(oc['count'], 1):.0f} ms" if oc.get("count") else "-"
    st = m["time_per_stage"]
    loops = f"{m['loops_true']}/{m['loops_false']}" if "loops_true" in m and label != "odometry only" else "-"
    return (f"| {label} | {_fmt(ate)} | {cut} | {loops} | {rejected} | {_fmt(b, 3)} -> {_fmt(a, 3)} | "
            f"{m['fps']:.1f} | {corr} | {st['odometry']['ms_per_call']:.1f} | "
            f"{st.get('descriptor', {}).get('ms_per_call', float('nan')):.1f} | {m['num_keyframes']} | {m['num_lost']} |")


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--data", default=os.environ.get("ATTNLOOP_DATA", "../shared/data"), help="the shared data folder (default: ATTNLOOP_DATA or ../shared/data)")
    p.add_argument("--no-kitchen", action="store_true", help="leave out 7-Scenes redkitchen")
    p.add_argument("--building", default=None, metavar="DIR",
                   help="the building tour's folder (generated there when it does not exist)")
    p.add_argument("--sequence", nargs="*", default=[], help="more sequence folders")
    p.add_argument("--backbone", default="efficientnet_lite0", help="descriptor backbone")
    p.add_argument("--frame-step", type=int, default=1, help="use every N-th frame")
    p.add_argument("--max-frames", type=int, default=None, help="first frames to run (default: all)")
    p.add_argument("--out", default="runs/bench_slam", help="output folder")
    p.add_argument("--modes", nargs="+", default=list(MODES), help="fusion modes to run (default: all)")
    p.add_argument("--fps-ab", type=int, default=0, metavar="R", help="rounds of the online-correction A/B")
    args = p.parse_args()
    torch.set_num_threads(1)
    seqs = [] if args.no_kitchen else [Path(args.data) / "7scenes-redkitchen"]
    if args.building:
        b = Path(args.building)
        if not b.exists():
            from slam.synthetic.building_tour import generate_building_sequence

            t0, c0 = time.perf_counter(), time.process_time()
            generate_building_sequence(b, progress=True)
            print(f"generated {b}: {time.perf_counter() - t0:.0f} s wall, {time.process_time() - c0:.0f} s CPU "
                  "(this process)", flush=True)
        seqs.append(b)
    seqs += [Path(s) for s in args.sequence]
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    opts = dict(backbone=args.backbone, frame_step=args.frame_step, max_frames=args.max_frames, no_map=True)

    odo = {}
    for s in seqs:
        seq = open_sequence(s)
        cfg = config_from_args(run_options(no_loop=True, **opts), seq)
        odo[seq.name] = evaluate_run(run_slam(seq, cfg, max_frames=args.max_frames, frame_step=args.frame_step,
                                              progress=False))
        print(f"odometry {seq.name}: ATE {_fmt(odo[seq.name].get('ate_rmse'))} m", flush=True)
    table = run_ablation(seqs, out, modes=args.modes, **opts)

    head = ("| run | ATE RMSE (m) | vs odometry | loops kept (true/false) | inconsistent / switched off (false) "
            "| max recall @100% P before -> after verification | frames/s | online corrections | odometry ms/frame "
            "| descriptor ms/keyframe | keyframes | lost |")
    text = [f"{time.strftime('%Y-%m-%d %H:%M')}, frame step {args.frame_step}, backbone {args.backbone}, "
            f"torch threads {torch.get_num_threads()}", ""]
    for name, m0 in odo.items():
        text += [f"### {name} ({m0['num_frames']} frames, {m0.get('rig', '')})", "", head, "|" + "---|" * 12]
        text.append(_row("odometry only", m0, None))
        for mode in args.modes:
            text.append(_row(f"{args.backbone} + {mode}", table[mode][name], m0.get("ate_rmse")))
        text.append("")
    text += [markdown_table(table)]
    if args.fps_ab > 0:
        seq = open_sequence(seqs[0])
        fps = {True: [], False: []}
        for _ in range(args.fps_ab):
            for online in (True, False):
                # the command's default run: the map is built too
                cfg = config_from_args(run_options(**{**opts, "no_map": False}), seq, fusion=args.modes[0])
                cfg.backend.optimize_on_loop = online
                m = evaluate_run(run_slam(seq, cfg, max_frames=args.max_frames, frame_step=args.frame_step,
                                          progress=False))
                fps[online].append(m["fps"])
                print(f"fps A/B online={online}: {m['fps']:.2f} frames/s, ATE {_fmt(m.get('ate_rmse'))}", flush=True)
        ratios = [a / b for a, b in zip(fps[True], fps[False])]
        text += ["", f"Online correction A/B on {seq.name} ({args.modes[0]}, {args.fps_ab} rounds, interleaved): "
                 f"on {statistics.median(fps[True]):.2f} frames/s (runs {fps[True]}), off "
                 f"{statistics.median(fps[False]):.2f} (runs {fps[False]}); median ratio on/off "
                 f"{statistics.median(ratios):.3f}"]
    out_text = "\n".join(text) + "\n"
    print(out_text)
    (out / "slam.md").write_text(out_text)
    (out / "slam.json").write_text(json.dumps({"odometry_only": odo, **table}, indent=2, default=float))


if __name__ == "__main__":
    main()
