"""The built-in scenes of ``attnloop-slam --demo --demo-scene NAME`` (its choices and defaults); a new scene is one
entry of :data:`DEMO_SCENES`.

Example:
    >>> sorted(DEMO_SCENES), DEMO_SCENES["room"].default_trajectory, DEMO_SCENES["building"].default_size
    (['building', 'room'], 'loop', (320, 240))
"""
from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

from slam.synthetic.trajectories import TRAJECTORIES

__all__ = ["DEFAULT_DEMO_SCENE", "DEMO_SCENES", "DemoScene", "generate_demo"]


@dataclass(frozen=True)
class DemoScene:
    """One demo scene.

    Attributes:
        description: one line for ``--help``.
        generate: ``generate(out_dir, trajectory=, num_frames=, seed=, width=, height=, progress=)`` writes the
            sequence (TUM layout with ``groundtruth.txt``) into ``out_dir`` and returns it; ``progress`` logs its
            advance (logger ``slam.synthetic``).
        trajectories: the camera paths it offers.
        default_trajectory: the one used when none is asked for.
        default_frames: its default length.
        min_frames: the shortest sequence that can be tracked and evaluated (fewer is a usage error).
        default_size: its default image size (width, height).
    """

    description: str
    generate: Callable[..., Path]
    trajectories: tuple[str, ...]
    default_trajectory: str
    default_frames: int
    min_frames: int = 10
    default_size: tuple[int, int] = (640, 480)


def _room(out_dir, **kwargs) -> Path:
    from slam.synthetic.sequence import generate_sequence  # imported when used: the CLI's --help stays light

    return generate_sequence(out_dir, **kwargs)


def _building(out_dir, **kwargs) -> Path:
    from slam.synthetic.building_tour import generate_building_sequence

    return generate_building_sequence(out_dir, **kwargs)


DEMO_SCENES: dict[str, DemoScene] = {
    "room": DemoScene("one photo-textured 7 x 6 m room, a loop back to the first views",
                      _room, tuple(TRAJECTORIES), "loop", 300),
    # 320 x 240 by default: a quarter of the room's pixels, for 8 times its frames
    "building": DemoScene("four rooms around a corridor, two of them furnished identically (perceptual "
                          "aliasing); a 53 m tour back into the first room through its other door",
                          _building, ("tour",), "tour", 2400, min_frames=60, default_size=(320, 240)),
}
DEFAULT_DEMO_SCENE = "room"


def generate_demo(out_dir: str | os.PathLike, scene: str = DEFAULT_DEMO_SCENE, trajectory: str | None = None,
                  num_frames: int | None = None, seed: int = 0, width: int | None = None,
                  height: int | None = None, progress: bool = False) -> Path:
    """Generate the sequence of demo scene ``scene`` into ``out_dir`` (its defaults where None).

    Raises:
        ValueError: an unknown scene or trajectory, fewer frames than the scene's ``min_frames``, or a
            non-positive image size (the message lists the choices).
    """
    if scene not in DEMO_SCENES:
        raise ValueError(f"unknown demo scene {scene!r}; choose one of {', '.join(DEMO_SCENES)}")
    s = DEMO_SCENES[scene]
    trajectory = s.default_trajectory if trajectory is None else trajectory
    if trajectory not in s.trajectories:
        raise ValueError(f"demo scene {scene!r} has no trajectory {trajectory!r}; choose one of "
                         f"{', '.join(s.trajectories)}")
    n = s.default_frames if num_frames is None else int(num_frames)
    width = s.default_size[0] if width is None else width
    height = s.default_size[1] if height is None else height
    if n < s.min_frames:
        raise ValueError(f"demo scene {scene!r} needs at least {s.min_frames} frames, got {n}")
    if int(width) < 16 or int(height) < 16:
        raise ValueError(f"demo images must be at least 16 x 16 pixels, got {width} x {height}")
    return s.generate(out_dir, trajectory=trajectory, num_frames=n, seed=int(seed), width=int(width),
                      height=int(height), progress=bool(progress))
