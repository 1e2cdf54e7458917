"""What runs where (docs/devices.md): ``--device`` (the descriptor) and ``--backend-device`` (the pose graph)
checked with errors naming the flag, each device setting wired to what it moves, the CPU settings giving the
default run's numbers, and the same run on CUDA where there is one."""
from __future__ import annotations

import argparse
import dataclasses
import math

import pytest
import torch

from slam.backend import PoseGraphBackend
from slam.config import BackendConfig, DescriptorConfig, SLAMConfig, override
from slam.keyframe_graph import EdgeKind, KeyframeGraph
from slam.lie import se3_between, se3_compose, se3_exp, se3_identity
from slam.options import UsageError, add_run_arguments, check_device, given_settings, resolve_settings

D = torch.float64
SCALE = {EdgeKind.ODOMETRY: 1.0, EdgeKind.LOOP: 1.0}
CUDA = pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device")


def _parse(*argv):
    p = argparse.ArgumentParser()
    add_run_arguments(p)
    return p.parse_args(list(argv))

def _config(*argv, sequence=None):
    """The config the command builds from ``argv`` (and the dataset's rig of ``sequence``)."""
    return resolve_settings(given_settings(_parse(*argv)), sequence=sequence).config


def _loop_graph():
    """A drifting walk round a square (odometry with a heading bias) closed by two loops."""
    truth = [se3_identity(dtype=D)]
    for side in range(4):
        for k in range(5):
            truth.append(se3_compose(truth[-1], se3_exp(torch.tensor(
                [0.5, 0, 0, 0, 0, math.pi / 2 if k == 4 else 0.0], dtype=D))))
    bias = se3_exp(torch.tensor([0, 0, 0, 0, 0, math.radians(1.0)], dtype=D))
    info = torch.diag(torch.tensor([100.0, 100, 100, 1000, 1000, 1000], dtype=D))
    g = KeyframeGraph()
    g.add_keyframe(truth[0])
    for j in range(1, len(truth)):
        m = se3_compose(se3_between(truth[j - 1], truth[j]), bias)
        g.add_odometry(j - 1, m, info, se3_compose(g.estimate(j - 1), m))
    for a, b in ((0, 20), (2, 18)):
        g.add_loop(a, b, se3_between(truth[a], truth[b]), info)
    return g


def test_flags_set_the_two_devices_and_default_to_the_cpu():
    cfg = _config()
    assert cfg.loop.descriptor.device is None and cfg.backend.device is None  # None: the CPU
    cfg = _config("--device", "cpu", "--backend-device", "cpu")
    assert cfg.loop.descriptor.device == "cpu" and cfg.backend.device == "cpu"


@pytest.mark.parametrize("flag, field", [("--device", "DescriptorConfig.device"),
                                         ("--backend-device", "BackendConfig.device")])
def test_unusable_devices_are_errors_naming_the_flag(flag, field):
    with pytest.raises(UsageError, match=f"^{flag} 'bogus': .*{field} 'bogus' is not a torch device"):
        _config(flag, "bogus")
    with pytest.raises(UsageError, match=f"^{flag} 'xla': .*device type 'xla' is not supported"):
        _config(flag, "xla")
    if not torch.cuda.is_available():
        with pytest.raises(UsageError, match=f"^{flag} 'cuda': .*CUDA is not available"):
            _config(flag, "cuda")


def test_the_pose_graph_needs_float64_so_not_mps():
    with pytest.raises(UsageError, match="^--backend-device 'mps': .*the pose graph is solved in float64"):
        _config("--backend-device", "mps")
    assert check_device("cpu", "--backend-device", float64=True) == "cpu"


def test_configs_name_the_device_fields():
    with pytest.raises(ValueError, match="BackendConfig.device 'bogus'"):
        override(SLAMConfig(), {"backend.device": "bogus"})
    with pytest.raises(ValueError, match="DescriptorConfig.device 'bogus'"):
        override(SLAMConfig(), {"loop.descriptor.device": "bogus"})


