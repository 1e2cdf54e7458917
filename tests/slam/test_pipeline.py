"""slam.pipeline.run_slam's per-frame callback: every used frame in order, an unreadable one as None, and an
error of the callback stops the run."""
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


def test_on_frame_sees_every_used_frame_with_its_state(sequence_with_a_missing_frame):
    from slam.pipeline import run_slam

    seen = []

    def on_frame(i, frame, state, slam):
        seen.append((i, frame is None, state.index, state.status, len(slam.keyframes)))

    run = run_slam(sequence_with_a_missing_frame, CONFIG, progress=False, frame_step=2, on_frame=on_frame)
    # input frames 0, 2, 4, 6 are the run's 0..3; input frame 4 cannot be read
    assert [(i, missing, index) for i, missing, index, _, _ in seen] == [(0, False, 0), (1, False, 1), (2, True, 2),
                                                                         (3, False, 3)]
    statuses = [status for _, _, _, status, _ in seen]
    assert statuses[2] == "skipped" and seen[0][4] == 1  # the first frame made the first keyframe
    assert run.result.tracked.tolist() == [s not in ("lost", "skipped") for s in statuses]


def test_an_error_of_on_frame_stops_the_run(sequence_with_a_missing_frame):
    from slam.pipeline import run_slam

    def on_frame(i, frame, state, slam):
        if i == 1:
            raise RuntimeError("the viewer went away")

    with pytest.raises(RuntimeError, match="viewer went away"):
        run_slam(sequence_with_a_missing_frame, CONFIG, progress=False, on_frame=on_frame)
