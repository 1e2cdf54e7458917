"""A multi-room building with identically furnished rooms: the scene of ``--demo-scene building``.

Rooms ``S1 .. Sn`` (south) and ``N1 .. Nn`` (north), numbered from the west, line a corridor; each has a door to
the corridor and one to each neighbour on its side. A room is built in its own frame (origin at its centre, +y
towards the corridor); north rooms are turned by 180 deg, so the building is symmetric under that half turn but
for the furnishing. Each room of ``BuildingConfig.twins`` (``Sk``) shares its design with its image ``N(n+1-k)``:
the two look identical from corresponding viewpoints (perceptual aliasing). World frame: x east (along the
corridor), y north, z up; the building spans ``[0, n * room_x] x [0, 2 * room_y + corridor_width]``.

Example:
    >>> layout = building_layout(BuildingConfig())
    >>> [s.name for s in layout.spaces]
    ['S1', 'S2', 'N1', 'N2', 'corridor']
    >>> layout.twin_of("S1"), layout.twin_of("S2")
    ('N2', None)
    >>> [round(float(v), 2) for v in layout.door("S1", "corridor").center]
    [2.5, 4.4]
"""
from __future__ import annotations

import functools
import math
from dataclasses import dataclass, field

import numpy as np

from slam.synthetic.scene import (
    BoxSpec,
    RoomConfig,
    Scene,
    compose_surface,
    load_photo_textures,
    tensorize,
)

__all__ = [
    "BuildingConfig",
    "BuildingLayout",
    "Door",
    "Space",
    "build_building_scene",
    "building_layout",
    "default_building_scene",
]

# Walls of a space in its local frame: name -> (axis of the wall's normal, sign of the wall's side).
_WALLS = {"west": (0, -1.0), "east": (0, 1.0), "south": (1, -1.0), "north": (1, 1.0)}
# Face index (-x, +x, -y, +y, -z, +z) of a half-wall box's face that looks into its own space.
_INNER_FACE = {"west": 1, "east": 0, "south": 3, "north": 2}


@dataclass(frozen=True)
class BuildingConfig:
    """Settings of the building (metres unless stated).

    Attributes:
        rooms_per_side: rooms on each side of the corridor (>= 2).
        room_size: (x, y) of a room between wall centre lines; x runs along the corridor.
        corridor_width: between the corridor's wall centre lines.
        height: floor to ceiling.
        wall_thickness: of every wall (each side owns half of it).
        door_width, door_height: of every door.
        twins: south rooms furnished identically to their image under the half turn (``"S1"`` -> ``N(n)``).
        texel_density: texels per metre of walls, floors and ceilings.
        object_texel_density: texels per metre on the furniture.
        seed: seed of the designs (texture composition, furniture jitter of the unique rooms).
        ambient: fraction of the light that does not depend on the surface orientation.
    """

    rooms_per_side: int = 2
    room_size: tuple[float, float] = (5.0, 4.4)
    corridor_width: float = 2.4
    height: float = 2.8
    wall_thickness: float = 0.12
    door_width: float = 1.2
    door_height: float = 2.1
    twins: tuple[str, ...] = ("S1",)
    texel_density: float = 160.0
    object_texel_density: float = 240.0
    seed: int = 0
    ambient: float = 0.55

    def __post_init__(self) -> None:
        if self.rooms_per_side < 2:
            raise ValueError(f"BuildingConfig.rooms_per_side must be >= 2, got {self.rooms_per_side}")
        rx, ry = self.room_size
        if min(rx, ry, self.corridor_width, self.height) <= 0 or self.wall_thickness <= 0:
            raise ValueError("BuildingConfig: sizes must be positive")
        if not (self.door_width + 2 * self.wall_thickness < min(rx, ry, self.corridor_width)
                and self.door_height < self.height):
            raise ValueError(f"BuildingConfig: a {self.door_width} x {self.door_height} m door does not fit "
                             f"rooms of {rx} x {ry} x {self.height} m")
        south = {f"S{k}" for k in range(1, self.rooms_per_side + 1)}
        bad = [t for t in self.twins if t not in south]
        if bad:
            raise ValueError(f"BuildingConfig.twins must name south rooms {sorted(south)}, got {bad}")


