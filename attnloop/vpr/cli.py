"""``attnloop-vpr``: place recognition on an image collection, in steps with files between them.

Bad input or flags exit with code 2 and one line naming the file or flag; nothing already written is lost.
"""
from __future__ import annotations

import argparse
import csv
import importlib.util
import json
import sys
from dataclasses import asdict
from pathlib import Path

import numpy as np
import torch

from attnloop.vpr.describe import MANIFEST, VPRInputError, describe, describe_images, load_descriptors, read_manifest
from slam.options import non_negative_int, positive_int

_DESCRIPTOR_PREFIX = "loop.descriptor."


def _add_descriptor_arguments(parser: argparse.ArgumentParser) -> None:
    """The descriptor flags of ``attnloop-slam`` (:data:`slam.options.OPTIONS`), with their help and checks."""
    from slam.options import OPTIONS

    group = parser.add_argument_group("descriptor (as attnloop-slam)")
    for opt in OPTIONS:
        if opt.key.startswith(_DESCRIPTOR_PREFIX):
            kw = {"metavar": opt.flag[2:].upper(), **opt.kwargs} if "choices" not in opt.kwargs else opt.kwargs
            group.add_argument(opt.flag, dest=opt.key, default=argparse.SUPPRESS, help=opt.help, **kw)


def _descriptor_settings(args: argparse.Namespace) -> dict:
    from slam.config import DescriptorConfig
    from slam.options import check_weights_file

    typed = {k[len(_DESCRIPTOR_PREFIX):]: v for k, v in vars(args).items() if k.startswith(_DESCRIPTOR_PREFIX)}
    try:
        config = DescriptorConfig(**typed)
    except ValueError as e:
        raise VPRInputError(str(e)) from None
    check_weights_file(config.weights)
    return asdict(config)


def build_model(settings: dict) -> tuple[torch.nn.Module, dict]:
    """The descriptor of :class:`slam.config.DescriptorConfig` fields, and the fields with ``backbone``
    resolved (``"auto"`` becomes the backbone that ran, so the manifest rebuilds the same model anywhere)."""
    from slam.config import DescriptorConfig
    from slam.loop.closer import build_descriptor

    model = build_descriptor(DescriptorConfig(**settings))
    return model, {**settings, "backbone": model.backbone_name, "weights": settings.get("weights")}


def _images_or_descriptors(inputs: list[str], args) -> tuple[list[str], np.ndarray]:
    """A descriptor folder's ``(paths, X)``, or the images of ``inputs`` described now with the flags' model."""
    if len(inputs) == 1 and (Path(inputs[0]) / MANIFEST).is_file():
        paths, x = load_descriptors(inputs[0])
        total = len(read_manifest(inputs[0])["paths"])
        if len(paths) != total:
            raise VPRInputError(f"{inputs[0]}: {total - len(paths)} of its {total} images were skipped as unreadable; "
                                "a ground truth indexes every image")
        return paths, x
    if not hasattr(args, "model"):
        args.model = build_model(_descriptor_settings(args))[0]
    return describe_images(args.model, inputs, batch_size=args.batch_size, workers=args.workers)


def cmd_describe(args) -> int:
    if args.engine == "ray" and importlib.util.find_spec("ray") is None:
        raise VPRInputError("--engine ray needs Ray Data: pip install 'attnloop[ray]'")
    model, settings = build_model(_descriptor_settings(args))
    options = {"batch_size": args.batch_size}
    if args.engine == "ray":
        options.update(actors=args.ray_actors, cpus_per_actor=args.ray_cpus, gpus_per_actor=args.ray_gpus,
                       address=args.ray_address)
    else:
        options["workers"] = args.workers
    m = describe(args.images, args.out, model, settings, shard_size=args.shard_size, engine=args.engine,
                 strict=args.strict, progress=not args.no_progress, **options)
    skipped = sum(len(s["skipped"]) for s in m["shards"])
    print(f"{len(m['paths']) - skipped} images described ({skipped} skipped) into {args.out}: {len(m['shards'])} "
          f"shards of {m['dim']}-d float32")
    return 0


