"""TUM RGB-D reader and TUM association: generated folders, the real fr1_xyz lists, error paths."""
from __future__ import annotations

import logging
import shutil

import cv2
import numpy as np
import pytest
import torch

from slam.io import (
    TUM_CAMERAS,
    DatasetError,
    DatasetNotFoundError,
    FrameReadError,
    TUMSequence,
    camera_from_name,
    open_sequence,
)
from slam.io.associate import associate

H, W = 24, 32


def tum_associate_reference(first: dict, second: dict, offset: float = 0.0, max_difference: float = 0.02):
    """TUM's associate.py (Sturm et al.), verbatim apart from the Python 3 details."""
    first_keys = list(first.keys())
    second_keys = list(second.keys())
    potential_matches = [(abs(a - (b + offset)), a, b) for a in first_keys for b in second_keys
                         if abs(a - (b + offset)) < max_difference]
    potential_matches.sort()
    matches = []
    for diff, a, b in potential_matches:
        if a in first_keys and b in second_keys:
            first_keys.remove(a)
            second_keys.remove(b)
            matches.append((a, b))
    matches.sort()
    return matches


def _stamps(path):
    return [float(ln.split()[0]) for ln in path.read_text().splitlines() if ln and ln[0].isdigit()]


def _write_rgb(path, value):
    img = np.zeros((H, W, 3), np.uint8)
    img[..., 0], img[..., 1], img[..., 2] = value, 100, 200  # B, G, R on disk
    cv2.imwrite(str(path), img)


def _make_tum(root, rgb_stamps, depth_stamps, gt_lines=None, header="# color images\n"):
    (root / "rgb").mkdir(parents=True)
    (root / "depth").mkdir()
    rgb_lines, depth_lines = [header], ["# depth maps\n"]
    for k, t in enumerate(rgb_stamps):
        _write_rgb(root / "rgb" / f"{t:.6f}.png", 10 + k)
        rgb_lines.append(f"{t:.6f} rgb/{t:.6f}.png\n")
    for k, t in enumerate(depth_stamps):
        d = np.full((H, W), 5000 * (k + 1), np.uint16)
        d[0, 0] = 0
        cv2.imwrite(str(root / "depth" / f"{t:.6f}.png"), d)
        depth_lines.append(f"{t:.6f} depth/{t:.6f}.png\n")
    (root / "rgb.txt").write_text("".join(rgb_lines))
    (root / "depth.txt").write_text("".join(depth_lines))
    if gt_lines is not None:
        (root / "groundtruth.txt").write_text("# timestamp tx ty tz qx qy qz qw\n" + "".join(gt_lines))
    return root


@pytest.fixture
def tum_dir(tmp_path):
    rgb = [1.000, 1.033, 1.066, 1.100]
    depth = [1.004, 1.030, 1.090, 1.101]  # 1.066 has no depth within 0.02 s (1.090 is 0.024 away)
    gt = [f"{t:.4f} {t} 0 0 0 0 0 1\n" for t in (0.99, 1.0, 1.01, 1.04, 1.07, 1.08)]
    return _make_tum(tmp_path / "rgbd_dataset_freiburg1_tiny", rgb, depth, gt)


def test_association_hand_computed_case():
    # candidates (< 0.02 s): (0.0, 0.009) 0.009, (0.011, 0.009) 0.002, (0.011, 0.025) 0.014.
    # Greedy by difference: (0.011, 0.009) first; then both others are blocked -> one match only.
    # (A nearest-neighbour matcher would pair 0.0 with 0.009 as well.)
    i, j = associate(np.array([0.0, 0.011]), np.array([0.009, 0.025]))
    assert i.tolist() == [1] and j.tolist() == [0]
    # strict "<" as TUM: exactly 0.02 apart is not a match
    i, j = associate(np.array([0.0]), np.array([0.02]))
    assert i.numel() == 0 and i.dtype == torch.long
    assert associate(np.array([0.0]), np.array([0.0199999]))[0].tolist() == [0]
    # offset is added to the second list; unsorted inputs are fine; the result is sorted by first
    i, j = associate(torch.tensor([5.0, 1.0, 3.0]), torch.tensor([2.9, 0.9, 4.9]), offset=0.1)
    assert i.tolist() == [1, 2, 0] and j.tolist() == [1, 0, 2]
    i, j = associate(np.array([]), np.array([1.0]))
    assert i.shape == (0,) and j.shape == (0,)


