"""``attnloop-eval``: its figures equal those of the ``evo_ape`` / ``evo_rpe`` commands (skipped where evo is
not installed), its plot and JSON, and its errors."""
from __future__ import annotations

import json
import shutil
import subprocess
import zipfile

import numpy as np
import pytest
import torch
from helpers import perturb_trajectory  # known drift, noise and a global rigid motion

from slam.eval.cli import main
from slam.io.trajectory import Trajectory, read_tum_trajectory, write_tum_trajectory

TOL = 1e-6  # metres: agreement with evo required


@pytest.fixture(scope="module", params=["fr1_xyz-groundtruth.txt", "fr3_long_office_household-groundtruth.txt"])
def files(request, tum_gt_dir, tmp_path_factory):
    """(ground truth as evo reads it, estimate) for each shared TUM ground-truth file."""
    tmp = tmp_path_factory.mktemp("eval_cli")
    gt = read_tum_trajectory(tum_gt_dir / request.param)
    gt_path, est_path = tmp / "gt.txt", tmp / "est.txt"
    write_tum_trajectory(gt_path, gt)  # '#' header: evo rejects the shared files' bare 'timestamp ...' line
    write_tum_trajectory(est_path, Trajectory(gt.timestamps, perturb_trajectory(gt.poses, gt.timestamps, seed=3)))
    return gt_path, est_path


def _printed_rmse(capsys, argv) -> tuple[float, str]:
    assert main(argv) == 0
    out = capsys.readouterr().out
    first = out.splitlines()[0].split()
    return float(first[first.index("RMSE") + 1]), out


def _evo_command(tool: str, args: list, tmp_path) -> dict:
    exe = shutil.which(tool)
    if exe is None:
        pytest.skip(f"{tool} is not on PATH (pip install evo)")
    res = tmp_path / f"{tool}.zip"
    subprocess.run([exe, "tum", *map(str, args), "--save_results", str(res), "--no_warnings"], check=True,
                   capture_output=True)
    with zipfile.ZipFile(res) as z:
        return json.loads(z.read("stats.json"))


@pytest.mark.parametrize("align, evo_flags", [("se3", ["-a"]), ("sim3", ["-as"]), ("none", [])])
def test_ate_equals_evo_ape(files, align, evo_flags, capsys, tmp_path):
    gt, est = files
    rmse, out = _printed_rmse(capsys, ["ate", str(gt), str(est), "--align", align, "--json", str(tmp_path / "a.json")])
    evo = _evo_command("evo_ape", [gt, est, *evo_flags, "--t_max_diff", "0.02"], tmp_path)
    ours = json.loads((tmp_path / "a.json").read_text())
    for key in ("rmse", "mean", "median", "std", "min", "max", "sse"):
        assert ours[key] == pytest.approx(evo[key], abs=TOL), key
    assert rmse == pytest.approx(evo["rmse"], abs=TOL)  # the printed figure too (6 decimals)
    assert "m (" in out and ours["num_pairs"] > 700


def test_rpe_equals_evo_rpe(files, capsys, tmp_path):
    gt, est = files
    assert main(["rpe", str(gt), str(est), "--json", str(tmp_path / "r.json")]) == 0
    ours = json.loads((tmp_path / "r.json").read_text())
    evo_t = _evo_command("evo_rpe", [gt, est, "--delta", "1", "--delta_unit", "f", "--t_max_diff", "0.02"], tmp_path)
    evo_r = _evo_command("evo_rpe", [gt, est, "--delta", "1", "--delta_unit", "f", "--t_max_diff", "0.02",
                                     "--pose_relation", "angle_deg"], tmp_path)
    for key in ("rmse", "mean", "max", "sse"):
        assert ours["translation_m"][key] == pytest.approx(evo_t[key], abs=TOL), key
        assert ours["rotation_deg"][key] == pytest.approx(evo_r[key], abs=1e-6 * max(1.0, evo_r[key])), key


def test_plot_with_labels(files, capsys, tmp_path):
    import cv2

    gt, est = files
    png = tmp_path / "ate.png"
    assert main(["ate", str(gt), str(est), "--plot", str(png), "--labels", "mocap", "ours"]) == 0
    img = cv2.imread(str(png))
    assert img is not None and img.shape[2] == 3 and (img < 128).any()


def test_errors_exit_2_with_the_file(tmp_path, capsys):
    gt = tmp_path / "gt.txt"
    gt.write_text("1.0 0 0 0 0 0 0 1\n2.0 1 0 0 0 0 0 1\n3.0 2 1 0 0 0 0 1\n")
    bad = tmp_path / "bad.txt"
    bad.write_text("1.0 0 0 0 0 0 0\n")
    assert main(["ate", str(gt), str(bad)]) == 2
    err = capsys.readouterr().err
    assert "bad.txt" in err and "attnloop-eval:" in err
    assert main(["ate", str(gt), str(tmp_path / "missing.txt")]) == 2
    assert "missing.txt" in capsys.readouterr().err
    far = tmp_path / "far.txt"
    far.write_text("100.0 0 0 0 0 0 0 1\n")
    assert main(["ate", str(gt), str(far)]) == 2  # nothing associates
    assert "within 0.02 s" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main(["rpe", str(gt), str(gt), "--delta", "nan"])
    assert main(["rpe", str(gt), str(gt), "--delta", "5"]) == 2  # no pair 5 frames apart
    assert "smaller delta" in capsys.readouterr().err


