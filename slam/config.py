"""Typed configuration of the whole SLAM system (every default commented), and its TOML form.

Every config is a frozen dataclass checked when built (a ValueError naming ``Class.field``); change a nested
field by its dotted path with :func:`override`. TOML (``--config FILE.toml``; every run writes its
``config.toml``): one table per nested config, a key left out keeps its default, None is written ``"None"``.

Example:
    >>> cfg = override(SLAMConfig(), {"loop.descriptor.fusion": "eam", "threads": 2})
    >>> cfg.loop.descriptor.fusion, cfg.threads
    ('eam', 2)
    >>> config_from_dict(config_to_dict(cfg)) == cfg
    True
"""
from __future__ import annotations

import dataclasses
import math
import numbers
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Optional

import numpy as np

from attnloop.backbones import AUTO, BACKBONES
from attnloop.fusion import FUSION_MODES
from attnloop.index import LoopDetectorConfig
from attnloop.presets import PRESETS, preset
from attnloop.threshold import ThresholdConfig
from slam.backend import check_backend_config
from slam.loop.acceptance import DriftBoundConfig
from slam.loop.consistency import ConsistencyConfig
from slam.mapping import MapConfig
from slam.maps.config import RelocalisationConfig
from slam.odometry.config import OdometryConfig, RegistrationConfig, check_bool, check_choice, check_int, check_number

__all__ = ["REGISTERED", "BackendConfig", "CameraRig", "ConfigError", "DescriptorConfig", "LoopClosureConfig",
           "SLAMConfig", "UsageError", "check_device", "check_intrinsics", "check_sequence_intrinsics",
           "config_from_dict", "config_to_dict", "describe_rig", "override", "read_toml",
           "save_config", "toml_text"]


class ConfigError(ValueError):
    """A config key or value that cannot be used (the message names the key)."""


def check_device(device, what: str, float64: bool = False) -> Optional[str]:
    """A torch device name this torch can use (None stays None: the CPU).

    Args:
        device: ``"cpu"``, ``"cuda"``, ``"cuda:1"``, ``"mps"`` or None.
        what: the field or flag named in the error.
        float64: the work needs float64 (the pose graph): MPS, which has none, is refused.

    Raises:
        ValueError: a name torch does not know (``"bogus"``), or a device this machine lacks.
    """
    if device is None:
        return None
    import torch

    try:
        dev = torch.device(device)
    except (RuntimeError, TypeError, ValueError):
        raise ValueError(f"{what} {device!r} is not a torch device (e.g. cpu, cuda, cuda:1, mps)") from None
    if dev.type == "cuda":
        if not torch.cuda.is_available():
            build = "a CPU-only torch build" if torch.version.cuda is None else "no CUDA device is visible"
            raise ValueError(f"{what} {device!r}: CUDA is not available ({build}); use {what} cpu")
        if dev.index is not None and dev.index >= torch.cuda.device_count():
            raise ValueError(f"{what} {device!r}: only {torch.cuda.device_count()} CUDA device(s)")
    elif dev.type == "mps":
        if float64:
            raise ValueError(f"{what} {device!r}: the pose graph is solved in float64, which MPS lacks; use "
                             f"{what} cpu")
        if not (hasattr(torch.backends, "mps") and torch.backends.mps.is_available()):
            raise ValueError(f"{what} {device!r}: MPS is not available on this machine; use {what} cpu")
    elif dev.type != "cpu":
        raise ValueError(f"{what} {device!r}: device type {dev.type!r} is not supported (cpu, cuda, mps)")
    return device