@dataclass(frozen=True)
class Door:
    """A door between two spaces.

    Attributes:
        a, b: the names of the spaces it joins.
        center: ``(2,)`` world (x, y) of the door's centre (on the wall's centre line).
        normal: ``(2,)`` unit world direction from ``a`` into ``b``.
    """

    a: str
    b: str
    center: np.ndarray
    normal: np.ndarray


@dataclass
class Space:
    """A room or the corridor.

    Attributes:
        name: ``"S1"``, ..., ``"N1"``, ..., ``"corridor"``.
        center: ``(2,)`` world (x, y) of its centre.
        size: (x, y) between wall centre lines, in its own frame.
        yaw_deg: its frame's rotation about z (0 or 180).
        openings: wall name (own frame) -> offsets of door centres along that wall (own-frame x for the
            south/north walls, y for the west/east walls).
        design: the key of its design (twins share one).
    """

    name: str
    center: np.ndarray
    size: tuple[float, float]
    yaw_deg: float
    openings: dict[str, list[float]] = field(default_factory=dict)
    design: str = ""

    def to_world(self, local: np.ndarray) -> np.ndarray:
        """Own-frame (x, y) points ``(..., 2)`` -> world."""
        c, s = math.cos(math.radians(self.yaw_deg)), math.sin(math.radians(self.yaw_deg))
        p = np.asarray(local, np.float64)
        return np.stack([c * p[..., 0] - s * p[..., 1], s * p[..., 0] + c * p[..., 1]], -1) + self.center


@dataclass
class BuildingLayout:
    """Where the spaces and doors are (what the camera paths need), without textures.

    Attributes:
        config: the :class:`BuildingConfig`.
        spaces: the rooms (south then north, west to east) and the corridor.
        doors: every door.
        extent: (x, y, z) size of the building.
    """

    config: BuildingConfig
    spaces: list[Space]
    doors: list[Door]
    extent: tuple[float, float, float]

    def space(self, name: str) -> Space:
        for s in self.spaces:
            if s.name == name:
                return s
        raise KeyError(f"no space named {name!r}; the building has {[s.name for s in self.spaces]}")

    def door(self, a: str, b: str) -> Door:
        """The door from space ``a`` to space ``b`` (its normal points from a into b)."""
        for d in self.doors:
            if (d.a, d.b) == (a, b):
                return d
            if (d.b, d.a) == (a, b):
                return Door(a, b, d.center, -d.normal)
        raise KeyError(f"no door between {a!r} and {b!r}")

    def twin_of(self, name: str) -> str | None:
        """The room furnished identically to room ``name`` (None for a unique room)."""
        d = self.space(name).design
        others = [s.name for s in self.spaces if s.design == d and s.name != name]
        return others[0] if others else None