def test_plot_labels_validated():
    from slam.eval.plot import plot_trajectory

    t = torch.arange(3, dtype=torch.float64)
    poses = torch.zeros(3, 7, dtype=torch.float64)
    poses[:, 6] = 1
    poses[:, 0], poses[:, 1] = t, t * t
    with pytest.raises(ValueError, match="two strings"):
        plot_trajectory(None, Trajectory(t, poses), labels=("only one",))
    img = plot_trajectory(None, Trajectory(t, poses), Trajectory(t, poses), labels=("a", "b"), size=(300, 200))
    assert img.shape == (200, 300, 3) and np.isfinite(img).all()


def test_association_option(tmp_path, capsys):
    """--association evo (default, |dt| <= max) or tum (|dt| < max): a pair exactly 2^-6 s apart."""
    gt, est = tmp_path / "gt.txt", tmp_path / "est.txt"
    gt.write_text("0.5 0 0 0 0 0 0 1\n1.5 1 0 0 0 0 0 1\n2.5 2 1 0 0 0 0 1\n")
    est.write_text("0.515625 0 0 0 0 0 0 1\n1.515625 1 0 0 0 0 0 1\n2.515625 2 1 0 0 0 0 1\n")
    common = ["ate", str(gt), str(est), "--t-max-diff", "0.015625"]
    assert main(common) == 0 and "(3 pose pairs" in capsys.readouterr().out
    assert main([*common, "--association", "evo"]) == 0
    assert main([*common, "--association", "tum"]) == 2 and "within 0.015625 s" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main([*common, "--association", "greedy"])


def test_the_plot_shows_the_alignment_the_figures_used(tmp_path, monkeypatch):
    # --align sim3 on an estimate at 0.37 of the true scale: the plot drew it with its own rigid alignment
    # (2.6 x too small) under a title that named the Sim(3) scale
    import slam.eval.plot as plot_module

    t = torch.arange(40, dtype=torch.float64) * 0.1
    gt = torch.zeros(40, 7, dtype=torch.float64)
    gt[:, 0], gt[:, 1], gt[:, 6] = torch.cos(t), torch.sin(t), 1.0
    est = gt.clone()
    est[:, :3] = 0.37 * gt[:, :3] + torch.tensor([2.0, -1.0, 0.5], dtype=torch.float64)
    write_tum_trajectory(tmp_path / "gt.txt", Trajectory(t, gt))
    write_tum_trajectory(tmp_path / "est.txt", Trajectory(t, est))
    drawn = {}
    original = plot_module.plot_trajectory

    def capture(path, estimate, reference=None, align=True, **kw):
        drawn["align"] = align
        return original(path, estimate, reference, align=align, **kw)

    monkeypatch.setattr(plot_module, "plot_trajectory", capture)
    assert main(["ate", str(tmp_path / "gt.txt"), str(tmp_path / "est.txt"), "--align", "sim3", "--plot",
                 str(tmp_path / "ate.png")]) == 0
    res = drawn["align"]
    assert abs(res.scale - 1 / 0.37) < 1e-9 and res.rmse < 1e-9  # the figure is given the Sim(3) result
    est_pos = est[:, :3]
    aligned = res.scale * est_pos @ res.rotation.T + res.translation
    assert torch.allclose(aligned, gt[:, :3], atol=1e-9)


def test_rpe_frames_delta_must_be_whole_and_bad_files_are_named(tmp_path, capsys):
    gt = tmp_path / "gt.txt"
    gt.write_text("".join(f"{k}.0 {k} 0 0 0 0 0 1\n" for k in range(6)))
    assert main(["rpe", str(gt), str(gt), "--delta", "2.5"]) == 2  # it ran 2 frames apart
    assert "delta in frames must be a positive integer, got 2.5" in capsys.readouterr().err
    assert main(["rpe", str(gt), str(gt), "--delta", "2", "--delta-unit", "seconds"]) == 0  # seconds need not
    capsys.readouterr()
    empty = tmp_path / "empty.txt"
    empty.write_text("# nothing\n")
    assert main(["ate", str(gt), str(empty)]) == 2
    assert f"estimate {empty} holds no pose" in capsys.readouterr().err
    assert main(["ate", str(gt), str(tmp_path)]) == 2
    assert "a folder, not a trajectory file" in capsys.readouterr().err