@dataclass(frozen=True)
class DescriptorConfig:
    """The attention-guided keyframe descriptor (:class:`attnloop.AttentionDescriptor`).

    ``preset`` names the descriptor (:mod:`attnloop.presets`: ``default``, ``paper``, ``guclu2019``);
    ``fusion`` and ``num_rnn`` left at None take the preset's.

    Example:
        >>> DescriptorConfig(preset="paper").recipe.out_dim
        1024
    """

    preset: str = "default"  # attnloop.presets.PRESETS: the measured default, the paper's, its baseline's
    backbone: str = "auto"  # "auto": vgg16 when its weights are found (always for the paper's presets), else Lite0
    fusion: Optional[str] = None  # "none" | "dam" | "eam" | "gaf" | "ega"; None: the preset's (paper: DAM)
    num_rnn: Optional[int] = None  # random RNNs after the pooling (num_rnn * 64 dims); None: the preset's
    seed: int = 0  # seed of the random RNN weights when there are RNNs (same seed, same descriptor)
    pretrained: bool = True  # ImageNet weights; False = seeded random weights (plumbing tests only)
    weights: Optional[str] = None  # explicit checkpoint path (else torch hub cache, else download)
    device: Optional[str] = None  # None: CPU (library code follows its inputs; this picks where they live)

    def __post_init__(self) -> None:
        n = "DescriptorConfig"
        check_choice(n, "preset", self.preset, tuple(PRESETS))
        check_choice(n, "backbone", self.backbone, (AUTO, *BACKBONES))
        if self.fusion is not None:
            check_choice(n, "fusion", self.fusion, FUSION_MODES)
        if self.num_rnn is not None:
            check_int(n, "num_rnn", self.num_rnn, 0)
        check_int(n, "seed", self.seed, 0)
        check_bool(n, "pretrained", self.pretrained)
        if self.weights is not None and not isinstance(self.weights, (str, Path)):
            raise ValueError(f"{n}.weights must be a file path or None, got {self.weights!r}")
        check_device(self.device, f"{n}.device")
        p = preset(self.preset)
        if p.fixed:
            for name, own in (("num_rnn", p.recipe.get("num_rnn")), ("fusion", p.fusion)):
                value = getattr(self, name)
                if own is not None and value is not None and value != own:
                    raise ValueError(f"{n}.{name} is {own!r} in the preset {self.preset!r}, got {value!r} "
                                     f"(leave it None, or choose another preset)")
        _ = self.recipe  # the recipe's own checks, now rather than when the descriptor is built

    @property
    def recipe(self):
        """The :class:`attnloop.descriptor.DescriptorRecipe` of this config (the preset's, with ``fusion``,
        ``num_rnn`` and ``seed``)."""
        from attnloop.descriptor import DescriptorRecipe

        p = preset(self.preset)
        settings = dict(p.recipe)
        fusion = self.fusion if self.fusion is not None else p.fusion
        if fusion is not None:
            settings["fusion"] = fusion
        if self.num_rnn is not None:
            settings["num_rnn"] = self.num_rnn
        return DescriptorRecipe(**settings, seed=self.seed)

    def settings(self) -> dict:
        """The keyword arguments of :class:`attnloop.AttentionDescriptor` this config stands for."""
        kw = {"backbone": self.backbone, "preset": self.preset, "seed": self.seed, "pretrained": self.pretrained,
              "weights": None if self.weights is None else str(self.weights)}
        if self.fusion is not None:
            kw["fusion"] = self.fusion
        if self.num_rnn is not None:
            kw["num_rnn"] = self.num_rnn
        return kw


