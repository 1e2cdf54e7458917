"""The descriptor's presets at every entry point: ``AttentionDescriptor(preset=...)``, ``DescriptorConfig(preset=...)``,
``attnloop-slam --preset``, ``examples/ablation.py --preset`` (Table 1 in the paper's layout). The paper's
presets need VGG16's weights and never run another network in their place.

The VGG16 here is seeded random weights in torchvision's state-dict layout (written from that layout's
key names and shapes, not from this library's module): it checks the plumbing, never accuracy."""
from __future__ import annotations

import json

import pytest
import torch

from attnloop.descriptor import DescriptorRecipe
from attnloop.presets import PRESETS
from slam.ablation import markdown_table
from slam.cli import main
from slam.config import DescriptorConfig

#: torchvision's VGG16: the convolutions' indices in ``features`` and the three linear layers of ``classifier``.
_CONVS = {0: (3, 64), 2: (64, 64), 5: (64, 128), 7: (128, 128), 10: (128, 256), 12: (256, 256), 14: (256, 256),
          17: (256, 512), 19: (512, 512), 21: (512, 512), 24: (512, 512), 26: (512, 512), 28: (512, 512)}
_LINEAR = {0: (512 * 7 * 7, 4096), 3: (4096, 4096), 6: (4096, 1000)}


@pytest.fixture(scope="module")
def random_vgg16(tmp_path_factory):
    """A seeded random VGG16 checkpoint in torchvision's layout (He-scaled, so activations stay finite)."""
    g = torch.Generator().manual_seed(0)
    state = {}
    for i, (cin, cout) in _CONVS.items():
        state[f"features.{i}.weight"] = torch.randn(cout, cin, 3, 3, generator=g) * (2.0 / (9 * cin)) ** 0.5
        state[f"features.{i}.bias"] = torch.zeros(cout)
    for i, (cin, cout) in _LINEAR.items():
        state[f"classifier.{i}.weight"] = torch.randn(cout, cin, generator=g) * (2.0 / cin) ** 0.5
        state[f"classifier.{i}.bias"] = torch.zeros(cout)
    path = tmp_path_factory.mktemp("vgg") / "random-vgg16.pth"
    torch.save(state, path)
    return path


@pytest.fixture(scope="module")
def tiny_sequence(tmp_path_factory):
    from slam.io import Trajectory
    from slam.synthetic import generate_sequence, make_trajectory

    loop = make_trajectory("loop", 300)
    return generate_sequence(tmp_path_factory.mktemp("tiny") / "rgbd_dataset_freiburg1_tiny", width=160,
                             height=120, trajectory=Trajectory(loop.timestamps[:16:2], loop.poses[:16:2]))


@pytest.fixture
def empty_hub(monkeypatch, tmp_path):
    """No VGG16 in the torch hub cache, and downloads off."""
    monkeypatch.setenv("TORCH_HOME", str(tmp_path / "torch_home"))
    monkeypatch.setenv("ATTNLOOP_OFFLINE", "1")


def test_the_presets_are_the_papers_settings():
    paper = DescriptorRecipe(fusion="dam", pooling="flat", num_rnn=16, out_features=64, pool_scale=None, merge=True)
    assert DescriptorConfig(preset="paper").recipe == paper
    assert DescriptorConfig(preset="paper", fusion="gaf").recipe == DescriptorRecipe(
        fusion="gaf", pooling="flat", num_rnn=16, out_features=64, pool_scale=None, merge=True)
    # the baseline: the same encoding, without attention and without the merge of channel pairs
    assert DescriptorConfig(preset="guclu2019").recipe == DescriptorRecipe(
        fusion="none", pooling="flat", num_rnn=16, out_features=64, pool_scale=None, merge=False)
    assert DescriptorConfig().recipe == DescriptorRecipe()  # the default: ours
    assert set(PRESETS) == {"default", "paper", "guclu2019"}
    assert PRESETS["paper"].auto_backbone == PRESETS["guclu2019"].auto_backbone == "vgg16"