def cmd_index(args) -> int:
    from attnloop.index import IndexConfig
    from attnloop.vpr.search import ShardedIndex

    _, x = load_descriptors(args.dir)
    index = ShardedIndex.build(x, IndexConfig(backend=args.backend, background=False), args.max_rows)
    files = index.save(args.dir)
    print(f"{x.shape[0]} descriptors indexed in {len(files)} index file(s) in {args.dir}")
    return 0


def cmd_query(args) -> int:
    from attnloop.index import IndexConfig
    from attnloop.vpr.search import ShardedIndex

    refs, x = load_descriptors(args.dir)
    index = ShardedIndex.load(args.dir) or ShardedIndex.build(x, IndexConfig(backend="exact", background=False))
    model, _ = build_model(read_manifest(args.dir)["descriptor"])
    paths, q = describe_images(model, args.images, batch_size=args.batch_size, workers=args.workers)
    ids, sims = index.search(q, k=args.k)
    rows = [["query", "rank", "reference", "similarity"]]
    for path, row_ids, row_sims in zip(paths, ids.tolist(), sims.tolist()):
        rows += [[path, r + 1, refs[i], f"{s:.6f}"] for r, (i, s) in enumerate(zip(row_ids, row_sims)) if i >= 0]
    if args.out is None:
        csv.writer(sys.stdout).writerows(rows)
    else:
        with open(args.out, "w", newline="") as f:
            csv.writer(f).writerows(rows)
    return 0


def _poses(path: str) -> torch.Tensor:
    """One pose per image, ``tx ty tz qx qy qz qw`` (a leading timestamp column, as TUM's, is dropped)."""
    try:
        p = np.loadtxt(path, ndmin=2, comments="#")
    except (OSError, ValueError) as e:
        raise VPRInputError(f"{path}: not a pose file ({e})") from None
    if p.shape[1] not in (7, 8):
        raise VPRInputError(f"{path}: {p.shape[1]} columns, expected 7 (tx ty tz qx qy qz qw) or 8 (a timestamp first)")
    return torch.from_numpy(p[:, -7:])


def _evaluation_set(args):
    from attnloop.vpr import datasets
    from attnloop.vpr.evaluate import ground_truth_from_poses, read_ground_truth, sequence_candidates
    from slam.eval.loops import LoopGroundTruthConfig

    if args.nordland:
        return datasets.nordland(args.nordland, args.step, args.aligned if args.aligned is not None else 1)
    if args.rtabmap:
        return datasets.rtabmap(args.rtabmap, args.min_gap or 10)
    if not args.query:
        raise VPRInputError("give --query (with --reference, or --min-gap for one set against itself), --rtabmap or "
                            "--nordland")
    sources = [args.ground_truth is not None, args.poses is not None, args.aligned is not None]
    if sum(sources) != 1:
        raise VPRInputError("give one ground truth: --ground-truth FILE, --poses FILE [FILE] or --aligned K")
    if args.reference is None and not args.min_gap:
        raise VPRInputError("one set against itself needs --min-gap N (the frames nearer than N are not candidates)")
    if args.reference is not None and args.min_gap:
        raise VPRInputError("--min-gap applies to one set against itself; it has no meaning with --reference")
    if args.aligned is not None:
        return datasets.VPRSet(args.query, args.reference, None)
    if args.poses is not None:
        if len(args.poses) != 1 + (args.reference is not None):
            raise VPRInputError("--poses takes one file per set: the queries' (and the references')")
        gt_config = LoopGroundTruthConfig(args.max_distance, args.max_angle, args.min_gap or 1)
        gt = ground_truth_from_poses(*map(_poses, args.poses), config=gt_config)
    else:
        gt = read_ground_truth(args.ground_truth)
    cand = sequence_candidates(gt.shape[0], args.min_gap) if args.reference is None else None
    return datasets.VPRSet(args.query, args.reference, gt, cand)


