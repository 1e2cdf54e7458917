"""End-to-end SLAM: ATE against odometry alone, loops (true/false, and what the group check and the back end
rejected), recall at 100 % precision, frames/s, for every fusion mode, on real and synthetic sequences.

    python -m benchmarks.slam_pipeline [--data ../shared/data] [--frame-step N] [--out runs/bench_slam]
    python -m benchmarks.slam_pipeline --building runs/building_seq [--modes dam]  # the aliased building
    python -m benchmarks.slam_pipeline --modes dam --fps-ab 3                       # online correction's cost

Sequences: 7-Scenes redkitchen (``--data``; its Kinect v1 rig, as ``attnloop-slam`` sets it) unless
``--no-kitchen``; the building tour when ``--building DIR`` names its folder (generated there first if the
folder does not exist, as ``attnloop-slam --demo --demo-scene building`` does); any other folders with
``--sequence``. Per sequence: one odometry-only run, then one run per fusion mode (slam.ablation), all with
the same options. Prints (and writes to OUT/slam.md, OUT/slam.json) one row per run and the paper's Table 1
layout.

Columns beyond ATE and loops: the ATE's maximum, the final chi2 per edge, and each edge kind's median squared
Mahalanobis error against ground truth with the information the back end used (a calibrated edge: the chi2
of 6 dof, median 5.35). ``--set FIELD=VALUE`` overrides config
fields of every run (e.g. ``loop.information_scale=0.005``).

``--fps-ab R``: afterwards, R rounds on the first sequence of the first mode (as ``attnloop-slam`` runs it by
default: with the map) alternating online correction on and off (same process, interleaved, so that the machine's
load hits both alike): the median frames/s of each and the median of the per-round ratios.

``--fps-ab R --fps-ref DIR``: instead, R rounds alternating this checkout's code and the code in DIR (another
checkout, e.g. ``git worktree add DIR 07d01e5``), each the default ``attnloop-slam`` run of the first
sequence in a fresh process (``python -m slam.cli SEQ --out ... --quiet``, its ``--max-frames``,
``--frame-step``, ``--modes``' first fusion): the frames/s each run writes in ``metrics.json``, the CPU
seconds of its process (every thread) per frame, the median of each and of the per-round ratios. The
frame rate's code A/B; with ``--no-kitchen --sequence DIR`` on any other sequence.
"""
import argparse
import ast
import json
import os
import statistics
import time
from pathlib import Path

import torch

from benchmarks._common import add_data_argument
from slam.ablation import COLUMNS, markdown_table, run_ablation
from slam.config import ConfigError, override
from slam.graph.costs import edge_residuals
from slam.io import open_sequence
from slam.lie import se3_compose, se3_inv
from slam.options import resolve_settings
from slam.pipeline import run_slam
from slam.report import evaluate_run


def edge_chi2_against_truth(run) -> dict:
    """Each edge kind's squared Mahalanobis error against ground truth, with the information the back end
    used (the registration's, scaled): ``{"odometry": {...}, "loop": {...}}`` with the median, mean and
    count. A calibrated graph has the chi2 distribution of 6 dof there (median 5.35, mean 6); far
    below it, the robust kernels (whose widths are in sigmas) never act.

    The loop edges are those of ``run.result.loops`` (the kept ones); ground truth is moved into the tracked
    camera's frame (the colour camera's, for an unregistered rig)."""
    res = run.result
    pg = res.graph
    if pg is None or run.gt_poses_per_frame is None or pg.num_edges == 0:
        return {}
    gt = run.gt_poses_per_frame[res.keyframe_frames].to(torch.float64)
    t = (tuple(run.config.odometry.features.rgb_from_depth_translation) if run.config.odometry.features.rgb_intrinsics
         else (0, 0, 0))
    T_rd = torch.tensor([*t, 0.0, 0.0, 0.0, 1.0], dtype=torch.float64)  # the depth camera in the colour camera
    i, j = pg.ii, pg.jj
    n = gt.shape[0]
    gt = se3_compose(se3_compose(T_rd.expand(n, 7), gt), se3_inv(T_rd).expand(n, 7))  # P_rgb = T_rd P_depth T_rd^-1
    e, _ = edge_residuals(gt, i, j, pg.measurements.to(torch.float64))
    s = torch.einsum("ei,eij,ej->e", e, pg.information.to(torch.float64), e)
    loops = {(lp.kf_a, lp.kf_b) for lp in res.loops}
    is_loop = torch.tensor([(int(a), int(b)) in loops for a, b in zip(i, j)], dtype=torch.bool)
    out = {}
    for name, mask in (("odometry", ~is_loop), ("loop", is_loop)):
        v = s[mask & torch.isfinite(s)]
        if v.numel():
            out[name] = {"median": float(v.median()), "mean": float(v.mean()), "count": int(v.numel())}
    return out


