"""Camera trajectories through the default room with known revisits, timed for a 30 Hz hand-held RGB-D camera:
``loop`` (1.1 turns of a ~0.9 m circle looking outwards, revisiting its first views), ``figure_eight`` (a lemniscate
facing south) and ``out_and_back`` (a 3 m sideways sweep facing north and back). Poses are camera-to-world
``(N, 7) = [t, q_xyzw]`` float64 (camera x right, y down, z forward; world z up).

Example:
    >>> traj = make_trajectory("loop", num_frames=50)
    >>> traj.poses.shape, traj.timestamps.shape
    (torch.Size([50, 7]), torch.Size([50]))
"""
from __future__ import annotations

import logging
import math
from typing import Callable

import numpy as np
import torch

from slam.io.trajectory import Trajectory
from slam.lie import quat_mul, rotmat_to_quat, se3_between, so3_exp, so3_log

Tensor = torch.Tensor
logger = logging.getLogger(__name__)

__all__ = [
    "TRAJECTORIES",
    "look_rotation",
    "make_trajectory",
    "trajectory_rates",
]

ROOM_CENTER = (3.5, 3.0)  # centre of the default 7 x 6 m room


# Timing and hand shake of every trajectory
_FPS = 30.0  # frame rate (TUM and 7-Scenes: 30 Hz)
_T0 = 1_700_000_000.0  # first timestamp in seconds (a Unix time, like TUM's files)
_REF_SPEED = 0.8  # m/s weighing translation against rotation when spacing the frames
_REF_ANGULAR_SPEED = 50.0  # deg/s weighing rotation against translation
_MAX_SPEED = 1.0  # m/s: a faster peak linear speed logs a warning (too fast for 30 Hz)
_MAX_ANGULAR_SPEED = 60.0  # deg/s: a faster peak angular speed logs a warning
_RAMP = 0.06  # fraction of the duration spent accelerating from rest (and again stopping)
_SHAKE_TRANSLATION = 0.006  # amplitude (m) of the smooth hand shake of the position
_SHAKE_ROTATION_DEG = 0.4  # amplitude (deg) of the smooth hand shake of the orientation


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


PathFn = Callable[[np.ndarray], tuple[np.ndarray, np.ndarray, np.ndarray]]


def _loop_path(s):
    cx, cy = ROOM_CENTER
    th = 2 * math.pi * 1.1 * s
    r = 0.9 + 0.1 * s / 1.1  # ~10 cm further out after one turn: a real revisit
    pos = np.stack([cx + r * np.cos(th), cy + r * np.sin(th), 1.35 + 0.06 * np.sin(2 * th)], -1)
    yaw = th + math.radians(10.0)  # outwards, a little towards the direction of travel
    pitch = np.radians(-14.0 + 5.0 * np.sin(3 * th))
    return pos, view_direction(yaw, pitch), np.radians(2.0 * np.sin(th))


def _figure_eight_path(s):
    cx, _ = ROOM_CENTER
    a = 2 * math.pi * s
    x = cx + 1.2 * np.sin(a)
    y = 3.3 + 0.7 * np.sin(a) * np.cos(a)
    # facing south, away from a pivot behind the camera: the crossing is passed twice with the same heading
    yaw = np.arctan2(y - 6.0, x - cx)
    pos = np.stack([x, y, 1.3 + 0.06 * s], -1)
    pitch = np.radians(-13.0 + 4.0 * np.sin(2 * a))
    return pos, view_direction(yaw, pitch), np.radians(1.5 * np.sin(a))


def _out_and_back_path(s):
    cx, _ = ROOM_CENTER
    a = 2 * math.pi * s
    x = cx - 0.5 * 3.0 * np.cos(a)  # out (s < 0.5) and back, at rest at both ends
    # odd in (s - 0.5): the way back runs up to 24 cm beside and below the way out
    y = 3.2 + 0.12 * np.sin(a)
    z = 1.35 + 0.5 * 0.12 * np.sin(a)
    yaw = np.radians(90.0 + 30.0 * np.cos(2 * a))  # facing north, panning; equal at s and 1 - s
    pitch = np.radians(-10.0 + 3.0 * np.cos(2 * a))
    return np.stack([x, y, z], -1), view_direction(yaw, pitch), np.zeros_like(s)


def _shake(rng: np.random.Generator, times: np.ndarray, dims: int) -> np.ndarray:
    """Smooth zero-mean noise ``(N, dims)`` with unit-ish amplitude: a few random sinusoids per axis."""
    out = np.zeros((len(times), dims))
    for d in range(dims):
        freqs = rng.uniform(0.2, 1.5, 3)
        phases = rng.uniform(0, 2 * np.pi, 3)
        amps = rng.uniform(0.5, 1.0, 3)
        out[:, d] = (amps[None] * np.sin(2 * np.pi * freqs[None] * times[:, None] + phases[None])).sum(-1) / 2.0
    return out