def building_layout(config: BuildingConfig | None = None) -> BuildingLayout:
    """The rooms, corridor and doors of a building (see the module docstring).

    Returns:
        :class:`BuildingLayout`.
    """
    cfg = config or BuildingConfig()
    n = cfg.rooms_per_side
    rx, ry = cfg.room_size
    cw = cfg.corridor_width
    width, depth = n * rx, 2 * ry + cw
    spaces: list[Space] = []

    def room_openings(k: int) -> dict[str, list[float]]:
        # own frame: the corridor is north; the neighbour with the smaller own-frame x is west
        out = {"north": [0.0]}
        if k > 1:
            out["west"] = [0.0]
        if k < n:
            out["east"] = [0.0]
        return out

    for k in range(1, n + 1):  # south rooms, own frame = world frame
        spaces.append(Space(f"S{k}", np.array([(k - 0.5) * rx, ry / 2]), (rx, ry), 0.0, room_openings(k), f"S{k}"))
    for j in range(1, n + 1):  # north rooms: the half turn of S(n+1-j), whose design a twin shares
        k = n + 1 - j
        spaces.append(Space(f"N{j}", np.array([width - (k - 0.5) * rx, depth - ry / 2]), (rx, ry), 180.0,
                            room_openings(k), f"S{k}" if f"S{k}" in cfg.twins else f"N{j}"))
    xs = [(k - 0.5) * rx - width / 2 for k in range(1, n + 1)]
    spaces.append(Space("corridor", np.array([width / 2, ry + cw / 2]), (width, cw), 0.0,
                        {"south": list(xs), "north": list(xs)}, "corridor"))
    doors = []
    for k in range(1, n + 1):
        doors.append(Door(f"S{k}", "corridor", np.array([(k - 0.5) * rx, ry]), np.array([0.0, 1.0])))
        doors.append(Door("corridor", f"N{k}", np.array([(k - 0.5) * rx, ry + cw]), np.array([0.0, 1.0])))
    for k in range(1, n):
        doors.append(Door(f"S{k}", f"S{k + 1}", np.array([k * rx, ry / 2]), np.array([1.0, 0.0])))
        doors.append(Door(f"N{k}", f"N{k + 1}", np.array([k * rx, depth - ry / 2]), np.array([1.0, 0.0])))
    return BuildingLayout(cfg, spaces, doors, (width, depth, cfg.height))


@dataclass
class _Style:
    """How a design's surfaces look: wall bases/tints/posters (west, east, south, north), floor, ceiling."""

    walls: tuple[tuple[str, tuple[float, float, float], tuple[str, ...]], ...]
    floor: tuple[str, tuple[float, float, float]]
    ceiling: tuple[str, tuple[float, float, float]]
    furniture: tuple[str, ...]  # the photographs of the furniture faces, taken in turn


_STYLES = {
    # the twins' design: brick, plaster, wallpaper, plaster
    "a": _Style(walls=(("brick", (0.72, 0.42, 0.33), ("astronaut", "clock")),
                       ("gravel", (0.88, 0.82, 0.66), ("hubble", "chelsea")),
                       ("cell", (0.62, 0.72, 0.82), ("rocket", "camera", "motorcycle")),
                       ("grass", (0.60, 0.74, 0.52), ("moon", "ihc"))),
                floor=("gravel", (0.58, 0.55, 0.52)), ceiling=("moon", (0.92, 0.92, 0.90)),
                furniture=("coffee", "retina", "page", "coins", "horse", "text", "chelsea", "astronaut")),
    "b": _Style(walls=(("grass", (0.80, 0.70, 0.55), ("coins", "logo")),
                       ("cell", (0.70, 0.62, 0.78), ("retina", "horse")),
                       ("brick", (0.66, 0.50, 0.40), ("page", "coffee", "text")),
                       ("gravel", (0.60, 0.70, 0.80), ("color", "rocket"))),
                floor=("brick", (0.50, 0.45, 0.40)), ceiling=("gravel", (0.90, 0.90, 0.86)),
                furniture=("motorcycle", "camera", "hubble", "clock", "ihc", "moon", "astronaut", "logo")),
    "c": _Style(walls=(("gravel", (0.55, 0.65, 0.60), ("chelsea", "text")),
                       ("brick", (0.80, 0.55, 0.45), ("moon", "camera")),
                       ("grass", (0.75, 0.78, 0.60), ("ihc", "logo", "horse")),
                       ("cell", (0.82, 0.74, 0.70), ("astronaut", "coins"))),
                floor=("cell", (0.55, 0.52, 0.58)), ceiling=("grass", (0.92, 0.90, 0.88)),
                furniture=("rocket", "page", "coffee", "color", "retina", "clock", "hubble", "motorcycle")),
    "corridor": _Style(walls=(("cell", (0.80, 0.80, 0.74), ("clock",)),
                              ("cell", (0.80, 0.80, 0.74), ("logo",)),
                              ("gravel", (0.74, 0.70, 0.62), ("retina", "coins", "motorcycle", "page")),
                              ("brick", (0.70, 0.52, 0.44), ("camera", "horse", "text", "coffee"))),
                       floor=("gravel", (0.45, 0.47, 0.50)), ceiling=("moon", (0.90, 0.90, 0.90)),
                       furniture=("chelsea", "hubble", "ihc", "rocket", "astronaut", "moon", "page", "color")),
}