def apply_overrides(cfg, settings):
    """Set config fields from ``["backend.odometry_information_scale=1.0", ...]`` (values as Python
    literals); an unknown field is an error naming it."""
    changes = {}
    for item in settings:
        key, sep, value = item.partition("=")
        if not sep:
            raise SystemExit(f"--set expects FIELD=VALUE, got {item!r}")
        try:
            changes[key] = ast.literal_eval(value)
        except (ValueError, SyntaxError):
            changes[key] = value
    try:
        return override(cfg, changes)  # the config's own checks run on the new values
    except ConfigError as e:
        if "unknown key" in str(e):
            raise SystemExit(f"--set: the config has no field: {e}") from None
        raise


def _fmt(x, digits=4):
    return "-" if x is None else f"{x:.{digits}f}"


def _row(label, m, odo_ate):
    det = m.get("loop_detection", {})
    b = det.get("before_verification", {}).get("max_recall_at_full_precision")
    a = det.get("after_verification", {}).get("max_recall_at_full_precision")
    ate = m.get("ate_rmse")
    # the change of ATE against odometry alone: -43 % is a 43 % cut
    cut = f"{100 * (ate / odo_ate - 1):+.0f} %" if ate is not None and odo_ate else "-"
    hyp, false = m.get("loop_hypotheses", {}), m.get("loop_hypotheses_false", {})
    rejected = (f"{hyp.get('inconsistent', 0)} ({false.get('inconsistent', 0)} false) / "
                f"{hyp.get('switched_off', 0)} ({false.get('switched_off', 0)} false)") if hyp else "-"
    oc = m.get("online_corrections", {})
    corr = f"{oc['count']} x {oc['total_ms'] / max(oc['count'], 1):.0f} ms" if oc.get("count") else "-"
    st = m["time_per_stage"]
    loops = f"{m['loops_true']}/{m['loops_false']}" if "loops_true" in m and label != "odometry only" else "-"
    amax = m.get("ate", {}).get("max")
    chi = m.get("edge_chi2_vs_truth", {})
    vs_truth = " / ".join(_fmt(chi.get(k, {}).get("median"), 2) for k in ("odometry", "loop"))
    final = (_fmt(m["final_chi2"] / m["num_edges"], 3) if m.get("final_chi2") is not None and m.get("num_edges")
             else "-")
    return (f"| {label} | {_fmt(ate)} | {_fmt(amax, 3)} | {cut} | {loops} | {rejected} | "
            f"{_fmt(b, 3)} -> {_fmt(a, 3)} | {final} | {vs_truth} | {m['fps']:.1f} | {corr} | "
            f"{st['odometry']['ms_per_call']:.1f} | {st.get('descriptor', {}).get('ms_per_call', float('nan')):.1f} | "
            f"{m['num_keyframes']} | {m['num_lost']} |")


