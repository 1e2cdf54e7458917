"""Synthetic RGB-D sequences with exact ground truth, deterministic by ``seed`` and independent of batching:
rendered in memory (:class:`SyntheticSequence`) or written by :func:`generate_sequence` in the TUM layout::

    out/
      rgb/<timestamp>.png       8-bit RGB
      depth/<timestamp>.png     16-bit, 5000 units per metre, 0 = no measurement
      rgb.txt, depth.txt        "timestamp filename" lists with TUM's comment header
      groundtruth.txt           "timestamp tx ty tz qx qy qz qw" (camera-to-world), one line per frame
      calibration.txt           "fx fy cx cy" of the pinhole camera (no distortion)
      synthetic.json            the generator's settings (trajectory, frames, seed, noise)

Example:
    >>> seq = SyntheticSequence("loop", num_frames=4, width=32, height=24, scene=_tiny_scene())
    >>> frame = seq[0]
    >>> frame.rgb.shape, frame.rgb.dtype, frame.depth.shape, frame.depth.dtype, frame.pose_gt.shape
    ((24, 32, 3), dtype('uint8'), (24, 32), dtype('float32'), (7,))
"""
from __future__ import annotations

import json
import logging
import os
from collections.abc import Iterator, Sequence
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import cv2
import numpy as np
import torch

from slam.io.frame import RGBDFrame
from slam.io.images import depth_to_metres
from slam.io.sequence import RGBDSequence
from slam.io.trajectory import Trajectory, write_tum_trajectory
from slam.synthetic.render import (
    DepthNoiseConfig,
    ImageNoiseConfig,
    apply_depth_noise,
    apply_image_noise,
    apply_motion_blur,
    render_frames,
)
from slam.synthetic.scene import RoomConfig, Scene, build_room_scene, default_room_scene
from slam.synthetic.trajectories import make_trajectory
from slam.threads import limit_threads

__all__ = [
    "DEPTH_FACTOR",
    "SyntheticSequence",
    "generate_sequence",
    "synthetic_intrinsics",
]

logger = logging.getLogger(__name__)

DEPTH_FACTOR = 5000.0  # raw depth units per metre, as in TUM RGB-D
_MAX_RAW = 65535  # largest 16-bit value; deeper points cannot be stored and read as invalid


def synthetic_intrinsics(width: int = 640, height: int = 480) -> np.ndarray:
    """Pinhole ``K (3, 3)`` float64: the ROS default (525, 525, 319.5, 239.5) at 640 x 480, scaled with the
    image size otherwise (same field of view, principal point at the image centre)."""
    if width <= 0 or height <= 0:
        raise ValueError(f"width and height must be positive, got {width} x {height}")
    return np.array([[525.0 * width / 640.0, 0.0, (width - 1) / 2.0],
                     [0.0, 525.0 * height / 480.0, (height - 1) / 2.0],
                     [0.0, 0.0, 1.0]])


def _tiny_scene() -> Scene:
    """A low-texture-resolution room for doctests and quick tests (same geometry)."""
    return build_room_scene(RoomConfig(texel_density=24.0, object_texel_density=24.0))