# (name, centre (x, y as fractions of the half sizes, z metres), size (m), yaw deg) in the own frame of a
# room whose neighbour door is east (mirrored when it is west), out of the door lanes and the camera's circle
_ROOM_FURNITURE = (
    ("shelf", (-0.38, -0.86, 0.9), (2.0, 0.45, 1.8), 0.0),
    ("cabinet", (0.55, -0.85, 0.45), (1.0, 0.5, 0.9), 0.0),
    ("crate_on_cabinet", (0.62, -0.85, 1.1), (0.35, 0.35, 0.4), 15.0),
    ("table", (-0.62, 0.74, 0.375), (1.0, 0.6, 0.75), -8.0),
    ("stand", (0.66, 0.80, 0.5), (0.5, 0.5, 1.0), 20.0),
    ("cupboard", (-0.88, 0.25, 0.55), (0.5, 1.2, 1.1), 0.0),
    ("panel", (-0.85, -0.45, 0.8), (0.04, 1.0, 1.4), 25.0),
    ("crate", (0.80, -0.55, 0.3), (0.6, 0.6, 0.6), 30.0),
)
_CORRIDOR_FURNITURE = (  # x as a fraction of the half length, y of the half width; between the doors
    ("bench", (-0.84, -0.78, 0.25), (1.4, 0.4, 0.5), 0.0),
    ("cabinet", (0.0, 0.76, 0.6), (1.0, 0.45, 1.2), 0.0),
    ("bin", (0.12, -0.80, 0.4), (0.4, 0.4, 0.8), 0.0),
    ("notice_board", (0.84, 0.93, 1.4), (0.9, 0.04, 0.8), 0.0),
)


_FURNITURE_BASES = (("brick", (0.62, 0.48, 0.40)), ("gravel", (0.70, 0.66, 0.58)), ("grass", (0.55, 0.62, 0.50)),
                    ("cell", (0.60, 0.62, 0.72)))


def _furniture_faces(rng: np.random.Generator, photos: dict[str, np.ndarray], size, names, density: float):
    """Six face textures (-x, +x, -y, +y, -z, +z) of a piece of furniture: a tinted, tiled base with the
    face's photograph framed on it (on the sides large enough; tops stay plain)."""
    sx, sy, sz = size
    faces = []
    for k, (name, (w, h)) in enumerate(zip(names, [(sy, sz), (sy, sz), (sx, sz), (sx, sz), (sx, sy), (sx, sy)])):
        base, tint = _FURNITURE_BASES[int(rng.integers(len(_FURNITURE_BASES)))]
        posters = [name] if min(w, h) > 0.25 and k < 4 else []
        faces.append(compose_surface(rng, photos, base, tint, w, h, density, 0.3, 0.6, posters, (0.45 * h, 0.75 * h),
                                     (0.05 * h, 0.97 * h)))
    return faces


def _wall_segments(length: float, openings: list[float], door_width: float) -> list[tuple[float, float]]:
    """Solid spans ``(lo, hi)`` along a wall of ``length`` (centred on 0) around door openings."""
    cuts = sorted((o - door_width / 2, o + door_width / 2) for o in openings)
    spans, lo = [], -length / 2
    for a, b in cuts:
        if a > lo + 1e-9:
            spans.append((lo, a))
        lo = max(lo, b)
    if lo < length / 2 - 1e-9:
        spans.append((lo, length / 2))
    return spans