def sample_path(path: PathFn, num_frames: int, seed: int) -> Trajectory:
    """``num_frames`` frames along ``path`` (``s in [0, 1] -> (position, viewing direction, roll)``), spaced so that
    the effort ``sqrt((dl / v_ref)^2 + (dtheta / w_ref)^2)`` grows evenly in time, starting and stopping smoothly,
    with a seeded hand shake."""
    if num_frames < 2:
        raise ValueError(f"num_frames must be >= 2, got {num_frames}")
    # Effort along a dense sampling of the path.
    s = np.linspace(0.0, 1.0, 4001)
    pos, fwd, roll = path(s)
    R = torch.from_numpy(look_rotation(fwd, roll))
    dl = np.linalg.norm(np.diff(pos, axis=0), axis=-1)
    dth = so3_log(rotmat_to_quat(R[:-1].transpose(-1, -2) @ R[1:])).norm(dim=-1).numpy()
    effort = np.sqrt((dl / _REF_SPEED) ** 2 + (dth / math.radians(_REF_ANGULAR_SPEED)) ** 2)
    cum = np.concatenate([[0.0], np.cumsum(effort)])
    cum /= cum[-1]
    # Frames: effort progress follows the integral of the speed, cosine ramps up from rest and back down to rest.
    tau_fine = np.linspace(0.0, 1.0, 20001)
    mid = 0.5 * (tau_fine[1:] + tau_fine[:-1])
    speed = 0.5 - 0.5 * np.cos(np.pi * np.minimum(np.clip(mid / _RAMP, 0, 1), np.clip((1 - mid) / _RAMP, 0, 1)))
    prog = np.concatenate([[0.0], np.cumsum(speed)])
    prog /= prog[-1]
    tau = np.linspace(0.0, 1.0, num_frames)
    s_frames = np.interp(np.interp(tau, tau_fine, prog), cum, s)
    pos, fwd, roll = path(s_frames)
    Rf = look_rotation(fwd, roll)
    # Hand shake: a smooth body-frame rotation and a world-frame translation, seeded.
    times = np.arange(num_frames) / _FPS
    rng = np.random.default_rng(np.random.SeedSequence([int(seed), 314159]))
    pos = pos + _SHAKE_TRANSLATION * _shake(rng, times, 3)
    dphi = torch.from_numpy(math.radians(_SHAKE_ROTATION_DEG) * _shake(rng, times, 3))
    q = quat_mul(rotmat_to_quat(torch.from_numpy(Rf)), so3_exp(dphi))
    poses = torch.cat([torch.from_numpy(pos), q], -1)
    timestamps = torch.from_numpy(np.round(_T0 + times, 6))
    traj = Trajectory(timestamps=timestamps, poses=poses)
    lin, ang = trajectory_rates(traj)
    if len(lin) and (float(lin.max()) > _MAX_SPEED or float(ang.max()) > _MAX_ANGULAR_SPEED):
        logger.warning("trajectory too fast for %.0f Hz with %d frames: peak %.2f m/s, %.1f deg/s "
                       "(limits %.2f m/s, %.1f deg/s); use more frames", _FPS, num_frames,
                       float(lin.max()), float(ang.max()), _MAX_SPEED, _MAX_ANGULAR_SPEED)
    return traj


def trajectory_rates(traj: Trajectory) -> tuple[Tensor, Tensor]:
    """Linear speed ``(N-1,)`` in m/s and angular speed ``(N-1,)`` in deg/s between consecutive poses."""
    dt = (traj.timestamps[1:] - traj.timestamps[:-1]).clamp_min(1e-9)
    rel = se3_between(traj.poses[:-1], traj.poses[1:])
    lin = rel[:, :3].norm(dim=-1) / dt
    ang = torch.rad2deg(so3_log(rel[:, 3:]).norm(dim=-1)) / dt
    return lin, ang


# name -> path: s (S,) in [0, 1] -> positions (S, 3), forward directions (S, 3), roll (S,) radians
TRAJECTORIES: dict[str, PathFn] = {
    "loop": _loop_path,
    "figure_eight": _figure_eight_path,
    "out_and_back": _out_and_back_path,
}


def make_trajectory(name: str, num_frames: int = 300, seed: int = 0) -> Trajectory:
    """The trajectory called ``name`` (one of ``TRAJECTORIES``) with ``num_frames`` poses.

    Returns:
        :class:`~slam.io.trajectory.Trajectory` with timestamps ``(N,)`` and poses ``(N, 7)``, float64.
    """
    key = name.replace("-", "_").lower()
    if key not in TRAJECTORIES:
        raise ValueError(f"unknown trajectory {name!r}; choose one of {sorted(TRAJECTORIES)}")
    return sample_path(TRAJECTORIES[key], num_frames, seed)