def test_plotting_with_an_ate_result_draws_its_aligned_estimate():
    # the same picture as the estimate aligned by hand, measured without alignment (the same errors, the same
    # statistics) and named as the result's alignment
    import dataclasses

    from slam.eval.metrics import ate
    from slam.eval.plot import plot_trajectory

    t = torch.arange(30, dtype=torch.float64) * 0.2
    gt = torch.zeros(30, 7, dtype=torch.float64)
    gt[:, 0], gt[:, 1], gt[:, 6] = torch.cos(t), 0.5 * torch.sin(2 * t), 1.0
    est = gt.clone()
    est[:, :3] = 2.5 * gt[:, :3] + 1.0 + 0.01 * torch.sin(5 * t)[:, None]
    ref, raw = Trajectory(t, gt), Trajectory(t, est)
    res = ate(ref, raw, alignment="sim3")
    by_hand = Trajectory(t, res.estimate_aligned.poses)
    measured = dataclasses.replace(ate(ref, by_hand, alignment="none"), alignment="sim3")
    a = plot_trajectory(None, raw, ref, align=res, plane="xy", title="x")
    b = plot_trajectory(None, by_hand, ref, align=measured, plane="xy", title="x")
    assert np.array_equal(a, b)
    assert not np.array_equal(a, plot_trajectory(None, raw, ref, align=False, plane="xy", title="x"))


def test_without_a_metric_it_is_the_ate(tmp_path, capsys):
    t = torch.arange(20, dtype=torch.float64) / 10
    poses = torch.zeros(20, 7, dtype=torch.float64)
    poses[:, 0], poses[:, 1], poses[:, 6] = t, torch.sin(t), 1.0
    gt, est = tmp_path / "gt.txt", tmp_path / "est.txt"
    write_tum_trajectory(gt, Trajectory(t, poses))
    moved = poses.clone()
    moved[:, 2] += 0.01 * torch.cos(7 * t)  # 1 cm of wobble off the plane
    write_tum_trajectory(est, Trajectory(t, moved))
    assert main([str(gt), str(est), "--align", "none"]) == 0
    bare = capsys.readouterr().out
    assert main(["ate", str(gt), str(est), "--align", "none"]) == 0
    assert bare == capsys.readouterr().out and bare.startswith("ATE RMSE ")
    rms = float(torch.sqrt(torch.mean((0.01 * torch.cos(7 * t)) ** 2)))  # by hand: no alignment
    assert float(bare.split()[2]) == pytest.approx(rms, abs=1e-6)


def test_stamps_that_do_not_overlap_get_a_t_offset_hint(tmp_path, capsys):
    t = torch.arange(20, dtype=torch.float64) / 10
    poses = torch.zeros(20, 7, dtype=torch.float64)
    poses[:, 0], poses[:, 1], poses[:, 6] = t, torch.sin(t), 1.0
    gt, est = tmp_path / "gt.txt", tmp_path / "est.txt"
    write_tum_trajectory(gt, Trajectory(t + 1000.0, poses))  # a clock that started 1000 s earlier
    write_tum_trajectory(est, Trajectory(t, poses))
    assert main(["ate", str(gt), str(est)]) == 2
    err = capsys.readouterr().err
    assert "do not overlap" in err and "--t-offset 1000.000000" in err and len(err.splitlines()) == 1
    assert main(["ate", str(gt), str(est), "--t-offset", "1000"]) == 0  # the hint works: ATE 0
    assert float(capsys.readouterr().out.split()[2]) == pytest.approx(0.0, abs=1e-9)
    write_tum_trajectory(est, Trajectory(t + 1000.05, poses))  # overlapping, half a sample (0.1 s) apart
    assert main(["ate", str(gt), str(est)]) == 2
    assert "overlap in time but are sampled apart: try a larger tolerance (--t-max-diff" in capsys.readouterr().err
    write_tum_trajectory(est, Trajectory(t * 1e9, poses))  # nanoseconds against seconds
    assert main(["ate", str(gt), str(est)]) == 2
    assert "the reference's stamps look like seconds and the estimate's like nanoseconds" in capsys.readouterr().err


def _closed_stdout(argv) -> tuple[int, str]:
    """Run ``python -m argv`` with its stdout closed before it writes (a reader that stopped: ``| head``)."""
    import subprocess
    import sys

    p = subprocess.Popen([sys.executable, "-m", *argv], stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    p.stdout.close()  # the reader is gone before the first line (the imports take longer)
    err = p.stderr.read().decode()
    return p.wait(), err


@pytest.mark.slow
def test_a_reader_that_stops_early_is_no_error(files):
    """``attnloop-eval ... | head``: no "[Errno 32] Broken pipe": exit code 1, Python's own for EPIPE."""
    code, err = _closed_stdout(["slam.eval.cli", "ate", *map(str, files)])
    assert code == 1 and err == "", err


@pytest.mark.slow
def test_a_reader_that_stops_early_is_no_error_for_the_slam_command(tmp_path):
    code, err = _closed_stdout(["slam.cli", "--demo", "--demo-frames", "24", "--demo-size", "160", "120", "--no-loop",
                                "--no-map", "--quiet", "--out", str(tmp_path / "out")])
    assert code == 1 and "Broken pipe" not in err and "Traceback" not in err, err
