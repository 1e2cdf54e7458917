"""TUM trajectory files: round trips, strictness, line numbers, duplicates, evo agreement."""
from __future__ import annotations

import io
import warnings

import numpy as np
import pytest
import torch

from slam.io.trajectory import Trajectory, TrajectoryFormatError, read_tum_trajectory, write_tum_trajectory
from slam.lie import quat_normalize


def _random_traj(n: int = 20) -> Trajectory:
    g = torch.Generator().manual_seed(3)
    stamps = 1305031102.0 + torch.cumsum(torch.rand(n, generator=g, dtype=torch.float64) * 0.05 + 0.01, 0)
    t = torch.randn(n, 3, generator=g, dtype=torch.float64) * 3
    q = quat_normalize(torch.randn(n, 4, generator=g, dtype=torch.float64))
    return Trajectory(torch.round(stamps * 1e6) / 1e6, torch.cat([t, q], -1))


def test_round_trip_path_and_stream(tmp_path):
    traj = _random_traj()
    path = tmp_path / "traj.txt"
    write_tum_trajectory(path, traj)
    back = read_tum_trajectory(path)
    assert back.poses.dtype == torch.float64 and back.poses.shape == (20, 7)
    assert torch.allclose(back.timestamps, traj.timestamps, atol=1e-6, rtol=0)
    assert torch.allclose(back.poses, traj.poses, atol=2e-9, rtol=0)
    buf = io.StringIO()
    write_tum_trajectory(buf, traj, header=False)
    assert not buf.getvalue().startswith("#") and buf.getvalue().count("\n") == 20
    buf.seek(0)
    assert torch.allclose(read_tum_trajectory(buf).poses, back.poses, atol=0, rtol=0)
    with open(path) as f:  # a real text file object
        assert len(read_tum_trajectory(f)) == 20


def test_comments_blank_lines_separators_and_normalisation():
    text = "# header\n\n1.0 0 0 0 0 0 0 2\n  # indented comment\n2.0,1,2,3,0,0,0,1\n3.0\t1\t2\t3\t0\t0\t1\t1\n"
    traj = read_tum_trajectory(io.StringIO(text))
    assert traj.timestamps.tolist() == [1.0, 2.0, 3.0]
    # commas with spaces around them, and mixed separators, are still one separator each
    mixed = read_tum_trajectory(io.StringIO("timestamp,tx,ty,tz,qx,qy,qz,qw\n1.0, 0 ,0,\t0 0,0,0, 1\n"))
    assert mixed.poses[0].tolist() == [0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0]
    assert traj.poses[0, 6].item() == 1.0  # (0, 0, 0, 2) normalised
    assert torch.allclose(traj.poses[2, 3:], torch.tensor([0, 0, 2 ** -0.5, 2 ** -0.5], dtype=torch.float64))
    assert traj.poses[1, :3].tolist() == [1.0, 2.0, 3.0]


@pytest.mark.parametrize(
    "bad_line, reason",
    [
        ("2.0 1 2 3 0 0 0", "expected 8 values"),
        ("2.0 1 2 3 0 0 0 1 9", "expected 8 values"),
        ("2.0 1 2 x 0 0 0 1", "not a number"),
        ("2.0 1 2 nan 0 0 0 1", "non-finite"),
        ("2.0 1 2 3 0 0 0 0", "zero quaternion"),
        ("2.0 1 2 3 1e-9 0 0 0", "zero quaternion"),
        ("2.0 1e300 2 3 0 0 0 1", r"translation beyond 1e\+09 m"),
        ("2.0 1 2 -inf 0 0 0 1", "non-finite"),
        ("2.0,,2,3,0,0,0,1,0", "comma-separated cell 2 is empty"),  # not read shifted as 2.0 2 3 0 0 0 1 0
        ("2.0,1,2,3,0,0,0,1,", "comma-separated cell 9 is empty"),
        (",2.0,1,2,3,0,0,0,1", "comma-separated cell 1 is empty"),
        ("2.0, 1 ,  ,3,0,0,0,1", "comma-separated cell 3 is empty"),
    ],
)
def test_bad_line_names_file_and_line(tmp_path, bad_line, reason):
    path = tmp_path / "bad.txt"
    path.write_text("# comment\n1.0 0 0 0 0 0 0 1\n\n" + bad_line + "\n")
    with pytest.raises(TrajectoryFormatError, match=reason) as info:
        read_tum_trajectory(path)
    assert info.value.line_number == 4
    assert info.value.path == str(path)
    assert f"{path}:4:" in str(info.value)
    assert isinstance(info.value, ValueError)


