"""A coloured point-cloud map of the keyframes' depth, placed with the optimised poses, and its PLY file.

Each keyframe keeps, in its own depth-camera frame, the voxel-downsampled coloured points of its depth that the
keyframes just before it do not hold (int16 coordinates, uint8 colours: 9 bytes a point); at the end they are
placed with the optimised keyframe poses and merged on one voxel grid, written as a binary PLY
(docs/pipeline.md, "The map").

Example:
    >>> import numpy as np, torch
    >>> K = np.array([[100., 0, 31.5], [0, 100., 23.5], [0, 0, 1]])
    >>> m = PointCloudMap(MapConfig(voxel_size=0.05))
    >>> m.add(0, np.full((48, 64, 3), 200, np.uint8), np.full((48, 64), 2.0, np.float32), K)  # a wall 2 m ahead
    520
    >>> pts, rgb = m.points(torch.tensor([[0., 0., 1., 0., 0., 0., 1.]]))
    >>> pts.shape[1], rgb.dtype, float(pts[:, 2].min()) == float(pts[:, 2].max())
    (3, dtype('uint8'), True)
"""
from __future__ import annotations

import math
import os
from dataclasses import dataclass
from pathlib import Path
from typing import BinaryIO, Union

import numpy as np
import torch

from slam.input_checks import source_name
from slam.lie import quat_to_rotmat, se3_to_matrix
from slam.odometry.depth_registration import register_depth_to_color, rig_pose
from slam.odometry.config import check_int, check_number

__all__ = ["MapConfig", "PLYFormatError", "PointCloudMap", "keyframe_cloud", "read_ply", "voxel_downsample",
           "write_ply"]

PathOrFile = Union[str, os.PathLike, BinaryIO]


@dataclass(frozen=True)
class MapConfig:
    """The keyframe point-cloud map written as ``map.ply``."""

    enabled: bool = True  # False: no map is kept or written (--no-map)
    voxel_size: float = 0.02  # m: one point (the centroid, mean colour) per occupied voxel, per keyframe and merged
    # pixels are sampled every k-th row and column, k = voxel * fx / sample_depth (samples there a voxel apart)
    sample_depth: float = 2.0  # m
    # Depth range kept in the map (m); None: the odometry's (FeatureConfig.min_depth / max_depth).
    min_depth: float | None = None
    max_depth: float | None = None
    # A keyframe keeps only its points in voxels that none of this many keyframes before it holds (placed by
    # the odometry between them). 0: every keyframe keeps all its points.
    overlap_keyframes: int = 3

    def __post_init__(self):
        for name in ("voxel_size", "sample_depth"):
            check_number("MapConfig", name, getattr(self, name), 0, lo_open=True, finite=True)
        for name in ("min_depth", "max_depth"):
            v = getattr(self, name)
            if v is not None and not (isinstance(v, (int, float)) and v >= 0):  # inf: no far bound
                raise ValueError(f"MapConfig.{name} must be None or a number >= 0, got {v!r}")
        check_int("MapConfig", "overlap_keyframes", self.overlap_keyframes, 0)
        if self.min_depth is not None and self.max_depth is not None and not self.max_depth > self.min_depth:
            raise ValueError(f"MapConfig: max_depth ({self.max_depth}) must be > min_depth ({self.min_depth})")


class PLYFormatError(ValueError):
    """A PLY file this reader cannot read (the message names the file and what was expected)."""


