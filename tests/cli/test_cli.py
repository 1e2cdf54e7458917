"""The command line: argument errors, wrong folders, the offline VGG16 message (no network is touched), and
small end-to-end demo runs (outputs, --frame-step, the map on the scene's surfaces)."""
from __future__ import annotations

import json
import math

import numpy as np
import pytest
import torch

from slam.cli import build_parser, main

DEMO = ["--demo", "--demo-frames", "24", "--demo-size", "160", "120", "--quiet"]


def _strict_json(path):
    def refuse(name):
        raise AssertionError(f"{path} holds {name}: not valid JSON")
    return json.loads(path.read_text(), parse_constant=refuse)


def _tum_folder(tmp_path):
    seq = tmp_path / "seq"
    seq.mkdir()
    (seq / "rgb.txt").write_text("0.0 rgb/0.png\n")
    (seq / "depth.txt").write_text("0.0 depth/0.png\n")
    return seq


def test_flags_not_typed_leave_the_configs_defaults():
    from attnloop.fusion import FUSION_MODES
    from slam.config import SLAMConfig
    from slam.options import RunOptions, given_settings, resolve_settings

    args = build_parser().parse_args(["seq", "--out", "o"])
    assert given_settings(args) == {} and args.demo_scene is None and args.config_file is None
    spec = resolve_settings(given_settings(args))
    assert spec.config == SLAMConfig() and spec.run == RunOptions()
    assert spec.config.loop.descriptor.recipe.fusion == "none"  # the default preset's fusion
    fusion = next(a for a in build_parser()._actions if a.dest == "loop.descriptor.fusion")
    assert tuple(fusion.choices) == FUSION_MODES  # one list of modes


def test_wrong_folder_is_a_clear_error(tmp_path, capsys):
    missing = tmp_path / "no_such_sequence"
    assert main([str(missing), "--out", str(tmp_path / "out"), "--no-loop"]) == 2
    err = capsys.readouterr().err
    assert "no_such_sequence" in err and "does not exist" in err
    assert not (tmp_path / "out").exists()  # nothing created for a run that cannot start


def test_folder_of_wrong_layout_names_what_was_expected(tmp_path, capsys):
    (tmp_path / "notes.txt").write_text("hello")
    assert main([str(tmp_path), "--out", str(tmp_path / "out"), "--no-loop"]) == 2
    err = capsys.readouterr().err
    assert "rgb.txt" in err and "frame-000000.color" in err


def test_sequence_and_demo_together_is_an_error(tmp_path, capsys):
    assert main(["somewhere", "--demo", "--out", str(tmp_path)]) == 2
    assert "either" in capsys.readouterr().err


def test_rgb_from_depth_on_a_registered_dataset_needs_rgb_intrinsics(tmp_path, capsys):
    seq = _tum_folder(tmp_path)
    assert main([str(seq), "--out", str(tmp_path / "o"), "--rgb-from-depth", "-0.025", "0", "0"]) == 2
    assert "--rgb-intrinsics" in capsys.readouterr().err


def test_offline_without_vgg16_weights_says_what_to_do(tmp_path, monkeypatch, capsys):
    """The paper's default backbone without its weights, offline: the message names the file and the fix."""
    monkeypatch.setenv("TORCH_HOME", str(tmp_path / "torch_home"))
    monkeypatch.setenv("ATTNLOOP_OFFLINE", "1")
    seq = _tum_folder(tmp_path)
    assert main([str(seq), "--out", str(tmp_path / "out"), "--backbone", "vgg16"]) == 2
    err = capsys.readouterr().err
    assert "vgg16-397923af.pth" in err
    assert "--backbone efficientnet_lite0" in err


@pytest.fixture(scope="module")
def demo_run(tmp_path_factory):
    """A short demo (24 frames, 160 x 120, odometry only): the command's outputs."""
    out = tmp_path_factory.mktemp("demo")
    assert main([*DEMO, "--no-loop", "--out", str(out)]) == 0
    return out


@pytest.fixture(scope="module")
def room_sequence(tmp_path_factory):
    """30 frames of the room demo's loop at a hand-held pace (every 2nd of its first 60), 160 x 120."""
    from slam.io import Trajectory
    from slam.synthetic import generate_sequence, make_trajectory

    loop = make_trajectory("loop", 300)
    return generate_sequence(tmp_path_factory.mktemp("room") / "seq", width=160, height=120,
                             trajectory=Trajectory(loop.timestamps[:60:2], loop.poses[:60:2]))


@pytest.fixture(scope="module")
def room_run(room_sequence, tmp_path_factory):
    out = tmp_path_factory.mktemp("room_run")
    assert main([str(room_sequence), "--no-loop", "--quiet", "--out", str(out)]) == 0
    return out


