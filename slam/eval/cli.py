"""``attnloop-eval``: evaluate a trajectory file against ground truth, as ``evo_ape`` / ``evo_rpe`` do
(:func:`slam.eval.ate`, :func:`slam.eval.rpe`, :func:`slam.eval.plot_trajectory`; examples in ``--help``).

``ate GT EST`` is ``evo_ape tum GT EST -a --t_max_diff 0.02`` (TUM's association tolerance; evo's own
default is 0.01 s, give ``--t-max-diff 0.01`` to match a bare ``evo_ape``); ``rpe GT EST`` is
``evo_rpe tum GT EST --delta 1 --delta_unit f`` with the same tolerance. The exit code is 0 on success and
2 with a one-line message for a file that cannot be read or trajectories that cannot be compared.
"""
from __future__ import annotations

import argparse
import json
import math
import os
import sys
from pathlib import Path

from slam.io.associate import TUM_MAX_DIFFERENCE

__all__ = ["build_parser", "main"]

_STAT_KEYS = ("rmse", "mean", "median", "std", "min", "max", "sse")
_METRICS = ("ate", "rpe")


def _positive(text: str) -> float:
    value = float(text)
    if not math.isfinite(value) or value <= 0:
        raise argparse.ArgumentTypeError(f"must be a positive finite number, got {text}")
    return value


def _finite(text: str) -> float:
    value = float(text)
    if not math.isfinite(value):
        raise argparse.ArgumentTypeError(f"must be a finite number, got {text}")
    return value


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="attnloop-eval",
        description="Absolute (ate) and relative (rpe) pose error of a TUM-format trajectory against a TUM-format "
                    "ground truth, with evo's semantics. Prints the statistics; --json and --plot write files.",
        formatter_class=argparse.RawDescriptionHelpFormatter,
        epilog="examples:\n"
               "  attnloop-eval ate groundtruth.txt trajectory.txt\n"
               "  attnloop-eval groundtruth.txt trajectory.txt          # the same: ate by default\n"
               "  attnloop-eval ate groundtruth.txt trajectory.txt --align sim3 --plot ate.png\n"
               "  attnloop-eval rpe groundtruth.txt trajectory.txt --delta 1 --delta-unit seconds --all-pairs\n")
    sub = p.add_subparsers(dest="metric", required=True, metavar="{ate,rpe}",
                           help="the metric (default ate: 'attnloop-eval GT EST' is 'attnloop-eval ate GT EST')")
    for name, text in (("ate", "absolute trajectory error: camera-centre distance after alignment (evo_ape -a)"),
                       ("rpe", "relative pose error over a fixed delta (evo_rpe)")):
        s = sub.add_parser(name, help=text, description=text)
        s.add_argument("reference", help="ground-truth trajectory, TUM format (timestamp tx ty tz qx qy qz qw)")
        s.add_argument("estimate", help="estimated trajectory, TUM format")
        s.add_argument("--t-max-diff", type=_positive, default=TUM_MAX_DIFFERENCE,
                       help=f"association tolerance in seconds (default {TUM_MAX_DIFFERENCE}, TUM's)")
        s.add_argument("--t-offset", type=_finite, default=0.0,
                       help="seconds added to the estimate's timestamps before association (default 0)")
        s.add_argument("--association", choices=("evo", "tum"), default="evo",
                       help="timestamp association: evo (default: nearest stamp of the longer trajectory, "
                            "|dt| <= --t-max-diff, as evo) or tum (greedy one-to-one, |dt| < --t-max-diff, "
                            "as TUM's evaluate_ate.py)")
        s.add_argument("--json", metavar="FILE", default=None, help="also write every statistic to this JSON file")
        if name == "ate":
            s.add_argument("--align", choices=("se3", "sim3", "none"), default="se3",
                           help="alignment of the estimate: se3 rigid (default, evo -a), sim3 rigid + scale "
                                "(evo -as), none")
            s.add_argument("--plot", metavar="PNG", default=None,
                           help="draw both trajectories (aligned, top view) into this PNG")
            s.add_argument("--labels", nargs=2, metavar=("REFERENCE", "ESTIMATE"),
                           default=("ground truth", "estimate"), help="legend of the plot")
            s.add_argument("--plane", choices=("auto", "xy", "xz", "yz"), default="auto",
                           help="plane of the plot (default: the two axes with the largest spread)")
        else:
            s.add_argument("--delta", type=_positive, default=1,
                           help="pair distance (default 1), in --delta-unit")
            s.add_argument("--delta-unit", choices=("frames", "seconds"), default="frames",
                           help="frames (evo_rpe's default) or seconds (TUM's evaluate_rpe.py uses 1 s)")
            s.add_argument("--all-pairs", action="store_true",
                           help="use every start pose (default: consecutive non-overlapping pairs, as evo)")
            s.add_argument("--align", choices=("none", "se3", "sim3"), default="none",
                           help="align first (default none: a rigid alignment does not change the RPE)")
    return p