def voxel_downsample(points: np.ndarray, colors: np.ndarray, voxel_size: float) -> tuple[np.ndarray, np.ndarray]:
    """One point per occupied voxel: the centroid of its points and their mean colour.

    Args:
        points: ``(N, 3)`` float coordinates (metres).
        colors: ``(N, 3)`` uint8 RGB.
        voxel_size: the voxel edge (> 0).

    Returns:
        ``(M, 3)`` float32 points and ``(M, 3)`` uint8 colours, ``M <= N``, ordered by voxel.

    Raises:
        ValueError: wrong shapes, a voxel size that is not positive, or non-finite points.

    Example:
        >>> p = np.array([[0.01, 0.0, 0.0], [0.03, 0.0, 0.0], [0.2, 0.0, 0.0]])
        >>> c = np.array([[0, 0, 0], [100, 100, 100], [9, 9, 9]], np.uint8)
        >>> q, d = voxel_downsample(p, c, 0.1)
        >>> q.astype(float).round(3).tolist(), d.tolist()
        ([[0.02, 0.0, 0.0], [0.2, 0.0, 0.0]], [[50, 50, 50], [9, 9, 9]])
    """
    points = np.asarray(points)
    colors = np.asarray(colors)
    if points.ndim != 2 or points.shape[1] != 3:
        raise ValueError(f"points must have shape (N, 3), got {points.shape}")
    if colors.shape != points.shape:
        raise ValueError(f"colors must have shape {points.shape} like the points, got {colors.shape}")
    if not (math.isfinite(voxel_size) and voxel_size > 0):
        raise ValueError(f"voxel_size must be positive and finite, got {voxel_size}")
    if points.shape[0] == 0:
        return np.zeros((0, 3), np.float32), np.zeros((0, 3), np.uint8)
    p = points.astype(np.float64)
    bad = ~np.isfinite(p).all(axis=1)
    if bad.any():  # floor(NaN) cast to int64 is one arbitrary cell: such points would merge with real ones
        raise ValueError(f"points must be finite: {int(bad.sum())} of {p.shape[0]} are not "
                         f"(the first: row {int(np.flatnonzero(bad)[0])})")
    fcells = np.floor(p / voxel_size)
    if not np.isfinite(fcells).all():
        raise ValueError(f"points up to {np.abs(p).max():.3g} are too far for voxels of {voxel_size:g}")
    if np.abs(fcells).max() >= 2.0 ** 62:
        # beyond int64 (~4.6e18 voxels away): the float cells are exact integers, unique rows
        _, inverse, counts = np.unique(fcells, axis=0, return_inverse=True, return_counts=True)
    else:
        cells = fcells.astype(np.int64)
        cells -= cells.min(axis=0)
        span = cells.max(axis=0) + 1
        if float(np.prod(span.astype(np.float64))) < 2.0 ** 62:  # one int64 key per voxel: a 1-D unique
            key = (cells[:, 0] * span[1] + cells[:, 1]) * span[2] + cells[:, 2]
            _, inverse, counts = np.unique(key, return_inverse=True, return_counts=True)
        else:  # a huge extent: unique rows
            _, inverse, counts = np.unique(cells, axis=0, return_inverse=True, return_counts=True)
    inverse = inverse.reshape(-1)
    m = counts.shape[0]
    pc = np.concatenate([p, colors.astype(np.float64)], axis=1)  # the means of the points and of the colours
    out = np.stack([np.bincount(inverse, weights=pc[:, k], minlength=m) for k in range(6)], 1) / counts[:, None]
    return out[:, :3].astype(np.float32), np.clip(np.rint(out[:, 3:]), 0, 255).astype(np.uint8)