def test_demo_writes_every_output_and_its_sequence(demo_run):
    out = demo_run
    for name in ("trajectory.txt", "loops.txt", "metrics.json", "trajectory.png", "map.ply"):
        assert (out / name).is_file(), name
    assert (out / "demo_sequence" / "groundtruth.txt").is_file()  # the generated folder stays inside --out
    assert not [p.name for p in out.iterdir() if p.name.startswith(".")]  # no temporary files left
    traj = np.loadtxt(out / "trajectory.txt")
    assert traj.shape == (24, 8) and np.isfinite(traj).all()
    m = _strict_json(out / "metrics.json")
    assert m["num_frames"] == 24 and m["frame_step"] == 1
    # 24 frames for a whole loop are fast: some are lost, most tracked (a run of 12 tracks none:
    # tests/cli/test_cli_inputs.py), so the run is a result
    assert m["status"] == "ok" and m["num_tracked"] == 24 - m["num_lost"] >= 12 and m["ate_rmse"] < 0.5
    assert m["backbone"] is None and m["descriptor"] is None  # --no-loop: no descriptor was built
    assert m["rig"].startswith("registered")
    assert m["camera"]["name"] == "calibration.txt" and len(m["camera"]["intrinsics"]) == 4


def test_map_points_lie_on_the_rooms_surfaces(room_run, room_sequence):
    """map.ply: coloured points in the trajectory's frame; moved into the room's frame by the first
    ground-truth pose (the estimate starts at the identity there), they lie on the known surfaces."""
    from slam.io import read_tum_trajectory
    from slam.lie import quat_to_rotmat
    from slam.mapping import read_ply
    from slam.synthetic.scene import default_room_scene

    pts, cols = read_ply(room_run / "map.ply")
    assert pts.shape[0] >= 10_000 and cols is not None and cols.std() > 10
    m = _strict_json(room_run / "metrics.json")
    assert m["map"]["points"] == pts.shape[0]
    assert m["map"]["keyframes"] == m["num_keyframes"] - m["released_keyframes"]  # a released revisit has no points
    gt0 = read_tum_trajectory(room_sequence / "groundtruth.txt").poses[0]
    R, t = quat_to_rotmat(gt0[3:]).numpy(), gt0[:3].numpy()
    room = torch.from_numpy((pts @ R.T + t).astype(np.float32))
    dist = default_room_scene().surface_distance(room).numpy()
    # within the odometry's own error (ATE ~2.4 cm at 160 x 120) plus the 2 cm voxels; the same points
    # placed with the true poses are within 6 mm (median), tests/slam/maps/test_mapping.py checks that exactly
    assert m["ate_rmse"] < 0.04
    assert np.median(dist) < 0.025, np.median(dist)
    assert np.quantile(dist, 0.9) < 0.08, np.quantile(dist, 0.9)


def test_frame_step_uses_every_nth_frame(room_sequence, tmp_path):
    """--frame-step 3 on 24 frames: 8 frames, their own timestamps, the metrics on them."""
    from slam.io import read_tum_trajectory

    out = tmp_path / "step3"
    seq = room_sequence
    assert main([str(seq), "--out", str(out), "--no-loop", "--no-map", "--frame-step", "3", "--max-frames", "24",
                 "--quiet"]) == 0
    traj = read_tum_trajectory(out / "trajectory.txt")
    gt = read_tum_trajectory(seq / "groundtruth.txt")
    assert torch.equal(traj.timestamps, gt.timestamps[:24:3])
    m = _strict_json(out / "metrics.json")
    assert (m["num_frames"], m["frame_step"]) == (8, 3) and m["ate"]["num_pairs"] == 8
    assert not (out / "map.ply").exists()  # --no-map


def test_map_voxel_sets_the_density(room_run, room_sequence, tmp_path):
    from slam.mapping import read_ply

    out = tmp_path / "coarse"
    assert main([str(room_sequence), "--out", str(out), "--no-loop", "--map-voxel", "0.1", "--max-frames", "10",
                 "--quiet"]) == 0
    fine, _ = read_ply(room_run / "map.ply")  # 2 cm, all 30 frames
    coarse, _ = read_ply(out / "map.ply")  # 10 cm, the first 10 frames (a third of the views at most)
    assert 0 < coarse.shape[0] < fine.shape[0] / 10  # 5x the edge: ~25x fewer points on the same surfaces
    assert _strict_json(out / "metrics.json")["map"]["voxel_size"] == 0.1