def test_association_equals_tum_script_on_random_streams():
    rng = np.random.default_rng(0)
    for _ in range(20):
        a = np.round(np.cumsum(rng.uniform(0.005, 0.05, 60)), 6)
        b = np.round(np.cumsum(rng.uniform(0.005, 0.05, 70)), 6)
        expected = tum_associate_reference(dict.fromkeys(a.tolist()), dict.fromkeys(b.tolist()))
        i, j = associate(a, b)
        assert list(zip(a[i.numpy()].tolist(), b[j.numpy()].tolist())) == expected


def test_association_equals_tum_script_on_real_lists(tum_gt_dir):
    rgb = _stamps(tum_gt_dir / "fr1_xyz-rgb.txt")
    depth = _stamps(tum_gt_dir / "fr1_xyz-depth.txt")
    gt = _stamps(tum_gt_dir / "fr1_xyz-groundtruth.txt")
    for first, second in ((rgb, depth), (rgb, gt[::7])):  # gt thinned: the O(N M) reference is slow
        expected = tum_associate_reference(dict.fromkeys(first), dict.fromkeys(second))
        i, j = associate(np.array(first), np.array(second))
        got = list(zip(np.array(first)[i.numpy()].tolist(), np.array(second)[j.numpy()].tolist()))
        assert got == expected and len(got) > 350


def test_generated_folder(tum_dir):
    seq = open_sequence(tum_dir)
    assert isinstance(seq, TUMSequence) and seq.camera_name == "fr1" and len(seq) == 3
    assert np.allclose(seq.K, TUM_CAMERAS["fr1"].K) and seq.K[0, 0] == 517.3
    assert seq.timestamps.dtype == np.float64 and seq.timestamps.tolist() == [1.0, 1.033, 1.1]
    assert seq.depth_timestamps.tolist() == [1.004, 1.03, 1.101]
    f = seq[1]
    assert f.index == 1 and f.timestamp == 1.033
    assert f.rgb.shape == (H, W, 3) and f.rgb.dtype == np.uint8
    assert f.rgb[5, 5].tolist() == [200, 100, 11]  # RGB order (written as BGR)
    assert f.depth.dtype == np.float32 and f.depth[3, 3] == 2.0 and f.depth[0, 0] == 0.0  # 10000 / 5000
    assert f.K.shape == (3, 3) and f.rgb_path.endswith("rgb/1.033000.png") and f.depth_path.endswith("1.030000.png")
    # ground truth = nearest gt stamp within 0.02 s: 1.0 -> 1.0, 1.033 -> 1.04, 1.1 -> 1.08 (0.02: not < 0.02)
    assert seq[0].pose_gt[0] == 1.0 and seq[1].pose_gt[0] == pytest.approx(1.04)
    assert seq[2].pose_gt is None
    gt = seq.groundtruth
    assert len(gt) == 2 and gt.timestamps.tolist() == [1.0, 1.033] and gt.poses.dtype == torch.float64
    assert seq.groundtruth_file == tum_dir / "groundtruth.txt"
    assert [f.index for f in seq] == [0, 1, 2] and seq[-1].timestamp == 1.1
    view = seq[1:]
    assert len(view) == 2 and view[0].timestamp == 1.033 and view[0].index == 0 and len(view.groundtruth) == 1
    with pytest.raises(IndexError):
        seq[3]


def test_uncommented_header_and_no_groundtruth(tmp_path):
    root = _make_tum(tmp_path / "fr3_nogt", [2.0, 2.05], [2.001, 2.049], header="timestamp filename\n")
    seq = TUMSequence(root)
    assert len(seq) == 2 and seq.camera_name == "fr3" and seq.groundtruth is None and seq[0].pose_gt is None
    assert seq.groundtruth_file is None