@dataclass(frozen=True)
class LoopClosureConfig:
    """Loop detection (descriptor + index + adaptive threshold), geometric verification and acceptance
    (the defaults measured: docs/results.md, "Loop candidates")."""

    enabled: bool = True  # False = odometry only (--no-loop)
    descriptor: DescriptorConfig = field(default_factory=DescriptorConfig)
    # keyframe ids are milliseconds since the first keyframe: ``window`` is 3 s at any frame rate or step; a low
    # threshold, as verification and the group check reject the false candidates
    detector: LoopDetectorConfig = field(default_factory=lambda: LoopDetectorConfig(
        window=3000, threshold=ThresholdConfig(k_sigma=1.5, min_samples=16)))
    # replaces ``detector.threshold`` for a backbone's default descriptor: an absolute floor belongs to the
    # descriptor (Lite0's similarities sit near 0.97); backbones not listed keep ``detector.threshold``
    threshold_by_backbone: dict = field(default_factory=lambda: {
        "efficientnet_lite0": ThresholdConfig(k_sigma=0.5, min_margin=0.005, min_similarity=0.975, min_samples=16)},
        metadata={"values": ThresholdConfig})
    registration: RegistrationConfig = field(default_factory=RegistrationConfig)  # the odometry's, stricter below
    max_candidates: int = 5  # candidates verified per query keyframe (most similar first), 1..detector.top_k
    min_inliers: int = 40  # RANSAC inliers an accepted loop needs
    min_inlier_ratio: float = 0.25  # inliers / matches
    # a loop edge joins views this close and this little turned; below the evaluation's 0.5 m / 45 deg
    max_translation: float = 0.4  # m
    max_rotation_deg: float = 40.0  # degrees
    # agreement with the current estimate within a bound growing with the distance travelled (slam.loop.acceptance)
    drift: DriftBoundConfig = field(default_factory=DriftBoundConfig)
    # True: no drift bound across a tracking loss (mends a long loss, but may take an identical room for the old)
    recover_after_loss: bool = False
    # the largest set of mutually consistent loops is kept (slam.loop.consistency)
    consistency: ConsistencyConfig = field(default_factory=ConsistencyConfig)
    # multiplies the loop edges' information: RANSAC's point-based sigma is ~10x optimistic, and loop edges share
    # their errors (odometry edges: backend.odometry_information_scale)
    information_scale: float = 0.001
    # True: a keyframe whose kept loop joins it to an earlier one within the keyframe thresholds adds nothing: it
    # is left out of the detector's database, its data released (RGBDSLAM.released), and the next keyframe is
    # verified first near it (LoopQuery.followed); off while a map is saved (the map keeps every keyframe)
    release_revisits: bool = True
    # a loop that the estimate already satisfies within these triggers no online correction (0: every one does)
    settled_translation: float = 0.02  # m
    settled_rotation_deg: float = 1.0  # degrees

    def __post_init__(self) -> None:
        n = "LoopClosureConfig"
        check_int(n, "max_candidates", self.max_candidates, 1)
        if self.max_candidates > self.detector.top_k:
            raise ValueError(f"LoopClosureConfig.max_candidates ({self.max_candidates}) must be <= "
                             f"LoopClosureConfig.detector.top_k ({self.detector.top_k}): the detector proposes at "
                             "most top_k candidates per query keyframe")
        check_int(n, "min_inliers", self.min_inliers, 0)
        check_number(n, "min_inlier_ratio", self.min_inlier_ratio, 0, 1)
        check_number(n, "max_translation", self.max_translation, 0, lo_open=True)  # inf: no bound
        check_number(n, "max_rotation_deg", self.max_rotation_deg, 0, lo_open=True)
        check_number(n, "information_scale", self.information_scale, 0, lo_open=True, finite=True)
        check_number(n, "settled_translation", self.settled_translation, 0, finite=True)
        check_number(n, "settled_rotation_deg", self.settled_rotation_deg, 0, finite=True)
        check_bool(n, "recover_after_loss", self.recover_after_loss)
        check_bool(n, "release_revisits", self.release_revisits)
        if not isinstance(self.threshold_by_backbone, dict):
            raise ValueError(f"LoopClosureConfig.threshold_by_backbone must be a dict backbone name -> "
                             f"ThresholdConfig, got {type(self.threshold_by_backbone).__name__}")
        for backbone, thr in self.threshold_by_backbone.items():
            if not isinstance(thr, ThresholdConfig):
                raise ValueError(f"LoopClosureConfig.threshold_by_backbone[{backbone!r}] must be a ThresholdConfig, "
                                 f"got {type(thr).__name__}")
            try:  # the loop closer puts it in the detector's config: its own checks, now rather than then
                dataclasses.replace(self.detector, threshold=thr)
            except ValueError as e:
                raise ValueError(f"LoopClosureConfig.threshold_by_backbone[{backbone!r}]: {e}") from None


