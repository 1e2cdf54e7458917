"""Watch a run in the rerun viewer (https://rerun.io), live or recorded to a ``.rrd`` file: ``--viewer``,
``--connect ADDR``, ``--rrd FILE`` (``pip install 'attnloop[viewer]'``; the entities logged: docs/pipeline.md,
"Watching a run"). When the run ends, the final poses, path, map and loops are logged again.
"""
from __future__ import annotations

import logging
import os
import sys
import threading
import time
from collections import deque
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import cv2
import numpy as np
import torch

from slam.config import UsageError

logger = logging.getLogger(__name__)

__all__ = ["VIEWER_EXTRA", "VIEWER_FLAGS", "RunViewer", "check_viewer", "open_viewer", "viewer_flags"]

#: What installs rerun.
VIEWER_EXTRA = "pip install 'attnloop[viewer]'"
_FIELDS = {"--viewer": "viewer", "--connect": "connect", "--rrd": "rrd"}
#: The flags of :class:`slam.options.RunOptions` this module serves (a command that runs no viewer excludes them).
VIEWER_FLAGS = tuple(_FIELDS)


def viewer_flags(run) -> list[str]:
    """The viewer flags ``run`` sets (``--viewer``, ``--connect``, ``--rrd``); ``run`` is the command's
    :class:`slam.options.RunOptions`, or anything with its ``viewer``, ``connect`` and ``rrd`` fields."""
    return [flag for flag, name in _FIELDS.items() if getattr(run, name)]


def _rerun(flags: list[str]):
    try:
        import rerun
    except ImportError:
        raise UsageError(f"{', '.join(flags)}: rerun is not installed; {VIEWER_EXTRA}") from None
    return rerun


def check_viewer(run) -> None:
    """Refuse, before any work, a viewer without rerun installed, a viewer to spawn without a display (Linux), or
    an ``rrd`` file that cannot be written.

    Raises:
        UsageError: naming the flags and the extra to install, or the file.
    """
    flags = viewer_flags(run)
    if not flags:
        return
    _rerun(flags)
    if run.viewer and sys.platform.startswith("linux") and not (os.environ.get("DISPLAY")
                                                                 or os.environ.get("WAYLAND_DISPLAY")):
        raise UsageError("--viewer: no display to show the viewer on (DISPLAY and WAYLAND_DISPLAY unset); record the "
                         "run with --rrd FILE and open it with `rerun FILE` where there is one, or stream it with "
                         "--connect HOST:PORT to a viewer running there")
    if run.rrd:
        path = Path(run.rrd).expanduser()
        if path.is_dir() or not path.parent.is_dir() or not os.access(path.parent, os.W_OK):
            raise UsageError(f"--rrd {run.rrd}: not a file in a writable folder")


def open_viewer(run, name: str = "attnloop-slam") -> RunViewer | None:
    """The viewer ``run`` asks for: spawned (``viewer``), a running one at ``connect``, and/or the file ``rrd``;
    None when it asks for none."""
    flags = viewer_flags(run)
    if not flags:
        return None
    rr = _rerun(flags)
    rec = rr.RecordingStream("attnloop-slam")
    rec.send_recording_name(name)
    if run.viewer:
        rec.spawn(connect=False)
    sinks = [rr.FileSink(str(Path(run.rrd).expanduser()))] if run.rrd else []
    if run.viewer or run.connect:
        addr = run.connect
        sinks.append(rr.GrpcSink(addr if addr is None or "://" in addr else f"rerun+http://{addr}/proxy"))
    rec.set_sinks(*sinks)
    return RunViewer(rec)


def _transform(rr, pose: list):
    return rr.Transform3D(translation=pose[:3], quaternion=rr.Quaternion(xyzw=pose[3:]))