class SyntheticSequence(RGBDSequence):
    """A rendered RGB-D sequence held as a trajectory: ``seq[i]`` / ``for frame in seq`` render
    :class:`~slam.io.frame.RGBDFrame` s (rgb ``(H, W, 3)`` uint8, depth ``(H, W)`` float32 metres quantised to
    1/5000 m, ``K (3, 3)``, ``pose_gt (7,)``) identical to what :func:`generate_sequence` writes.

    Args:
        trajectory: ``"loop"``, ``"figure_eight"``, ``"out_and_back"`` or a
            :class:`~slam.io.trajectory.Trajectory` (camera-to-world poses in the scene's frame).
        num_frames: frames of a named trajectory at 30 Hz (ignored for a given Trajectory).
        width: image columns W.
        height: image rows H.
        seed: seeds the depth/image noise of every frame and the trajectory's hand shake (equal seeds give
            byte-identical frames).
        depth_noise: Kinect-like depth noise, quantisation and holes (``depth_noise_config``).
        image_noise: exposure and pixel noise (``image_noise_config``).
        scene: the scene (default: the shared :func:`default_room_scene`).
        depth_noise_config: the depth noise model (default :class:`DepthNoiseConfig`).
        image_noise_config: the image noise model (default :class:`ImageNoiseConfig`).
        batch_size: frames rendered together when iterating.
        trajectory_name: the name of a given Trajectory (default ``"custom"``).
    """

    depth_scale = DEPTH_FACTOR

    def __init__(self, trajectory: str | Trajectory = "loop", num_frames: int = 300, width: int = 640,
                 height: int = 480, seed: int = 0, depth_noise: bool = True, image_noise: bool = True,
                 scene: Scene | None = None, depth_noise_config: DepthNoiseConfig | None = None,
                 image_noise_config: ImageNoiseConfig | None = None, batch_size: int = 4,
                 trajectory_name: str | None = None):
        if isinstance(trajectory, Trajectory):  # its poses are (N, 7): Trajectory checks them
            self.trajectory = trajectory
            self.trajectory_name = trajectory_name or "custom"
        else:
            self.trajectory = make_trajectory(trajectory, num_frames, seed=seed)
            self.trajectory_name = str(trajectory)
        self.width, self.height, self.seed = int(width), int(height), int(seed)
        self.K = synthetic_intrinsics(self.width, self.height)
        self.scene = scene if scene is not None else default_room_scene()
        self.depth_noise = (depth_noise_config or DepthNoiseConfig()) if depth_noise else None
        self.image_noise = (image_noise_config or ImageNoiseConfig()) if image_noise else None
        self.batch_size = max(1, int(batch_size))
        self.name = f"synthetic_{self.trajectory_name}_seed{self.seed}"
        self.root = Path(self.name)
        self._poses = self.trajectory.poses.to(torch.float64).cpu().numpy()
        self._stamps = self.trajectory.timestamps.to(torch.float64).cpu().numpy()
        self._interval = float(np.median(np.diff(self._stamps))) if len(self._stamps) > 1 else 1.0 / 30.0

    def __len__(self) -> int:
        return int(self._stamps.shape[0])

    @property
    def timestamps(self) -> np.ndarray:
        return self._stamps.copy()

    def _groundtruth_array(self) -> np.ndarray:
        return self._poses.copy()

    def render_raw(self, indices: Sequence[int]) -> tuple[np.ndarray, np.ndarray]:
        """Render frames ``indices`` with noise: rgb ``(n, H, W, 3)`` uint8 and raw depth ``(n, H, W)``
        uint16 (5000 per metre, 0 = invalid), exactly the PNGs :func:`generate_sequence` writes."""
        idx = [int(i) for i in indices]
        K = torch.from_numpy(self.K)
        out = render_frames(self.scene, K, torch.from_numpy(self._poses[idx]), self.height, self.width)
        seeds = [self.seed * 100_003 + i for i in idx]  # per-frame noise: independent of batching
        depth, rgb = out.depth, out.rgb
        if self.image_noise is not None and self.image_noise.exposure_time > 0:
            # blur from the exact depth (before the depth noise) and the neighbouring frames' poses
            n = len(self)
            before = torch.from_numpy(self._poses[[max(i - 1, 0) for i in idx]])  # a frame's own at the ends
            after = torch.from_numpy(self._poses[[min(i + 1, n - 1) for i in idx]])
            rgb = apply_motion_blur(rgb, depth, K, torch.from_numpy(self._poses[idx]), before, after,
                                    min(2.0, self.image_noise.exposure_time / self._interval),
                                    self.image_noise.blur_samples)
        if self.depth_noise is not None:
            depth = apply_depth_noise(depth, out.cos_incidence, self.depth_noise, seeds)
        if self.image_noise is not None:
            rgb = apply_image_noise(rgb, self.image_noise, seeds)
        raw = torch.round(depth.double() * DEPTH_FACTOR)
        raw = torch.where(raw > _MAX_RAW, torch.zeros_like(raw), raw)  # not storable -> invalid
        return rgb.cpu().numpy(), raw.cpu().numpy().astype(np.uint16)

    def _frame(self, i: int, rgb: np.ndarray, raw: np.ndarray) -> RGBDFrame:
        return RGBDFrame(index=i, timestamp=float(self._stamps[i]), rgb=rgb,
                         depth=depth_to_metres(raw, DEPTH_FACTOR), K=self.K.copy(),
                         pose_gt=self._poses[i].copy())

    def _load(self, i: int) -> RGBDFrame:
        rgb, raw = self.render_raw([i])
        return self._frame(i, rgb[0], raw[0])

    def __iter__(self) -> Iterator[RGBDFrame]:
        n = len(self)
        for start in range(0, n, self.batch_size):
            idx = list(range(start, min(n, start + self.batch_size)))
            rgb, raw = self.render_raw(idx)
            for k, i in enumerate(idx):
                yield self._frame(i, rgb[k], raw[k])

    def settings(self) -> dict:
        """The generator's settings (written to ``synthetic.json``)."""
        return {
            "generator": "slam.synthetic", "trajectory": self.trajectory_name, "num_frames": len(self),
            "width": self.width, "height": self.height, "seed": self.seed,
            "K": self.K.tolist(), "depth_factor": DEPTH_FACTOR,
            "depth_noise": None if self.depth_noise is None else vars(self.depth_noise),
            "image_noise": None if self.image_noise is None else vars(self.image_noise),
            "room_size": list(self.scene.room_size),
        }


