"""RGB-D sequences recorded as ROS bags (a ROS1 ``.bag`` file, as TUM RGB-D ships them, or a ROS2 bag folder).

Read with rosbags (``pip install attnloop[rosbag]``). Opening scans the colour and depth topics once, keeping
only each message's stamps; a frame's images are decoded when it is requested. Colour and depth are paired by
their header stamps with TUM's association (:func:`slam.io.associate.associate`); the first message of the
camera-info topic gives ``K``.

Encodings: colour ``rgb8``, ``bgr8``, ``mono8``; depth ``32FC1`` (metres, NaN = no depth) or ``16UC1``
(millimetres unless ``depth_scale`` says otherwise, 0 = no depth). A missing topic, another encoding, or a bag
that cannot be read (truncated, not a bag) is a :class:`~slam.io.sequence.DatasetError` naming the topic, the
encoding or the file.
"""
from __future__ import annotations

import contextlib
import sqlite3
import threading
from pathlib import Path

import numpy as np

from slam.io.associate import TUM_MAX_DIFFERENCE, associate
from slam.io.frame import RGBDFrame, check_intrinsics
from slam.io.images import FrameReadError, depth_to_metres
from slam.io.sequence import DatasetError, check_depth_scale, check_depth_units
from slam.io.trajectory import read_tum_trajectory
from slam.io.tum import TimeAssociatedSequence, tum_camera

__all__ = ["BAG_OPTIONS", "COLOUR_ENCODINGS", "DEPTH_ENCODINGS", "TUM_TOPICS", "RosbagSequence", "is_rosbag"]

#: The topics of TUM RGB-D's bags: colour, depth (32FC1 metres, registered to colour) and the colour camera.
TUM_TOPICS = {"rgb_topic": "/camera/rgb/image_color", "depth_topic": "/camera/depth/image",
              "camera_info_topic": "/camera/rgb/camera_info"}
COLOUR_ENCODINGS = ("rgb8", "bgr8", "mono8")
DEPTH_ENCODINGS = ("32FC1", "16UC1")
_MILLIMETRES = 1000.0  # 16UC1 depth: ROS's convention (REP 118)
#: The reader's arguments that only a bag has, and their flags.
BAG_OPTIONS = {"rgb_topic": "--rgb-topic", "depth_topic": "--depth-topic", "camera_info_topic": "--camera-info-topic",
               "groundtruth": "--ground-truth"}


def is_rosbag(path: Path) -> bool:
    """A ROS1 bag file (``*.bag``) or a ROS2 bag folder (one holding ``metadata.yaml``)."""
    return (path.is_file() and path.suffix == ".bag") or (path.is_dir() and (path / "metadata.yaml").is_file())


def _reader_errors():
    from rosbags.highlevel import AnyReaderError
    from rosbags.rosbag1 import ReaderError as Reader1Error
    from rosbags.rosbag2 import ReaderError as Reader2Error
    from rosbags.serde import SerdeError

    # a truncated chunk or database surfaces as whatever its parser met first
    return (AnyReaderError, Reader1Error, Reader2Error, SerdeError, sqlite3.DatabaseError, EOFError, KeyError,
            ValueError, OSError)


class _Cursor:
    """The messages of one connection in order, read forward; a step back restarts at that message's time."""

    def __init__(self, reader, connection, times: np.ndarray):
        self.reader, self.connection, self.times = reader, connection, times
        self.messages, self.next = None, 0

    def raw(self, k: int) -> bytes:
        if self.messages is None or k < self.next:
            t = int(self.times[k])
            self.messages = self.reader.messages(connections=[self.connection], start=t)
            self.next = int(np.searchsorted(self.times, t, side="left"))
        while True:
            _, _, data = next(self.messages)
            self.next += 1
            if self.next - 1 == k:
                return data