def keyframe_cloud(rgb: np.ndarray, depth: np.ndarray, K: np.ndarray, config: MapConfig | None = None,
                   rgb_intrinsics: tuple[float, float, float, float] | None = None,
                   rgb_from_depth: tuple[float, float, float] = (0.0, 0.0, 0.0),
                   depth_range: tuple[float, float] = (0.3, 4.0)) -> tuple[np.ndarray, np.ndarray]:
    """The coloured points of one RGB-D frame in its depth camera's frame, voxel-downsampled.

    Args:
        rgb: ``(H, W, 3)`` uint8 colour image.
        depth: ``(h, w)`` float32 metres, 0 = invalid (the same size as ``rgb`` when registered).
        K: ``(3, 3)`` intrinsics of the depth image.
        config: :class:`MapConfig` (voxel size, sampling, depth range).
        rgb_intrinsics: ``(fx, fy, cx, cy)`` of the colour camera when the frame is unregistered.
        rgb_from_depth: with ``rgb_intrinsics``: the depth camera's position in the colour camera (m).
        depth_range: ``(min, max)`` metres used where ``config`` leaves them None (the odometry's).

    Returns:
        ``(N, 3)`` float32 points (metres, depth-camera frame: x right, y down, z forward), ``(N, 3)`` uint8 colours.
    """
    cfg = config or MapConfig()
    rgb = np.asarray(rgb)
    depth = np.asarray(depth)
    if rgb.ndim != 3 or rgb.shape[2] != 3 or rgb.dtype != np.uint8:
        raise ValueError(f"rgb must be (H, W, 3) uint8, got {rgb.shape} {rgb.dtype}")
    if depth.ndim != 2:
        raise ValueError(f"depth must have shape (H, W), got {depth.shape}")
    K = np.asarray(K, dtype=np.float64)
    if K.shape != (3, 3):
        raise ValueError(f"K must have shape (3, 3), got {K.shape}")
    lo = cfg.min_depth if cfg.min_depth is not None else depth_range[0]
    hi = cfg.max_depth if cfg.max_depth is not None else depth_range[1]
    d = torch.from_numpy(np.nan_to_num(np.ascontiguousarray(depth, dtype=np.float32), nan=0.0, posinf=0.0))
    offset = np.zeros(3)
    if rgb_intrinsics is not None:
        fx, fy, cx, cy = (float(v) for v in rgb_intrinsics)
        K_rgb = np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])
        d = register_depth_to_color(d, torch.from_numpy(K), torch.from_numpy(K_rgb),
                                    rig_pose(rgb_from_depth), rgb.shape[:2])
        K, offset = K_rgb, np.asarray(rgb_from_depth, dtype=np.float64)
    elif depth.shape != rgb.shape[:2]:
        raise ValueError(f"registered rgb {rgb.shape[:2]} and depth {depth.shape} must have the same size")
    step = max(1, int(cfg.voxel_size * min(K[0, 0], K[1, 1]) / cfg.sample_depth))
    z = d.numpy()[::step, ::step].astype(np.float64)
    H, W = z.shape
    v, u = np.mgrid[0:H, 0:W]
    u, v = (u * step).astype(np.float64), (v * step).astype(np.float64)
    ok = (z > lo) & (z < hi)
    z, u, v = z[ok], u[ok], v[ok]
    pts = np.stack([(u - K[0, 2]) / K[0, 0] * z, (v - K[1, 2]) / K[1, 1] * z, z], axis=1)
    pts -= offset  # colour camera -> depth camera (parallel axes); zero when registered
    cols = rgb[::step, ::step][ok]
    return voxel_downsample(pts, cols, cfg.voxel_size)


def _voxel_keys(points: np.ndarray, voxel_size: float) -> np.ndarray:
    """One int64 per voxel of ``points`` ``(N, 3)`` (21 bits an axis: +-10^6 voxels, 20 km at 2 cm; farther
    points share keys, which only makes the overlap test keep fewer of them)."""
    c = np.clip(np.floor(points / voxel_size), -(1 << 20), (1 << 20) - 1).astype(np.int64) + (1 << 20)
    return (c[:, 0] << 42) | (c[:, 1] << 21) | c[:, 2]


