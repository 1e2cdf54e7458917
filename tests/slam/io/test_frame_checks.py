"""RGBDFrame: programming mistakes are errors that say what was expected, not frames the tracker calls lost."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from slam.config import override
from slam.io import RGBDFrame, check_intrinsics
from slam.io.frame import MAX_DEPTH_MEDIAN

H, W = 48, 64
K = np.array([[525.0, 0.0, 31.5], [0.0, 525.0, 23.5], [0.0, 0.0, 1.0]])
RGB = np.zeros((H, W, 3), np.uint8)
DEPTH = np.full((H, W), 1.5, np.float32)


def _frame(**kw):
    args = dict(index=0, timestamp=0.0, rgb=RGB, depth=DEPTH, K=K)
    args.update(kw)
    return RGBDFrame(**args)


@pytest.mark.parametrize("kw, error, pattern", [
    # depth
    (dict(depth=np.full((H, W), 1500, np.uint16)), TypeError,
     r"depth must be float32 metres, got uint16 \(48, 64\); divide by your depth scale \(TUM 5000, Kinect millimetres"),
    (dict(depth=np.full((H, W), 1500.0, np.float32)), ValueError, r"median valid value is 1500 .*millimetres or raw"),
    (dict(depth=np.full((H, W), 7500.0, np.float64)), ValueError, r"median valid value is 7500"),
    (dict(depth=-DEPTH), ValueError, r"depth has negative values \(min -1.5\)"),
    (dict(depth=DEPTH[:, :10]), ValueError, r"depth is 10x48 but rgb is 64x48"),
    (dict(depth=np.zeros((H, W, 2), np.float32)), ValueError, r"depth must have shape \(H, W\), got \(48, 64, 2\)"),
    (dict(depth=torch.from_numpy(DEPTH)), TypeError, r"depth must be a numpy array .* got a torch tensor; pass x.cpu"),
    (dict(depth=DEPTH.tolist()), TypeError, r"depth must be a numpy array \(H, W\) float32 metres, got list"),
    # colour
    (dict(rgb=RGB[..., 0]), ValueError, r"rgb must be \(H, W, 3\) RGB, got a greyscale image \(48, 64\); convert it"),
    (dict(rgb=RGB[..., :1]), ValueError, r"greyscale image \(48, 64, 1\)"),
    (dict(rgb=np.zeros((H, W, 4), np.uint8)), ValueError, r"rgb must have shape \(H, W, 3\), got \(48, 64, 4\)"),
    (dict(rgb=RGB.astype(np.float32) / 255), TypeError, r"rgb must be uint8 in \[0, 255\], got float32 \(floats in"),
    (dict(rgb=torch.zeros(3, H, W, dtype=torch.uint8)), TypeError, r"rgb must be a numpy array .* got a torch tensor"),
    # intrinsics
    (dict(K=torch.from_numpy(K)), TypeError, r"K must be a numpy array \(3, 3\) float64, got a torch"),
    (dict(K=K[:2]), ValueError, r"K must have shape \(3, 3\), got \(2, 3\)"),
    (dict(K=np.zeros((3, 3))), ValueError, r"K must have focal lengths fx = K\[0, 0\] > 0 and fy = K\[1, 1\] > 0"),
    (dict(K=np.where(np.eye(3) > 0, np.nan, K)), ValueError, r"K has a non-finite entry"),
    (dict(K=K.T), ValueError, r"K must be a pinhole matrix \[\[fx, s, cx\], \[0, fy, cy\], \[0, 0, 1\]\]"),
    (dict(K="525 525 320 240"), TypeError, r"K must be a \(3, 3\) array of numbers, got str"),
    # the rest
    (dict(timestamp=float("nan")), ValueError, r"timestamp must be finite, got nan"),
    (dict(timestamp="0.1"), TypeError, r"timestamp must be a number of seconds, got str"),
    (dict(index=1.0), TypeError, r"index must be an int, got float"),
    (dict(pose_gt=[0, 0, 0, 0, 0, 0, 0]), ValueError, r"pose_gt has a zero quaternion"),
    (dict(pose_gt=[0, 0, np.nan, 0, 0, 0, 1]), ValueError, r"pose_gt has a non-finite value: .* \(use None for an"),
    (dict(pose_gt=[1e300, 0, 0, 0, 0, 0, 1]), ValueError, r"pose_gt has a translation beyond 1e\+09 m"),
    (dict(pose_gt=np.eye(4)), ValueError, r"pose_gt must have shape \(7,\)"),
])
def test_mistakes_raise_what_was_expected(kw, error, pattern):
    with pytest.raises(error, match=pattern):
        _frame(**kw)


def test_what_is_converted_silently():
    f = _frame(K=K.tolist(), depth=DEPTH.astype(np.float64), pose_gt=[1, 2, 3, 1e200, 1e200, 0, 0])
    assert f.K.dtype == np.float64 and np.array_equal(f.K, K)
    assert f.depth.dtype == np.float32 and np.array_equal(f.depth, DEPTH)
    assert f.pose_gt.dtype == np.float64 and np.allclose(f.pose_gt, [1, 2, 3, 0.5 ** 0.5, 0.5 ** 0.5, 0, 0])
    assert _frame(K=np.array([[500, 0, 32], [0, 500, 24], [0, 0, 1]])).K.dtype == np.float64  # integer K
    d = DEPTH.copy()
    d[0, :3] = [np.nan, np.inf, 0.0]  # ROS float depth: NaN / +inf = no measurement
    f = _frame(depth=d)
    assert f.depth[0, :3].tolist() == [0.0, 0.0, 0.0] and np.isfinite(f.depth).all()
    assert np.isnan(d[0, 0])  # the caller's array is not modified
    # a few far pixels are not "millimetres": the median of the valid depth decides
    d = DEPTH.copy()
    d[:5] = 3 * MAX_DEPTH_MEDIAN
    assert _frame(depth=d).depth.max() == 3 * MAX_DEPTH_MEDIAN
    one = RGBDFrame(0, 0.0, np.zeros((1, 1, 3), np.uint8), np.zeros((1, 1), np.float32), K)  # tiny, but well-formed
    assert one.shape == (1, 1)
    assert check_intrinsics([[1, 0, 0], [0, 1, 0], [0, 0, 1]], "mine").tolist() == np.eye(3).tolist()
    with pytest.raises(ValueError, match="^mine must have shape"):
        check_intrinsics(np.eye(4), "mine")


def test_real_frames_pass_unchanged(redkitchen_dir):
    from slam.io import check_frame, open_sequence

    f = open_sequence(redkitchen_dir)[100]
    before = (f.rgb.copy(), f.depth.copy(), f.K.copy(), f.pose_gt.copy())
    check_frame(f)
    for a, b in zip(before, (f.rgb, f.depth, f.K, f.pose_gt)):
        assert np.array_equal(a, b)


# the same mistakes at RGBDSLAM.track(): a field set after construction (frame.depth = depth_mm), or a frame that
# is not an RGBDFrame, is the same error, raised before anything is tracked
@pytest.mark.parametrize("field, value, error, pattern", [
    ("depth", np.full((H, W), 1500, np.uint16), TypeError, r"depth must be float32 metres, got uint16"),
    ("depth", np.full((H, W), 1500.0, np.float32), ValueError, r"median valid value is 1500 .*millimetres"),
    ("depth", torch.from_numpy(DEPTH), TypeError, r"depth must be a numpy array .* got a torch tensor"),
    ("depth", DEPTH[:, :10], ValueError, r"depth is 10x48 but rgb is 64x48"),
    ("rgb", RGB[..., 0], ValueError, r"greyscale image \(48, 64\); convert it"),
    ("rgb", RGB.astype(np.float32), TypeError, r"rgb must be uint8 in \[0, 255\], got float32"),
    ("rgb", torch.zeros(H, W, 3, dtype=torch.uint8), TypeError, r"rgb must be a numpy array .* got a torch tensor"),
    ("K", K[:2], ValueError, r"K must have shape \(3, 3\), got \(2, 3\)"),
    ("K", "525 525 31.5 23.5", TypeError, r"K must be a \(3, 3\) array of numbers, got str"),
    ("K", torch.from_numpy(K), TypeError, r"K must be a numpy array \(3, 3\) float64, got a torch"),
])
def test_track_refuses_the_same_mistakes(field, value, error, pattern):
    from slam.config import SLAMConfig
    from slam.system import RGBDSLAM

    cfg = SLAMConfig()
    cfg = override(cfg, {"loop.enabled": False})
    slam = RGBDSLAM(cfg)
    good = _frame()
    assert slam.track(good).status == "lost"  # a blank frame: lost, not an error
    bad = _frame(index=1, timestamp=0.1)
    setattr(bad, field, value)
    with pytest.raises(error, match=pattern):
        slam.track(bad)
    assert len(slam.finish().trajectory) == 1  # nothing of the bad frame was recorded


def test_track_takes_only_frames():
    from slam.config import SLAMConfig
    from slam.system import RGBDSLAM

    cfg = SLAMConfig()
    cfg = override(cfg, {"loop.enabled": False})
    with pytest.raises(TypeError, match=r"track\(\) takes a slam.io.RGBDFrame, got dict"):
        RGBDSLAM(cfg).track(dict(index=0, timestamp=0.0, rgb=RGB, depth=DEPTH, K=K))