def test_camera_selection(tmp_path, caplog):
    assert camera_from_name("rgbd_dataset_freiburg3_long_office_household") == "fr3"
    assert camera_from_name("FR2_desk") == "fr2" and camera_from_name("fr12") is None
    assert camera_from_name("my_frames") is None and camera_from_name("freiburg") is None
    root = _make_tum(tmp_path / "my_sequence", [1.0], [1.0])
    with caplog.at_level(logging.WARNING):
        seq = TUMSequence(root)
    assert seq.camera_name == "ros" and seq.K[0, 0] == 525.0 and "ROS default" in caplog.text
    assert TUMSequence(root, camera="freiburg2").K[0, 2] == 325.1
    K = np.array([[500.0, 0, 16], [0, 500.0, 12], [0, 0, 1]])
    seq = open_sequence(root, K=K)
    assert np.array_equal(seq[0].K, K) and seq.camera_name is None
    with pytest.raises(DatasetError, match="unknown TUM camera"):
        TUMSequence(root, camera="fr4")
    with pytest.raises(ValueError, match=r"\(3, 3\)"):
        TUMSequence(root, K=np.eye(4))


def test_calibration_file(tmp_path):
    root = _make_tum(tmp_path / "fr1_synthetic", [1.0], [1.0])
    (root / "calibration.txt").write_text("# fx fy cx cy\n262.5 262.5 159.5 119.5\n")
    seq = TUMSequence(root)  # the file wins over the folder name ...
    assert seq.camera_name == "calibration.txt" and seq.K[0, 0] == 262.5 and seq.K[1, 2] == 119.5
    assert not np.any(seq.distortion)
    assert TUMSequence(root, camera="fr1").K[0, 0] == 517.3  # ... but not over an explicit camera
    (root / "calibration.txt").write_text("500 500 16 12 0.1 0 0 0 0\n")
    assert TUMSequence(root).distortion[0] == 0.1
    (root / "calibration.txt").write_text("\n500 500 16\n")
    with pytest.raises(DatasetError, match=r"calibration.txt:2: expected 4 or 9 numbers"):
        TUMSequence(root)


