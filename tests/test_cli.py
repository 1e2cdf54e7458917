"""The command line: argument errors, wrong folders and the offline VGG16 message (no network is touched)."""
from __future__ import annotations

import pytest

from slam.cli import build_parser, main


def test_parser_defaults_are_the_papers():
    args = build_parser().parse_args(["seq", "--out", "o"])
    assert (args.fusion, args.backbone, args.no_loop, args.max_frames) == ("dam", "vgg16", False, None)


def test_wrong_folder_is_a_clear_error(tmp_path, capsys):
    missing = tmp_path / "no_such_sequence"
    assert main([str(missing), "--out", str(tmp_path / "out"), "--no-loop"]) == 2
    err = capsys.readouterr().err
    assert "no_such_sequence" in err and "does not exist" in err


def test_folder_of_wrong_layout_names_what_was_expected(tmp_path, capsys):
    (tmp_path / "notes.txt").write_text("hello")
    assert main([str(tmp_path), "--out", str(tmp_path / "out"), "--no-loop"]) == 2
    err = capsys.readouterr().err
    assert "rgb.txt" in err and "frame-000000.color" in err


def test_sequence_and_demo_together_is_an_error(tmp_path, capsys):
    assert main(["somewhere", "--demo", "--out", str(tmp_path)]) == 2
    assert "either" in capsys.readouterr().err


def test_rgb_from_depth_needs_rgb_intrinsics(tmp_path, capsys):
    assert main(["somewhere", "--out", str(tmp_path), "--rgb-from-depth", "-0.025", "0", "0"]) == 2
    assert "--rgb-intrinsics" in capsys.readouterr().err


def test_offline_without_vgg16_weights_says_what_to_do(tmp_path, monkeypatch, capsys):
    """The paper's default backbone without its weights, offline: the message names the file and the fix."""
    monkeypatch.setenv("TORCH_HOME", str(tmp_path / "torch_home"))
    monkeypatch.setenv("ATTNLOOP_OFFLINE", "1")
    seq = tmp_path / "seq"
    seq.mkdir()
    (seq / "rgb.txt").write_text("0.0 rgb/0.png\n")
    (seq / "depth.txt").write_text("0.0 depth/0.png\n")
    assert main([str(seq), "--out", str(tmp_path / "out"), "--backbone", "vgg16"]) == 2
    err = capsys.readouterr().err
    assert "vgg16-397923af.pth" in err
    assert "--backbone efficientnet_lite0" in err


@pytest.mark.timeout(600)
def test_cli_runs_on_real_frames(redkitchen_dir, tmp_path, capsys):
    out = tmp_path / "out"
    assert main([str(redkitchen_dir), "--out", str(out), "--no-loop", "--max-frames", "30", "--quiet"]) == 0
    assert "ATE" in capsys.readouterr().out
    lines = [ln for ln in (out / "trajectory.txt").read_text().splitlines() if not ln.startswith("#")]
    assert len(lines) == 30
    for name in ("loops.txt", "metrics.json", "trajectory.png"):
        assert (out / name).is_file()