class PointCloudMap:
    """The keyframes' coloured points, each kept in its keyframe's camera frame until it is placed.

    Args:
        config: :class:`MapConfig`.
        rgb_intrinsics: ``(fx, fy, cx, cy)`` of the colour camera for unregistered frames (else None).
        rgb_from_depth: the depth camera's position in the colour camera (m), with ``rgb_intrinsics``.
        depth_range: the odometry's valid depth range (m), used where ``config`` leaves it None.
    """

    def __init__(self, config: MapConfig | None = None,
                 rgb_intrinsics: tuple[float, float, float, float] | None = None,
                 rgb_from_depth: tuple[float, float, float] = (0.0, 0.0, 0.0),
                 depth_range: tuple[float, float] = (0.3, 4.0)):
        self.config = config or MapConfig()
        self.rgb_intrinsics = None if rgb_intrinsics is None else tuple(float(v) for v in rgb_intrinsics)
        self.rgb_from_depth = tuple(float(v) for v in rgb_from_depth)
        self.depth_range = (float(depth_range[0]), float(depth_range[1]))
        self._clouds: dict[int, tuple[np.ndarray, float, np.ndarray]] = {}  # id -> (int16 (N, 3), step, uint8)
        # the last keyframes' full clouds for the overlap test: (id, 4x4 pose in a local chain, points)
        self._recent: list[tuple[int, np.ndarray, np.ndarray]] = []

    @classmethod
    def for_config(cls, config) -> PointCloudMap:
        """The map of a :class:`slam.config.SLAMConfig` (its map settings, rig and depth range)."""
        f = config.odometry.features
        return cls(config.map, f.rgb_intrinsics, tuple(f.rgb_from_depth_translation), (f.min_depth, f.max_depth))

    def add(self, keyframe_id: int, rgb: np.ndarray, depth: np.ndarray, K: np.ndarray,
            reference: tuple[int, torch.Tensor] | None = None) -> int:
        """Keep the points of keyframe ``keyframe_id`` (replacing any it had) that the last
        ``overlap_keyframes`` keyframes added do not hold; returns how many are kept.

        Args:
            keyframe_id: its id.
            rgb, depth, K: its frame (see :func:`keyframe_cloud`).
            reference: ``(id, T_ref_kf)``: a keyframe added before and this keyframe's ``(7,)`` pose in it (the
                odometry edge); None (or a reference not among the last ones): every point is kept.
        """
        pts, cols = keyframe_cloud(rgb, depth, K, self.config, self.rgb_intrinsics, self.rgb_from_depth,
                                   self.depth_range)
        n_recent = self.config.overlap_keyframes
        local = np.eye(4)
        by_id = {k: T for k, T, _ in self._recent}
        if reference is not None and int(reference[0]) in by_id and n_recent:
            T_ref_kf = se3_to_matrix(torch.as_tensor(reference[1], dtype=torch.float64).detach().cpu()[None])[0].numpy()
            local = by_id[int(reference[0])] @ T_ref_kf
        else:
            self._recent = []  # a new chain: nothing to compare with
        keep = np.ones(pts.shape[0], bool)
        if self._recent and pts.shape[0]:
            inv = np.linalg.inv(local)
            held = np.concatenate([(q @ (inv @ T)[:3, :3].T + (inv @ T)[:3, 3]) for _, T, q in self._recent])
            keep = ~np.isin(_voxel_keys(pts.astype(np.float64), self.config.voxel_size),
                            _voxel_keys(held, self.config.voxel_size))
        if n_recent:
            self._recent = (self._recent + [(int(keyframe_id), local, pts.astype(np.float64))])[-n_recent:]
        kept = pts[keep]
        reach = float(np.abs(kept).max()) if kept.size else 0.0
        step = max(self.config.voxel_size / 16.0, reach / 32000.0)
        self._clouds[int(keyframe_id)] = (np.rint(kept / step).astype(np.int16), step, cols[keep])
        return int(kept.shape[0])

    def drop(self, keyframe_ids) -> None:
        """Forget the points of keyframes ``keyframe_ids`` (released revisits; ids without points are skipped)."""
        for k in keyframe_ids:
            self._clouds.pop(int(k), None)

    def __len__(self) -> int:
        """Number of keyframes with points."""
        return len(self._clouds)

    @property
    def num_points(self) -> int:
        """Points kept over all keyframes (before the final merge)."""
        return sum(q.shape[0] for q, _, _ in self._clouds.values())

    @property
    def nbytes(self) -> int:
        """Memory held by the points and colours."""
        return sum(q.nbytes + c.nbytes + 8 for q, _, c in self._clouds.values())

    def local_points(self, keyframe_id: int) -> tuple[np.ndarray, np.ndarray]:
        """Keyframe ``keyframe_id``'s kept points ``(N, 3)`` float32 in its camera frame, and colours ``(N, 3)``."""
        q, step, c = self._clouds[int(keyframe_id)]
        return (q.astype(np.float64) * step).astype(np.float32), c

    def points(self, keyframe_poses: torch.Tensor) -> tuple[np.ndarray, np.ndarray]:
        """Every keyframe's points placed with its pose, merged on the voxel grid.

        Args:
            keyframe_poses: ``(M, 7)`` world-from-camera depth-camera poses ``[t, q_xyzw]`` of keyframes ``0 .. M-1``;
                keyframes beyond ``M`` or with a non-finite pose are left out.

        Returns:
            ``(N, 3)`` float32 world points and ``(N, 3)`` uint8 colours (N = 0 when nothing was kept).
        """
        poses = keyframe_poses.detach().to("cpu", torch.float64).numpy() if isinstance(
            keyframe_poses, torch.Tensor) else np.asarray(keyframe_poses, dtype=np.float64)
        if poses.ndim != 2 or poses.shape[1] != 7:
            raise ValueError(f"keyframe_poses must have shape (M, 7), got {poses.shape}")
        ids = [k for k in sorted(self._clouds) if k < poses.shape[0] and np.isfinite(poses[k]).all()
               and self._clouds[k][0].shape[0] > 0]
        if not ids:
            return np.zeros((0, 3), np.float32), np.zeros((0, 3), np.uint8)
        counts = np.array([self._clouds[k][0].shape[0] for k in ids])
        ends = np.cumsum(counts)
        R = quat_to_rotmat(torch.from_numpy(poses[ids, 3:])).numpy()  # (m, 3, 3)
        t = poses[ids, :3]
        world = np.empty((int(ends[-1]), 3), np.float64)  # placed keyframe by keyframe: no (N, 3, 3) temporary
        for j, k in enumerate(ids):
            q, step, _ = self._clouds[k]
            world[ends[j] - counts[j]:ends[j]] = (q * step) @ R[j].T + t[j]
        colors = np.concatenate([self._clouds[k][2] for k in ids])
        return voxel_downsample(world, colors, self.config.voxel_size)


