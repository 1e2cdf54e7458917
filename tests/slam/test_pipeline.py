"""slam.pipeline.run_slam's observer: every used frame in order, an unreadable one as None, the final result
once, and an error of the observer stops the run."""
from __future__ import annotations

import pytest

from slam.config import SLAMConfig, override

CONFIG = override(SLAMConfig(), {"loop.enabled": False, "map.enabled": False})


@pytest.fixture(scope="module")
def sequence_with_a_missing_frame(tmp_path_factory):
    from slam.io import open_sequence
    from slam.synthetic import generate_sequence

    folder = generate_sequence(tmp_path_factory.mktemp("hook") / "seq", num_frames=8, width=160, height=120)
    sorted((folder / "rgb").iterdir())[4].unlink()  # frame 4 cannot be read
    return open_sequence(folder)


class Recorder:
    def __init__(self, fail_at=None):
        self.seen, self.finished, self.fail_at = [], [], fail_at

    def frame(self, frame, state, slam):
        i = len(self.seen)
        if i == self.fail_at:
            raise RuntimeError("the viewer went away")
        self.seen.append((i, frame is None, state.index, state.status, len(slam.keyframes)))

    def finish(self, result):
        self.finished.append(result)


def test_the_observer_sees_every_used_frame_with_its_state(sequence_with_a_missing_frame):
    from slam.pipeline import run_slam

    observer = Recorder()
    run = run_slam(sequence_with_a_missing_frame, CONFIG, progress=False, frame_step=2, observer=observer)
    seen = observer.seen
    # input frames 0, 2, 4, 6 are the run's 0..3; input frame 4 cannot be read
    assert [(i, missing, index) for i, missing, index, _, _ in seen] == [(0, False, 0), (1, False, 1), (2, True, 2),
                                                                         (3, False, 3)]
    statuses = [status for _, _, _, status, _ in seen]
    assert statuses[2] == "skipped" and seen[0][4] == 1  # the first frame made the first keyframe
    assert run.result.tracked.tolist() == [s not in ("lost", "skipped") for s in statuses]
    assert observer.finished == [run.result]


def test_an_error_of_the_observer_stops_the_run(sequence_with_a_missing_frame):
    from slam.pipeline import run_slam

    with pytest.raises(RuntimeError, match="viewer went away"):
        run_slam(sequence_with_a_missing_frame, CONFIG, progress=False, observer=Recorder(fail_at=1))


def test_finished_map_jobs_are_let_go_and_their_errors_raised():
    """The run keeps only the map worker's pending jobs (not one per keyframe of the whole run); a finished
    job that failed raises its error."""
    import threading
    from concurrent.futures import ThreadPoolExecutor

    from slam.pipeline import _running

    gate = threading.Event()
    with ThreadPoolExecutor(max_workers=1) as pool:
        done = [pool.submit(int, k) for k in range(5)]
        for job in done:
            job.result()
        pending = pool.submit(gate.wait)
        kept = _running(done + [pending])
        assert kept == [pending]
        gate.set()
        failed = pool.submit(int, "not a number")
        failed.exception()
        with pytest.raises(ValueError, match="not a number"):
            _running([failed])
