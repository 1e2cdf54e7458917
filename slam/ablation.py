"""The paper's ablation (Table 1): the SLAM system with each attention fusion on one or more sequences.

Used by ``examples/ablation.py`` and ``benchmarks/slam_pipeline.py``. Each run's config comes from the
same options as ``attnloop-slam`` (:func:`slam.options.config_from_args`), so a 7-Scenes folder gets
its Kinect v1 rig and ``--frame-step`` means the same here as there.
"""
from __future__ import annotations

import math
from pathlib import Path

from attnloop.fusion import FUSION_MODES
from slam.eval import plot_pr_curves
from slam.io import open_sequence
from slam.options import config_from_args, reader_options, run_options
from slam.pipeline import evaluate_run, prepare_output_dir, run_slam, write_outputs

__all__ = ["MODES", "markdown_table", "run_ablation"]

MODES = FUSION_MODES  # the rows of the table: every fusion mode (attnloop.fusion is the one list)


def run_ablation(sequences, out_dir, options=None, modes=MODES, *, configure=None, measure=None, given=None,
                 **overrides):
    """Run every mode on every sequence; returns ``{mode: {sequence: metrics}}``.

    Args:
        sequences: sequence folders.
        out_dir: each run writes into ``out_dir/<mode>/<sequence>/`` (every such folder is checked, and
            its previous outputs removed, before the first run); ``pr_<sequence>.png`` beside them.
        options: an ``argparse.Namespace`` of :func:`slam.options.add_run_arguments` (None: the defaults).
        modes: the fusion modes (rows).
        configure: optional ``SLAMConfig -> SLAMConfig``, applied to each run's config (e.g. settings that
            have no command-line option).
        measure: optional ``(run, metrics) -> None``, called after each run with its
            :class:`~slam.pipeline.RunResult` and its metrics (to add figures that need the run itself).
        given: the options given on the command line (:func:`slam.options.given_options`): those that
            other options make idle are refused, as by ``attnloop-slam``; None: not known.
        **overrides: option values by name, over ``options`` (e.g. ``backbone="efficientnet_lite0"``,
            ``max_frames=300``, ``frame_step=3``, ``rgb_intrinsics=(525, 525, 320, 240)``).

    Raises:
        slam.options.UsageError: an unknown option or mode, or an unusable setting.
    """
    opts = run_options(options, **overrides)
    bad = [m for m in modes if m not in FUSION_MODES]
    if bad:
        raise ValueError(f"unknown fusion mode(s) {bad}; choose from {', '.join(FUSION_MODES)}")
    out_dir = Path(out_dir)
    opened = [open_sequence(path, **reader_options(opts)) for path in sequences]  # every folder checked first
    configs = {(mode, k): config_from_args(opts, seq, fusion=mode, given=given) for mode in modes
               for k, seq in enumerate(opened)}
    if configure is not None:
        configs = {key: configure(cfg) for key, cfg in configs.items()}
    targets = {(mode, k): prepare_output_dir(out_dir / mode / seq.name) for mode in modes
               for k, seq in enumerate(opened)}
    table = {}
    curves = {}
    for mode in modes:
        table[mode] = {}
        for k, seq in enumerate(opened):
            run = run_slam(seq, configs[(mode, k)], max_frames=opts.max_frames, frame_step=opts.frame_step)
            metrics = evaluate_run(run)
            write_outputs(run, targets[(mode, k)])
            if measure is not None:
                measure(run, metrics)
            table[mode][seq.name] = metrics
            if "before_verification" in run.loop_curves:
                curves.setdefault(seq.name, {})[mode] = run.loop_curves["before_verification"]
            ate = metrics.get("ate_rmse")
            print(f"{mode:5s} {seq.name}: ATE {'-' if ate is None else f'{ate:.4f} m'}, "
                  f"{metrics['num_loops']} loops, {metrics['fps']:.1f} frames/s", flush=True)
    for name, by_mode in curves.items():
        plot_pr_curves(out_dir / f"pr_{name}.png", by_mode, title=f"{name}: loop detection before verification")
    return table


def _number(value, digits: int) -> str:
    return "-" if value is None or not math.isfinite(value) else f"{value:.{digits}f}"


def markdown_table(table) -> str:
    """The paper's Table 1 layout: rows = fusion modes, columns = sequences + average ("-": no ATE; "n/a":
    loops or recall that could not be measured)."""
    modes = list(table)
    names = list(next(iter(table.values())))
    head = "| fusion | " + " | ".join(names) + " | average |"
    lines = ["RMS-ATE (m):", "", head, "|" + "---|" * (len(names) + 2)]
    for mode in modes:
        vals = [table[mode][n].get("ate_rmse") for n in names]
        known = [v for v in vals if v is not None and math.isfinite(v)]
        avg = sum(known) / len(known) if len(known) == len(vals) and known else None
        lines.append(f"| {mode} | " + " | ".join(_number(v, 4) for v in vals) + f" | {_number(avg, 4)} |")
    lines += ["", ("Loop closure (per sequence: accepted true/false; max recall at 100% precision before -> after "
                  "verification):"), "", head.replace(" average |", ""), "|" + "---|" * (len(names) + 1)]
    for mode in modes:
        lines.append(f"| {mode} | " + " | ".join(_loop_cell(table[mode][n]) for n in names) + " |")
    return "\n".join(lines) + "\n"


def _loop_cell(m: dict) -> str:
    """``true/false; recall before -> after``, each part ``n/a`` where nothing could be measured: no ground
    truth to judge the loops, no revisit in it (a recall of no positives), no keyframe query."""
    loops = f"{m['loops_true']}/{m['loops_false']}" if m.get("loops_true") is not None else "n/a"
    det = m.get("loop_detection") or {}
    before, after = det.get("before_verification") or {}, det.get("after_verification") or {}
    if not before.get("num_positives"):
        return f"{loops}; n/a"
    return (f"{loops}; {_number(before.get('max_recall_at_full_precision'), 2)} -> "
            f"{_number(after.get('max_recall_at_full_precision'), 2)}")