def test_the_default_taps_lite0_at_stage5_of_a_256_x_320_input_with_gem_p3_and_no_attention():
    from attnloop import AttentionDescriptor

    d = AttentionDescriptor("efficientnet_lite0", pretrained=False)
    net = d.backbone
    assert (net.tap, net.input_size, net.tap_groups) == ("stage5", (256, 320), (112,))
    assert (d.preset, d.recipe.fusion, d.recipe.pooling, d.recipe.num_rnn, d.recipe.gem_p) == (
        "default", "none", "regional", 0, 3.0)
    assert d.out_dim == 5 * 112  # the whole map and 2 x 2 regions of stage5's 112 channels
    # the paper's fusion stays DAM, whatever the default's
    assert AttentionDescriptor("efficientnet_lite0", pretrained=False, preset="paper").recipe.fusion == "dam"
    assert AttentionDescriptor("efficientnet_lite0", pretrained=False, preset="paper", fusion="gaf").fusion == "gaf"


@pytest.mark.parametrize("kwargs, match", [
    (dict(preset="guclu2019", fusion="dam"), r"DescriptorConfig\.fusion is 'none' in the preset 'guclu2019'"),
    (dict(preset="paper", num_rnn=8), r"DescriptorConfig\.num_rnn is 16 in the preset 'paper', got 8"),
    (dict(preset="Paper"), r"DescriptorConfig\.preset must be one of 'default', 'paper', 'guclu2019'"),
])
def test_a_setting_the_preset_fixes_is_refused(kwargs, match):
    with pytest.raises(ValueError, match=match):
        DescriptorConfig(**kwargs)


def test_guclu2019_builds_a_1024d_descriptor_without_the_merge(random_vgg16):
    from slam.loop.closer import build_descriptor

    base = build_descriptor(DescriptorConfig(preset="guclu2019", backbone="vgg16", weights=str(random_vgg16)))
    paper = build_descriptor(DescriptorConfig(preset="paper", backbone="vgg16", weights=str(random_vgg16)))
    assert base.out_dim == paper.out_dim == 1024 and base.backbone_name == paper.backbone_name == "vgg16"
    # each of the 16 RNNs reads VGG16's pool5 (512 x 7 x 7): all 512 channels unmerged, 256 merged pairs
    assert base.pool.weights.shape == (16, 64, 512 * 7 * 7) and paper.pool.weights.shape == (16, 64, 256 * 7 * 7)
    assert (base.preset, base.recipe.fusion, paper.preset, paper.recipe.fusion) == ("guclu2019", "none", "paper", "dam")
    with torch.no_grad():
        d = base(torch.randint(0, 256, (2, 3, 120, 160), dtype=torch.uint8))
    assert d.shape == (2, 1024) and torch.allclose(d.norm(dim=1), torch.ones(2))


