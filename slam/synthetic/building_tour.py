"""The camera's tour of the building (:mod:`slam.synthetic.building`): a circle looking outwards in each room,
straight lines from door to circle, the corridor's centre line between rooms that are not neighbours. The default
tour starts in ``S1``, visits its twin ``N2`` (the false-loop bait), ``N1`` and ``S2``, and comes back into ``S1``
through its other door.

Example:
    >>> from slam.synthetic.building import building_layout
    >>> traj = building_trajectory(building_layout(), num_frames=50)
    >>> traj.poses.shape
    torch.Size([50, 7])
"""
from __future__ import annotations

import math
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from slam.io.trajectory import Trajectory
from slam.synthetic.building import BuildingConfig, BuildingLayout, building_layout, default_building_scene
from slam.synthetic.render import DepthNoiseConfig, ImageNoiseConfig
from slam.synthetic.sequence import SyntheticSequence, generate_sequence
from slam.synthetic.trajectories import sample_path, view_direction

__all__ = ["BUILDING_DEPTH_NOISE", "BUILDING_IMAGE_NOISE", "DEFAULT_TOUR", "TourConfig", "Visit",
           "building_sequence", "building_trajectory", "generate_building_sequence", "tour_polyline"]

# The building's sensor is a less ideal Kinect v1 than the room demo's: a fixed-pattern disparity distortion,
# axial noise correlated over the sensor's matching blocks, and motion blur (20 ms exposure).
BUILDING_DEPTH_NOISE = DepthNoiseConfig(disparity_distortion=0.1, noise_correlation_px=1.5)
BUILDING_IMAGE_NOISE = ImageNoiseConfig(exposure_time=0.02)


@dataclass(frozen=True)
class Visit:
    """One stay in a room: at least ``turns`` turns of the circle, counter-clockwise when ``sense`` = +1."""

    room: str
    turns: float
    sense: int = 1


DEFAULT_TOUR = (
    Visit("S1", 1.25, +1),  # start: the last quarter turn revisits the first
    Visit("N2", 0.75, -1),  # S1's twin: its views match S1's
    Visit("N1", 0.75, -1),
    Visit("S2", 0.75, +1),
    Visit("S1", 0.75, -1),  # back through the door from S2, circling the other way
)


@dataclass(frozen=True)
class TourConfig:
    """Shape of the tour (metres, degrees).

    Attributes:
        radius: of the circle in each room.
        start_angle_deg: where on the first room's circle the tour starts (0 = east of the centre).
        height: of the camera above the floor.
        pitch_deg: looking slightly down (floors carry texture too).
        lead_deg: on a circle, the heading leads the outward direction by this much towards the travel.
        corridor_pan_deg: amplitude of the heading's sway in the corridor (its walls are seen at a slant).
        corridor_pan_period: metres of path per sway.
        door_glance_deg: going through a door the camera looks this far aside (alternately left and right),
            at the wall beside it rather than at the far side of the next room (beyond the depth range),
            fading over ``door_glance_sigma`` metres of path on either side.
        smoothing: Gaussian sigma (metres of path) of the positions: rounds the corners.
        yaw_smoothing: the same for the heading: spreads the turns.
    """

    radius: float = 0.85
    start_angle_deg: float = 0.0
    height: float = 1.4
    pitch_deg: float = -10.0
    lead_deg: float = 10.0
    corridor_pan_deg: float = 15.0
    corridor_pan_period: float = 4.0
    door_glance_deg: float = 40.0
    door_glance_sigma: float = 0.8
    smoothing: float = 0.25
    yaw_smoothing: float = 0.4


_STEP = 0.01  # metres between polyline samples