# Faces nobody sees (wall backs, tops) and door jambs: one small texture each, shared by every design.
_HIDDEN = np.full((2, 2, 3), 128, np.uint8)
_JAMB = np.full((4, 4, 3), (200, 190, 170), np.uint8)


def _half_wall(name: str, wall: str, space_size: tuple[float, float], t: float, mid: float, length: float,
               z0: float, height: float, tex: np.ndarray, bottom: np.ndarray) -> BoxSpec:
    """A box of thickness ``t`` (m) along ``wall`` of a space (own frame), ``length`` m centred at ``mid`` along
    it, from ``z0`` up ``height`` m, with ``tex`` on its inner face; its ends are door jambs (or hidden)."""
    axis, sign = _WALLS[wall]
    sx, sy = space_size
    faces = [_JAMB] * 4 + [bottom, _HIDDEN]
    faces[_INNER_FACE[wall]], faces[_INNER_FACE[wall] ^ 1] = tex, _HIDDEN
    if axis == 1:  # a wall along x
        return BoxSpec(name, (mid, sign * (sy / 2 - t / 2), z0 + height / 2), (length, t, height), 0.0, faces)
    return BoxSpec(name, (sign * (sx / 2 - t / 2), mid, z0 + height / 2), (t, length, height), 0.0, faces)


def _design_boxes(cfg: BuildingConfig, photos: dict[str, np.ndarray], space: Space, style: _Style,
                  rng: np.random.Generator, furniture, mirror: bool, jitter: float) -> list[BoxSpec]:
    """The textured boxes of one design in the space's own frame. Every wall is two half-thickness boxes back to
    back (one per space), a door a gap in both with a lintel above."""
    sx, sy = space.size
    H, t, d, h = cfg.height, cfg.wall_thickness / 2, cfg.texel_density, _HIDDEN
    lh = H - cfg.door_height
    # floor and ceiling slabs (extending under the half walls)
    floor = compose_surface(rng, photos, style.floor[0], style.floor[1], sx, sy, d, 0.6, 0.6,
                            [], (1.0, 1.6), (0.0, sy), grout_m=0.6)
    ceiling = compose_surface(rng, photos, style.ceiling[0], style.ceiling[1], sx, sy, d * 0.5, 1.2,
                              0.35, [], (0.5, 0.6), (0.0, sy), grout_m=0.6)
    out = [BoxSpec("floor", (0.0, 0.0, -0.025), (sx, sy, 0.05), 0.0, [h, h, h, h, h, floor]),
           BoxSpec("ceiling", (0.0, 0.0, H + 0.025), (sx, sy, 0.05), 0.0, [h, h, h, h, ceiling, h])]
    for (wall, (axis, _)), (base, tint, posters) in zip(_WALLS.items(), style.walls):
        openings = space.openings.get(wall, [])
        spans = _wall_segments(sy if axis == 0 else sx, openings, cfg.door_width)
        for k, (lo, hi) in enumerate(spans):
            mine = posters[k::len(spans)] if hi - lo > 1.2 else []  # the wall's posters, in turn, where they fit
            tex = compose_surface(rng, photos, base, tint, hi - lo, H, d, 1.1, 0.55, mine, (0.5, 0.9), (0.85, H - 0.2))
            out.append(_half_wall(f"{wall}_wall_{k}", wall, space.size, t, 0.5 * (lo + hi), hi - lo, 0.0, H, tex, h))
        for k, o in enumerate(openings):  # lintels above the doors
            lint = compose_surface(rng, photos, base, tint, cfg.door_width, lh, d, 1.1, 0.55, [], (0.1, 0.2),
                                   (0.0, lh))
            out.append(_half_wall(f"{wall}_lintel_{k}", wall, space.size, t, o, cfg.door_width, cfg.door_height, lh,
                                  lint, _JAMB))
    names = list(style.furniture)
    for m, (name, (fx, fy, z), size, yaw) in enumerate(furniture):
        x, y = fx * sx / 2, fy * sy / 2
        if jitter > 0:
            x += float(rng.uniform(-jitter, jitter))
            y += float(rng.uniform(-jitter, jitter))
            yaw += float(rng.uniform(-15.0, 15.0))
        if mirror:
            x, yaw = -x, -yaw
        tex_names = [names[(m + q) % len(names)] for q in range(6)]
        out.append(BoxSpec(name, (x, y, z), size, yaw,
                           _furniture_faces(rng, photos, size, tex_names, cfg.object_texel_density)))
    return out


