"""7-Scenes reader: generated folders, the shared redkitchen sequence, error paths."""
from __future__ import annotations

import logging
import warnings

import cv2
import numpy as np
import pytest
import torch

from slam.io import (
    DatasetError,
    DatasetNotFoundError,
    DatasetWarning,
    FrameReadError,
    SevenScenesSequence,
    open_sequence,
)
from slam.lie import se3_exp, se3_to_matrix

H, W = 24, 32


def _pose_matrix(k: int) -> np.ndarray:
    xi = torch.tensor([0.1 * k, -0.2, 0.3 + k, 0.2, -0.1 * k, 0.5], dtype=torch.float64)
    return se3_to_matrix(se3_exp(xi)).numpy()


def _write_frame(root, number, ext="jpg", depth_mm=1500, pose=True):
    stem = root / f"frame-{number:06d}"
    img = np.zeros((H, W, 3), np.uint8)
    img[..., 2] = 250  # red on disk (BGR)
    cv2.imwrite(f"{stem}.color.{ext}", img)
    d = np.full((H, W), depth_mm, np.uint16)
    d[0, 0], d[0, 1] = 0, 65535
    cv2.imwrite(f"{stem}.depth.png", d)
    if pose is True:
        np.savetxt(f"{stem}.pose.txt", _pose_matrix(number))
    elif pose is not None:
        (root / f"frame-{number:06d}.pose.txt").write_text(pose)


@pytest.fixture
def scenes_dir(tmp_path):
    root = tmp_path / "seq-01"
    root.mkdir()
    for k in (0, 1, 2, 5):  # frame 3 and 4 dropped: numbering need not be contiguous
        _write_frame(root, k, depth_mm=1000 + k)
    return root


def test_generated_folder(scenes_dir):
    seq = open_sequence(scenes_dir)
    assert isinstance(seq, SevenScenesSequence) and len(seq) == 4 and seq.name == "seq-01"
    assert np.array_equal(seq.K, [[585, 0, 320], [0, 585, 240], [0, 0, 1]])  # no intrinsics file
    assert seq.timestamps.dtype == np.float64
    assert np.allclose(seq.timestamps, [0, 1 / 30, 2 / 30, 5 / 30])
    f = seq[3]
    assert f.index == 3 and f.timestamp == pytest.approx(5 / 30)
    assert f.rgb.shape == (H, W, 3) and f.rgb.dtype == np.uint8 and f.rgb[4, 4, 0] >= 245  # RGB order
    assert f.depth.dtype == np.float32 and f.depth[5, 5] == np.float32(1.005)
    assert f.depth[0, 0] == 0.0 and f.depth[0, 1] == 0.0  # 0 and 65535 are invalid
    # pose: camera-to-world 4x4 -> [t, q_xyzw]
    assert np.allclose(se3_to_matrix(torch.from_numpy(f.pose_gt)).numpy(), _pose_matrix(5), atol=1e-12)
    gt = seq.groundtruth
    assert len(gt) == 4 and np.allclose(gt.timestamps.numpy(), seq.timestamps)
    assert np.allclose(gt.poses[3].numpy(), f.pose_gt, atol=1e-12)
    assert np.allclose(seq[3].pose_gt, f.pose_gt)  # via the cached array now
    assert f.rgb_path.endswith("frame-000005.color.jpg") and f.depth_path.endswith("frame-000005.depth.png")


def test_intrinsics_file_png_preference_and_missing_poses(tmp_path):
    root = tmp_path / "seq"
    root.mkdir()
    _write_frame(root, 0, ext="png")
    _write_frame(root, 0, ext="jpg")
    _write_frame(root, 1, pose=None)
    _write_frame(root, 2, pose="-inf -inf -inf -inf\n" * 4)  # 7-Scenes' mark for lost tracking
    np.savetxt(root / "camera-intrinsics.txt", [[500, 0, 16], [0, 501, 12], [0, 0, 1]])
    seq = SevenScenesSequence(root)
    assert len(seq) == 3 and seq.K[1, 1] == 501.0
    assert seq.paths(0)[0].name == "frame-000000.color.png"
    assert seq[0].pose_gt is not None and seq[1].pose_gt is None and seq[2].pose_gt is None
    gt = seq.groundtruth
    assert len(gt) == 1 and gt.timestamps.tolist() == [0.0]
    K = np.diag([1.0, 2.0, 1.0])
    assert np.array_equal(open_sequence(root, K=K)[0].K, K)
    with pytest.raises(DatasetError, match="TUM sequences only"):
        open_sequence(root, camera="fr1")