class RosbagSequence(TimeAssociatedSequence):
    """An RGB-D sequence in a ROS bag, read lazily; colour and depth paired by header stamp as TUM's association.

    Args:
        path: a ROS1 ``.bag`` file or a ROS2 bag folder.
        rgb_topic, depth_topic, camera_info_topic: the topics (default: TUM RGB-D's, :data:`TUM_TOPICS`).
        camera: a TUM camera (``fr1``, ``fr2``, ``fr3``, ``ros``) whose intrinsics replace the camera info's
            (TUM's bags carry the ROS defaults there).
        K: ``(3, 3)`` intrinsics replacing the camera info's; the camera-info topic is then not read.
        depth_scale: ``16UC1`` depth units per metre (default millimetres, 1000); refused for ``32FC1`` (metres,
            NaN = no depth).
        check_units: check the first frames' median ``16UC1`` depth at ``depth_scale``
            (:func:`~slam.io.sequence.check_depth_units`).
        groundtruth: a TUM trajectory file associated with the frames as a TUM folder's ``groundtruth.txt``.
        max_difference: association tolerance in seconds (TUM: 0.02).

    Raises:
        DatasetError: rosbags not installed, an unreadable bag, a missing topic, an unknown encoding, colour and
            depth of different sizes, no colour/depth pair within ``max_difference``.
    """

    def __init__(self, path, rgb_topic: str | None = None, depth_topic: str | None = None,
                 camera_info_topic: str | None = None, camera: str | None = None, K=None,
                 depth_scale: float | None = None, check_units: bool = True, groundtruth=None,
                 max_difference: float = TUM_MAX_DIFFERENCE):
        self.root = Path(path).expanduser()
        self.name = self.root.stem if self.root.is_file() else self.root.name
        try:
            from rosbags.highlevel import AnyReader
        except ImportError:
            raise DatasetError(self.root, "reading a ROS bag needs rosbags: pip install attnloop[rosbag]") from None
        topics = {"rgb_topic": rgb_topic, "depth_topic": depth_topic, "camera_info_topic": camera_info_topic}
        self.topics = {k: v if v is not None else TUM_TOPICS[k] for k, v in topics.items()}
        self._errors = _reader_errors()
        self._lock = threading.Lock()
        self._reader = None
        try:
            self._reader = AnyReader([self.root])
            self._reader.open()
        except self._errors as e:
            raise DatasetError(self.root, f"not a readable ROS bag: truncated or corrupt ({e})") from None
        try:
            self._open(camera, K, depth_scale, check_units, groundtruth, max_difference)
        except BaseException:
            self.close()
            raise

    def _connection(self, key: str):
        topic = self.topics[key]
        found = [c for c in self._reader.connections if c.topic == topic]
        if not found:
            have = ", ".join(sorted({c.topic for c in self._reader.connections})) or "none"
            raise DatasetError(self.root, f"no topic {topic} (the bag has: {have}); name the topic with "
                                          f"{BAG_OPTIONS[key]}")
        return found[0]

    def _messages(self, conn):
        """The ``(time ns, message)`` of a connection in order; a reader error is a DatasetError naming the topic."""
        try:
            for _, t, raw in self._reader.messages(connections=[conn]):
                yield t, self._reader.deserialize(raw, conn.msgtype)
        except self._errors as e:
            raise DatasetError(self.root, f"cannot read {conn.topic}: the bag is truncated or corrupt ({e})") from None

    def _scan(self, key: str, encodings: tuple[str, ...]):
        """Record time (ns) and header stamp (s) of every message of a topic; checks the encodings and sizes."""
        conn = self._connection(key)
        times, stamps, first = [], [], None
        for t, msg in self._messages(conn):
            if msg.encoding not in encodings:
                raise DatasetError(self.root, f"{conn.topic}: unsupported image encoding {msg.encoding!r} "
                                              f"(expected {', '.join(encodings)})")
            first = first or (msg.encoding, msg.height, msg.width)
            if (msg.encoding, msg.height, msg.width) != first:
                raise DatasetError(self.root, f"{conn.topic}: a {msg.encoding} {msg.width}x{msg.height} image "
                                              f"among {first[0]} {first[2]}x{first[1]} ones")
            times.append(t)
            stamps.append(msg.header.stamp.sec + msg.header.stamp.nanosec * 1e-9)
        if not times:
            raise DatasetError(self.root, f"the topic {conn.topic} has no messages")
        return conn, np.asarray(times, np.int64), np.asarray(stamps, np.float64), first

    def _open(self, camera, K, depth_scale, check_units, groundtruth, max_difference) -> None:
        rgb, rgb_times, rgb_stamps, (self.rgb_encoding, h, w) = self._scan("rgb_topic", COLOUR_ENCODINGS)
        depth, depth_times, depth_stamps, (self.depth_encoding, dh, dw) = self._scan("depth_topic", DEPTH_ENCODINGS)
        if (dh, dw) != (h, w):
            raise DatasetError(self.root, f"depth images ({self.topics['depth_topic']}) are {dw}x{dh} but colour "
                                          f"images ({self.topics['rgb_topic']}) {w}x{h}: expected registered images")
        if depth_scale is not None and self.depth_encoding != "16UC1":
            raise DatasetError(self.root, f"depth_scale (--depth-scale) applies to 16UC1 depth; "
                                          f"{self.topics['depth_topic']} is {self.depth_encoding} metres")
        self.depth_scale = _MILLIMETRES if depth_scale is None else check_depth_scale(depth_scale, self.root)
        i, j = associate(rgb_stamps, depth_stamps, max_difference)
        if i.numel() == 0:
            raise DatasetError(self.root, f"no colour and depth header stamps are within {max_difference} s")
        self._rgb_index, self._depth_index = i.numpy(), j.numpy()
        self._timestamps = rgb_stamps[self._rgb_index]
        self.depth_timestamps = depth_stamps[self._depth_index]
        self._cursors = {"rgb": _Cursor(self._reader, rgb, rgb_times), "depth": _Cursor(self._reader, depth,
                                                                                        depth_times)}
        self.camera_name = camera
        if K is not None:
            self.K = check_intrinsics(K, "K")
        elif camera is not None:
            try:
                self.K = tum_camera(camera).K
            except ValueError as e:
                raise DatasetError(self.root, str(e)) from None
        else:
            self.K = self._camera_info()
        self.max_difference = float(max_difference)
        self.groundtruth_file = None if groundtruth is None else Path(groundtruth).expanduser()
        self._gt_trajectory = None if groundtruth is None else read_tum_trajectory(self.groundtruth_file)
        self._gt = self._associate_groundtruth(self._timestamps)
        if check_units and self.depth_encoding == "16UC1":
            check_depth_units(self.root, range(min(len(self), 10)), self.depth_scale, read=self._raw_depth)

    def _camera_info(self) -> np.ndarray:
        conn = self._connection("camera_info_topic")
        for _, msg in self._messages(conn):
            k = getattr(msg, "k", None)
            try:
                return check_intrinsics(np.asarray(msg.K if k is None else k, np.float64).reshape(3, 3),
                                        f"{conn.topic}: K")
            except ValueError as e:
                raise DatasetError(self.root, f"{e}; give the intrinsics with --intrinsics") from None
        raise DatasetError(self.root, f"the topic {conn.topic} has no messages; give the intrinsics with --intrinsics")

    def _message(self, which: str, k: int):
        cursor = self._cursors[which]
        try:
            with self._lock:
                raw = cursor.raw(int(k))
            return self._reader.deserialize(raw, cursor.connection.msgtype)
        except (StopIteration, *self._errors) as e:
            raise FrameReadError(str(self.root), f"{cursor.connection.topic} message {k}: cannot read it ({e})"
                                 ) from None

    def _raw_depth(self, i: int) -> np.ndarray:
        msg = self._message("depth", self._depth_index[i])
        return _pixels(msg, np.float32 if msg.encoding == "32FC1" else np.uint16, 1, self.topics["depth_topic"])

    def _load(self, i: int) -> RGBDFrame:
        msg = self._message("rgb", self._rgb_index[i])
        if msg.encoding == "mono8":
            rgb = np.repeat(_pixels(msg, np.uint8, 1, self.topics["rgb_topic"])[..., None], 3, axis=2)
        else:
            rgb = _pixels(msg, np.uint8, 3, self.topics["rgb_topic"])
            rgb = np.ascontiguousarray(rgb[..., ::-1]) if msg.encoding == "bgr8" else rgb
        raw = self._raw_depth(i)
        depth = raw.astype(np.float32) if raw.dtype == np.float32 else depth_to_metres(raw, self.depth_scale)
        return self._frame(i, rgb, depth, self._gt[i])

    def close(self) -> None:
        """Close the bag (also when the sequence is garbage-collected)."""
        if getattr(self, "_reader", None) is not None and self._reader.stack is not None:
            self._reader.close()

    def __del__(self):
        with contextlib.suppress(Exception):  # at interpreter exit rosbags' modules may be gone already
            self.close()


def _pixels(msg, dtype, channels: int, topic: str) -> np.ndarray:
    """``(H, W)`` or ``(H, W, C)`` copy of an image message's pixels (row padding and byte order handled)."""
    dt = np.dtype(dtype).newbyteorder(">" if msg.is_bigendian else "<")
    row = msg.width * channels * dt.itemsize
    data = np.frombuffer(np.asarray(msg.data, np.uint8).tobytes(), np.uint8)
    if data.size < msg.step * (msg.height - 1) + row:
        raise FrameReadError(topic, f"a {msg.encoding} image of {data.size} bytes, too few for {msg.width}x"
                                    f"{msg.height} (row step {msg.step})")
    rows = np.lib.stride_tricks.as_strided(data, (msg.height, row), (msg.step, 1))
    out = np.ascontiguousarray(rows).view(dt).astype(dtype)
    return out.reshape(msg.height, msg.width, channels) if channels > 1 else out.reshape(msg.height, msg.width)
