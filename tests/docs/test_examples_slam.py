"""examples/tum_slam.py and examples/ablation.py: their --help reads as written, they share the command's
options (rig flags, --frame-step, --config, --preset) and report errors as it does."""
from __future__ import annotations

import json

import pytest

from slam.config import override


@pytest.fixture(scope="module")
def tiny_sequence(tmp_path_factory):
    from slam.io import Trajectory
    from slam.synthetic import generate_sequence, make_trajectory

    loop = make_trajectory("loop", 300)
    return generate_sequence(tmp_path_factory.mktemp("tiny") / "seq", width=160, height=120,
                             trajectory=Trajectory(loop.timestamps[:16:2], loop.poses[:16:2]))


@pytest.mark.parametrize("script, lines", [
    ("examples/tum_slam.py",
     ["    python examples/tum_slam.py ~/data/rgbd_dataset_freiburg1_room --out runs/fr1_room"]),
    ("examples/ablation.py", [("  python examples/ablation.py ~/data/rgbd_dataset_freiburg1_room "
                              "~/data/rgbd_dataset_freiburg2_desk \\"), ("      --preset paper --weights "
                              "vgg16-397923af.pth --out runs/table1     # the paper's descriptor and columns")]),
])
def test_help_keeps_the_docstrings_lines(script, lines, load_script, capsys):
    mod = load_script(script)
    with pytest.raises(SystemExit) as e:
        mod.main(["--help"])
    assert e.value.code == 0
    out = capsys.readouterr().out
    for line in lines:
        assert line in out.splitlines(), line
    for flag in ("--rgb-intrinsics", "--rgb-from-depth", "--registered", "--frame-step", "--backbone", "--preset",
                 "--config"):
        assert flag in out


def test_tum_slam_runs_with_the_commands_options(tiny_sequence, tmp_path, load_script, capsys):
    mod = load_script("examples/tum_slam.py")
    out = tmp_path / "out"
    assert mod.main([str(tiny_sequence), "--out", str(out), "--no-loop", "--frame-step", "2"]) == 0
    m = json.loads((out / "metrics.json").read_text())
    assert (m["num_frames"], m["frame_step"]) == (4, 2)
    assert "ate_rmse" in capsys.readouterr().out


def test_tum_slam_reports_missing_weights_as_the_command_does(tiny_sequence, tmp_path, load_script, capsys,
                                                              monkeypatch):
    monkeypatch.setenv("TORCH_HOME", str(tmp_path / "torch_home"))
    monkeypatch.setenv("ATTNLOOP_OFFLINE", "1")
    mod = load_script("examples/tum_slam.py")
    assert mod.main([str(tiny_sequence), "--out", str(tmp_path / "o"), "--backbone", "vgg16"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("tum_slam.py: ") and "vgg16-397923af.pth" in err and "--backbone efficientnet_lite0" in err
    assert "Traceback" not in err


def test_tum_slam_refuses_a_flag_another_makes_idle_as_the_command_does(tiny_sequence, tmp_path, load_script,
                                                                         capsys):
    mod = load_script("examples/tum_slam.py")
    out = tmp_path / "out"
    assert mod.main([str(tiny_sequence), "--out", str(out), "--no-loop", "--fusion", "dam"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("tum_slam.py: --no-loop") and "--fusion" in err and not out.exists()


def test_ablation_runs_our_columns_and_writes_its_table(tiny_sequence, tmp_path, load_script, capsys):
    mod = load_script("examples/ablation.py")
    out = tmp_path / "abl"
    assert mod.main([str(tiny_sequence), "--out", str(out), "--no-loop", "--no-map", "--quiet"]) == 0
    table = (out / "table1.md").read_text()
    assert "| sequence | none | dam | eam | gaf | ega |" in table and "| other average |" in table
    data = json.loads((out / "table1.json").read_text(), parse_constant=lambda c: pytest.fail(c))
    assert list(data) == ["none", "dam", "eam", "gaf", "ega"]
    for mode in data:
        assert (out / mode / "seq" / "trajectory.txt").is_file()
    assert "frames/s" not in capsys.readouterr().out  # --quiet: the tables only
    text = (out / "gaf" / "seq" / "config.toml").read_text()  # each run's own settings, its column's fusion
    assert 'preset = "default"' in text and 'fusion = "gaf"' in text
    from slam.cli import main

    again = tmp_path / "again"
    assert main([str(tiny_sequence), "--config", str(out / "gaf" / "seq" / "config.toml"), "--out", str(again),
                 "--quiet"]) == 0
    assert (again / "trajectory.txt").read_text() == (out / "gaf" / "seq" / "trajectory.txt").read_text()


def test_ablation_refuses_a_bad_folder_before_any_run(tmp_path, load_script, capsys):
    mod = load_script("examples/ablation.py")
    assert mod.main([str(tmp_path / "missing"), "--out", str(tmp_path / "abl")]) == 2
    assert "does not exist" in capsys.readouterr().err


def test_ablation_refuses_a_flag_another_makes_idle(tiny_sequence, tmp_path, load_script, capsys):
    mod = load_script("examples/ablation.py")
    out = tmp_path / "abl"
    assert mod.main([str(tiny_sequence), "--out", str(out), "--no-map", "--map-voxel", "0.05"]) == 2
    assert "--map-voxel" in capsys.readouterr().err and not out.exists()


def test_run_ablation_applies_configure_and_calls_measure(tiny_sequence, tmp_path):
    # benchmarks/slam_pipeline.py's --set and its extra figures go through these two hooks
    from slam.ablation import run_ablation

    seen = []

    def configure(cfg):
        return override(cfg, {"backend.optimize_on_loop": False})

    def measure(run, metrics):
        seen.append((run.sequence_name, run.config.loop.descriptor.fusion, run.config.backend.optimize_on_loop))
        metrics["extra"] = len(seen)

    columns = {m: {"loop.descriptor.fusion": m} for m in ("none", "dam")}
    from slam.options import resolve_settings

    spec = resolve_settings({"loop.enabled": False, "map.enabled": False}, sequence=tiny_sequence)
    table = run_ablation([spec], tmp_path / "abl", columns,
                         configure=configure, measure=measure, quiet=True)
    name = tiny_sequence.name
    assert seen == [(name, "none", False), (name, "dam", False)]
    assert [table[m][name]["extra"] for m in ("none", "dam")] == [1, 2]
