"""The synthetic indoor scene: boxes with a yaw about world z (a panel is a thin box, the room a box seen from
inside), each face textured from the photographs in scikit-image's wheel (seeded procedural patterns without it).
World frame: x east, y north, z up, metres; the room spans ``[0, size_x] x [0, size_y] x [0, size_z]``.

Example:
    >>> scene = build_room_scene(RoomConfig(texel_density=32.0))
    >>> scene.centers.shape, scene.face_tex.shape
    (torch.Size([10, 3]), torch.Size([10, 6]))
    >>> scene.surface_distance(torch.tensor([[0.0, 3.0, 1.0]])).shape
    torch.Size([1])
"""
from __future__ import annotations

import functools
import importlib.util
import logging
import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np
import torch

Tensor = torch.Tensor
logger = logging.getLogger(__name__)

__all__ = [
    "BoxSpec",
    "RoomConfig",
    "Scene",
    "box_signed_distance",
    "build_room_scene",
    "default_room_scene",
    "load_photo_textures",
    "procedural_texture",
]

# name -> file inside skimage/data
PHOTO_FILES: dict[str, str] = {
    "astronaut": "astronaut.png", "chelsea": "chelsea.png", "coffee": "coffee.png",
    "rocket": "rocket.jpg", "motorcycle": "motorcycle_left.png", "hubble": "hubble_deep_field.jpg",
    "ihc": "ihc.png", "retina": "retina.jpg", "color": "color.png", "camera": "camera.png",
    "coins": "coins.png", "moon": "moon.png", "page": "page.png", "text": "text.png",
    "clock": "clock_motion.png", "brick": "brick.png", "gravel": "gravel.png", "grass": "grass.png",
    "cell": "cell.png", "horse": "horse.png", "logo": "logo.png",
}


@dataclass(frozen=True)
class RoomConfig:
    """Settings of the default room.

    Attributes:
        size: room extent (x, y, z) in metres; the camera trajectories assume the default.
        texel_density: texels per metre of the room's walls, floor and ceiling.
        object_texel_density: texels per metre on the objects.
        seed: seed of the texture composition (poster placement, crops, tints).
        ambient: fraction of the light that does not depend on the surface orientation.
        lights: point-light positions in world coordinates (Lambertian shading, no shadows).
    """

    size: tuple[float, float, float] = (7.0, 6.0, 2.8)
    texel_density: float = 256.0
    object_texel_density: float = 384.0
    seed: int = 0
    ambient: float = 0.55
    lights: tuple[tuple[float, float, float], ...] = ((2.5, 2.5, 2.7), (5.0, 4.0, 2.7))


@dataclass
class BoxSpec:
    """One box before tensorisation (numpy textures, metres, degrees).

    Attributes:
        name: a label (debugging, tests).
        center: (3,) world position of the box centre.
        size: (3,) full extent along the box's local x, y, z.
        yaw_deg: rotation about world z (counter-clockwise seen from above).
        faces: six ``(h, w, 3)`` uint8 textures in face order -x, +x, -y, +y, -z, +z; each texture's
            row 0 is the face's top edge (vertical faces) as seen from its visible side.
        inside: True for the room (seen from the inside: normals point inwards).
    """

    name: str
    center: Sequence[float]
    size: Sequence[float]
    yaw_deg: float
    faces: list[np.ndarray]
    inside: bool = False