@pytest.mark.parametrize("preset", ["paper", "guclu2019"])
def test_the_command_refuses_the_papers_presets_without_vgg16_weights(preset, empty_hub, tiny_sequence, tmp_path,
                                                                      capsys):
    out = tmp_path / "out"
    assert main([str(tiny_sequence), "--preset", preset, "--out", str(out), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert "vgg16-397923af.pth" in err and "--weights FILE" in err and err.startswith("attnloop-slam: VGG16")
    assert not out.exists()  # before any work


@pytest.mark.timeout(600)
def test_the_command_runs_the_paper_preset_with_given_weights(random_vgg16, empty_hub, tiny_sequence, tmp_path):
    out = tmp_path / "out"
    assert main([str(tiny_sequence), "--preset", "paper", "--weights", str(random_vgg16), "--out", str(out),
                 "--no-map", "--quiet"]) == 0
    d = json.loads((out / "metrics.json").read_text())["descriptor"]
    assert (d["preset"], d["backbone"], d["dim"], d["fusion"]) == ("paper", "vgg16", 1024, "dam")
    assert (d["recipe"]["pooling"], d["recipe"]["num_rnn"], d["recipe"]["merge"], d["recipe"]["pool_scale"]) == (
        "flat", 16, True, None)
    text = (out / "config.toml").read_text()
    assert 'preset = "paper"' in text and 'backbone = "vgg16"' in text


@pytest.mark.slow
@pytest.mark.timeout(900)
def test_ablation_writes_table1_in_the_papers_layout(random_vgg16, empty_hub, tiny_sequence, tmp_path, load_script,
                                                    capsys):
    mod = load_script("examples/ablation.py")
    out = tmp_path / "abl"
    assert mod.main([str(tiny_sequence), "--preset", "paper", "--weights", str(random_vgg16), "--out", str(out),
                     "--no-map", "--quiet"]) == 0
    table = (out / "table1.md").read_text()
    assert "| sequence | baseline | GAF | EAM | EGA | DAM |" in table
    assert "| rgbd_dataset_freiburg1_tiny |" in table and "| fr1 average |" in table
    data = json.loads((out / "table1.json").read_text())
    assert list(data) == ["baseline", "GAF", "EAM", "EGA", "DAM"]
    runs = {c: data[c]["rgbd_dataset_freiburg1_tiny"]["descriptor"] for c in data}
    assert (runs["baseline"]["preset"], runs["baseline"]["fusion"]) == ("guclu2019", "none")
    assert [(runs[c]["preset"], runs[c]["fusion"]) for c in ("GAF", "EAM", "EGA", "DAM")] == [
        ("paper", "gaf"), ("paper", "eam"), ("paper", "ega"), ("paper", "dam")]
    assert all(r["backbone"] == "vgg16" and r["dim"] == 1024 for r in runs.values())


def _metrics(ate, true=3, false=0):
    return {"ate_rmse": ate, "loops_true": true, "loops_false": false,
            "loop_detection": {"before_verification": {"num_positives": 8, "max_recall_at_full_precision": 0.5},
                               "after_verification": {"num_positives": 8, "max_recall_at_full_precision": 0.75}}}


def test_table1_rows_by_sequence_groups_by_camera_and_the_papers_figures_beside_ours():
    names = ["7scenes-redkitchen", "rgbd_dataset_freiburg2_desk", "rgbd_dataset_freiburg1_room",
             "rgbd_dataset_freiburg1_desk"]
    ates = {"baseline": [0.03, 0.05, 0.0213, 0.04], "DAM": [0.02, 0.06, 0.0100, 0.03]}
    table = {c: {n: _metrics(a) for n, a in zip(names, v)} for c, v in ates.items()}
    md = markdown_table(table, paper={"freiburg1_room": {"DAM": 0.018, "baseline": 0.020},
                                      "freiburg1_desk": {"DAM": 0.026}})
    lines = md.splitlines()
    assert lines[2] == "| sequence | baseline | DAM |"
    rows = [ln.split(" | ")[0].lstrip("| ") for ln in lines[4:11]]
    assert rows == ["rgbd_dataset_freiburg1_room", "rgbd_dataset_freiburg1_desk", "rgbd_dataset_freiburg2_desk",
                    "7scenes-redkitchen", "fr1 average", "fr2 average", "other average"]  # fr1, fr2, fr3, other
    assert lines[4] == "| rgbd_dataset_freiburg1_room | 0.0213 (paper 0.020) | 0.0100 (paper 0.018) |"
    assert lines[5] == "| rgbd_dataset_freiburg1_desk | 0.0400 | 0.0300 (paper 0.026) |"
    # fr1: (0.0213 + 0.04) / 2 and (0.01 + 0.03) / 2; the paper's average only where it has both
    assert lines[8] == "| fr1 average | 0.0307 | 0.0200 (paper 0.022) |"
    assert lines[9] == "| fr2 average | 0.0500 | 0.0600 |"
    assert "| rgbd_dataset_freiburg1_room | 3/0; 0.50 -> 0.75 | 3/0; 0.50 -> 0.75 |" in lines
