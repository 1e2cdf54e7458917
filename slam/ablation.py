"""The paper's ablation (Table 1): the SLAM system with each attention fusion on one or more sequences.

Used by ``examples/ablation.py`` and ``benchmarks/slam_pipeline.py``.
"""
from __future__ import annotations

from pathlib import Path

from slam.config import SLAMConfig
from slam.eval import plot_pr_curves
from slam.io import open_sequence
from slam.pipeline import evaluate_run, run_slam, write_outputs

__all__ = ["MODES", "run_ablation", "markdown_table"]

MODES = ("none", "dam", "eam", "gaf", "ega")


def run_ablation(sequences, out_dir, backbone="vgg16", modes=MODES, max_frames=None, weights=None,
                 rgb_intrinsics=None, rgb_from_depth=None):
    """Run every mode on every sequence; returns ``{mode: {sequence: metrics}}``.

    ``rgb_intrinsics`` ``(fx, fy, cx, cy)``: the colour camera's, for unregistered colour and depth;
    ``rgb_from_depth`` ``(tx, ty, tz)``: the depth camera's position in the colour camera (metres).
    """
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
            cfg.odometry.features.rgb_intrinsics = tuple(rgb_intrinsics) if rgb_intrinsics else None
            if rgb_from_depth is not None:
                cfg.odometry.features.rgb_from_depth_translation = tuple(rgb_from_depth)
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