@dataclass
class Scene:
    """Tensorised scene, ready for :func:`slam.synthetic.render.render_frames` (B boxes, T textures).

    Geometry (box-local quantities use the box's own frame, ``p_world = R @ p_local + center``):
        centers: ``(B, 3)``; rotations: ``(B, 3, 3)`` local-to-world; half_sizes: ``(B, 3)``;
        inside: ``(B,)`` bool (True: the room, seen from within).
    Faces (6 per box, order -x, +x, -y, +y, -z, +z of the local frame):
        face_origin: ``(B, 6, 3)`` local corner where the texture coordinate is (0, 0);
        face_u, face_v: ``(B, 6, 3)`` local unit axes of the texture's columns and rows;
        face_extent: ``(B, 6, 2)`` metres covered along u and v;
        face_normal: ``(B, 6, 3)`` local unit normal pointing to the visible side;
        face_tex: ``(B, 6)`` int64 texture id; face_density: ``(B, 6)`` texels per metre.
    Textures (a mip pyramid of ``L`` levels, all levels of all textures in one flat buffer):
        tex_buffer: ``(M, 3)`` uint8 RGB texels; tex_offset: ``(T, L)`` int64 start of each level;
        tex_size: ``(T, L, 2)`` int64 (width, height) of each level.
    Lighting: lights ``(Q, 3)`` world positions; ambient (float).
    """

    centers: Tensor
    rotations: Tensor
    half_sizes: Tensor
    inside: Tensor
    face_origin: Tensor
    face_u: Tensor
    face_v: Tensor
    face_extent: Tensor
    face_normal: Tensor
    face_tex: Tensor
    face_density: Tensor
    tex_buffer: Tensor
    tex_offset: Tensor
    tex_size: Tensor
    lights: Tensor
    ambient: float
    names: list[str] = field(default_factory=list)
    room_size: tuple[float, float, float] = (7.0, 6.0, 2.8)

    @property
    def device(self) -> torch.device:
        return self.centers.device

    @property
    def num_boxes(self) -> int:
        return int(self.centers.shape[0])

    def surface_distance(self, points: Tensor) -> Tensor:
        """Distance ``(N,)`` from world points ``(N, 3)`` to the nearest surface of the scene."""
        return box_signed_distance(points, self.centers, self.rotations, self.half_sizes).abs().min(-1).values


def box_signed_distance(points: Tensor, centers: Tensor, rotations: Tensor, half_sizes: Tensor) -> Tensor:
    """Signed distance ``(N, B)`` from points ``(N, 3)`` to oriented boxes (negative inside).

    Args:
        points: ``(N, 3)`` world points.
        centers: ``(B, 3)``; rotations: ``(B, 3, 3)`` local-to-world; half_sizes: ``(B, 3)``.
    """
    if points.ndim != 2 or points.shape[-1] != 3:
        raise ValueError(f"points must have shape (N, 3), got {tuple(points.shape)}")
    dt = points.dtype
    local = torch.einsum("nbi,bij->nbj", points[:, None, :] - centers[None].to(dt), rotations.to(dt))
    q = local.abs() - half_sizes[None].to(dt)
    outside = q.clamp_min(0.0).norm(dim=-1)
    inside = q.max(dim=-1).values.clamp_max(0.0)
    return outside + inside


def _skimage_data_dir() -> Path | None:
    # find_spec locates the package without importing it (slow)
    spec = importlib.util.find_spec("skimage")
    if spec is None or not spec.submodule_search_locations:
        return None
    path = Path(next(iter(spec.submodule_search_locations))) / "data"
    return path if path.is_dir() else None


def _read_rgb(path: Path) -> np.ndarray | None:
    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if img is None or img.dtype != np.uint8:
        return None
    if img.ndim == 2:
        return np.repeat(img[:, :, None], 3, axis=2)
    if img.shape[2] == 4:  # composite over white: the RGBA logos have transparent backgrounds
        alpha = img[:, :, 3:4].astype(np.float32) / 255.0
        img = (img[:, :, :3].astype(np.float32) * alpha + 255.0 * (1.0 - alpha)).round().astype(np.uint8)
    return np.ascontiguousarray(img[:, :, ::-1])  # BGR -> RGB