class RunViewer:
    """Logs a run to a rerun recording, as :func:`slam.pipeline.run_slam`'s ``observer``; :meth:`close` when done.

    The logging runs in a thread of its own (rerun calls from the tracking thread waited on the interpreter's
    lock); at most 8 frames wait for it, the tracking thread waits beyond that.

    Args:
        recording: a ``rerun.RecordingStream`` with its sinks set.
        max_image_width: a wider colour image is logged resized to this width in pixels (its pinhole likewise).
        map_stride: every ``map_stride``-th pixel of a keyframe's depth, in rows and columns, goes to the map.
    """

    def __init__(self, recording, max_image_width: int = 320, map_stride: int = 8):
        import rerun as rr

        self.rr, self.rec = rr, recording
        self.max_image_width, self.map_stride = int(max_image_width), int(map_stride)
        self._recent: deque = deque(maxlen=4)  # the frames a new keyframe can come from (this one or a promoted one)
        self._ticks: deque = deque(maxlen=30)
        self._indices: list[int] = []  # the frame index of every observed frame
        self._kf_frames: list[int] = []  # per keyframe id: its frame index (names its map entity)
        self._placed = torch.zeros(0, 7, dtype=torch.float64)  # per keyframe: the pose its map points were placed at
        self._loops: list[tuple[int, int]] = []
        self._stats: list[tuple] = []  # (frame, frames/s or None, inliers) not yet sent
        self._pinhole = False
        self._worker = ThreadPoolExecutor(max_workers=1, thread_name_prefix="slam-viewer")
        self._slots = threading.BoundedSemaphore(8)
        self._error: BaseException | None = None
        self.rec.log("world", rr.ViewCoordinates.RDF, static=True)  # the first camera's axes: x right, y down

    def frame(self, frame, state, slam) -> None:
        """Log one frame: ``frame`` (:class:`slam.io.RGBDFrame`, None when unreadable), its
        :class:`slam.system.FrameState` and the :class:`slam.system.RGBDSLAM` that tracked it."""
        changed = state.new_keyframes or state.new_loops or state.correction is not None
        keyframes = [slam.keyframes[kf].frame_index for kf in state.new_keyframes]
        self._submit(self._log_frame, frame, state.index, state.pose.tolist(), float(state.num_inliers),
                     time.perf_counter(), keyframes, [(lp.kf_a, lp.kf_b) for lp in state.new_loops],
                     slam.keyframe_poses() if changed else None)

    def finish(self, result) -> None:
        """Log the final optimisation (:class:`slam.system.SLAMResult`): every frame's pose at its frame, the path,
        the map and the loops at the last frame."""
        self._submit(self._log_finish, result.trajectory.poses.clone(), result.num_frames,
                     [(lp.kf_a, lp.kf_b) for lp in result.loops], result.keyframe_trajectory.poses.clone())

    def close(self) -> None:
        """Log what was handed over, send it and close the sinks.

        Raises:
            the logging thread's error, if it had one.
        """
        self._worker.shutdown(wait=True)
        if self._error is None:
            self._send_stats()
        try:
            self.rec.flush()
        except RuntimeError as e:  # a viewer that went away or never came: the run's own outputs are still written
            logger.warning("rerun: %s", e)
        self.rec.disconnect()
        if self._error is not None:
            raise self._error

    def _submit(self, fn, *args) -> None:
        if self._error is not None:
            raise self._error
        self._slots.acquire()
        self._worker.submit(fn, *args).add_done_callback(self._done)

    def _done(self, job) -> None:
        self._slots.release()
        if job.exception() is not None and self._error is None:
            self._error = job.exception()

    def _log_frame(self, frame, index, pose, inliers, tick, keyframes, loops, keyframe_poses) -> None:
        rr, rec = self.rr, self.rec
        rec.set_time("frame", sequence=index)
        self._indices.append(index)
        camera = [_transform(rr, pose)]
        if frame is not None:
            self._recent.append(frame)
            camera.append(self._image(frame))
        rec.log("world/camera", *camera)
        self._ticks.append(tick)
        fps = (len(self._ticks) - 1) / (self._ticks[-1] - self._ticks[0]) if len(self._ticks) > 1 else None
        self._stats.append((index, fps, inliers))
        if len(self._stats) >= 10:
            self._send_stats()
        self._loops += loops
        for frame_index in keyframes:
            self._add_keyframe(frame_index)
        if keyframe_poses is not None:
            self._draw(keyframe_poses)

    def _log_finish(self, poses, num_frames, loops, keyframe_poses) -> None:
        self._send_stats()
        rr, n = self.rr, min(len(self._indices), num_frames)
        if n == 0:
            return
        poses = poses[:n].numpy()
        self.rec.send_columns("world/camera", indexes=[rr.TimeColumn("frame", sequence=self._indices[:n])],
                              columns=rr.Transform3D.columns(translation=poses[:, :3], quaternion=poses[:, 3:]))
        self.rec.set_time("frame", sequence=self._indices[n - 1])
        self._loops = loops
        self._draw(keyframe_poses)

    def _send_stats(self) -> None:
        """The frames/s and inliers of the frames since the last call: one call per series (a call per frame
        costs as much as the colour image)."""
        rr = self.rr
        for name, col in (("stats/fps", 1), ("stats/inliers", 2)):
            rows = [(row[0], row[col]) for row in self._stats if row[col] is not None]
            if rows:
                self.rec.send_columns(name, indexes=[rr.TimeColumn("frame", sequence=[i for i, _ in rows])],
                                      columns=rr.Scalars.columns(scalars=[v for _, v in rows]))
        self._stats.clear()

    def _image(self, frame):
        """The frame's colour image to log (its pinhole logged with the first)."""
        rr = self.rr
        h, w = frame.rgb.shape[:2]
        s = min(1.0, self.max_image_width / w)
        size = (max(1, round(w * s)), max(1, round(h * s)))
        if not self._pinhole:  # the intrinsics of the image as logged: pixel centres scaled
            K = frame.K
            self.rec.log("world/camera", rr.Pinhole(focal_length=(K[0, 0] * s, K[1, 1] * s), resolution=size,
                                                    principal_point=((K[0, 2] + 0.5) * s - 0.5,
                                                                     (K[1, 2] + 0.5) * s - 0.5)), static=True)
            self._pinhole = True
        return rr.Image(frame.rgb if s == 1 else cv2.resize(frame.rgb, size, interpolation=cv2.INTER_AREA))

    def _add_keyframe(self, frame_index: int) -> None:
        """Back-project the keyframe's subsampled depth into its camera (its map entity)."""
        self._kf_frames.append(int(frame_index))
        frame = next((f for f in self._recent if int(f.index) == int(frame_index)), None)
        if frame is None:  # not among the recent frames: no points for this keyframe
            return
        s, K = self.map_stride, frame.K
        z = frame.depth[::s, ::s]
        v, u = np.mgrid[0:frame.depth.shape[0]:s, 0:frame.depth.shape[1]:s]
        ok = np.isfinite(z) & (z > 0)
        z, u, v = z[ok], u[ok], v[ok]
        points = np.stack([(u - K[0, 2]) * z / K[0, 0], (v - K[1, 2]) * z / K[1, 1], z], axis=-1)
        colours = frame.rgb[::s, ::s][ok] if frame.rgb.shape[:2] == frame.depth.shape else None
        self.rec.log(f"world/map/{frame_index}", self.rr.Points3D(points, colors=colours))

    def _draw(self, poses: torch.Tensor) -> None:
        """The path, the loops and the keyframes' map points placed by ``poses`` ``(M, 7)`` (moved ones only)."""
        rr, m = self.rr, min(poses.shape[0], len(self._kf_frames))
        poses = poses[:m]
        xyz = poses[:, :3].numpy()
        self.rec.log("world/trajectory", rr.LineStrips3D([xyz]))
        self.rec.log("world/loops", rr.LineStrips3D([[xyz[a], xyz[b]] for a, b in self._loops if b < m]))
        old = self._placed.shape[0]
        moved = torch.cat([torch.nonzero((poses[:old] != self._placed[:m]).any(dim=-1))[:, 0],
                           torch.arange(old, m)]).tolist()
        for k in moved:
            self.rec.log(f"world/map/{self._kf_frames[k]}", _transform(rr, poses[k].tolist()))
        self._placed = poses.clone()