@dataclass(frozen=True)
class BackendConfig:
    """Pose-graph optimisation over the keyframes (slam.backend)."""

    method: str = "lm"  # "lm" (Levenberg-Marquardt) or "gn" (Gauss-Newton): slam.backend.OPTIMIZER_METHODS
    kernel: Optional[str] = "cauchy"  # robust kernel on the odometry edges (a slam.graph.make_kernel name or None)
    kernel_width: Optional[float] = None  # None: sqrt(chi2_0.95(6)) = 3.55
    # on the loop edges: "dcs" (dynamic covariance scaling), a make_kernel name, "none" or None (``kernel``'s)
    loop_kernel: Optional[str] = "dcs"
    loop_kernel_width: Optional[float] = None  # None: sqrt(chi2_0.95(6)) = 3.55
    max_iterations: int = 50  # LM iterations of the final optimisation (>= 1)
    odometry_information_scale: float = 0.01  # multiplies the odometry edges' information (see loop.information_scale)
    # after a keyframe whose loops changed the graph, optimise and re-anchor tracking (False: only in finish())
    optimize_on_loop: bool = True
    # keyframes the loop worker may lag behind tracking; 0: tracking waits, the result is the same on any machine
    loop_backlog: int = 0
    online_max_iterations: int = 10  # LM iterations of an online correction (bounds its time; >= 1)
    # an online correction optimises the keyframes within this many of the changed ones (None: the whole graph)
    online_window: Optional[int] = 50
    # ... with at most this many newest loop edges per keyframe (None: all), so its cost does not grow with laps
    online_loops_per_keyframe: Optional[int] = 4
    switch_off_weight: float = 0.1  # a loop edge whose final kernel weight is below this is reported switched off
    device: Optional[str] = None  # torch device of the pose graph (float64: not MPS); None: the CPU

    def __post_init__(self) -> None:
        check_backend_config(self)  # names checked by the factories slam.backend dispatches on
        check_device(self.device, "BackendConfig.device", float64=True)


@dataclass(frozen=True)
class SLAMConfig:
    """Everything :class:`slam.system.RGBDSLAM` needs."""

    odometry: OdometryConfig = field(default_factory=OdometryConfig)
    loop: LoopClosureConfig = field(default_factory=LoopClosureConfig)
    backend: BackendConfig = field(default_factory=BackendConfig)
    map: MapConfig = field(default_factory=MapConfig)  # map.ply of a run (slam.pipeline)
    relocalisation: RelocalisationConfig = field(default_factory=RelocalisationConfig)  # in a saved map (--map)
    threads: Optional[int] = 1  # torch, BLAS and OpenCV threads of a run (None: as they are; slam.threads)
    # a run tracking fewer than this fraction of its frames failed (exit code 1): an input error, as 8-bit depth
    min_tracked_fraction: float = 0.1

    def __post_init__(self) -> None:
        from slam.threads import check_threads

        check_threads(self.threads, "SLAMConfig.threads")
        check_number("SLAMConfig", "min_tracked_fraction", self.min_tracked_fraction, 0.0, 1.0)
        # the map's depth range with the odometry's filling a None
        f = self.odometry.features
        lo = f.min_depth if self.map.min_depth is None else self.map.min_depth
        hi = f.max_depth if self.map.max_depth is None else self.map.max_depth
        if not hi > lo:
            raise ValueError(f"SLAMConfig.map: the depth range must have max_depth > min_depth, got min_depth {lo!r}, "
                             f"max_depth {hi!r} (None takes odometry.features': {f.min_depth!r}, {f.max_depth!r})")