_PLY_FIELDS = [("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("red", "u1"), ("green", "u1"), ("blue", "u1")]
_PLY_TYPES = {"float": "<f4", "float32": "<f4", "double": "<f8", "float64": "<f8", "uchar": "u1",
              "uint8": "u1", "char": "i1", "int8": "i1", "ushort": "<u2", "uint16": "<u2", "short": "<i2",
              "int16": "<i2", "uint": "<u4", "uint32": "<u4", "int": "<i4", "int32": "<i4"}


def write_ply(target: PathOrFile, points: np.ndarray, colors: np.ndarray, comment: str = "") -> None:
    """Write a coloured point cloud as a binary little-endian PLY.

    Args:
        target: a path or a binary file object.
        points: ``(N, 3)`` coordinates (written as float32).
        colors: ``(N, 3)`` uint8 RGB.
        comment: one line put in the header (e.g. what the points are).

    Raises:
        ValueError: wrong shapes or dtypes, non-finite coordinates, or coordinates beyond float32's range.
    """
    points = np.asarray(points)
    colors = np.asarray(colors)
    if points.ndim != 2 or points.shape[1] != 3:
        raise ValueError(f"points must have shape (N, 3), got {points.shape}")
    if colors.shape != points.shape or colors.dtype != np.uint8:
        raise ValueError(f"colors must be ({points.shape[0]}, 3) uint8, got {colors.shape} {colors.dtype}")
    if not np.isfinite(points).all():
        raise ValueError("cannot write non-finite point coordinates")
    big = np.abs(points.astype(np.float64)) > np.finfo(np.float32).max if points.size else np.zeros(0, bool)
    if big.any():  # written as float32 they would be inf
        rows = np.flatnonzero(big.any(axis=1))
        raise ValueError(f"cannot write coordinates beyond float32's range (+-3.4e38) as PLY float: "
                         f"{rows.size} point(s), the first row {int(rows[0])}")
    vertex = np.empty(points.shape[0], dtype=_PLY_FIELDS)
    for k, (name, _) in enumerate(_PLY_FIELDS):
        vertex[name] = points[:, k] if k < 3 else colors[:, k - 3]
    lines = ["ply", "format binary_little_endian 1.0"]
    lines += [f"comment {c}" for c in comment.replace("\r", "").split("\n") if c]
    lines += [f"element vertex {points.shape[0]}"]
    lines += [f"property {'float' if dt == '<f4' else 'uchar'} {name}" for name, dt in _PLY_FIELDS]
    lines += ["end_header"]
    data = ("\n".join(lines) + "\n").encode("ascii", errors="replace") + vertex.tobytes()
    if isinstance(target, (str, os.PathLike)):
        with open(os.fspath(target), "wb") as f:
            f.write(data)
    elif hasattr(target, "write"):
        target.write(data)
    else:
        raise TypeError(f"expected a path or a binary file object, got {type(target).__name__}")


def read_ply(source: PathOrFile) -> tuple[np.ndarray, np.ndarray | None]:
    """Read the vertices of a binary little-endian or ASCII PLY (what :func:`write_ply` writes, and more).

    Args:
        source: a path or a binary file object.

    Returns:
        ``(N, 3)`` float64 ``x y z`` and ``(N, 3)`` uint8 ``red green blue`` (None when absent).

    Raises:
        PLYFormatError: not a PLY, a big-endian one, no vertex element or no x/y/z, a count that is not a
            non-negative integer, a vertex line with too few values, or fewer bytes than the header
            announces (the message names the file, and the line where there is one).
    """
    name = source_name(source)
    data = Path(source).read_bytes() if isinstance(source, (str, os.PathLike)) else source.read()
    # the header ends at the first line that is exactly "end_header" (a comment may contain the words)
    header, body_start, pos = [], None, 0
    while pos < len(data):
        nl = data.find(b"\n", pos)
        line = data[pos:] if nl < 0 else data[pos:nl]
        pos = len(data) if nl < 0 else nl + 1
        text = line.decode("ascii", errors="replace").rstrip("\r")
        if text.strip() == "end_header":
            body_start = pos
            break
        header.append(text)
    if not data.startswith(b"ply") or body_start is None:
        raise PLYFormatError(f"{name}: not a PLY file (expected 'ply' ... 'end_header')")
    fmt, elements = None, []  # [(name, count, [(prop, dtype)])]
    for number, line in enumerate(header, start=1):
        words = line.split()
        if not words or words[0] in ("ply", "comment", "obj_info"):
            continue
        if words[0] == "format":
            fmt = words[1] if len(words) > 1 else None
        elif words[0] == "element" and len(words) == 3:
            if not words[2].isdigit():
                raise PLYFormatError(f"{name}:{number}: the element count must be a non-negative integer ({line!r})")
            elements.append((words[1], int(words[2]), []))
        elif words[0] == "property" and elements:
            if len(elements) > 1:  # a later element (faces, edges): not read, any properties
                continue
            if words[1:2] == ["list"]:
                raise PLYFormatError(f"{name}:{number}: list properties are not supported ({line!r})")
            if len(words) != 3 or words[1] not in _PLY_TYPES:
                raise PLYFormatError(f"{name}:{number}: unknown property {line!r}")
            elements[-1][2].append((words[2], _PLY_TYPES[words[1]]))
        else:
            raise PLYFormatError(f"{name}:{number}: unexpected header line {line!r}")
    if fmt not in ("binary_little_endian", "ascii"):
        raise PLYFormatError(f"{name}: format {fmt!r} is not supported (binary_little_endian or ascii)")
    if not elements or elements[0][0] != "vertex":
        raise PLYFormatError(f"{name}: the first element must be 'vertex'")
    _, count, props = elements[0]
    names = [p for p, _ in props]
    if not {"x", "y", "z"} <= set(names):
        raise PLYFormatError(f"{name}: the vertex element has no x, y, z properties ({names})")
    if fmt == "ascii":
        rows = data[body_start:].decode("ascii", errors="replace").split("\n")[:count]
        first = len(header) + 2  # the file's line number of the first vertex line
        for k, r in enumerate(rows):
            if len(r.split()) < len(props):
                raise PLYFormatError(f"{name}:{first + k}: a vertex line of {len(r.split())} values, expected "
                                     f"{len(props)} ({', '.join(names)})")
        try:
            table = np.array([[float(v) for v in r.split()[: len(props)]] for r in rows], dtype=np.float64)
        except ValueError:
            raise PLYFormatError(f"{name}: a vertex line is not numeric") from None
        table = table.reshape(-1, len(props)) if count == 0 else table
        if table.shape != (count, len(props)):
            raise PLYFormatError(f"{name}: expected {count} vertex lines of {len(props)} numbers")
        col = {p: table[:, k] for k, p in enumerate(names)}
    else:
        dt = np.dtype(props)
        if len(data) - body_start < count * dt.itemsize:
            raise PLYFormatError(f"{name}: {count} vertices announced, {len(data) - body_start} bytes of data "
                                 f"(need {count * dt.itemsize})")
        table = np.frombuffer(data, dtype=dt, count=count, offset=body_start)
        col = {p: table[p] for p in names}
    xyz = np.stack([col["x"], col["y"], col["z"]], 1).astype(np.float64)
    has_rgb = {"red", "green", "blue"} <= set(names)
    return xyz, np.stack([col["red"], col["green"], col["blue"]], 1).astype(np.uint8) if has_rgb else None