def _line(p0: np.ndarray, p1: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Samples of a straight walk from p0 to p1 (end excluded), heading along it."""
    d = p1 - p0
    n = max(1, math.ceil(float(np.linalg.norm(d)) / _STEP))
    f = np.arange(n)[:, None] / n
    yaw = np.full(n, math.atan2(d[1], d[0]))
    return p0 + f * d, yaw


def _arc(center: np.ndarray, radius: float, phi0: float, sweep: float, lead: float) -> tuple[np.ndarray, np.ndarray]:
    """Samples of a circle from angle ``phi0`` over ``sweep`` radians (signed, end excluded), looking out."""
    n = max(1, math.ceil(abs(sweep) * radius / _STEP))
    phi = phi0 + sweep * np.arange(n) / n
    pos = center + radius * np.stack([np.cos(phi), np.sin(phi)], -1)
    return pos, phi + math.copysign(lead, sweep)


def _sweep(phi0: float, phi1: float, sense: int, turns: float) -> float:
    """Signed angle from phi0 to phi1 in direction ``sense`` covering at least ``turns`` turns."""
    d = (sense * (phi1 - phi0)) % (2 * math.pi)
    while d < 2 * math.pi * turns - 1e-9:
        d += 2 * math.pi
    return sense * d


def tour_polyline(layout: BuildingLayout, tour=DEFAULT_TOUR, config: TourConfig | None = None
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The tour as dense samples ~1 cm apart, before smoothing.

    Returns:
        positions ``(S, 2)`` world (x, y), headings ``(S,)`` radians, ``(S,)`` bool: in the corridor, and
        the door centres ``(D, 2)`` crossed, in order.
    """
    cfg = config or TourConfig()
    if not tour:
        raise ValueError("the tour needs at least one visit")
    r, lead = cfg.radius, math.radians(cfg.lead_deg)
    pos, yaw, corr, doors = [], [], [], []

    def add(p, y, in_corridor=False):
        pos.append(p)
        yaw.append(y)
        corr.append(np.full(len(y), in_corridor))

    cw = layout.config.corridor_width
    phi = math.radians(cfg.start_angle_deg)
    for k, visit in enumerate(tour):
        room = layout.space(visit.room)
        c = room.center
        if k == len(tour) - 1:  # end on the circle after exactly ``turns``
            sweep = visit.sense * 2 * math.pi * visit.turns
            add(*_arc(c, r, phi, sweep, lead))
            end = phi + sweep
            add(c[None] + r * np.array([[math.cos(end), math.sin(end)]]), np.array([end + math.copysign(lead, sweep)]))
            break
        nxt = layout.space(tour[k + 1].room)
        try:
            door = layout.door(room.name, nxt.name)
            via_corridor = False
        except KeyError:  # not neighbours: through the corridor
            door = layout.door(room.name, "corridor")
            via_corridor = True
        m = door.normal
        doors.append(door.center)
        phi_out = math.atan2(m[1], m[0])
        add(*_arc(c, r, phi, _sweep(phi, phi_out, visit.sense, visit.turns), lead))
        start = c + r * m
        if via_corridor:
            door_b = layout.door("corridor", nxt.name)
            doors.append(door_b.center)
            y_line = door.center + m * (cw / 2)
            corner = np.array([door_b.center[0], y_line[1]])
            add(*_line(start, y_line))
            add(*_line(y_line, corner), True)
            n_in = door_b.normal
            far = nxt.center + r * n_in
            add(*_line(corner, far))
        else:
            n_in = m
            far = nxt.center + r * n_in
            add(*_line(start, far))
        phi = math.atan2(n_in[1], n_in[0])
    P = np.concatenate(pos)
    Y = np.unwrap(np.concatenate(yaw))
    return P, Y, np.concatenate(corr), np.array(doors).reshape(-1, 2)


def _smooth(x: np.ndarray, sigma_samples: float) -> np.ndarray:
    from scipy.ndimage import gaussian_filter1d

    return gaussian_filter1d(x, sigma_samples, axis=0, mode="nearest") if sigma_samples > 0 else x


def building_trajectory(layout: BuildingLayout, num_frames: int = 2400, seed: int = 0, tour=DEFAULT_TOUR,
                        config: TourConfig | None = None) -> Trajectory:
    """The timed tour: camera-to-world poses ``(num_frames, 7)`` at 30 Hz (see the module docstring).

    Args:
        layout: the building (:func:`slam.synthetic.building.building_layout`).
        num_frames: frames of the whole tour (2400 = 80 s: ~0.7 m/s on the default tour).
        seed: hand-shake seed.
        tour: the :class:`Visit` s in order.
        config: :class:`TourConfig`.
    """
    cfg = config or TourConfig()
    P, Y, corridor, doors = tour_polyline(layout, tour, cfg)
    seg = np.linalg.norm(np.diff(P, axis=0), axis=1)
    arc = np.concatenate([[0.0], np.cumsum(seg)])
    # the sway in the corridor, faded in and out with the smoothing
    pan = math.radians(cfg.corridor_pan_deg) * np.sin(2 * math.pi * arc / cfg.corridor_pan_period)
    weight = _smooth(corridor.astype(np.float64), cfg.yaw_smoothing / _STEP)
    Y = Y + pan * weight
    # a glance at the wall beside each door crossed (left, right, left, ...)
    i = 0
    for k, d in enumerate(doors):
        i += int(np.argmin(np.linalg.norm(P[i:] - d, axis=1)))
        glance = math.radians(cfg.door_glance_deg) * np.exp(-0.5 * ((arc - arc[i]) / cfg.door_glance_sigma) ** 2)
        Y = Y + (-1.0) ** k * glance
    P = _smooth(P, cfg.smoothing / _STEP)
    Y = _smooth(Y, cfg.yaw_smoothing / _STEP)
    # re-measure the arc length of the smoothed path: the sampler's parameter runs along it
    seg = np.linalg.norm(np.diff(P, axis=0), axis=1)
    arc = np.concatenate([[0.0], np.cumsum(seg)])
    u = arc / arc[-1]
    pitch0 = math.radians(cfg.pitch_deg)

    def path(s):
        x = np.interp(s, u, P[:, 0])
        y = np.interp(s, u, P[:, 1])
        yaw = np.interp(s, u, Y)
        a = 2 * math.pi * s * arc[-1] / 7.0  # slow variations, a period every 7 m of path
        z = cfg.height + 0.05 * np.sin(a)
        pitch = pitch0 + math.radians(3.0) * np.sin(1.3 * a)
        return np.stack([x, y, z], -1), view_direction(yaw, pitch), math.radians(1.5) * np.sin(0.7 * a)

    return sample_path(path, num_frames, seed)


def building_sequence(num_frames: int = 2400, seed: int = 0, width: int = 320, height: int = 240,
                      building: BuildingConfig | None = None, **kwargs) -> SyntheticSequence:
    """The building tour as a :class:`~slam.synthetic.sequence.SyntheticSequence` (rendered when read).

    Args:
        num_frames: frames of the tour.
        seed: seeds the sensor noise and the hand shake (the designs have their own ``building.seed``).
        width, height: image size (a quarter of the room demo's pixels by default: 2400 frames render in minutes).
        building: :class:`~slam.synthetic.building.BuildingConfig`.
        **kwargs: passed to :class:`~slam.synthetic.sequence.SyntheticSequence` (the noise models default to
            :data:`BUILDING_DEPTH_NOISE` and :data:`BUILDING_IMAGE_NOISE`).
    """
    cfg = building or BuildingConfig()
    traj = building_trajectory(building_layout(cfg), num_frames=num_frames, seed=seed)
    kwargs.setdefault("depth_noise_config", BUILDING_DEPTH_NOISE)
    kwargs.setdefault("image_noise_config", BUILDING_IMAGE_NOISE)
    return SyntheticSequence(traj, width=width, height=height, seed=seed, scene=default_building_scene(cfg),
                             trajectory_name="building_tour", **kwargs)


def generate_building_sequence(out_dir: str | os.PathLike, trajectory: str = "tour", num_frames: int = 2400,
                               seed: int = 0, width: int = 320, height: int = 240, **kwargs) -> Path:
    """Render the building tour and write it in the TUM RGB-D layout with its ``groundtruth.txt``
    (:func:`slam.synthetic.sequence.generate_sequence`; same files, same determinism by ``seed``).

    Args:
        out_dir: the sequence folder.
        trajectory: ``"tour"`` (the only camera path of the building).
        num_frames, seed, width, height: as for :func:`building_sequence`.
        **kwargs: passed to :func:`~slam.synthetic.sequence.generate_sequence` (workers, progress, noise;
            the noise models default to the building's, as for :func:`building_sequence`).
    """
    if trajectory != "tour":
        raise ValueError(f"the building has one camera path, 'tour'; got {trajectory!r}")
    cfg = BuildingConfig()
    kwargs.setdefault("depth_noise_config", BUILDING_DEPTH_NOISE)
    kwargs.setdefault("image_noise_config", BUILDING_IMAGE_NOISE)
    return generate_sequence(out_dir, trajectory=building_trajectory(building_layout(cfg), num_frames, seed),
                             width=width, height=height, seed=seed, scene=default_building_scene(cfg),
                             trajectory_name="building_tour", **kwargs)