def test_backend_device_moves_the_graph_and_returns_cpu_float64(monkeypatch):
    from slam.graph.pose_graph import PoseGraph

    g = _loop_graph()
    moved = []
    to = PoseGraph.to

    def spy(self, device=None, dtype=None):
        moved.append(torch.device(device) if device is not None else None)
        return to(self, device, dtype)

    monkeypatch.setattr(PoseGraph, "to", spy)
    ref = PoseGraphBackend(BackendConfig(), SCALE).optimize(g)
    assert moved == []  # None: built on the CPU, nothing moved
    res = PoseGraphBackend(dataclasses.replace(BackendConfig(), device="cpu"), SCALE).optimize(g)
    assert moved == [torch.device("cpu")]
    assert res.poses.device.type == "cpu" and res.poses.dtype == torch.float64
    assert torch.equal(res.poses, ref.poses) and res.loop_weights == ref.loop_weights
    assert float((ref.poses - g.odometry_poses()).abs().max()) > 0.05  # the loops did move the poses


def test_descriptor_device_places_the_network():
    from slam.loop.closer import build_descriptor

    model = build_descriptor(DescriptorConfig(backbone="efficientnet_lite0", pretrained=False, device="cpu"))
    assert {p.device.type for p in model.parameters()} == {"cpu"}
    assert {b.device.type for b in model.buffers()} <= {"cpu"}


@CUDA
def test_cuda_backend_gives_the_cpu_poses():
    g = _loop_graph()
    ref = PoseGraphBackend(BackendConfig(), SCALE).optimize(g)
    res = PoseGraphBackend(dataclasses.replace(BackendConfig(), device="cuda"), SCALE).optimize(g)
    assert res.poses.device.type == "cpu"
    assert torch.allclose(res.poses, ref.poses, atol=1e-9)


@CUDA
def test_cuda_descriptor_and_backend_run_end_to_end(tmp_path):
    from slam.io import open_sequence
    from slam.pipeline import run_slam
    from slam.synthetic import generate_sequence

    seq = open_sequence(generate_sequence(tmp_path / "seq", num_frames=30, width=160, height=120))
    cfg = SLAMConfig()
    cfg = override(cfg, {"map.enabled": False})
    ref = run_slam(seq, cfg, progress=False)
    cfg = override(cfg, {"loop.descriptor.device": "cuda", "backend.device": "cuda"})
    run = run_slam(seq, cfg, progress=False)
    # the same keyframes and loops; positions within 1 cm (float32 convolutions differ a little on the GPU)
    assert run.result.num_keyframes == ref.result.num_keyframes and len(run.result.loops) == len(ref.result.loops)
    diff = (run.result.trajectory.poses[:, :3] - ref.result.trajectory.poses[:, :3]).norm(dim=-1)
    assert float(diff.max()) < 0.01


def test_optimize_g2o_takes_threads_and_device(tmp_path, load_script, monkeypatch):
    ex = load_script("examples/optimize_g2o.py")
    src = tmp_path / "line.g2o"
    src.write_text("VERTEX_SE2 0 0 0 0\nVERTEX_SE2 1 1 0 0\nVERTEX_SE2 2 2.1 0 0\n"
                   "EDGE_SE2 0 1 1 0 0 1 0 0 1 0 1\nEDGE_SE2 1 2 1 0 0 1 0 0 1 0 1\n")
    seen = {}
    real = ex.optimize

    def spy(graph, *a, **kw):
        seen.update(device=graph.device, threads=torch.get_num_threads())
        return real(graph, *a, **kw)

    monkeypatch.setattr(ex, "optimize", spy)
    ex.main([str(src)])
    assert seen == {"device": torch.device("cpu"), "threads": 1}  # the example's --threads default
    res = ex.main([str(src), "--threads", "2", "--device", "cpu"])
    assert seen == {"device": torch.device("cpu"), "threads": 2} and res.chi2 < 1e-9
    for bad in (["--threads", "0"], ["--device", "bogus"], ["--device", "mps"]):
        with pytest.raises(SystemExit):
            ex.parse_args([str(src), *bad])
