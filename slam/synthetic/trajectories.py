"""Camera trajectories through the default room (:func:`slam.synthetic.scene.build_room_scene`) with
known revisits, timed for a 30 Hz hand-held RGB-D camera.

Each path is a smooth curve ``s in [0, 1] -> (position, viewing direction, roll)``. The frames are placed
along it so that a combined effort ``sqrt((dl / v_ref)^2 + (dtheta / w_ref)^2)`` grows evenly in time
(slower where the camera turns fast), starting and stopping smoothly; small seeded hand shake is added.

* ``loop``: around the room's centre on a circle of ~0.9 m radius, looking outwards at the walls and the
  objects; a little more than one full turn, so the last frames revisit the first views from ~10 cm
  further out.
* ``figure_eight``: a lemniscate near the room's centre, facing south and panning with the lobes; it
  passes its crossing twice with the same heading and ends where it started (a few cm higher).
* ``out_and_back``: a 3 m sideways sweep facing the north wall, panning, and back along a slightly
  offset line (up to ~25 cm), revisiting every view in reverse order.

Poses are camera-to-world ``(N, 7) = [t, q_xyzw]`` float64 (camera x right, y down, z forward; world z up).

Example:
    >>> traj = make_trajectory("loop", num_frames=50)
    >>> traj.poses.shape, traj.timestamps.shape
    (torch.Size([50, 7]), torch.Size([50]))
"""
from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from typing import Callable

import numpy as np
import torch

from slam.io.trajectory import Trajectory
from slam.lie import quat_mul, rotmat_to_quat, se3_between, so3_exp, so3_log

Tensor = torch.Tensor
logger = logging.getLogger(__name__)

__all__ = [
    "TRAJECTORIES",
    "TrajectoryConfig",
    "figure_eight_trajectory",
    "look_rotation",
    "loop_trajectory",
    "make_trajectory",
    "out_and_back_trajectory",
    "trajectory_rates",
]

ROOM_CENTER = (3.5, 3.0)  # centre of the default 7 x 6 m room


@dataclass(frozen=True)
class TrajectoryConfig:
    """Timing and hand-shake settings shared by all trajectories.

    Attributes:
        fps: frame rate (TUM and 7-Scenes: 30 Hz).
        t0: first timestamp in seconds (a Unix time, like TUM's files).
        ref_speed: linear speed (m/s) weighing translation against rotation when spacing the frames.
        ref_angular_speed: angular speed (deg/s) weighing rotation against translation.
        max_speed: peak linear speed (m/s) above which a warning is logged (too fast for 30 Hz).
        max_angular_speed: peak angular speed (deg/s) above which a warning is logged.
        ramp: fraction of the duration spent accelerating from rest (and again stopping).
        shake_translation: amplitude (m) of the smooth hand shake of the position.
        shake_rotation_deg: amplitude (deg) of the smooth hand shake of the orientation.
    """

    fps: float = 30.0
    t0: float = 1_700_000_000.0
    ref_speed: float = 0.8
    ref_angular_speed: float = 50.0
    max_speed: float = 1.0
    max_angular_speed: float = 60.0
    ramp: float = 0.06
    shake_translation: float = 0.006
    shake_rotation_deg: float = 0.4


def look_rotation(forward: np.ndarray, roll: np.ndarray | None = None) -> np.ndarray:
    """Camera-to-world rotations ``(N, 3, 3)`` looking along ``forward (N, 3)`` with the image's up
    towards world +z, rotated by ``roll (N,)`` radians about the viewing direction."""
    f = forward / np.linalg.norm(forward, axis=-1, keepdims=True)
    up = np.array([0.0, 0.0, 1.0])
    y = -(up - (f @ up)[:, None] * f)  # camera y points down
    y /= np.linalg.norm(y, axis=-1, keepdims=True)
    x = np.cross(y, f)
    R = np.stack([x, y, f], axis=-1)
    if roll is not None:
        c, s = np.cos(roll), np.sin(roll)
        Rz = np.zeros((len(roll), 3, 3))
        Rz[:, 0, 0], Rz[:, 0, 1], Rz[:, 1, 0], Rz[:, 1, 1], Rz[:, 2, 2] = c, -s, s, c, 1.0
        R = R @ Rz
    return R


def view_direction(yaw: np.ndarray, pitch: np.ndarray) -> np.ndarray:
    return np.stack([np.cos(pitch) * np.cos(yaw), np.cos(pitch) * np.sin(yaw), np.sin(pitch)], -1)


