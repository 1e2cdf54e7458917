"""Table 1 of the paper: the SLAM system with each descriptor column (:data:`COLUMNS`) on one or more sequences,
each resolved by the caller as ``attnloop-slam`` resolves it (:func:`slam.options.resolve_settings`); used by
``examples/ablation.py`` and ``benchmarks/slam_pipeline.py``.
"""
from __future__ import annotations

import dataclasses
import math
import re
from collections.abc import Mapping
from pathlib import Path
from typing import Any, Optional

from attnloop.fusion import FUSION_MODES
from slam.config import UsageError, override
from slam.eval import plot_pr_curves
from slam.outputs import prepare_output_dir, write_outputs
from slam.pipeline import run_slam
from slam.report import evaluate_run
from slam.viewer import viewer_flags

__all__ = ["COLUMNS", "PAPER_TABLE1", "camera_group", "columns_for", "markdown_table", "run_ablation"]

_PAPER_FUSIONS = ("gaf", "eam", "ega", "dam")  # the paper's column order after the baseline

#: Table 1's columns by layout: column name -> the descriptor settings of its runs.
COLUMNS: dict[str, dict[str, dict[str, Any]]] = {
    "paper": {"baseline": {"loop.descriptor.preset": "guclu2019", "loop.descriptor.fusion": None},
              **{m.upper(): {"loop.descriptor.preset": "paper", "loop.descriptor.fusion": m} for m in _PAPER_FUSIONS}},
    "default": {m: {"loop.descriptor.preset": "default", "loop.descriptor.fusion": m} for m in FUSION_MODES},
}

#: The paper's Table 1 RMS-ATE figures (m), ``{TUM sequence: {column: value}}`` (the sequence as in TUM's
#: folder names without ``rgbd_dataset_``, e.g. ``freiburg1_room``); each known one is shown beside ours.
PAPER_TABLE1: dict[str, dict[str, float]] = {}


def columns_for(preset: Optional[str]) -> dict[str, dict[str, Any]]:
    """The columns of a preset's table: the paper's layout for ``paper`` and ``guclu2019``, else ours."""
    return COLUMNS["default" if preset in (None, "default") else "paper"]


def camera_group(name: str) -> str:
    """``fr1``, ``fr2``, ``fr3`` for a TUM sequence folder name (``rgbd_dataset_freiburg1_room``), else ``other``.

    Example:
        >>> camera_group("rgbd_dataset_freiburg2_desk"), camera_group("7scenes-redkitchen")
        ('fr2', 'other')
    """
    m = re.search(r"freiburg([123])", name)
    return f"fr{m.group(1)}" if m else "other"


