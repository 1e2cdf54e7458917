"""The paper's Table 1: RMS-ATE of the SLAM system with each attention fusion, plus loop precision/recall.

Runs ``none`` (no attention), ``dam``, ``eam``, ``gaf`` and ``ega`` on one or more sequences and writes

* ``table1.md``: RMS-ATE (m) per sequence and the average, one row per fusion mode, then the loop-closure
  figures: accepted loops (true/false by ground truth) and the maximum recall at 100 % precision of the
  detector before and after geometric verification;
* ``pr_<sequence>.png``: precision/recall curves (before verification) of the five modes;
* ``<mode>/<sequence>/``: each run's trajectory.txt, loops.txt, metrics.json, trajectory.png.

Usage::

    python examples/ablation.py ../shared/data/7scenes-redkitchen --backbone efficientnet_lite0 --out runs/ablation
    python examples/ablation.py ~/data/rgbd_dataset_freiburg1_room ~/data/rgbd_dataset_freiburg2_desk \
        --out runs/table1          # the paper's setting (VGG16 weights needed)
"""
import argparse
import json
import logging
from pathlib import Path

from slam.config import SLAMConfig
from slam.eval import plot_pr_curves
from slam.io import open_sequence
from slam.pipeline import evaluate_run, run_slam, write_outputs

MODES = ("none", "dam", "eam", "gaf", "ega")


def run_ablation(sequences, out_dir, backbone="vgg16", modes=MODES, max_frames=None, weights=None):
    """Run every mode on every sequence; returns ``{mode: {sequence: metrics}}``."""
    out_dir = Path(out_dir)
    table = {}
    curves = {}
    for mode in modes:
        table[mode] = {}
        for path in sequences:
            seq = open_sequence(path)
            cfg = SLAMConfig()
            cfg.loop.descriptor.backbone = backbone
            cfg.loop.descriptor.fusion = mode
            cfg.loop.descriptor.weights = weights
            run = run_slam(seq, cfg, max_frames=max_frames)
            metrics = evaluate_run(run)
            write_outputs(run, out_dir / mode / seq.name)
            table[mode][seq.name] = metrics
            if "before_verification" in run.loop_curves:
                curves.setdefault(seq.name, {})[mode] = run.loop_curves["before_verification"]
            print(f"{mode:5s} {seq.name}: ATE {metrics.get('ate_rmse', float('nan')):.4f} m, "
                  f"{metrics['num_loops']} loops, {metrics['fps']:.1f} frames/s", flush=True)
    for name, by_mode in curves.items():
        plot_pr_curves(out_dir / f"pr_{name}.png", by_mode, title=f"{name}: loop detection before verification")
    return table


def markdown_table(table) -> str:
    """The paper's Table 1 layout: rows = fusion modes, columns = sequences + average."""
    modes = list(table)
    names = list(next(iter(table.values())))
    head = "| fusion | " + " | ".join(names) + " | average |"
    lines = ["RMS-ATE (m):", "", head, "|" + "---|" * (len(names) + 2)]
    for mode in modes:
        vals = [table[mode][n].get("ate_rmse", float("nan")) for n in names]
        lines.append(f"| {mode} | " + " | ".join(f"{v:.4f}" for v in vals) + f" | {sum(vals) / len(vals):.4f} |")
    lines += ["", "Loop closure (per sequence: accepted true/false; max recall at 100% precision before -> after "
                  "verification):", "", head.replace(" average |", ""), "|" + "---|" * (len(names) + 1)]
    for mode in modes:
        cells = []
        for n in names:
            m = table[mode][n]
            det = m.get("loop_detection", {})
            b = det.get("before_verification", {}).get("max_recall_at_full_precision", float("nan"))
            a = det.get("after_verification", {}).get("max_recall_at_full_precision", float("nan"))
            cells.append(f"{m.get('loops_true', '?')}/{m.get('loops_false', '?')}; {b:.2f} -> {a:.2f}")
        lines.append(f"| {mode} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("sequences", nargs="+")
    p.add_argument("--out", default="runs/ablation")
    p.add_argument("--backbone", default="vgg16", choices=["vgg16", "efficientnet_lite0"])
    p.add_argument("--weights", default=None)
    p.add_argument("--modes", nargs="+", default=list(MODES), choices=list(MODES))
    p.add_argument("--max-frames", type=int, default=None)
    args = p.parse_args()
    logging.basicConfig(level=logging.WARNING)
    table = run_ablation(args.sequences, args.out, args.backbone, args.modes, args.max_frames, args.weights)
    md = markdown_table(table)
    Path(args.out).mkdir(parents=True, exist_ok=True)
    (Path(args.out) / "table1.md").write_text(md)
    (Path(args.out) / "table1.json").write_text(json.dumps(table, indent=2, default=float))
    print(md)


if __name__ == "__main__":
    main()
