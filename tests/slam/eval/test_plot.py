"""trajectory.png: plane choice, alignment, loop edges, axes; all drawn with OpenCV."""
from __future__ import annotations

import math

import cv2
import numpy as np
import pytest
import torch

from slam.eval.plot import PALETTE, Axes, choose_plane, nice_step, plot_trajectory
from slam.io.trajectory import Trajectory
from slam.lie import se3_compose, se3_exp


def _loop_trajectory(n=200, axis_flat=1):
    """Two laps of a 1 m-radius circle (with a wobble), flat along ``axis_flat``."""
    t = torch.arange(n, dtype=torch.float64)
    a = 2 * math.pi * t / (n / 2)
    pos = torch.zeros(n, 3, dtype=torch.float64)
    other = [k for k in range(3) if k != axis_flat]
    pos[:, other[0]] = torch.cos(a) * (1 + 0.1 * torch.sin(3 * a))
    pos[:, other[1]] = torch.sin(a)
    pos[:, axis_flat] = 0.01 * torch.sin(a)
    poses = torch.cat([pos, torch.tensor([[0, 0, 0, 1.0]], dtype=torch.float64).expand(n, 4)], -1)
    return Trajectory(t / 30.0, poses)


def _mask(img, color, tol=40):
    return (np.abs(img.astype(int) - np.array(color)).sum(-1) < tol)


def test_nice_step_and_axes():
    assert [nice_step(s) for s in (1.0, 3.0, 0.12, 12.0, 0.0)] == [0.2, 0.5, 0.02, 2.0, 1.0]
    ax = Axes.fit((400, 300), (0.0, 2.0), (0.0, 1.0), margins=(50, 20, 10, 30), equal=True)
    assert (ax.right - ax.left) / (ax.x1 - ax.x0) == pytest.approx((ax.bottom - ax.top) / (ax.y1 - ax.y0))
    assert ax.to_px([[ax.x0, ax.y0], [ax.x1, ax.y1]]).tolist() == [[50, 270], [390, 20]]
    assert ax.x0 <= 0.0 and ax.x1 >= 2.0 and ax.y0 <= 0.0 and ax.y1 >= 1.0


@pytest.mark.parametrize("flat, plane", [(2, (0, 1)), (1, (0, 2)), (0, (1, 2))])
def test_choose_plane(flat, plane):
    assert choose_plane(_loop_trajectory(axis_flat=flat).positions) == plane
    with pytest.raises(ValueError, match=r"\(N, 3\)"):
        choose_plane(torch.zeros(4, 2))


def test_alignment_puts_estimate_on_ground_truth(tmp_path):
    ref = _loop_trajectory()
    X = se3_exp(torch.tensor([3.0, -1.0, 2.0, 0.3, 1.0, -0.2], dtype=torch.float64))
    moved = Trajectory(ref.timestamps, se3_compose(X.expand(len(ref), 7), ref.poses))
    alone = plot_trajectory(None, ref)  # the estimate drawn where the ground truth is
    aligned = plot_trajectory(tmp_path / "a.png", moved, ref)
    unaligned = plot_trajectory(None, moved, ref, align=False, plane="xz")
    m0, m1, m2 = (_mask(img, PALETTE[0]) for img in (alone, aligned, unaligned))
    iou = (m0 & m1).sum() / (m0 | m1).sum()
    assert iou > 0.9 and m0.sum() > 1000
    assert (m0 & m2).sum() / (m0 | m2).sum() < 0.2
    assert np.array_equal(cv2.imread(str(tmp_path / "a.png")), aligned)
    assert aligned.shape == (700, 800, 3) and aligned.dtype == np.uint8


def test_loop_edges_are_drawn():
    traj = _loop_trajectory()
    without = plot_trajectory(None, traj, traj)
    # loops between points on opposite sides of the circle: long chords, clearly visible
    loops = torch.stack([traj.timestamps[[150, 160]], traj.timestamps[[25, 35]]], -1)
    with_loops = plot_trajectory(None, traj, traj, loops=loops)
    assert _mask(without, PALETTE[1]).sum() == 0
    assert _mask(with_loops, PALETTE[1]).sum() > 300
    # a loop given by timestamps far off any pose still maps to the nearest poses
    plot_trajectory(None, traj, loops=torch.tensor([[-5.0, 1e9]], dtype=torch.float64))


def test_edge_cases_and_errors():
    assert plot_trajectory(None, Trajectory.empty(), size=(300, 200)).shape == (200, 300, 3)
    one = Trajectory(torch.zeros(1, dtype=torch.float64), torch.tensor([[1.0, 2, 3, 0, 0, 0, 1]], dtype=torch.float64))
    assert plot_trajectory(None, one).shape == (700, 800, 3)
    traj = _loop_trajectory()
    far = Trajectory(traj.timestamps + 1000.0, traj.poses)
    with pytest.warns(UserWarning, match="not aligned"):
        plot_trajectory(None, far, traj)
    with pytest.raises(ValueError, match="plane"):
        plot_trajectory(None, traj, plane="xw")
    with pytest.raises(TypeError):
        plot_trajectory(None, traj.poses)
