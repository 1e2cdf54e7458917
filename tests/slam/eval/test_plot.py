"""trajectory.png (matplotlib): the PNG at its size, the plane, the error colouring with a reference, loop edges."""
from __future__ import annotations

import math

import cv2
import numpy as np
import pytest
import torch

from slam.eval.plot import choose_plane, plot_trajectory
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


def _count(img, rgb, tol=40) -> int:
    """Pixels of ``img`` (BGR) within ``tol`` of the colour ``rgb``."""
    return int((np.abs(img.astype(int) - np.array(rgb[::-1])).sum(-1) < tol).sum())


#: matplotlib's first colour (an estimate without error colouring) and its fourth (loop edges); the two ends of
#: the jet colour map (the smallest and the largest error)
C0, C3, JET_LOW, JET_HIGH = (31, 119, 180), (214, 39, 40), (0, 0, 127), (127, 0, 0)


@pytest.mark.parametrize("flat, plane", [(2, (0, 1)), (1, (0, 2)), (0, (1, 2))])
def test_choose_plane(flat, plane):
    assert choose_plane(_loop_trajectory(axis_flat=flat).positions) == plane
    with pytest.raises(ValueError, match=r"\(N, 3\)"):
        choose_plane(torch.zeros(4, 2))


def test_png_written_at_its_size(tmp_path):
    ref = _loop_trajectory()
    X = se3_exp(torch.tensor([3.0, -1.0, 2.0, 0.3, 1.0, -0.2], dtype=torch.float64))
    noisy = ref.poses.clone()
    noisy[:, :3] += 0.02 * torch.randn(len(ref), 3, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    moved = Trajectory(ref.timestamps, se3_compose(X.expand(len(ref), 7), noisy))
    for name, args, kwargs, shape in (("alone.png", (moved,), {}, (700, 800, 3)),
                                      ("sub/ate.png", (moved, ref), {}, (600, 1300, 3)),
                                      ("small.png", (moved, ref), {"size": (500, 300)}, (300, 500, 3))):
        img = plot_trajectory(tmp_path / name, *args, **kwargs)
        assert img.shape == shape and img.dtype == np.uint8 and (tmp_path / name).stat().st_size > 0
        assert np.array_equal(cv2.imread(str(tmp_path / name)), img)


def test_each_pose_coloured_by_its_error_with_a_reference():
    ref = _loop_trajectory()
    noisy = ref.poses.clone()
    noisy[:, :3] += 0.02 * torch.randn(len(ref), 3, generator=torch.Generator().manual_seed(1), dtype=torch.float64)
    est = Trajectory(ref.timestamps, noisy)
    coloured = plot_trajectory(None, est, ref)
    plain = plot_trajectory(None, est, ref, align=False)
    assert _count(coloured, JET_LOW) > 20 and _count(coloured, JET_HIGH) > 20  # the least and the most wrong poses
    assert _count(plain, JET_LOW) == 0 and _count(plain, C0) > 500


def test_loop_edges_are_drawn():
    traj = _loop_trajectory()
    without = plot_trajectory(None, traj)
    # loops between points on opposite sides of the circle: long chords, clearly visible
    loops = torch.stack([traj.timestamps[[150, 160]], traj.timestamps[[25, 35]]], -1)
    with_loops = plot_trajectory(None, traj, loops=loops)
    assert _count(without, C3) == 0 and _count(with_loops, C3) > 300
    # a loop given by timestamps far off any pose still maps to the nearest poses
    plot_trajectory(None, traj, loops=torch.tensor([[-5.0, 1e9]], dtype=torch.float64))


def test_edge_cases_and_errors():
    assert plot_trajectory(None, Trajectory.empty(), size=(300, 200)).shape == (200, 300, 3)
    one = Trajectory(torch.zeros(1, dtype=torch.float64), torch.tensor([[1.0, 2, 3, 0, 0, 0, 1]], dtype=torch.float64))
    assert plot_trajectory(None, one).shape == (700, 800, 3)
    traj = _loop_trajectory()
    far = Trajectory(traj.timestamps + 1000.0, traj.poses)
    with pytest.warns(UserWarning, match="not aligned"):
        assert plot_trajectory(None, far, traj).shape == (700, 800, 3)  # no error panel without an ATE
    with pytest.raises(ValueError, match="plane"):
        plot_trajectory(None, traj, plane="xw")
    with pytest.raises(ValueError, match="size"):
        plot_trajectory(None, traj, size=(0, 100))
    with pytest.raises(TypeError):
        plot_trajectory(None, traj.poses)