def _code_ab(seq_dir, args) -> list:
    """R rounds of the default run with this checkout's code and the reference checkout's, interleaved."""
    import resource
    import subprocess
    import sys

    here = Path(__file__).resolve().parents[1]
    ref = Path(args.fps_ref).resolve()
    if not (ref / "slam" / "cli.py").is_file():
        raise SystemExit(f"--fps-ref {ref}: not a checkout of this project (no slam/cli.py)")
    runs = {"new": [], "ref": []}
    for r in range(args.fps_ab):
        for name, code in (("new", here), ("ref", ref)) if r % 2 == 0 else (("ref", ref), ("new", here)):
            out = (Path(args.out) / "fps_ab" / name).resolve()  # each run works in its own checkout
            cmd = [sys.executable, "-m", "slam.cli", str(seq_dir), "--out", str(out), "--quiet",
                   "--fusion", args.modes[0], "--frame-step", str(args.frame_step)]
            if args.max_frames:
                cmd += ["--max-frames", str(args.max_frames)]
            env = {**os.environ, "PYTHONPATH": str(code), "OMP_NUM_THREADS": "1"}
            before = resource.getrusage(resource.RUSAGE_CHILDREN)
            subprocess.run(cmd, env=env, cwd=str(code), check=True)
            after = resource.getrusage(resource.RUSAGE_CHILDREN)
            m = json.loads((out / "metrics.json").read_text())
            cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
            runs[name].append({"fps": m["fps"], "cpu_ms_per_frame": 1000 * cpu / m["num_frames"],
                               "ate": m.get("ate_rmse"), "loops": m.get("num_loops"), "load": os.getloadavg()[0]})
            print(f"code A/B round {r + 1} {name}: {m['fps']:.2f} frames/s, {runs[name][-1]['cpu_ms_per_frame']:.1f} "
                  f"CPU ms/frame, ATE {_fmt(m.get('ate_rmse'))}, load {os.getloadavg()[0]:.1f}", flush=True)
    med = {k: statistics.median(x["fps"] for x in v) for k, v in runs.items()}
    cpu = {k: statistics.median(x["cpu_ms_per_frame"] for x in v) for k, v in runs.items()}
    ratios = [a["fps"] / b["fps"] for a, b in zip(runs["new"], runs["ref"])]
    line = (f"Code A/B on {Path(seq_dir).name} ({args.modes[0]}, {args.fps_ab} rounds, interleaved; reference {ref}): "
            f"this code {med['new']:.2f} frames/s (runs {[x['fps'] for x in runs['new']]}), reference "
            f"{med['ref']:.2f} (runs {[x['fps'] for x in runs['ref']]}); median ratio {statistics.median(ratios):.3f}; "
            f"process CPU ms/frame (all threads, whole process) {cpu['new']:.1f} vs {cpu['ref']:.1f}; ATE "
            f"{_fmt(runs['new'][0]['ate'])} vs {_fmt(runs['ref'][0]['ate'])}, loops {runs['new'][0]['loops']} vs "
            f"{runs['ref'][0]['loops']}; load averages {[round(x['load'], 1) for v in runs.values() for x in v]}")
    return [line]


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_data_argument(p)
    p.add_argument("--no-kitchen", action="store_true", help="leave out 7-Scenes redkitchen")
    p.add_argument("--building", default=None, metavar="DIR",
                   help="the building tour's folder (generated there when it does not exist)")
    p.add_argument("--sequence", nargs="*", default=[], help="more sequence folders")
    p.add_argument("--backbone", default="efficientnet_lite0", help="descriptor backbone")
    p.add_argument("--frame-step", type=int, default=1, help="use every N-th frame")
    p.add_argument("--max-frames", type=int, default=None, help="first frames to run (default: all)")
    p.add_argument("--out", default="runs/bench_slam", help="output folder")
    p.add_argument("--modes", nargs="+", default=list(COLUMNS["default"]),
                   help="fusion modes to run (default: all)")
    p.add_argument("--fps-ab", type=int, default=0, metavar="R", help="rounds of the online-correction A/B")
    p.add_argument("--fps-ref", default=None, metavar="DIR",
                   help="with --fps-ab: A/B of this checkout's code against the checkout in DIR instead")
    p.add_argument("--fps-only", action="store_true", help="with --fps-ab: skip the accuracy runs")
    p.add_argument("--set", nargs="*", default=[], metavar="FIELD=VALUE",
                   help="override SLAMConfig fields of the loop runs, e.g. backend.odometry_information_scale=1.0")
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
    opts = {"loop.descriptor.backbone": args.backbone, "run.frame_step": args.frame_step,
            "run.max_frames": args.max_frames, "map.enabled": False}
    opts = {k: v for k, v in opts.items() if v is not None}

    code_ab = None  # the code A/B runs first (and alone with --fps-only), its table goes at the end
    if args.fps_ab > 0 and args.fps_ref:
        code_ab = _code_ab(seqs[0], args)
        if args.fps_only:
            print("\n".join(code_ab))
            (out / "fps_ab.md").write_text("\n".join(code_ab) + "\n")
            return
    odo = {}
    for s in seqs:
        seq = open_sequence(s)
        odometry_opts = {k: v for k, v in opts.items() if not k.startswith("loop.")}  # idle without the loops
        cfg = apply_overrides(resolve_settings({**odometry_opts, "loop.enabled": False}, sequence=seq).config,
                              args.set)
        run = run_slam(seq, cfg, max_frames=args.max_frames, frame_step=args.frame_step, progress=False)
        odo[seq.name] = evaluate_run(run).as_dict()
        odo[seq.name]["edge_chi2_vs_truth"] = edge_chi2_against_truth(run)
        print(f"odometry {seq.name}: ATE {_fmt(odo[seq.name].get('ate_rmse'))} m, max "
              f"{_fmt(odo[seq.name].get('ate', {}).get('max'))} m; edge chi2 vs truth "
              f"{odo[seq.name]['edge_chi2_vs_truth']}", flush=True)
    # one run per mode and sequence (slam.ablation.run_ablation: outputs in OUT/<mode>/<sequence>/, PR curves
    # beside them), each run measured again for the edges' chi2 against ground truth and the final chi2
    def measure(run, m):
        m["edge_chi2_vs_truth"] = edge_chi2_against_truth(run)
        opt = run.result.optimization
        m["final_chi2"] = None if opt is None else float(opt.chi2)
        m["num_edges"] = None if run.result.graph is None else int(run.result.graph.num_edges)
        print(f"      {run.sequence_name}: ATE max {_fmt(m.get('ate', {}).get('max'))} m, hypotheses "
              f"{m.get('loop_hypotheses')} (false {m.get('loop_hypotheses_false')}), final chi2 {m['final_chi2']} "
              f"over {m['num_edges']} edges, edge chi2 vs truth {m['edge_chi2_vs_truth']}", flush=True)

    specs = [resolve_settings(opts, sequence=s) for s in seqs]
    table = run_ablation(specs, out, {m: COLUMNS["default"][m] for m in args.modes},
                         configure=lambda cfg: apply_overrides(cfg, args.set), measure=measure)

    head = ("| run | ATE RMSE (m) | ATE max (m) | vs odometry | loops kept (true/false) "
            "| inconsistent / switched off (false) | max recall @100% P before -> after verification "
            "| final chi2 / edge | median edge chi2 vs truth odometry / loop | frames/s | online corrections "
            "| odometry ms/frame | descriptor ms/keyframe | keyframes | lost |")
    text = [(f"{time.strftime('%Y-%m-%d %H:%M')}, frame step {args.frame_step}, backbone {args.backbone}, "
            f"torch threads {torch.get_num_threads()}, load {os.getloadavg()[0]:.1f}"
            + (f", overrides {' '.join(args.set)}" if args.set else "")), ""]
    for name, m0 in odo.items():
        text += [f"### {name} ({m0['num_frames']} frames, {m0.get('rig', '')})", "", head, "|" + "---|" * 15]
        text.append(_row("odometry only", m0, None))
        for mode in args.modes:
            text.append(_row(f"{args.backbone} + {mode}", table[mode][name], m0.get("ate_rmse")))
        text.append("")
    text += [markdown_table(table)]
    if code_ab is not None:
        text += [""] + code_ab
    elif args.fps_ab > 0:
        seq = open_sequence(seqs[0])
        fps = {True: [], False: []}
        for _ in range(args.fps_ab):
            for online in (True, False):
                # the command's default run: the map is built too
                cfg = resolve_settings({**opts, "map.enabled": True, "loop.descriptor.fusion": args.modes[0],
                                        "backend.optimize_on_loop": online}, sequence=seq).config
                m = evaluate_run(run_slam(seq, cfg, max_frames=args.max_frames, frame_step=args.frame_step,
                                          progress=False)).as_dict()
                fps[online].append(m["fps"])
                print(f"fps A/B online={online}: {m['fps']:.2f} frames/s, ATE {_fmt(m.get('ate_rmse'))}", flush=True)
        ratios = [a / b for a, b in zip(fps[True], fps[False])]
        text += ["", (f"Online correction A/B on {seq.name} ({args.modes[0]}, {args.fps_ab} rounds, interleaved): "
                 f"on {statistics.median(fps[True]):.2f} frames/s (runs {fps[True]}), off "
                 f"{statistics.median(fps[False]):.2f} (runs {fps[False]}); median ratio on/off "
                 f"{statistics.median(ratios):.3f}")]
    out_text = "\n".join(text) + "\n"
    print(out_text)
    (out / "slam.md").write_text(out_text)
    (out / "slam.json").write_text(json.dumps({"odometry_only": odo, **table}, indent=2, default=float))


if __name__ == "__main__":
    main()