# Paths: s (S,) in [0, 1] -> positions (S, 3), forward directions (S, 3), roll (S,) radians.
PathFn = Callable[[np.ndarray], tuple[np.ndarray, np.ndarray, np.ndarray]]


def _loop_path(turns: float = 1.1, radius: float = 0.9, drift: float = 0.1, height: float = 1.35) -> PathFn:
    cx, cy = ROOM_CENTER

    def path(s):
        th = 2 * math.pi * turns * s
        r = radius + drift * s / max(turns, 1e-9)  # ~10 cm further out after one turn: a real revisit
        pos = np.stack([cx + r * np.cos(th), cy + r * np.sin(th), height + 0.06 * np.sin(2 * th)], -1)
        yaw = th + math.radians(10.0)  # outwards, a little towards the direction of travel
        pitch = np.radians(-14.0 + 5.0 * np.sin(3 * th))
        return pos, view_direction(yaw, pitch), np.radians(2.0 * np.sin(th))

    return path


def _figure_eight_path(half_length: float = 1.2, half_width: float = 0.7, center_y: float = 3.3,
                       pivot_y: float = 6.0, height: float = 1.3, climb: float = 0.06) -> PathFn:
    cx, _ = ROOM_CENTER

    def path(s):
        a = 2 * math.pi * s
        x = cx + half_length * np.sin(a)
        y = center_y + half_width * np.sin(a) * np.cos(a)
        # Facing south, away from a pivot behind the camera: it pans with the lobes and passes the
        # crossing twice with the same heading (a revisit half-way through as well as at the end).
        yaw = np.arctan2(y - pivot_y, x - cx)
        pos = np.stack([x, y, height + climb * s], -1)
        pitch = np.radians(-13.0 + 4.0 * np.sin(2 * a))
        return pos, view_direction(yaw, pitch), np.radians(1.5 * np.sin(a))

    return path


def _out_and_back_path(length: float = 3.0, offset: float = 0.12, y_line: float = 3.2,
                       height: float = 1.35) -> PathFn:
    cx, _ = ROOM_CENTER

    def path(s):
        a = 2 * math.pi * s
        x = cx - 0.5 * length * np.cos(a)  # out (s < 0.5) and back, at rest at both ends
        # odd in (s - 0.5): the way back runs up to 2 * offset beside and below the way out
        y = y_line + offset * np.sin(a)
        z = height + 0.5 * offset * np.sin(a)
        yaw = np.radians(90.0 + 30.0 * np.cos(2 * a))  # facing north, panning; equal at s and 1 - s
        pitch = np.radians(-10.0 + 3.0 * np.cos(2 * a))
        return np.stack([x, y, z], -1), view_direction(yaw, pitch), np.zeros_like(s)

    return path


def _speed_profile(tau: np.ndarray, ramp: float) -> np.ndarray:
    """Relative speed over normalised time: cosine ramps up from rest and back down to rest."""
    if ramp <= 0:
        return np.ones_like(tau)
    up = np.clip(tau / ramp, 0, 1)
    down = np.clip((1 - tau) / ramp, 0, 1)
    return 0.5 - 0.5 * np.cos(np.pi * np.minimum(up, down))


def _shake(rng: np.random.Generator, times: np.ndarray, dims: int) -> np.ndarray:
    """Smooth zero-mean noise ``(N, dims)`` with unit-ish amplitude: a few random sinusoids per axis."""
    out = np.zeros((len(times), dims))
    for d in range(dims):
        freqs = rng.uniform(0.2, 1.5, 3)
        phases = rng.uniform(0, 2 * np.pi, 3)
        amps = rng.uniform(0.5, 1.0, 3)
        out[:, d] = (amps[None] * np.sin(2 * np.pi * freqs[None] * times[:, None] + phases[None])).sum(-1) / 2.0
    return out