def cmd_evaluate(args) -> int:
    from attnloop.vpr.datasets import aligned_ground_truth
    from attnloop.vpr.evaluate import evaluate, plot_place_recognition

    s = _evaluation_set(args)
    q_paths, q = _images_or_descriptors(s.query, args)
    r_paths, r = (q_paths, q) if s.reference is None else _images_or_descriptors(s.reference, args)
    typed = [k[len(_DESCRIPTOR_PREFIX):].replace("_", "-") for k in vars(args) if k.startswith(_DESCRIPTOR_PREFIX)]
    if typed and not hasattr(args, "model"):
        raise VPRInputError(f"--{', --'.join(typed)}: the sets are descriptor folders, described already; the "
                            "descriptor flags apply to images")
    gt, cand = s.ground_truth, s.candidates
    if gt is None:
        gt = aligned_ground_truth(range(len(q_paths)), range(len(r_paths)), args.aligned)
    if gt.shape != (len(q_paths), len(r_paths)):
        raise VPRInputError(f"the ground truth is {tuple(gt.shape)}, the images {len(q_paths)} queries x "
                            f"{len(r_paths)} references")
    step = 1 if args.nordland else args.step  # the Nordland set is subsampled as it is read
    if step > 1:
        q, r, gt = q[::step], r[::step], gt[::step, ::step]
        cand = None if cand is None else cand[::step, ::step]
    sim = torch.from_numpy(q).double() @ torch.from_numpy(r).double().T
    res = evaluate(sim, gt, candidates=cand)
    print(f"{res.num_queries} queries, {res.num_with_match} with a true match\n")
    print("| R@1 | R@5 | R@10 | AUC-PR (VPR-Bench) | R@P100 | threshold at P100 |\n|---|---|---|---|---|---|")
    print(f"| {res.recall_at(1):.3f} | {res.recall_at(5):.3f} | {res.recall_at(10):.3f} | {res.auc_pr:.3f} | "
          f"{res.recall_at_full_precision:.3f} | {res.threshold_at_full_precision:.3f} |")
    if args.out:
        args.out.mkdir(parents=True, exist_ok=True)
        (args.out / "metrics.json").write_text(json.dumps(res.to_dict(), indent=1))
        plot_place_recognition(args.out / "pr.png", {"attnloop": res})
    return 0