def procedural_texture(rng: np.random.Generator, height: int = 384, width: int = 384) -> np.ndarray:
    """A seeded, feature-rich RGB texture ``(height, width, 3)`` uint8 (multi-octave noise + shapes)."""
    img = np.zeros((height, width, 3), np.float32)
    for octave in range(5):  # value noise: random grids upsampled, each octave finer and weaker
        cells = 2 ** (octave + 2)
        grid = rng.random((cells, cells, 3)).astype(np.float32)
        img += cv2.resize(grid, (width, height), interpolation=cv2.INTER_CUBIC) * (0.6 ** octave)
    img = (img - img.min()) / max(float(img.max() - img.min()), 1e-6) * 160.0 + 40.0
    for _ in range(40):  # corners and blobs for feature detectors
        color = tuple(float(c) for c in rng.integers(0, 256, 3))
        x, y = int(rng.integers(0, width)), int(rng.integers(0, height))
        s = int(rng.integers(max(2, width // 40), max(3, width // 8)))
        if rng.random() < 0.5:
            cv2.rectangle(img, (x, y), (x + s, y + int(s * rng.uniform(0.4, 1.6))), color, -1)
        else:
            cv2.circle(img, (x, y), s // 2, color, -1)
    return np.clip(img, 0, 255).astype(np.uint8)


@functools.lru_cache(maxsize=1)
def _load_photos_cached() -> tuple[tuple[str, np.ndarray], ...]:
    folder = _skimage_data_dir()
    if folder is None:
        return ()
    out = []
    for name, fname in PHOTO_FILES.items():
        img = _read_rgb(folder / fname)
        if img is not None:
            img.setflags(write=False)
            out.append((name, img))
    return tuple(out)


def load_photo_textures(seed: int = 0) -> dict[str, np.ndarray]:
    """The photographs used as textures, by name (RGB ``(h, w, 3)`` uint8, read-only arrays); any that
    cannot be read is replaced by a seeded procedural texture, with a warning."""
    photos = dict(_load_photos_cached())
    missing = [n for n in PHOTO_FILES if n not in photos]
    if missing:
        logger.warning(
            "scikit-image's bundled photographs not found for %s: using procedural textures instead "
            "(install the 'demo' extra, scikit-image, for photographic textures)", ", ".join(missing))
        rng = np.random.default_rng(seed + 7919)
        for name in missing:
            photos[name] = procedural_texture(rng)
    return photos


def _crop_to_aspect(rng: np.random.Generator, img: np.ndarray, aspect: float, min_scale: float) -> np.ndarray:
    """A random crop of ``img`` with width/height ``aspect`` covering at least ``min_scale`` of it."""
    h, w = img.shape[:2]
    ch, cw = (h, round(h * aspect)) if w / h > aspect else (round(w / aspect), w)
    s = rng.uniform(min_scale, 1.0)
    ch, cw = max(2, int(ch * s)), max(2, int(cw * s))
    y0 = int(rng.integers(0, h - ch + 1))
    x0 = int(rng.integers(0, w - cw + 1))
    return img[y0:y0 + ch, x0:x0 + cw]


def _resize(img: np.ndarray, width: int, height: int) -> np.ndarray:
    width, height = max(2, int(width)), max(2, int(height))
    shrinking = width < img.shape[1] or height < img.shape[0]
    return cv2.resize(img, (width, height), interpolation=cv2.INTER_AREA if shrinking else cv2.INTER_CUBIC)


def _tinted_tiling(base: np.ndarray, width: int, height: int, tile_px: int, tint: Sequence[float],
                   contrast: float) -> np.ndarray:
    """``base`` (grey content) tiled with period ``tile_px`` texels and coloured by ``tint`` (RGB 0..1)."""
    grey = cv2.cvtColor(base, cv2.COLOR_RGB2GRAY).astype(np.float32) / 255.0
    tile = cv2.resize(grey, (tile_px, tile_px), interpolation=cv2.INTER_AREA)
    reps = (height // tile_px + 1, width // tile_px + 1)
    g = np.tile(tile, reps)[:height, :width]
    g = (g - g.mean()) / max(float(g.std()), 1e-6)
    shade = np.clip(1.0 + contrast * g, 0.2, 1.6)[:, :, None]
    return np.clip(shade * np.asarray(tint, np.float32)[None, None] * 255.0, 0, 255).astype(np.uint8)


def compose_surface(rng: np.random.Generator, photos: dict[str, np.ndarray], base: str,
                     tint: Sequence[float], width_m: float, height_m: float, density: float,
                     tile_m: float, contrast: float, posters: Sequence[str], poster_height: tuple[float, float],
                     band: tuple[float, float], grout_m: float = 0.0) -> np.ndarray:
    """A wall/floor texture: a tinted tileable base, optional grout lines, and framed photographs
    hanging inside ``band``, the (min, max) height in metres above the texture's bottom edge."""
    w, h = round(width_m * density), round(height_m * density)
    tex = _tinted_tiling(photos[base], w, h, max(8, int(tile_m * density)), tint, contrast)
    if grout_m > 0:  # tile joints: dark lines on a regular grid
        step = round(grout_m * density)
        for k in range(max(1, int(0.012 * density))):
            tex[:, k::step] = (tex[:, k::step] * 0.5).astype(np.uint8)
            tex[k::step, :] = (tex[k::step, :] * 0.5).astype(np.uint8)
    placed: list[tuple[int, int, int, int]] = []
    border = max(1, int(0.03 * density))
    for name in posters:
        img = photos[name]
        for _ in range(200):  # rejection sampling of a free spot
            ph = int(rng.uniform(*poster_height) * density)
            aspect = img.shape[1] / img.shape[0] * rng.uniform(0.8, 1.1)
            pw = int(ph * aspect)
            if pw + 2 * border >= w:
                continue
            x0 = int(rng.integers(border, w - pw - border))
            lo, hi = int(band[0] * density), int(band[1] * density) - ph
            if hi <= lo:
                continue
            bottom = int(rng.integers(lo, hi + 1))
            y0 = h - bottom - ph
            gap = int(0.15 * density)
            box = (x0 - gap, y0 - gap, x0 + pw + gap, y0 + ph + gap)
            if any(not (box[2] <= b[0] or b[2] <= box[0] or box[3] <= b[1] or b[3] <= box[1]) for b in placed):
                continue
            crop = _resize(_crop_to_aspect(rng, img, pw / ph, 0.75), pw, ph)
            y0, (ch, cw) = max(border, y0), crop.shape[:2]  # framed by ``border`` texels of a dark colour
            tex[y0 - border:y0 + ch + border, x0 - border:x0 + cw + border] = rng.integers(20, 90, 3)
            tex[y0:y0 + ch, x0:x0 + cw] = crop
            placed.append(box)
            break
    return tex


def _box_faces(rng: np.random.Generator, photos: dict[str, np.ndarray], size: Sequence[float],
               names: Sequence[str], density: float) -> list[np.ndarray]:
    """Six face textures (order -x, +x, -y, +y, -z, +z) for a box of ``size``: the photographs ``names`` cropped
    to each face's aspect ratio at ``density`` texels per metre."""
    sx, sy, sz = size
    faces = []
    for name, (a, b) in zip(names, [(sy, sz), (sy, sz), (sx, sz), (sx, sz), (sx, sy), (sx, sy)]):
        w, h = max(4, round(a * density)), max(4, round(b * density))
        faces.append(_resize(_crop_to_aspect(rng, photos[name], w / h, 0.6), w, h))
    return faces


def _default_boxes(cfg: RoomConfig, photos: dict[str, np.ndarray]) -> list[BoxSpec]:
    rng = np.random.default_rng(cfg.seed)
    X, Y, Z = cfg.size
    d = cfg.texel_density
    # west, east, south, north: every wall in its own colour with its own photographs (each direction unique)
    walls = [compose_surface(rng, photos, base, tint, length, Z, d, tile, contrast, posters, (0.55, 0.95),
                             (0.85, Z - 0.2)) for base, tint, length, tile, contrast, posters in (
        ("brick", (0.72, 0.42, 0.33), Y, 1.2, 0.55, ["astronaut", "clock", "coffee", "ihc", "text"]),
        ("gravel", (0.88, 0.82, 0.66), Y, 1.0, 0.5, ["hubble", "chelsea", "page", "camera", "color"]),
        ("cell", (0.62, 0.72, 0.82), X, 0.9, 0.6, ["rocket", "camera", "motorcycle", "retina", "coins", "chelsea"]),
        ("grass", (0.60, 0.74, 0.52), X, 1.0, 0.55, ["moon", "ihc", "horse", "coins", "astronaut", "logo"]))]
    floor = compose_surface(rng, photos, "gravel", (0.58, 0.55, 0.52), X, Y, d, 0.6, 0.6,
                             ["hubble", "logo", "ihc"], (1.0, 1.6), (0.4, Y - 0.4), grout_m=0.6)
    ceiling = compose_surface(rng, photos, "moon", (0.92, 0.92, 0.90), X, Y, d * 0.5, 1.2, 0.35,
                               [], (0.5, 0.6), (0.0, Y), grout_m=0.6)
    room = BoxSpec("room", (X / 2, Y / 2, Z / 2), (X, Y, Z), 0.0, walls + [floor, ceiling], inside=True)
    od = cfg.object_texel_density

    def box(name, center, size, yaw, textures):
        return BoxSpec(name, center, size, yaw, _box_faces(rng, photos, size, textures, od))

    return [
        room,
        box("cabinet", (X - 0.3, Y / 2 + 0.7, 0.45), (0.5, 1.2, 0.9), 0.0,
            ["coffee", "brick", "chelsea", "motorcycle", "gravel", "page"]),
        box("crate_on_cabinet", (X - 0.33, Y / 2 + 0.45, 1.1), (0.35, 0.35, 0.4), 15.0,
            ["rocket", "coins", "clock", "astronaut", "gravel", "text"]),
        box("stand", (X - 1.4, Y - 1.1, 0.5), (0.5, 0.5, 1.0), 20.0,
            ["retina", "astronaut", "camera", "ihc", "gravel", "clock"]),
        box("shelf", (2.2, Y - 0.25, 0.9), (1.0, 0.45, 1.8), 0.0,
            ["ihc", "camera", "hubble", "grass", "gravel", "coins"]),
        box("panel", (1.0, Y - 2.0, 0.9), (0.04, 1.2, 1.6), 30.0,
            ["horse", "motorcycle", "text", "text", "gravel", "gravel"]),
        box("cupboard", (0.3, Y / 2 - 0.5, 0.55), (0.5, 1.0, 1.1), 0.0,
            ["gravel", "coins", "coffee", "chelsea", "gravel", "retina"]),
        box("table", (1.3, 1.5, 0.375), (1.2, 0.8, 0.75), -10.0,
            ["retina", "chelsea", "ihc", "motorcycle", "gravel", "page"]),
        box("boxes", (X / 2 - 0.2, 0.3, 0.35), (1.0, 0.5, 0.7), 0.0,
            ["page", "cell", "gravel", "astronaut", "gravel", "hubble"]),
        box("crate", (X - 2.0, 1.2, 0.3), (0.6, 0.6, 0.6), 25.0,
            ["astronaut", "rocket", "camera", "coffee", "gravel", "coins"]),
    ]


def _face_frames(half: np.ndarray, inside: bool) -> tuple[np.ndarray, ...]:
    """Per face (order -x, +x, -y, +y, -z, +z): local corner ``(6, 3)``, u axis ``(6, 3)``, v axis ``(6, 3)``,
    extent (u, v) ``(6, 2)``, visible-side normal ``(6, 3)``."""
    frames = []
    ez = np.array([0.0, 0.0, 1.0])
    for axis, sign in ((0, -1.0), (0, 1.0), (1, -1.0), (1, 1.0), (2, -1.0), (2, 1.0)):
        e = np.eye(3)[axis]
        n = sign * e * (-1.0 if inside else 1.0)  # the side the face is seen from
        if axis < 2:  # u: the viewer's right facing the face upright; texture rows go down
            u, v = np.cross(ez, n), -ez
        else:
            u, v = np.array([1.0, 0.0, 0.0]), np.array([0.0, -1.0 if n[2] > 0 else 1.0, 0.0])
        ext_u, ext_v = 2.0 * float(np.abs(u) @ half), 2.0 * float(np.abs(v) @ half)
        frames.append((sign * half[axis] * e - 0.5 * ext_u * u - 0.5 * ext_v * v, u, v, (ext_u, ext_v), n))
    return tuple(np.array(x) for x in zip(*frames))


def _mip_chain(tex: np.ndarray, levels: int) -> list[np.ndarray]:
    chain = [np.ascontiguousarray(tex)]
    for _ in range(levels - 1):
        h, w = chain[-1].shape[:2]
        chain.append(cv2.resize(chain[-1], (max(1, w // 2), max(1, h // 2)), interpolation=cv2.INTER_AREA))
    return chain


def tensorize(boxes: Sequence[BoxSpec], cfg: RoomConfig) -> Scene:
    """Turn box specifications into a :class:`Scene` (float32 geometry, uint8 texture pyramid of 8 levels);
    a texture array shared by several faces is stored once."""
    centers, rots, halves, inside, frames, ft, fd = [], [], [], [], [], [], []
    textures: list[np.ndarray] = []
    tex_ids: dict[int, int] = {}  # id() of a texture array -> its texture id
    for b in boxes:
        if len(b.faces) != 6:
            raise ValueError(f"box {b.name!r} needs 6 face textures, got {len(b.faces)}")
        yaw = math.radians(b.yaw_deg)
        c, s = math.cos(yaw), math.sin(yaw)
        rots.append(np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]))
        half = np.asarray(b.size, np.float64) / 2.0
        centers.append(np.asarray(b.center, np.float64))
        halves.append(half)
        inside.append(b.inside)
        frames.append(_face_frames(half, b.inside))
        e = frames[-1][3]
        ids, dens = [], []
        for k, tex in enumerate(b.faces):
            if tex.ndim != 3 or tex.shape[2] != 3 or tex.dtype != np.uint8:
                raise ValueError(f"box {b.name!r} face {k}: texture must be (h, w, 3) uint8, got "
                                 f"{tex.shape} {tex.dtype}")
            if id(tex) not in tex_ids:
                tex_ids[id(tex)] = len(textures)
                textures.append(tex)
            ids.append(tex_ids[id(tex)])
            dens.append(max(tex.shape[1] / e[k][0], tex.shape[0] / e[k][1]))
        ft.append(ids)
        fd.append(dens)
    chains = [_mip_chain(tex, 8) for tex in textures]
    chunks = [lvl.reshape(-1, 3) for chain in chains for lvl in chain]
    offsets = np.cumsum([0] + [len(c) for c in chunks[:-1]]).reshape(len(chains), 8)
    sizes = [[(lvl.shape[1], lvl.shape[0]) for lvl in chain] for chain in chains]
    fo, fu, fv, fe, fn = (np.stack(x) for x in zip(*frames))
    f32 = torch.float32

    def t(x, dtype=f32):
        return torch.as_tensor(np.asarray(x), dtype=dtype)

    return Scene(
        centers=t(centers), rotations=t(rots), half_sizes=t(halves), inside=torch.tensor(inside),
        face_origin=t(fo), face_u=t(fu), face_v=t(fv), face_extent=t(fe), face_normal=t(fn),
        face_tex=t(ft, torch.int64), face_density=t(fd),
        tex_buffer=torch.from_numpy(np.concatenate(chunks, 0)),
        tex_offset=t(offsets, torch.int64), tex_size=t(sizes, torch.int64),
        lights=t(cfg.lights), ambient=float(cfg.ambient), names=[b.name for b in boxes],
        room_size=tuple(float(x) for x in cfg.size),
    )


def build_room_scene(config: RoomConfig | None = None) -> Scene:
    """The default demo room on the CPU: 7 x 6 x 2.8 m, four distinct walls with framed photographs, a tiled
    floor, a ceiling and nine photo-textured objects.

    Args:
        config: room settings (default :class:`RoomConfig`).
    """
    cfg = config or RoomConfig()
    return tensorize(_default_boxes(cfg, load_photo_textures(cfg.seed)), cfg)


@functools.lru_cache(maxsize=1)
def default_room_scene() -> Scene:
    """:func:`build_room_scene` with default settings, built once per process and shared (read-only)."""
    return build_room_scene()