# ----------------------------------------------------------------------------------------------------
# changing a nested field, and the TOML form
NONE = "None"  # TOML has no null: how a None field is spelt in a file


def override(config, changes: Mapping[str, Any], prefix: str = ""):
    """``config`` with fields changed by dotted path (``{"loop.descriptor.fusion": "eam"}``), every
    config on the way rebuilt with :func:`dataclasses.replace` (and so checked); ``prefix``: the key of
    ``config`` itself in the messages (``"run."``).

    Raises:
        ConfigError: an unknown key or a bad value, naming the key.
    """
    nested: dict = {}
    for key, value in changes.items():
        *tables, last = key.split(".")
        data = nested
        for t in tables:
            data = data.setdefault(t, {})
            if not isinstance(data, dict):
                raise ConfigError(f"{key}: {t} is a value, not a table")
        data[last] = value
    return _merge(config, nested, prefix)


def _field_value(current, value, key: str, values_type=None):
    if isinstance(value, Mapping) and values_type is not None:  # a dict of configs (threshold_by_backbone)
        out = dict(current)
        for name, table in value.items():
            if not isinstance(table, Mapping):
                raise ConfigError(f"{key}.{name}: expected a table of {values_type.__name__} fields, got {table!r}")
            out[name] = _merge(current.get(name, values_type()), table, f"{key}.{name}.")
        return out
    if dataclasses.is_dataclass(current) and isinstance(value, Mapping):
        return _merge(current, value, f"{key}.")
    if dataclasses.is_dataclass(current):
        raise ConfigError(f"{key}: expected a table of {type(current).__name__} fields, got {value!r}")
    if value == NONE:
        return None
    if isinstance(value, list):
        return tuple(value)
    return value


def _merge(config, changes: Mapping, prefix: str):
    fields = {f.name: f for f in dataclasses.fields(config)}
    kwargs = {}
    for name, value in changes.items():
        key = f"{prefix}{name}"
        if name not in fields:
            raise ConfigError(f"unknown key {key!r}; {type(config).__name__} has {', '.join(fields)}")
        f = fields[name]
        kwargs[name] = _field_value(getattr(config, name), value, key, f.metadata.get("values"))
    try:
        return dataclasses.replace(config, **kwargs)
    except (ValueError, TypeError) as e:
        where = f"{prefix.rstrip('.')}: " if prefix else ""
        raise ConfigError(f"{where}{e}") from None


def config_from_dict(data: Mapping, base=None, prefix: str = ""):
    """The config of nested tables ``{field: value or table}`` (a TOML file's) over ``base`` (None:
    ``SLAMConfig()``; any config dataclass); ``prefix``: the key of ``base`` in the messages (``"run."``).

    Raises:
        ConfigError: an unknown key or a bad value, naming the key.
    """
    return _merge(base if base is not None else SLAMConfig(), data, prefix)


def config_to_dict(config) -> dict:
    """A config as nested dicts of plain values (tuples as lists, None as ``"None"``): the TOML form."""
    out = {}
    for f in dataclasses.fields(config):
        value = getattr(config, f.name)
        if dataclasses.is_dataclass(value):
            out[f.name] = config_to_dict(value)
        elif isinstance(value, dict):
            out[f.name] = {k: config_to_dict(v) if dataclasses.is_dataclass(v) else v for k, v in value.items()}
        elif value is None:
            out[f.name] = NONE
        elif isinstance(value, (tuple, list)):
            out[f.name] = list(value)
        elif isinstance(value, Path):
            out[f.name] = str(value)
        else:
            out[f.name] = value
    return out


def _toml_value(value, key: str) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, numbers.Integral):
        return str(int(value))
    if isinstance(value, numbers.Real):
        v = float(value)
        if math.isnan(v):
            return "nan"
        return repr(v) if math.isfinite(v) else ("inf" if v > 0 else "-inf")
    if isinstance(value, str):
        return '"' + value.replace("\\", "\\\\").replace('"', '\\"').replace("\n", "\\n") + '"'
    if isinstance(value, (list, tuple)):
        return "[" + ", ".join(_toml_value(v, key) for v in value) + "]"
    raise ConfigError(f"{key}: {type(value).__name__} {value!r} has no TOML form")


