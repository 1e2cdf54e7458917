"""slam.threads and SLAMConfig.threads: torch/BLAS/OpenCV thread counts set for a run and the caller's restored
after it (also when it fails), ``--threads`` on the command line, bad counts refused by name."""
from __future__ import annotations

import argparse

import cv2
import pytest
import torch

from slam.config import ConfigError, SLAMConfig, override
from slam.options import add_run_arguments, given_settings, resolve_settings
from slam.threads import check_threads, limit_threads, thread_counts


def _parse(*argv):
    p = argparse.ArgumentParser()
    add_run_arguments(p)
    return p.parse_args(list(argv))

def _config(*argv, sequence=None):
    """The config the command builds from ``argv`` (and the dataset's rig of ``sequence``)."""
    return resolve_settings(given_settings(_parse(*argv)), sequence=sequence).config


@pytest.fixture
def caller_counts():
    """The caller's counts set to 2 (torch, OpenCV), whatever the environment set, and put back after."""
    saved = torch.get_num_threads(), cv2.getNumThreads()
    torch.set_num_threads(2)
    cv2.setNumThreads(2)
    yield thread_counts()
    torch.set_num_threads(saved[0])
    cv2.setNumThreads(saved[1])


def test_limit_threads_sets_inside_and_restores_after(caller_counts):
    with limit_threads(1):
        inside = thread_counts()
        assert inside["torch"] == 1 and inside["opencv"] == 1
        assert all(n == 1 for n in inside["blas"])
        import scipy.linalg  # noqa: F401  (its BLAS is among those limited: the pose graph's LAPACK calls)

        assert len(inside["blas"]) == len(thread_counts()["blas"])
    assert thread_counts() == caller_counts
    with limit_threads(None):  # None changes nothing
        assert thread_counts() == caller_counts
    with pytest.raises(KeyError), limit_threads(1):
        raise KeyError("boom")
    assert thread_counts() == caller_counts


@pytest.mark.parametrize("bad", [0, -1, 1.5, True, "2"])
def test_bad_counts_are_refused_by_name(bad):
    with pytest.raises(ValueError, match="threads must be a whole number >= 1"):
        check_threads(bad)
    with pytest.raises(ValueError, match="whole number"), limit_threads(bad):
        pass
    with pytest.raises(ConfigError, match="SLAMConfig.threads must be a whole number"):
        override(SLAMConfig(), {"threads": bad})
    with pytest.raises(ValueError, match="SLAMConfig.threads must be a whole number"):
        SLAMConfig(threads=bad)


def test_numpy_integers_are_counts():
    import numpy as np

    assert check_threads(np.int64(2)) == 2 and isinstance(check_threads(np.int64(2)), int)


def test_threads_flag_and_default():
    assert SLAMConfig().threads == 1
    assert _config().threads == 1
    assert _config("--threads", "3").threads == 3
    for bad in ("0", "-2", "1.5", "x"):
        with pytest.raises(SystemExit):  # argparse's usage error (exit code 2) naming --threads
            _parse("--threads", bad)


@pytest.fixture(scope="module")
def tiny_sequence(tmp_path_factory):
    from slam.io import open_sequence
    from slam.synthetic import generate_sequence

    return open_sequence(generate_sequence(tmp_path_factory.mktemp("thr") / "seq", num_frames=5, width=160,
                                           height=120))


def _record_track(monkeypatch, fail_at=None):
    from slam.system import RGBDSLAM

    seen = []
    original = RGBDSLAM.track

    def track(self, frame, **kwargs):
        seen.append((torch.get_num_threads(), cv2.getNumThreads()))
        if fail_at is not None and len(seen) == fail_at:
            raise RuntimeError("tracking failed on purpose")
        return original(self, frame, **kwargs)

    monkeypatch.setattr(RGBDSLAM, "track", track)
    return seen


@pytest.mark.parametrize("threads", [1, 3])
def test_run_slam_computes_with_the_configs_threads_and_restores_the_callers(tiny_sequence, caller_counts,
                                                                               monkeypatch, threads):
    from slam.pipeline import run_slam

    seen = _record_track(monkeypatch)
    cfg = SLAMConfig()
    cfg = override(cfg, {"loop.enabled": False, "map.enabled": False, "threads": threads})
    run = run_slam(tiny_sequence, cfg, progress=False)
    assert len(seen) == len(tiny_sequence) == run.result.num_frames
    assert set(seen) == {(threads, threads)}
    assert thread_counts() == caller_counts


def test_run_slam_with_threads_none_leaves_the_callers(tiny_sequence, caller_counts, monkeypatch):
    from slam.pipeline import run_slam

    seen = _record_track(monkeypatch)
    cfg = override(SLAMConfig(), {"loop.enabled": False, "map.enabled": False, "threads": None})
    run_slam(tiny_sequence, cfg, progress=False)
    assert set(seen) == {(2, 2)}


def test_a_failed_run_restores_the_callers_threads(tiny_sequence, caller_counts, monkeypatch):
    from slam.pipeline import run_slam

    seen = _record_track(monkeypatch, fail_at=2)
    cfg = override(SLAMConfig(), {"loop.enabled": False, "map.enabled": False})
    with pytest.raises(RuntimeError, match="on purpose"):
        run_slam(tiny_sequence, cfg, progress=False)
    assert seen == [(1, 1), (1, 1)]
    assert thread_counts() == caller_counts


def test_the_streaming_api_computes_with_the_callers_threads(tiny_sequence, caller_counts, monkeypatch):
    """No limit below the run's: RGBDSLAM.track / finish compute with whatever the caller set (here 2, while
    the config says 1), so a program driving it frame by frame wraps its loop in one limit_threads."""
    from slam.system import RGBDSLAM

    seen = []
    slam = RGBDSLAM(override(SLAMConfig(), {"loop.enabled": False, "threads": 1}))
    odo_track = slam.odometry.track

    def spy(frame, features=None):
        seen.append((torch.get_num_threads(), cv2.getNumThreads()))
        return odo_track(frame, features)

    slam.odometry.track = spy
    for i in range(len(tiny_sequence) - 1):
        slam.track(tiny_sequence[i])
    assert seen == [(2, 2)] * (len(tiny_sequence) - 1)
    with limit_threads(slam.config.threads):
        slam.track(tiny_sequence[len(tiny_sequence) - 1])
    slam.finish()
    assert seen[-1] == (1, 1)
    assert thread_counts() == caller_counts