def run_ablation(specs, out_dir, columns: Optional[Mapping[str, Mapping[str, Any]]] = None, *, configure=None,
                 measure=None, quiet: bool = False):
    """Run every column on every sequence; returns ``{column: {sequence: metrics}}``.

    Args:
        specs: each sequence's resolved settings (:func:`slam.options.resolve_settings`: its ``config``,
            ``run`` options and opened ``sequence``); every column changes its config.
        out_dir: each run writes into ``out_dir/<column>/<sequence>/`` (every such folder is checked, and
            its previous outputs removed, before the first run), with its ``config.toml`` (``attnloop-slam
            --config`` of it repeats that run); ``pr_<sequence>.png`` beside them.
        columns: ``{column: settings}`` (default: :func:`columns_for` the preset of the first config).
        configure: optional ``SLAMConfig -> SLAMConfig``, applied to each run's config.
        measure: optional ``(run, metrics) -> None``, called after each run with its
            :class:`~slam.pipeline.RunResult` and its metrics (to add figures that need the run itself).
        quiet: no progress bar and no line per run.

    Raises:
        slam.config.ConfigError: a column's setting that cannot be used, naming it.
    """
    if columns is None:
        columns = columns_for(specs[0].config.loop.descriptor.preset if specs else None)
    out_dir = Path(out_dir)
    if specs and viewer_flags(specs[0].run):
        raise UsageError(f"{', '.join(viewer_flags(specs[0].run))}: the viewer shows one run, an ablation makes "
                         "many; watch one with attnloop-slam")
    configs = {(col, k): override(spec.config, changes) for col, changes in columns.items()
               for k, spec in enumerate(specs)}
    if configure is not None:
        configs = {key: configure(cfg) for key, cfg in configs.items()}
    targets = {(col, k): prepare_output_dir(out_dir / col / spec.sequence.name) for col in columns
               for k, spec in enumerate(specs)}
    table: dict[str, dict[str, dict]] = {}
    curves: dict[str, dict] = {}
    for col in columns:
        table[col] = {}
        for k, spec in enumerate(specs):
            run = run_slam(spec.sequence, configs[(col, k)], max_frames=spec.run.max_frames,
                           frame_step=spec.run.frame_step, frames=spec.run.frames,
                           progress=False if quiet else None)
            metrics = evaluate_run(run).as_dict()
            write_outputs(run, targets[(col, k)])
            # --config of it repeats the run
            dataclasses.replace(spec, config=configs[(col, k)]).save(targets[(col, k)] / "config.toml")
            if measure is not None:
                measure(run, metrics)
            name = spec.sequence.name
            table[col][name] = metrics
            if "before_verification" in run.loop_curves:
                curves.setdefault(name, {})[col] = run.loop_curves["before_verification"]
            if not quiet:
                ate = metrics.get("ate_rmse")
                print(f"{col:8s} {name}: ATE {'-' if ate is None else f'{ate:.4f} m'}, {metrics['num_loops']} loops, "
                      f"{metrics['fps']:.1f} frames/s", flush=True)
    for name, by_col in curves.items():
        plot_pr_curves(out_dir / f"pr_{name}.png", by_col, title=f"{name}: loop detection before verification")
    return table


def _number(value, digits: int) -> str:
    return "-" if value is None or not math.isfinite(value) else f"{value:.{digits}f}"


def _mean(values) -> Optional[float]:
    known = [v for v in values if v is not None and math.isfinite(v)]
    return sum(known) / len(known) if known and len(known) == len(values) else None


def markdown_table(table, paper: Optional[Mapping[str, Mapping[str, float]]] = None) -> str:
    """Table 1's layout: one row per sequence, one column per descriptor, an average row per camera group
    (fr1, fr2, fr3, other; "-" where a run has no ATE), then the loop closure per sequence and column.

    Args:
        table: :func:`run_ablation`'s ``{column: {sequence: metrics}}``.
        paper: the paper's figures ``{sequence: {column: value}}`` (default :data:`PAPER_TABLE1`), shown
            as ``ours (paper x)`` where known.
    """
    paper = PAPER_TABLE1 if paper is None else paper
    cols = list(table)
    names = list(next(iter(table.values())))

    def ref(sequence, col):
        return paper.get(sequence.removeprefix("rgbd_dataset_"), {}).get(col)

    def cell(value, paper_value) -> str:
        return _number(value, 4) + ("" if paper_value is None else f" (paper {paper_value:.3f})")

    head = "| sequence | " + " | ".join(cols) + " |"
    rule = "|" + "---|" * (len(cols) + 1)
    lines = ["RMS-ATE (m):", "", head, rule]
    by_group: dict[str, list[str]] = {}
    for n in names:
        by_group.setdefault(camera_group(n), []).append(n)
    for group in ("fr1", "fr2", "fr3", "other"):
        for n in by_group.get(group, []):
            lines.append(f"| {n} | " + " | ".join(cell(table[c][n].get("ate_rmse"), ref(n, c)) for c in cols) + " |")
    for group in ("fr1", "fr2", "fr3", "other"):
        if group in by_group:
            avgs = [_mean([table[c][n].get("ate_rmse") for n in by_group[group]]) for c in cols]
            refs = [_mean([ref(n, c) for n in by_group[group]]) for c in cols]
            lines.append(f"| {group} average | " + " | ".join(cell(a, r) for a, r in zip(avgs, refs)) + " |")
    lines += ["", ("Loop closure (accepted true/false; max recall at 100% precision before -> after "
                   "verification):"), "", head, rule]
    for n in names:
        lines.append(f"| {n} | " + " | ".join(_loop_cell(table[c][n]) for c in cols) + " |")
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