def toml_text(data: Mapping, header: str = "") -> str:
    """Nested dicts as TOML text: each table's values, then its sub-tables as ``[a.b]`` sections."""
    lines = [f"# {line}" if line else "#" for line in header.splitlines()]

    def table(d: Mapping, path: str) -> None:
        values = [(k, v) for k, v in d.items() if not isinstance(v, Mapping)]
        if path and (values or not any(isinstance(v, Mapping) for v in d.values())):
            lines.extend(["", f"[{path}]"])
        for k, v in values:
            lines.append(f"{k} = {_toml_value(v, f'{path}.{k}' if path else k)}")
        for k, v in d.items():
            if isinstance(v, Mapping):
                table(v, f"{path}.{k}" if path else k)

    table(data, "")
    return "\n".join(lines).lstrip("\n") + "\n"


def read_toml(path) -> dict:
    """A TOML file's tables (tomllib, or tomli before Python 3.11).

    Raises:
        ConfigError: the file cannot be read or is not TOML, naming it (and the line).
    """
    try:
        import tomllib
    except ModuleNotFoundError:  # Python < 3.11
        import tomli as tomllib
    p = Path(path).expanduser()
    try:
        with open(p, "rb") as fh:
            return tomllib.load(fh)
    except OSError as e:
        raise ConfigError(f"{p}: cannot read the config file ({e.strerror or e})") from None
    except tomllib.TOMLDecodeError as e:
        raise ConfigError(f"{p}: not a valid TOML file: {e}") from None


def save_config(config: SLAMConfig, path, extra: Optional[Mapping] = None) -> Path:
    """Write ``config`` (plus ``extra`` tables, e.g. a command's run options) as TOML to ``path``."""
    data = config_to_dict(config) | dict(extra or {})
    p = Path(path)
    p.write_text(toml_text(data, "attnloop SLAM configuration (slam.config): every setting of the run"))
    return p


class UsageError(ValueError):
    """A setting that cannot be used (the message names it and says what was expected)."""


@dataclass(frozen=True)
class CameraRig:
    """How the colour image relates to the depth image.

    Attributes:
        rgb_intrinsics: ``(fx, fy, cx, cy)`` of the colour camera when it is not the depth camera
            (the frames' ``K`` is then the depth camera's); None: registered (colour pixel = depth pixel).
        rgb_from_depth: position (m) of the depth camera in the colour camera's frame (parallel axes).
    """

    rgb_intrinsics: tuple[float, float, float, float] | None
    rgb_from_depth: tuple[float, float, float] = (0.0, 0.0, 0.0)

    @property
    def registered(self) -> bool:
        return self.rgb_intrinsics is None


#: Colour and depth already registered (TUM RGB-D, the synthetic sequences).
REGISTERED = CameraRig(None)


def check_intrinsics(fx: float, fy: float, cx: float, cy: float, what: str) -> None:
    """Refuse pinhole intrinsics that cannot be a camera (non-finite, or a focal length <= 0)."""
    if not all(math.isfinite(float(v)) for v in (fx, fy, cx, cy)):
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


def describe_rig(config: SLAMConfig) -> str:
    """One line for the log and the report: the rig a config tracks with (registered, or the colour intrinsics
    and the baseline)."""
    feats = config.odometry.features
    if feats.rgb_intrinsics is None:
        return "registered colour and depth"
    fx, fy, cx, cy = feats.rgb_intrinsics
    tx, ty, tz = feats.rgb_from_depth_translation
    return (f"unregistered rig: colour camera {fx:g} {fy:g} {cx:g} {cy:g}, depth camera at {tx:g} {ty:g} {tz:g} m "
            "in it")
