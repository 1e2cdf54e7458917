"""glibc's allocator kept from returning tensor memory (slam.allocator), and the command that sets it."""
from __future__ import annotations

import json
import os
import subprocess
import sys

import pytest

from slam import allocator, cli

# the function itself: conftest.py replaces it in the test process for every test
keep_freed_memory = allocator.keep_freed_memory

_FAULTS = r"""
import json, resource, sys, torch
from slam.allocator import keep_freed_memory
applied = keep_freed_memory() if sys.argv[1] == "kept" else None
torch.set_num_threads(1)
from attnloop.backbones import efficientnet_lite0
net = efficientnet_lite0(pretrained=False, seed=0, tap="stage6+stage7", input_size=(224, 288))
frame = (torch.rand(1, 3, 480, 640) * 255).to(torch.uint8)
with torch.inference_mode():
    # Kept, the heap grows into its top pad over the first calls (fresh pages: faults up to call ~8), and
    # now and then later when a block does not fit the freed ones (one 6 MB activation's pages, seen at
    # call 25): warm up past the first, average over enough calls that one such event is diluted.
    for _ in range(10):
        net(frame)
    f0 = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
    for _ in range(20):
        net(frame)
print(json.dumps({"applied": applied, "faults": (resource.getrusage(resource.RUSAGE_SELF).ru_minflt - f0) / 20}))
"""


def _forward_faults(setting: str) -> dict:
    # glibc as it is: no tunables or preloaded allocator from the caller's environment
    env = {k: v for k, v in os.environ.items()
           if not (k.startswith("MALLOC_") or k in ("GLIBC_TUNABLES", "LD_PRELOAD"))}
    done = subprocess.run([sys.executable, "-c", _FAULTS, setting], capture_output=True, text=True, check=True,
                          env=env)
    return json.loads(done.stdout.strip().splitlines()[-1])


@pytest.mark.slow
@pytest.mark.skipif(allocator._glibc() is None, reason="glibc's mallopt only (Linux with glibc)")
def test_kept_memory_removes_the_forward_page_faults():
    # Each setting in a fresh interpreter: mallopt is for the whole process and for good.
    system, kept = _forward_faults("system"), _forward_faults("kept")
    assert kept["applied"] is True
    assert system["faults"] > 100  # glibc as is: the activations land on fresh pages every call
    assert kept["faults"] <= 0.05 * system["faults"]


def test_without_glibc_nothing_changes(monkeypatch):
    monkeypatch.setattr(allocator, "_glibc", lambda: None)
    assert keep_freed_memory() is False


def test_a_refused_setting_is_reported(monkeypatch):
    calls = []

    class RefusingLibc:
        def mallopt(self, param, value):
            calls.append((param, value))
            return 0 if param == -1 else 1  # the trim threshold refused

    monkeypatch.setattr(allocator, "_glibc", lambda: RefusingLibc())
    assert keep_freed_memory() is False
    # every setting tried, the refused one included: the mmap threshold at glibc's 64-bit maximum
    assert sorted(calls) == [(-3, 32 * 1024 * 1024), (-2, 64 * 1024 * 1024), (-1, 256 * 1024 * 1024)]


@pytest.mark.parametrize("flags,expected", [([], 1), (["--system-malloc"], 0)])
def test_the_command_keeps_freed_memory_unless_told(monkeypatch, capsys, flags, expected):
    calls = []
    monkeypatch.setattr(allocator, "keep_freed_memory", lambda: calls.append(1) or True)
    # no SEQUENCE and no --demo: a usage error right after the process is set up
    assert cli.main(["--out", "unused", *flags]) == 2
    assert len(calls) == expected
    assert "a SEQUENCE folder is required" in capsys.readouterr().err