def test_laziness_open_never_decodes(tmp_path):
    """A folder of undecodable files opens fine: images are read only in __getitem__."""
    root = tmp_path / "lazy"
    root.mkdir()
    for k in range(50):
        (root / f"frame-{k:06d}.color.png").write_bytes(b"garbage")
        (root / f"frame-{k:06d}.depth.png").write_bytes(b"garbage")
    seq = open_sequence(root)
    assert len(seq) == 50 and seq.groundtruth is None
    with pytest.raises(FrameReadError, match="frame-000007.color.png: not a decodable image"):
        seq[7]


def test_errors(tmp_path, scenes_dir, caplog):
    with pytest.raises(DatasetNotFoundError):
        SevenScenesSequence(tmp_path / "missing")
    empty = tmp_path / "empty"
    empty.mkdir()
    with pytest.raises(DatasetError, match="no 7-Scenes colour frames"):
        SevenScenesSequence(empty)
    scene = tmp_path / "redkitchen"
    (scene / "seq-01").mkdir(parents=True)
    with pytest.raises(DatasetError, match="open one of its sequences.*seq-01"):
        open_sequence(scene)

    (scenes_dir / "frame-000001.depth.png").unlink()
    with pytest.raises(FrameReadError, match="frame-000001.depth.png: file does not exist"):
        SevenScenesSequence(scenes_dir)[1]
    cv2.imwrite(str(scenes_dir / "frame-000002.depth.png"), np.zeros((H, W // 2), np.uint16))
    with pytest.raises(FrameReadError, match="16x24 but the colour image is 32x24"):
        SevenScenesSequence(scenes_dir)[2]
    seq = SevenScenesSequence(scenes_dir)
    with caplog.at_level(logging.WARNING):
        assert [f.index for f in seq.frames(on_error="skip")] == [0, 3]
    assert caplog.text.count("skipping frame") == 2
    (scenes_dir / "frame-000000.pose.txt").write_text("1 2 3\n")
    with pytest.warns(DatasetWarning, match=r"frame-000000.pose.txt: expected 16 numbers \(4x4\), got 3"):
        f = SevenScenesSequence(scenes_dir)[0]  # the frame keeps its images; only its ground truth is unknown
    assert f.pose_gt is None and f.rgb.shape == (H, W, 3)
    with pytest.warns(DatasetWarning, match="ground truth unknown for 1 frame"):
        assert len(SevenScenesSequence(scenes_dir).groundtruth) == 3
    (scenes_dir / "camera-intrinsics.txt").write_text("585 0 320\n0 585 240\n")
    with pytest.raises(DatasetError, match="camera-intrinsics.txt: expected 9 numbers"):
        SevenScenesSequence(scenes_dir)


def test_redkitchen(redkitchen_dir):
    seq = open_sequence(redkitchen_dir)
    assert isinstance(seq, SevenScenesSequence) and len(seq) == 1000
    assert seq.K[0, 0] == 585.0 and seq.K[1, 2] == 240.0
    assert seq.timestamps[-1] == pytest.approx(999 / 30)
    f = seq[500]
    assert f.rgb.shape == (480, 640, 3) and f.depth.shape == (480, 640) and f.depth.dtype == np.float32
    valid = f.depth[f.depth > 0]
    assert 0.5 * f.depth.size < valid.size and 0.3 < float(np.median(valid)) < 5.0 and valid.max() < 10
    T = np.loadtxt(redkitchen_dir / "frame-000500.pose.txt")
    assert abs(np.linalg.det(T[:3, :3]) - 1) > 1e-4  # KinectFusion's rotations are not orthonormal
    U, _, Vt = np.linalg.svd(T[:3, :3])
    T[:3, :3] = U @ Vt  # the nearest rotation
    assert np.allclose(se3_to_matrix(torch.from_numpy(f.pose_gt)).numpy(), T, atol=1e-12)
    gt = seq.groundtruth
    assert len(gt) == 1000
    # README: start and end are 0.29 m apart; frames ~240-270 are revisited at ~940-960
    assert float((gt.poses[0, :3] - gt.poses[-1, :3]).norm()) == pytest.approx(0.29, abs=0.01)
    assert float((gt.poses[255, :3] - gt.poses[950, :3]).norm()) < 0.5


def test_a_frame_decodes_each_of_its_images_once(scenes_dir, monkeypatch):
    """Reading a frame decodes its colour file and its depth file once each, and nothing else (the frame
    rate relies on it: a second decode would double the reader's ~5 ms; benchmarks/io_read.py times it)."""
    decoded = []
    real_imdecode = cv2.imdecode

    def counting_imdecode(buf, flags):
        decoded.append(len(buf))
        return real_imdecode(buf, flags)

    monkeypatch.setattr(cv2, "imdecode", counting_imdecode)
    monkeypatch.setattr(cv2, "imread", lambda *a, **k: pytest.fail("cv2.imread called: a second decoding path"))
    seq = open_sequence(scenes_dir)
    depth_sizes = [(scenes_dir / f"frame-{k:06d}.depth.png").stat().st_size for k in (0, 1, 2)]
    assert decoded == depth_sizes  # opening: the depth-unit check's three depth images, once per sequence
    decoded.clear()
    for i, number in enumerate((0, 1, 2, 5)):
        f = seq[i]
        assert f.rgb.shape == (H, W, 3) and f.depth.shape == (H, W)
        sizes = [(scenes_dir / f"frame-{number:06d}.{kind}").stat().st_size for kind in ("color.jpg", "depth.png")]
        assert decoded[2 * i:] == sizes  # the two files of this frame, in full, once each
    assert len(decoded) == 8


@pytest.mark.parametrize("text, reason", [
    ("0 0 0 1\n0 0 0 2\n0 0 0 3\n0 0 0 1\n", r"rotation block is not a rotation \(singular values \[0.0, 0.0, 0.0\]"),
    ("-1 0 0 1\n0 1 0 2\n0 0 1 3\n0 0 0 1\n", r"rotation block is not a rotation .*determinant -1"),
    ("2 0 0 1\n0 2 0 2\n0 0 2 3\n0 0 0 1\n", r"rotation block is not a rotation \(singular values \[2.0, 2.0, 2.0\]"),
    ("1 0 0 1e300\n0 1 0 2\n0 0 1 3\n0 0 0 1\n", r"translation .* is beyond 1e\+09 m"),
    ("1 0 0 1\n0 1 0 2\n0 0 1 3\n0 0 1 1\n", r"last row is \[0.0, 0.0, 1.0, 1.0\], expected \[0, 0, 0, 1\]"),
    ("1 0 0 1\n0 1 0 2\n0 0 1 3\n", r"expected 16 numbers \(4x4\), got 12"),
    ("tracking lost\n", r"frame-000001.pose.txt:1: expected 4x4 numbers, got 'tracking lost'"),
    (b"1 0 0 1\n0 1 0 2\n0 0 1 3 \xe9\n0 0 0 1\n", r"frame-000001.pose.txt:3: byte 0xe9 at column 9 is not UTF-8"),
])
def test_pose_files_that_are_not_poses_leave_the_frame_its_images(scenes_dir, text, reason):
    path = scenes_dir / "frame-000001.pose.txt"
    path.write_bytes(text if isinstance(text, bytes) else text.encode())
    with pytest.warns(DatasetWarning, match=reason):
        f = SevenScenesSequence(scenes_dir)[1]
    assert f.pose_gt is None and f.rgb.shape == (H, W, 3) and f.depth.shape == (H, W)  # never the identity
    with pytest.warns(DatasetWarning, match=r"ground truth unknown for 1 frame\(s\).*frame-000001.pose.txt"):
        gt = SevenScenesSequence(scenes_dir).groundtruth
    assert len(gt) == 3 and torch.isfinite(gt.poses).all()
    # non-finite entries are 7-Scenes' own mark of lost tracking: unknown, without a warning
    path.write_text("inf inf inf inf\n" * 4)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert SevenScenesSequence(scenes_dir)[1].pose_gt is None


def test_bad_intrinsics_are_refused_with_the_file(scenes_dir):
    for text, pattern in (("0 0 320\n0 0 240\n0 0 1\n", r"camera-intrinsics.txt: .*focal lengths"),
                          ("585 0 nan\n0 585 240\n0 0 1\n", r"camera-intrinsics.txt: .*non-finite"),
                          ("585 0 320\n0 585 240\n1 0 1\n", r"camera-intrinsics.txt: .*pinhole matrix")):
        (scenes_dir / "camera-intrinsics.txt").write_text(text)
        with pytest.raises(DatasetError, match=pattern):
            SevenScenesSequence(scenes_dir)
    with pytest.raises(ValueError, match=r"K must have focal lengths"):
        SevenScenesSequence(scenes_dir, K=np.zeros((3, 3)))


def test_a_bad_pose_file_is_warned_once(scenes_dir):
    (scenes_dir / "frame-000002.pose.txt").write_text("not a pose\n")
    seq = SevenScenesSequence(scenes_dir)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        for _ in range(3):
            seq[2]
        _ = seq.groundtruth
    assert [issubclass(w.category, DatasetWarning) for w in caught] == [True]
    assert "frame-000002.pose.txt:1: expected 4x4 numbers, got 'not a pose'" in str(caught[0].message)