def _frame_names(stamps: np.ndarray) -> list[str]:
    """The ``<timestamp>.png`` file names of the frames (1 microsecond resolution, as TUM writes them).

    Raises:
        ValueError: a non-finite timestamp, or two frames whose names would be the same.
    """
    bad = [i for i, t in enumerate(stamps) if not np.isfinite(t)]
    if bad:
        shown = ", ".join(f"frame {i} has {float(stamps[i])!r}" for i in bad[:3])
        more = f" (and {len(bad) - 3} more)" if len(bad) > 3 else ""
        raise ValueError(f"non-finite trajectory timestamps cannot name frame files: {shown}{more}")
    names = [f"{t:.6f}.png" for t in stamps]
    first: dict[float, int] = {}
    clashes = []
    for i, name in enumerate(names):
        key = float(name[:-4])  # "-0.000000" and "0.000000" are one stamp in rgb.txt
        if key in first:
            clashes.append((first[key], i))
        else:
            first[key] = i
    if clashes:
        shown = "; ".join(f"frames {a} and {b} ({float(stamps[a])!r} s and {float(stamps[b])!r} s) both give "
                          f"{names[b][:-4]}" for a, b in clashes[:3])
        more = f" (and {len(clashes) - 3} more pairs)" if len(clashes) > 3 else ""
        raise ValueError(f"trajectory timestamps collide at the 1 microsecond resolution of the frame file names "
                         f"(one frame's images would overwrite the other's): {shown}{more}")
    return names