def test_undistort_keeps_depth_values_and_principal_point(tmp_path):
    root = tmp_path / "fr1_big"
    (root / "rgb").mkdir(parents=True)
    (root / "depth").mkdir()
    yy, xx = np.mgrid[0:480, 0:640]
    rgb = np.stack([xx % 256, yy % 256, (xx + yy) % 256], -1).astype(np.uint8)
    depth = (5000 + (xx // 40) * 500 + (yy // 40) * 35).astype(np.uint16)  # 1-3.2 m at TUM's 5000 per metre
    cv2.imwrite(str(root / "rgb" / "a.png"), rgb)
    cv2.imwrite(str(root / "depth" / "a.png"), depth)
    (root / "rgb.txt").write_text("1.0 rgb/a.png\n")
    (root / "depth.txt").write_text("1.0 depth/a.png\n")
    plain, und = TUMSequence(root)[0], TUMSequence(root, undistort=True)[0]
    assert und.rgb.shape == plain.rgb.shape and und.depth.shape == plain.depth.shape
    assert not np.array_equal(und.depth, plain.depth)  # fr1 distortion is strong at the borders
    assert set(np.unique(und.depth)) <= set(np.unique(plain.depth)) | {0.0}  # nearest: no blended depths
    # the principal point does not move
    assert abs(int(und.rgb[255, 318, 0]) - int(plain.rgb[255, 318, 0])) <= 2
    assert not TUMSequence(root, camera="fr3", undistort=True).undistort  # fr3 has no distortion


def test_real_lists_open_lazily(tum_gt_dir, tmp_path):
    """The real fr1_xyz lists without images: opening works (nothing is decoded), reading fails cleanly."""
    root = tmp_path / "rgbd_dataset_freiburg1_xyz"
    root.mkdir()
    for src, dst in (("rgb", "rgb"), ("depth", "depth"), ("groundtruth", "groundtruth")):
        shutil.copy(tum_gt_dir / f"fr1_xyz-{src}.txt", root / f"{dst}.txt")
    seq = open_sequence(root)
    rgb, depth = _stamps(root / "rgb.txt"), _stamps(root / "depth.txt")
    expected = tum_associate_reference(dict.fromkeys(rgb), dict.fromkeys(depth))
    assert len(seq) == len(expected) and seq.timestamps.tolist() == [a for a, _ in expected]
    assert seq.camera_name == "fr1"
    gt = seq.groundtruth
    assert 0.95 * len(seq) < len(gt) <= len(seq)
    # every frame's gt is a groundtruth.txt pose less than 0.02 s away
    gt_stamps = np.array(_stamps(root / "groundtruth.txt"))
    nearest = np.abs(gt.timestamps.numpy()[:, None] - gt_stamps[None]).min(axis=1)
    assert nearest.max() < 0.02
    with pytest.raises(FrameReadError, match="does not exist") as info:
        seq[0]
    assert info.value.path.endswith(".png") and "rgb" in info.value.path


def test_open_time_errors(tmp_path):
    with pytest.raises(DatasetNotFoundError, match="does not exist") as info:
        open_sequence(tmp_path / "nope")
    assert isinstance(info.value, FileNotFoundError)
    root = tmp_path / "fr1_x"
    root.mkdir()
    (root / "rgb.txt").write_text("1.0 rgb/a.png\n")
    with pytest.raises(DatasetNotFoundError, match="depth.txt"):
        open_sequence(root)
    (root / "depth.txt").write_text("# only comments\n\n")
    with pytest.raises(DatasetError, match="empty"):
        open_sequence(root)
    (root / "depth.txt").write_text("# c\n1.0 depth/a.png\nbad depth/b.png\n")
    with pytest.raises(DatasetError, match="not a number") as info:
        open_sequence(root)
    assert info.value.line_number == 3 and "depth.txt:3" in str(info.value)
    (root / "depth.txt").write_text("1.0\n")
    with pytest.raises(DatasetError, match="timestamp filename"):
        open_sequence(root)
    # exactly two fields: an associated list, a name with a space, an empty CSV cell are refused by line
    for text, line, pattern in (("1.0 depth/a.png 1.01 rgb/a.png\n", 1, "expected 2 fields .* got 4"),
                                ("# c\n1.0 depth/my file.png\n", 2, "expected 2 fields .* got 3"),
                                ("1.0 depth/a.png\n2.0 depth/b.png extra\n", 2, "got 3"),
                                ("1.0,,depth/a.png\n", 1, "comma-separated cell 2 is empty"),
                                ("1.0,depth/a.png,\n", 1, "comma-separated cell 3 is empty")):
        (root / "depth.txt").write_text(text)
        with pytest.raises(DatasetError, match=pattern) as info:
            open_sequence(root)
        assert info.value.line_number == line and f"depth.txt:{line}:" in str(info.value)
    (root / "depth.txt").write_text("# timestamp filename\ntimestamp filename\n1.0,\tdepth/a.png\n")
    assert open_sequence(root).timestamps.tolist() == [1.0]  # header skipped, ', ' is one separator
    (root / "depth.txt").write_text("5.0 depth/a.png\n")
    with pytest.raises(DatasetError, match="within 0.02 s"):
        open_sequence(root)
    (root / "depth.txt").write_text("1.0 depth/a.png\n")
    (root / "groundtruth.txt").write_text("1.0 0 0 0\n")
    with pytest.raises(ValueError, match="groundtruth.txt:1"):
        open_sequence(root)
    (tmp_path / "afile").write_text("x")
    with pytest.raises(DatasetError, match="got a file"):
        open_sequence(tmp_path / "afile")
    other = tmp_path / "random"
    other.mkdir()
    with pytest.raises(DatasetError, match="not an RGB-D sequence folder"):
        open_sequence(other)


def test_read_time_errors_and_skipping(tum_dir, caplog):
    seq = TUMSequence(tum_dir)
    rgb1, _ = seq.paths(1)
    rgb1.write_bytes(b"not an image")
    with pytest.raises(FrameReadError, match="not a decodable image") as info:
        seq[1]
    assert info.value.path == str(rgb1)
    with caplog.at_level(logging.WARNING):
        kept = [f.timestamp for f in seq.frames(on_error="skip")]
    assert kept == [1.0, 1.1] and "skipping frame 1" in caplog.text
    assert [f.timestamp for f in seq.frames(on_error="skip", prefetch=2)] == [1.0, 1.1]
    with pytest.raises(FrameReadError):
        list(seq.frames())
    with pytest.raises(FrameReadError):
        list(seq.frames(prefetch=1))
    with pytest.raises(ValueError, match="on_error"):
        list(seq.frames(on_error="ignore"))

    rgb0, depth0 = seq.paths(0)
    cv2.imwrite(str(depth0), np.zeros((H, W), np.uint8))
    with pytest.raises(FrameReadError, match="16-bit"):
        seq[0]
    cv2.imwrite(str(depth0), np.zeros((H + 2, W), np.uint16))
    with pytest.raises(FrameReadError, match=rf"{W}x{H + 2} but the colour image is {W}x{H}"):
        seq[0]
    cv2.imwrite(str(depth0), np.zeros((H, W, 3), np.uint16))
    with pytest.raises(FrameReadError, match="one channel"):
        seq[0]
    cv2.imwrite(str(rgb0), np.zeros((H, W, 3), np.uint16))
    with pytest.raises(FrameReadError, match="8-bit"):
        seq[0]
    depth0.unlink()
    rgb0.write_bytes(b"")
    with pytest.raises(FrameReadError, match="not a decodable"):
        seq[0]


def test_grey_and_alpha_colour_images(tum_dir):
    seq = TUMSequence(tum_dir)
    rgb0, _ = seq.paths(0)
    cv2.imwrite(str(rgb0), np.full((H, W), 77, np.uint8))
    assert seq[0].rgb.shape == (H, W, 3) and seq[0].rgb[0, 0].tolist() == [77, 77, 77]
    bgra = np.zeros((H, W, 4), np.uint8)
    bgra[..., 0], bgra[..., 3] = 255, 128
    cv2.imwrite(str(rgb0), bgra)
    assert seq[0].rgb[0, 0].tolist() == [0, 0, 255]


def test_frames_then_runs_in_the_reading_thread(tum_dir):
    """frames(then=f) yields f(frame) in input order, computed by the thread that read the frame (prefetch),
    an unreadable frame as its FrameReadError (not passed to f), and f's own error where it happens."""
    import threading

    seq = TUMSequence(tum_dir)
    rgb1, _ = seq.paths(1)
    rgb1.write_bytes(b"not an image")
    for prefetch in (0, 2):
        seen = []

        def then(frame, seen=seen):
            seen.append(threading.current_thread().name)
            return frame.timestamp, float(frame.depth.sum())

        out = list(seq.frames(on_error="yield", prefetch=prefetch, then=then))
        assert [o if isinstance(o, FrameReadError) else o[0] for o in out][::2] == [1.0, 1.1]
        assert isinstance(out[1], FrameReadError) and len(seen) == 2
        assert out[0][1] == float(seq[0].depth.sum())
        assert all(name.startswith("rgbd-prefetch") for name in seen) == (prefetch > 0)
        assert [f[0] for f in seq.frames(on_error="skip", prefetch=prefetch, then=then)] == [1.0, 1.1]

    def boom(frame):
        raise KeyError("then failed")

    for prefetch in (0, 1):
        with pytest.raises(KeyError, match="then failed"):
            list(seq.frames(on_error="skip", prefetch=prefetch, then=boom))


def test_a_subset_of_frames_is_paired_with_ground_truth_among_itself(tmp_path):
    # 30 Hz frames, 25 Hz ground truth from +17 ms. On all six frames TUM's greedy one-to-one association gives
    # the pose at 0.017 to frame 1 (16.3 ms) rather than frame 0 (17 ms); every 2nd frame (--frame-step 2) must
    # be paired among itself, as evaluate_ate.py pairs the run's trajectory: frames 0, 2, 4 get poses 0, 1, 3.
    d = tmp_path / "rgbd_dataset_freiburg1_xyz"
    d.mkdir()
    frames = [100.0 + k / 30 for k in range(6)]
    gt = [100.0 + 0.017 + 0.04 * j for j in range(5)]
    (d / "rgb.txt").write_text("".join(f"{t:.6f} rgb/{k}.png\n" for k, t in enumerate(frames)))
    (d / "depth.txt").write_text("".join(f"{t:.6f} depth/{k}.png\n" for k, t in enumerate(frames)))
    (d / "groundtruth.txt").write_text("".join(f"{t:.4f} {j} 0 0 0 0 0 1\n" for j, t in enumerate(gt)))
    seq = open_sequence(d)
    assert seq.groundtruth_pose(0) is None and seq.groundtruth_pose(1)[0] == 0.0
    view = seq[::2]
    assert [view.groundtruth_pose(i)[0] for i in range(3)] == [0.0, 1.0, 3.0]
    assert view.groundtruth.timestamps.tolist() == list(view.timestamps)
    # a view of a view pairs among its own frames too: frames 0 and 4 of the sequence
    assert [p[0] for p in (view[::2].groundtruth_pose(i) for i in range(2))] == [0.0, 3.0]


def test_the_camera_comes_from_the_name_given_even_through_a_symlink(tmp_path):
    plain = tmp_path / "my_copy"
    plain.mkdir()
    for name in ("rgb.txt", "depth.txt"):
        (plain / name).write_text("1.0 x.png\n")
    link = tmp_path / "rgbd_dataset_freiburg2_xyz"
    link.symlink_to(plain, target_is_directory=True)
    seq = open_sequence(link)
    assert (seq.name, seq.camera_name) == ("rgbd_dataset_freiburg2_xyz", "fr2") and seq.K[0, 0] == 520.9
    # the other way round: a plainly named link to the folder that carries the camera
    back = tmp_path / "data"
    back.symlink_to(tmp_path / "rgbd_dataset_freiburg3_x", target_is_directory=True)
    (tmp_path / "rgbd_dataset_freiburg3_x").mkdir()
    for name in ("rgb.txt", "depth.txt"):
        (tmp_path / "rgbd_dataset_freiburg3_x" / name).write_text("1.0 x.png\n")
    assert open_sequence(back).camera_name == "fr3"


def test_ground_truth_that_matches_no_frame_says_so(tmp_path):
    from slam.pipeline import camera_of, unmatched_groundtruth

    d = tmp_path / "rgbd_dataset_freiburg1_xyz"
    d.mkdir()
    (d / "rgb.txt").write_text("".join(f"{10 + k / 30:.6f} rgb/{k}.png\n" for k in range(4)))
    (d / "depth.txt").write_text("".join(f"{10 + k / 30:.6f} depth/{k}.png\n" for k in range(4)))
    (d / "groundtruth.txt").write_text("".join(f"{110 + k / 30:.4f} 0 0 0 0 0 0 1\n" for k in range(4)))
    seq = open_sequence(d)
    assert seq.groundtruth is None and len(seq.groundtruth_trajectory) == 4
    note = unmatched_groundtruth(seq, seq.timestamps)
    assert "groundtruth.txt has 4 poses (110.000 to 110.100 s), none within 0.02 s of the 4 frames used " \
           "(10.000 to 10.100 s)" in note
    assert camera_of(seq) == {"name": "fr1", "intrinsics": [517.3, 516.5, 318.6, 255.3]}
    # a run on a view of it (--frame-step) reports the same: the view asks the sequence it was cut from
    assert camera_of(seq[::2]) == camera_of(seq) and "none within 0.02 s of the 2 frames" in \
        unmatched_groundtruth(seq[::2], seq[::2].timestamps)
    (d / "groundtruth.txt").unlink()
    assert unmatched_groundtruth(open_sequence(d), seq.timestamps) is None  # no file: nothing to explain


def test_depth_scale_reads_millimetre_depth(tum_dir):
    # the depth PNGs hold 10000 at (3, 3): TUM's 5000 per metre gives 2 m, millimetres (1000) 10 m
    assert open_sequence(tum_dir)[1].depth[3, 3] == 2.0
    assert open_sequence(tum_dir, depth_scale=1000)[1].depth[3, 3] == 10.0
    for bad in (0, -5000, float("nan"), "mm", True):
        with pytest.raises(DatasetError, match="depth_scale must be a positive number"):
            open_sequence(tum_dir, depth_scale=bad)


def test_the_command_passes_depth_scale_and_camera_to_the_reader(tum_dir, capsys, monkeypatch):
    import slam.io
    from slam.cli import main
    from slam.options import RunOptions, reader_options

    seen = {}

    def opened(path, **kw):
        seen.update(kw)
        raise DatasetError(path, "stop here")

    monkeypatch.setattr(slam.io, "open_sequence", opened)
    assert main([str(tum_dir), "--out", str(tum_dir.parent / "o"), "--depth-scale", "1000", "--camera", "fr2"]) == 2
    assert seen == {"camera": "fr2", "depth_scale": 1000.0}
    monkeypatch.undo()
    assert reader_options(RunOptions()) == {}
    assert reader_options(RunOptions(camera="fr2", depth_scale=1000.0)) == {"camera": "fr2", "depth_scale": 1000.0}
    assert main(["--demo", "--out", str(tum_dir.parent / "o"), "--depth-scale", "1000"]) == 2
    assert "--depth-scale applies to a SEQUENCE folder" in capsys.readouterr().err
