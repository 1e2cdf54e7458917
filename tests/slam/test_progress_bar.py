"""The run's progress bar (tqdm, on stderr): frames/s and the time left when shown, nothing when stderr is not a
terminal (unless asked for) or with ``progress=False``."""
from __future__ import annotations

import io
import re
import sys

import pytest

from slam.config import SLAMConfig, override
from slam.pipeline import run_slam


@pytest.fixture(scope="module")
def tiny_sequence(tmp_path_factory):
    from slam.io import open_sequence
    from slam.synthetic import generate_sequence

    return open_sequence(generate_sequence(tmp_path_factory.mktemp("bar") / "seq", num_frames=5, width=160,
                                           height=120))


class _Terminal(io.StringIO):
    def isatty(self) -> bool:
        return True


@pytest.mark.parametrize("stream, progress, shown", [(io.StringIO, None, False), (_Terminal, None, True),
                                                     (io.StringIO, True, True), (_Terminal, False, False)])
def test_bar_on_a_terminal_or_when_asked(tiny_sequence, monkeypatch, stream, progress, shown):
    err = stream()
    monkeypatch.setattr(sys, "stderr", err)
    run = run_slam(tiny_sequence, override(SLAMConfig(), {"loop.enabled": False, "map.enabled": False}),
                   progress=progress)
    assert run.result.num_frames == 5
    text = err.getvalue()
    if not shown:
        assert text == ""
        return
    last = text.replace("\r", "\n").strip().splitlines()[-1]
    # "seq: 100%|##########| 5/5 [00:01<00:00,  3.21frame/s, kf=2 loops=0]": frames/s and the time left
    m = re.search(r"5/5 \[(\d\d:\d\d)<(\d\d:\d\d), +([\d.]+)frame/s", last)
    assert m is not None, last
    assert m.group(2) == "00:00" and float(m.group(3)) > 0