def _place(box: BoxSpec, space: Space) -> BoxSpec:
    """A box given in the space's own frame, placed in the world (faces travel with the box)."""
    x, y, z = box.center
    wx, wy = space.to_world(np.array([x, y]))
    return BoxSpec(f"{space.name}/{box.name}", (float(wx), float(wy), float(z)), box.size,
                   box.yaw_deg + space.yaw_deg, box.faces, box.inside)


def build_building_scene(config: BuildingConfig | None = None) -> Scene:
    """The building of :func:`building_layout` as a renderable :class:`~slam.synthetic.scene.Scene` on the
    CPU, deterministic by ``config.seed`` (one seeded generator per design, shared by twins).

    Args:
        config: :class:`BuildingConfig`.
    """
    cfg = config or BuildingConfig()
    layout = building_layout(cfg)
    photos = load_photo_textures(cfg.seed)
    designs: dict[str, list[BoxSpec]] = {}
    boxes: list[BoxSpec] = []
    # the twins share style "a"; the unique rooms take "b" and "c" in turn
    unique = [d for d in dict.fromkeys(s.design for s in layout.spaces) if d != "corridor" and d not in cfg.twins]
    style_of = {"corridor": "corridor", **dict.fromkeys(cfg.twins, "a"),
                **{d: "bc"[k % 2] for k, d in enumerate(unique)}}
    for s in layout.spaces:
        if s.design not in designs:
            # one generator per design, seeded by its name: adding a room does not change the others
            key = sum(ord(ch) * 131 ** i for i, ch in enumerate(s.design)) % (2 ** 31)
            rng = np.random.default_rng(np.random.SeedSequence([cfg.seed, key]))
            if s.name == "corridor":
                furniture, mirror, jitter = _CORRIDOR_FURNITURE, False, 0.0
            else:
                furniture = _ROOM_FURNITURE
                mirror = "east" not in s.openings  # the neighbour door is on the west
                jitter = 0.0 if s.design in cfg.twins else 0.12
            designs[s.design] = _design_boxes(cfg, photos, s, _STYLES[style_of[s.design]], rng, furniture, mirror,
                                              jitter)
        boxes.extend(_place(b, s) for b in designs[s.design])
    lights = []
    for s in layout.spaces:
        sx = s.size[0]
        local = ([(-sx / 4, 0.0), (sx / 4, 0.0)] if s.name != "corridor"
                 else [(-sx / 3, 0.0), (0.0, 0.0), (sx / 3, 0.0)])
        for wx, wy in s.to_world(np.array(local)):  # symmetric in each space: the half turn maps them onto themselves
            lights.append((float(wx), float(wy), cfg.height - 0.1))
    room_cfg = RoomConfig(size=layout.extent, texel_density=cfg.texel_density,
                          object_texel_density=cfg.object_texel_density, seed=cfg.seed, ambient=cfg.ambient,
                          lights=tuple(lights))
    return tensorize(boxes, room_cfg)


@functools.lru_cache(maxsize=2)
def default_building_scene(config: BuildingConfig | None = None) -> Scene:
    """:func:`build_building_scene` on the CPU, built once per process and config: treat it as read-only."""
    return build_building_scene(config)