def test_stream_error_uses_stream_name():
    with pytest.raises(TrajectoryFormatError, match=r"<stream>:1:"):
        read_tum_trajectory(io.StringIO("oops\n"))


def test_unsorted_is_sorted_and_duplicates():
    text = "3.0 3 0 0 0 0 0 1\n1.0 1 0 0 0 0 0 1\n2.0 2 0 0 0 0 0 1\n2.0 20 0 0 0 0 0 1\n"
    with pytest.warns(UserWarning, match="duplicate timestamp"):
        last = read_tum_trajectory(io.StringIO(text))
    assert last.timestamps.tolist() == [1.0, 2.0, 3.0]
    assert last.poses[:, 0].tolist() == [1.0, 20.0, 3.0]
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # sorted, unique input: no warning
        read_tum_trajectory(io.StringIO("1 0 0 0 0 0 0 1\n2 0 0 0 0 0 0 1\n"))


def test_empty_file_gives_empty_shapes(tmp_path):
    path = tmp_path / "empty.txt"
    path.write_text("# nothing here\n\n")
    traj = read_tum_trajectory(path)
    assert traj.timestamps.shape == (0,) and traj.poses.shape == (0, 7) and len(traj) == 0


def test_source_errors(tmp_path):
    with pytest.raises(FileNotFoundError, match="missing.txt"):
        read_tum_trajectory(tmp_path / "missing.txt")
    path = tmp_path / "t.txt"
    path.write_text("1 0 0 0 0 0 0 1\n")
    with open(path, "rb") as f:  # a binary file object is decoded as UTF-8
        assert read_tum_trajectory(f).poses.tolist() == [[0.0, 0, 0, 0, 0, 0, 1]]
    with pytest.raises(TypeError, match="path or a text file"):
        read_tum_trajectory(42)


def test_write_rejects_bad_input(tmp_path):
    traj = _random_traj(3)
    traj.poses[1, 0] = float("nan")
    with pytest.raises(ValueError, match="non-finite"):
        write_tum_trajectory(tmp_path / "x.txt", traj)
    with pytest.raises(TypeError):
        write_tum_trajectory(tmp_path / "x.txt", traj.poses)


def test_trajectory_shape_checks():
    with pytest.raises(ValueError, match=r"\(N, 7\)"):
        Trajectory(torch.zeros(3, dtype=torch.float64), torch.zeros(3, 6, dtype=torch.float64))
    with pytest.raises(ValueError, match=r"\(N,\)"):
        Trajectory(torch.zeros(3, 1, dtype=torch.float64), torch.zeros(3, 7, dtype=torch.float64))
    empty = Trajectory.empty()
    assert empty.poses.shape == (0, 7) and empty.positions.shape == (0, 3)


def _without_uncommented_header(src, dst):
    # The shared copies carry an uncommented "timestamp tx ..." header, which evo (and TUM's scripts)
    # reject; give evo the same file with that header commented out.
    lines = src.read_text().splitlines()
    dst.write_text("\n".join("# " + ln if ln.startswith("timestamp") else ln for ln in lines) + "\n")
    return dst