def _stats_lines(title: str, stats: dict, unit: str) -> list[str]:
    return [title] + [f"{key:>8s}  {stats[key]:.6f} {unit}{'^2' if key == 'sse' else ''}" for key in _STAT_KEYS]


def _run(args: argparse.Namespace) -> dict:
    from slam.eval.metrics import ate, rpe

    common = {"max_difference": args.t_max_diff, "offset": args.t_offset, "association": args.association}
    if args.metric == "ate":
        res = ate(args.reference, args.estimate, alignment=args.align, **common)
        out = res.to_dict()
        what = {"se3": "rigid SE(3) alignment", "sim3": f"Sim(3) alignment, scale {res.scale:.6f}",
                "none": "no alignment"}[args.align]
        print(f"ATE RMSE {res.rmse:.6f} m ({res.num_pairs} pose pairs, {what})")
        print("\n".join(_stats_lines("translation error:", out, "m")))
        if args.plot:
            from slam.eval.metrics import as_trajectory
            from slam.eval.plot import plot_trajectory

            plot_trajectory(args.plot, as_trajectory(args.estimate, "estimate"),
                            as_trajectory(args.reference, "reference"), plane=args.plane,
                            align=res, labels=tuple(args.labels),
                            title=f"ATE {res.rmse:.4f} m ({what})")
            print(f"wrote {args.plot}")
    else:
        # a whole frame count as an int; any other value as given, for rpe() to refuse a fraction of a frame
        whole = args.delta_unit == "frames" and float(args.delta).is_integer()
        delta = int(args.delta) if whole else args.delta
        res = rpe(args.reference, args.estimate, delta=delta, delta_unit=args.delta_unit,
                  all_pairs=args.all_pairs, alignment=args.align, **common)
        out = res.to_dict()
        print(f"RPE translation RMSE {res.translation.rmse:.6f} m, rotation RMSE {res.rotation.rmse:.6f} deg "
              f"({res.num_pairs} pairs {delta} {args.delta_unit} apart)")
        print("\n".join(_stats_lines("translation error:", out["translation_m"], "m")))
        print("\n".join(_stats_lines("rotation error:", out["rotation_deg"], "deg")))
    return out


def stdout_gone() -> int:
    """The exit code of a command whose reader closed its output early (``attnloop-eval ... | head``), as
    Python's documentation of SIGPIPE recommends: standard output is pointed at ``os.devnull``, so that the
    flush at exit does not raise (and print "[Errno 32] Broken pipe") again, and the code is 1."""
    try:
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
    except (OSError, ValueError, AttributeError):  # a replaced sys.stdout without a file descriptor
        pass
    return 1


def main(argv: list[str] | None = None) -> int:
    try:
        return _main(sys.argv[1:] if argv is None else list(argv))
    except BrokenPipeError:  # attnloop-eval ... | head
        return stdout_gone()


def _main(argv: list[str]) -> int:
    if argv and not argv[0].startswith("-") and argv[0] not in _METRICS:
        argv = ["ate", *argv]  # attnloop-eval GT EST: the ATE, the metric TUM and evo report first
    args = build_parser().parse_args(argv)
    from slam.io import DatasetError

    try:
        out = _run(args)
        if args.json:
            Path(args.json).write_text(json.dumps(out, indent=2, allow_nan=False) + "\n")
            print(f"wrote {args.json}")
    except BrokenPipeError:
        raise
    except (DatasetError, OSError, ValueError) as e:
        print(f"attnloop-eval: {e}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