def sample_path(path: PathFn, num_frames: int, seed: int, cfg: TrajectoryConfig) -> Trajectory:
    if num_frames < 2:
        raise ValueError(f"num_frames must be >= 2, got {num_frames}")
    # Effort along a dense sampling of the path.
    s = np.linspace(0.0, 1.0, 4001)
    pos, fwd, roll = path(s)
    R = torch.from_numpy(look_rotation(fwd, roll))
    dl = np.linalg.norm(np.diff(pos, axis=0), axis=-1)
    dth = so3_log(rotmat_to_quat(R[:-1].transpose(-1, -2) @ R[1:])).norm(dim=-1).numpy()
    effort = np.sqrt((dl / cfg.ref_speed) ** 2 + (dth / math.radians(cfg.ref_angular_speed)) ** 2)
    cum = np.concatenate([[0.0], np.cumsum(effort)])
    cum /= cum[-1]
    # Frames: effort progress follows the integral of the speed profile.
    tau_fine = np.linspace(0.0, 1.0, 20001)
    prog = np.concatenate([[0.0], np.cumsum(_speed_profile(0.5 * (tau_fine[1:] + tau_fine[:-1]), cfg.ramp))])
    prog /= prog[-1]
    tau = np.linspace(0.0, 1.0, num_frames)
    s_frames = np.interp(np.interp(tau, tau_fine, prog), cum, s)
    pos, fwd, roll = path(s_frames)
    Rf = look_rotation(fwd, roll)
    # Hand shake: a smooth body-frame rotation and a world-frame translation, seeded.
    times = np.arange(num_frames) / cfg.fps
    rng = np.random.default_rng(np.random.SeedSequence([int(seed), 314159]))
    pos = pos + cfg.shake_translation * _shake(rng, times, 3)
    dphi = torch.from_numpy(math.radians(cfg.shake_rotation_deg) * _shake(rng, times, 3))
    q = quat_mul(rotmat_to_quat(torch.from_numpy(Rf)), so3_exp(dphi))
    poses = torch.cat([torch.from_numpy(pos), q], -1)
    timestamps = torch.from_numpy(np.round(cfg.t0 + times, 6))
    traj = Trajectory(timestamps=timestamps, poses=poses)
    lin, ang = trajectory_rates(traj)
    if len(lin) and (float(lin.max()) > cfg.max_speed or float(ang.max()) > cfg.max_angular_speed):
        logger.warning("trajectory too fast for %.0f Hz with %d frames: peak %.2f m/s, %.1f deg/s "
                       "(limits %.2f m/s, %.1f deg/s); use more frames", cfg.fps, num_frames,
                       float(lin.max()), float(ang.max()), cfg.max_speed, cfg.max_angular_speed)
    return traj


def trajectory_rates(traj: Trajectory) -> tuple[Tensor, Tensor]:
    """Linear speed ``(N-1,)`` in m/s and angular speed ``(N-1,)`` in deg/s between consecutive poses."""
    dt = (traj.timestamps[1:] - traj.timestamps[:-1]).clamp_min(1e-9)
    rel = se3_between(traj.poses[:-1], traj.poses[1:])
    lin = rel[:, :3].norm(dim=-1) / dt
    ang = torch.rad2deg(so3_log(rel[:, 3:]).norm(dim=-1)) / dt
    return lin, ang


def loop_trajectory(num_frames: int = 300, seed: int = 0, config: TrajectoryConfig | None = None,
                    turns: float = 1.1) -> Trajectory:
    """A loop around the room looking outwards; ``turns`` > 1 makes the end overlap the start."""
    return sample_path(_loop_path(turns=turns), num_frames, seed, config or TrajectoryConfig())


def figure_eight_trajectory(num_frames: int = 300, seed: int = 0,
                            config: TrajectoryConfig | None = None) -> Trajectory:
    """A figure-eight facing the south wall, panning with the lobes, back to its start."""
    return sample_path(_figure_eight_path(), num_frames, seed, config or TrajectoryConfig())


def out_and_back_trajectory(num_frames: int = 300, seed: int = 0,
                            config: TrajectoryConfig | None = None) -> Trajectory:
    """A sideways sweep facing the north wall and back along a slightly offset line."""
    return sample_path(_out_and_back_path(), num_frames, seed, config or TrajectoryConfig())


TRAJECTORIES: dict[str, Callable[..., Trajectory]] = {
    "loop": loop_trajectory,
    "figure_eight": figure_eight_trajectory,
    "out_and_back": out_and_back_trajectory,
}


def make_trajectory(name: str, num_frames: int = 300, seed: int = 0,
                    config: TrajectoryConfig | None = None) -> Trajectory:
    """The trajectory called ``name`` (one of ``TRAJECTORIES``) with ``num_frames`` poses.

    Returns:
        :class:`~slam.io.trajectory.Trajectory` with timestamps ``(N,)`` and poses ``(N, 7)``, float64.
    """
    key = name.replace("-", "_").lower()
    if key not in TRAJECTORIES:
        raise ValueError(f"unknown trajectory {name!r}; choose one of {sorted(TRAJECTORIES)}")
    return TRAJECTORIES[key](num_frames=num_frames, seed=seed, config=config)