def test_rerun_replaces_outputs_and_missing_weights_lose_nothing(demo_run, tmp_path, monkeypatch, capsys):
    """A second run into the same folder replaces the outputs; a run whose weights cannot be found (VGG16
    offline) stops before it touches the previous run's outputs, which stay as they were."""
    seq = demo_run / "demo_sequence"
    out = tmp_path / "out"
    assert main([str(seq), "--out", str(out), "--no-loop", "--no-map", "--max-frames", "10", "--quiet"]) == 0
    before = {p.name: p.read_bytes() for p in out.iterdir() if p.is_file()}
    assert "metrics.json" in before
    monkeypatch.setenv("TORCH_HOME", str(tmp_path / "torch_home"))
    monkeypatch.setenv("ATTNLOOP_OFFLINE", "1")
    assert main([str(seq), "--out", str(out), "--backbone", "vgg16", "--max-frames", "10", "--quiet"]) == 2
    assert "vgg16-397923af.pth" in capsys.readouterr().err
    assert {p.name: p.read_bytes() for p in out.iterdir() if p.is_file()} == before


def test_out_problems_are_found_before_the_work(tmp_path, capsys):
    seq = tmp_path / "not_looked_at"
    a_file = tmp_path / "file.txt"
    a_file.write_text("keep me")
    assert main([*DEMO, "--out", str(a_file)]) == 2
    assert "not a folder" in capsys.readouterr().err and a_file.read_text() == "keep me"
    assert main([*DEMO, "--out", str(a_file / "sub")]) == 2
    assert "cannot create" in capsys.readouterr().err
    out = tmp_path / "taken"
    (out / "metrics.json").mkdir(parents=True)
    (out / "trajectory.txt").write_text("an earlier run")
    assert main([*DEMO, "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert "metrics.json" in err and "not a regular file" in err
    assert (out / "trajectory.txt").read_text() == "an earlier run"  # nothing touched
    assert not (out / "demo_sequence").exists() and not seq.exists()


@pytest.mark.parametrize("argv, expected", [
    (["--demo-frames", "0"], "--demo-frames"),
    (["--demo-frames", "1"], "at least 10 frames"),
    (["--demo-frames", "3"], "at least 10 frames"),
    (["--demo-trajectory", "bogus"], "figure_eight"),
    (["--device", "bogus"], "not a torch device"),
    (["--rgb-from-depth", "inf", "0", "0"], "finite"),
    (["--rgb-intrinsics", "0", "0", "0", "0"], "focal lengths must be positive"),
    (["--rgb-intrinsics", "nan", "525", "320", "240"], "finite"),
    (["--frame-step", "0"], "--frame-step"),
    (["--map-voxel", "-1"], "--map-voxel"),
    (["--registered", "--rgb-intrinsics", "525", "525", "320", "240"], "--registered"),
    (["--camera", "fr1"], "--camera"),
])
def test_bad_demo_options_are_clear_errors(argv, expected, tmp_path, capsys):
    assert _exit_code([*DEMO, *argv, "--out", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err
    assert expected in err and "Traceback" not in err
    assert not (tmp_path / "out" / "demo_sequence").exists()  # refused before any rendering


def _exit_code(argv) -> int:
    """main's return value, or the exit code of argparse's own usage error."""
    try:
        return main(argv)
    except SystemExit as e:
        return e.code


def test_cuda_on_a_cpu_only_torch_is_a_clear_error(tmp_path, capsys):
    if torch.cuda.is_available():
        pytest.skip("a CUDA device is present")
    assert main([*DEMO, "--device", "cuda", "--out", str(tmp_path / "o")]) == 2
    assert "attnloop-slam: --device 'cuda': " in (err := capsys.readouterr().err) and "CUDA is not available" in err


@pytest.mark.timeout(600)
def test_cli_runs_on_real_frames_with_the_kinect_rig_by_default(redkitchen_dir, tmp_path, capsys):
    out = tmp_path / "out"
    assert main([str(redkitchen_dir), "--out", str(out), "--no-loop", "--max-frames", "30", "--quiet"]) == 0
    assert "ATE" in capsys.readouterr().out
    lines = [ln for ln in (out / "trajectory.txt").read_text().splitlines() if not ln.startswith("#")]
    assert len(lines) == 30
    for name in ("loops.txt", "metrics.json", "trajectory.png", "map.ply"):
        assert (out / name).is_file()
    m = _strict_json(out / "metrics.json")
    assert "525 525 320 240" in m["rig"] and "-0.025 0 0" in m["rig"]  # no rig flag given
    assert math.isfinite(m["ate_rmse"]) and m["ate_rmse"] < 0.05


def test_a_one_frame_run_that_initialised_does_not_warn(room_sequence, tmp_path, capsys):
    # it said "no frame could be tracked ... see the warnings above" with no warning above
    assert main([str(room_sequence), "--no-loop", "--no-map", "--quiet", "--max-frames", "1",
                 "--out", str(tmp_path / "one")]) == 0
    assert "no frame could be tracked" not in capsys.readouterr().err
    m = _strict_json(tmp_path / "one" / "metrics.json")
    assert m["num_frames"] == 1 and m["num_lost"] == 0