def generate_sequence(out_dir: str | os.PathLike, trajectory: str | Trajectory = "loop",
                      num_frames: int = 300, width: int = 640, height: int = 480, seed: int = 0,
                      depth_noise: bool = True, image_noise: bool = True, scene: Scene | None = None,
                      batch_size: int = 2, workers: int = 2, progress: bool = False, **kwargs) -> Path:
    """Render a synthetic sequence and write it in the TUM RGB-D layout (see the module docstring).

    Args:
        out_dir: the sequence folder (created; files of the same names are overwritten).
        trajectory: ``"loop"`` (default), ``"figure_eight"``, ``"out_and_back"``, or a
            :class:`~slam.io.trajectory.Trajectory`.
        num_frames: frames (30 Hz; 300 = 10 s).
        width: image columns.
        height: image rows.
        seed: noise and hand-shake seed; equal seeds give byte-identical files.
        depth_noise: Kinect-like depth noise, quantisation and holes.
        image_noise: exposure and pixel noise.
        scene: the scene (default: the standard room).
        batch_size: frames per rendering task.
        workers: rendering threads, each rendering whole frames with one torch thread (restored afterwards);
            1 renders in the caller with torch's settings untouched.
        progress: log a line every ~10 % of the frames.
        **kwargs: passed to :class:`SyntheticSequence` (noise and trajectory configs).

    Returns:
        The folder's path.

    Raises:
        ValueError: a trajectory timestamp that is not finite, or two that give the same file name (equal
            at 1 microsecond); nothing is written then.
    """
    seq = SyntheticSequence(trajectory, num_frames=num_frames, width=width, height=height, seed=seed,
                            depth_noise=depth_noise, image_noise=image_noise, scene=scene, batch_size=batch_size,
                            **kwargs)
    names = _frame_names(seq.timestamps)  # checked before anything is rendered or written
    out = Path(out_dir).expanduser()
    (out / "rgb").mkdir(parents=True, exist_ok=True)
    (out / "depth").mkdir(parents=True, exist_ok=True)
    n = len(seq)
    batches = [list(range(s, min(n, s + seq.batch_size))) for s in range(0, n, seq.batch_size)]
    workers = max(1, int(workers))

    def task(idx: list[int]) -> None:
        rgb, raw = seq.render_raw(idx)
        for k, i in enumerate(idx):
            ok = cv2.imwrite(str(out / "rgb" / names[i]), np.ascontiguousarray(rgb[k][:, :, ::-1]))
            ok = ok and cv2.imwrite(str(out / "depth" / names[i]), raw[k])
            if not ok:
                raise OSError(f"could not write frame {i} into {out}")

    step = max(1, len(batches) // 10)
    with limit_threads(1 if workers > 1 else None):  # the workers share the cores: one thread each
        if workers == 1:
            for b, idx in enumerate(batches):
                task(idx)
                if progress and b % step == 0:
                    logger.info("synthetic sequence: %d / %d frames", idx[-1] + 1, n)
        else:
            with ThreadPoolExecutor(max_workers=workers, thread_name_prefix="synthetic") as pool:
                for b, fut in enumerate([pool.submit(task, idx) for idx in batches]):
                    fut.result()  # re-raises a worker's error
                    if progress and b % step == 0:
                        logger.info("synthetic sequence: %d / %d frames", batches[b][-1] + 1, n)
    stamps = seq.timestamps
    for sub, kind in (("rgb", "color images"), ("depth", "depth maps")):
        with open(out / f"{sub}.txt", "w", encoding="utf-8") as f:
            f.write("\n".join([f"# {kind}", f"# file: '{seq.name}'", "# timestamp filename"]
                              + [f"{t:.6f} {sub}/{nm}" for t, nm in zip(stamps, names)]) + "\n")
    with open(out / "groundtruth.txt", "w", encoding="utf-8") as f:
        f.write("# ground truth trajectory\n")
        f.write(f"# file: '{seq.name}' (exact: the rendered camera-to-world poses)\n")
        write_tum_trajectory(f, Trajectory(torch.from_numpy(stamps), torch.from_numpy(seq._poses)), header=True)
    K = seq.K
    with open(out / "calibration.txt", "w", encoding="utf-8") as f:
        f.write("# pinhole intrinsics of the rendered images: fx fy cx cy (pixels), no distortion\n")
        f.write(f"{K[0, 0]:.6f} {K[1, 1]:.6f} {K[0, 2]:.6f} {K[1, 2]:.6f}\n")
    with open(out / "synthetic.json", "w", encoding="utf-8") as f:
        json.dump(seq.settings(), f, indent=2)
    return out