def test_uncommented_header_is_skipped_only_before_data():
    assert len(read_tum_trajectory(io.StringIO("timestamp tx ty tz qx qy qz qw\n1 0 0 0 0 0 0 1\n"))) == 1
    with pytest.raises(TrajectoryFormatError) as info:
        read_tum_trajectory(io.StringIO("1 0 0 0 0 0 0 1\ntimestamp tx ty tz qx qy qz qw\n"))
    assert info.value.line_number == 2


def test_real_groundtruth_matches_evo_reader(tum_gt_dir, tmp_path):
    from evo.tools import file_interface

    for name in ("fr1_xyz-groundtruth.txt", "fr3_long_office_household-groundtruth.txt"):
        path = tum_gt_dir / name
        ours = read_tum_trajectory(path)
        evo_traj = file_interface.read_tum_trajectory_file(str(_without_uncommented_header(path, tmp_path / name)))
        assert len(ours) == evo_traj.num_poses > 1000
        assert np.array_equal(ours.timestamps.numpy(), evo_traj.timestamps)
        assert np.array_equal(ours.poses[:, :3].numpy(), evo_traj.positions_xyz)
        q_evo = evo_traj.orientations_quat_wxyz[:, [1, 2, 3, 0]]
        q_evo = q_evo / np.linalg.norm(q_evo, axis=1, keepdims=True)
        assert np.allclose(ours.poses[:, 3:].numpy(), q_evo, atol=1e-15)


def test_values_from_the_wild(tmp_path):
    """Overflow in the quaternion check, non-UTF-8 bytes, float32 stamps, precision on writing."""
    traj = read_tum_trajectory(io.StringIO("1.0 0 0 0 1e200 1e200 0 0\n2.0 0 0 0 1e-3 0 0 1e-3\n"))
    assert torch.allclose(traj.poses[0, 3:], torch.tensor([0.5 ** 0.5, 0.5 ** 0.5, 0, 0], dtype=torch.float64))
    assert torch.isfinite(traj.poses).all()
    with pytest.raises(TrajectoryFormatError, match="zero quaternion"):
        read_tum_trajectory(io.StringIO("1.0 0 0 0 1e-200 0 0 0\n"))  # still "zero" (norm < 1e-6)
    path = tmp_path / "latin1.txt"
    path.write_bytes(b"# est\xe9\n1.0 0 0 0 0 0 0 1\n")
    with pytest.raises(TrajectoryFormatError, match=r"latin1.txt:1: byte 0xe9 at column 6 is not UTF-8 text") as info:
        read_tum_trajectory(path)
    assert info.value.line_number == 1
    # float32 stamps cannot hold Unix times: refused, with the rule; integers are converted exactly
    stamps = 1305031102.175304 + torch.arange(3000, dtype=torch.float64) / 30
    poses = torch.zeros(3000, 7, dtype=torch.float64)
    poses[:, 6] = 1
    assert torch.unique(stamps.float()).numel() < 30  # what float32 does to them
    with pytest.raises(TypeError, match="timestamps must be float64, got torch.float32: it steps by 128 s"):
        Trajectory(stamps.float(), poses)
    assert Trajectory(torch.arange(4), poses[:4].float()).timestamps.dtype == torch.float64
    assert Trajectory(torch.arange(4), poses[:4].float()).poses.dtype == torch.float64
    # full precision by default: what is written reads back bit for bit
    g = torch.Generator().manual_seed(0)
    t = Trajectory(stamps, torch.cat([torch.randn(3000, 3, generator=g, dtype=torch.float64) * 1e3,
                                      quat_normalize(torch.randn(3000, 4, generator=g, dtype=torch.float64))], -1))
    write_tum_trajectory(tmp_path / "full.txt", t)
    back = read_tum_trajectory(tmp_path / "full.txt")
    assert torch.equal(back.timestamps, t.timestamps) and torch.unique(back.timestamps).numel() == 3000
    assert torch.equal(back.poses[:, :3], t.poses[:, :3])
    assert torch.allclose(back.poses[:, 3:], t.poses[:, 3:], atol=1e-15, rtol=0)  # re-normalised on reading