class _Parser(argparse.ArgumentParser):
    """A usage error in one line (its subcommands' parsers are of this class too)."""

    def error(self, message):
        self.exit(2, f"{self.prog}: {message} (--help: usage)\n")


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(prog="attnloop-vpr", description=__doc__.split("\n")[0])
    sub = parser.add_subparsers(dest="command", required=True)
    images_help = "folders (images in natural order), glob patterns, image files or text files of paths"

    def loader(p):
        p.add_argument("--batch-size", type=positive_int, default=16, metavar="N", help="images per batch (16)")
        p.add_argument("--workers", type=non_negative_int, default=2, metavar="N",
                       help="DataLoader processes decoding images (2; 0: decode in the main process)")
        p.add_argument("--threads", type=positive_int, default=None, metavar="N",
                       help="torch threads (torch's default)")

    d = sub.add_parser("describe", help="the descriptor of every image, as resumable .npy shards and a manifest")
    d.add_argument("images", nargs="+", help=images_help)
    d.add_argument("--out", type=Path, required=True, metavar="DIR", help="descriptor folder (an existing one resumes)")
    d.add_argument("--shard-size", type=positive_int, default=None, metavar="N",
                   help="images per shard (default: the folder's when resuming, else 4096)")
    d.add_argument("--strict", action="store_true", help="stop at the first unreadable image (default: name, skip)")
    d.add_argument("--no-progress", action="store_true", help="no progress bar")
    d.add_argument("--engine", choices=("local", "ray"), default="local",
                   help="local: a DataLoader and this process's model; ray: Ray Data with an actor pool")
    d.add_argument("--ray-address", default=None, metavar="ADDR",
                   help="Ray cluster to join (auto, ray://HOST:10001); default: a local Ray on this machine")
    d.add_argument("--ray-actors", type=positive_int, default=1, metavar="N", help="actors, each holding a model (1)")
    d.add_argument("--ray-cpus", type=float, default=1.0, metavar="C", help="CPUs (= torch threads) per actor (1)")
    d.add_argument("--ray-gpus", type=float, default=0.0, metavar="G", help="GPUs per actor (0)")
    loader(d)
    _add_descriptor_arguments(d)
    d.set_defaults(func=cmd_describe)

    i = sub.add_parser("index", help="the keyframe index of a descriptor folder, one per shard when too large")
    i.add_argument("dir", type=Path, help="descriptor folder")
    i.add_argument("--backend", choices=("auto", "exact", "flann", "faiss"), default="auto", help="index backend")
    i.add_argument("--max-rows", type=positive_int, default=None, metavar="N",
                   help="descriptors per index (default: as many as half the memory holds)")
    i.set_defaults(func=cmd_index)

    q = sub.add_parser("query", help="the top-k references of query images, as CSV")
    q.add_argument("dir", type=Path, help="descriptor folder (its index if built, else an exact scan)")
    q.add_argument("images", nargs="+", help=images_help)
    q.add_argument("-k", type=positive_int, default=10, help="matches per query (10)")
    q.add_argument("--out", type=Path, default=None, metavar="FILE.csv", help="CSV file (default: stdout)")
    loader(q)
    q.set_defaults(func=cmd_query)

    e = sub.add_parser("evaluate", help="R@1/5/10, AUC-PR, recall at 100%% precision and the PR plot")
    e.add_argument("--query", nargs="+", metavar="IMAGES", help="query images, or a descriptor folder")
    e.add_argument("--reference", nargs="+", metavar="IMAGES", help="reference images, or a descriptor folder "
                   "(default: the queries against themselves, with --min-gap)")
    e.add_argument("--ground-truth", metavar="FILE", help="binary matrix (image or .npy) or VPR-Bench "
                   "ground_truth_new.npy, queries x references")
    e.add_argument("--poses", nargs="+", metavar="FILE", help="one pose per image (tx ty tz qx qy qz qw, a timestamp "
                   "first allowed), of the queries (and the references)")
    e.add_argument("--max-distance", type=float, default=0.5, metavar="M", help="with --poses: metres (0.5)")
    e.add_argument("--max-angle", type=float, default=45.0, metavar="DEG", help="with --poses: degrees (45)")
    e.add_argument("--aligned", type=int, default=None, metavar="K",
                   help="index-aligned sets: query i matches references i-K .. i+K (frames before --step)")
    e.add_argument("--min-gap", type=positive_int, default=None, metavar="N",
                   help="one set against itself: each image against those at least N earlier")
    e.add_argument("--step", type=positive_int, default=1, metavar="N", help="every Nth query and reference (1)")
    e.add_argument("--rtabmap", metavar="DIR", help="RTAB-Map's samples (84 images, samples_GT.bmp), gap 10")
    e.add_argument("--nordland", metavar="DIR", help="Nordland: winter vs summer, --aligned K (1), --step N")
    e.add_argument("--out", type=Path, default=None, metavar="DIR", help="write metrics.json and pr.png there")
    loader(e)
    _add_descriptor_arguments(e)
    e.set_defaults(func=cmd_evaluate)
    return parser


def main(argv=None) -> int:
    from attnloop.backbones.weights import WeightsNotFoundError
    from attnloop.vpr.evaluate import GroundTruthFormatError, ShapeMismatchError
    from slam.options import UsageError

    parser = build_parser()
    args = parser.parse_args(argv)
    if getattr(args, "threads", None):
        torch.set_num_threads(args.threads)
    try:
        return args.func(args)
    except (VPRInputError, UsageError, GroundTruthFormatError, ShapeMismatchError, WeightsNotFoundError,
            ImportError) as e:  # ImportError: an index backend whose package is not installed (it names it)
        print(f"attnloop-vpr {args.command}: {e}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
