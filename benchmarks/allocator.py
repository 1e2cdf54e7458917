"""Minor page faults and time per call of the CNN forward and the descriptor, glibc's allocator as is vs kept.

    python benchmarks/allocator.py [--rounds 40] [--batches 1 8] [--kitchen ../shared/data/7scenes-redkitchen]

Each setting runs in a fresh interpreter, because :func:`slam.allocator.keep_freed_memory` is for the whole
process and for good: ``system`` (glibc's defaults, what ``attnloop-slam --system-malloc`` keeps) and
``kept`` (what ``attnloop-slam`` sets by default). Each child times, at one thread, the plain forward of the
default descriptor's EfficientNet-Lite0 (random weights when the pretrained package is missing: the cost
does not depend on them) and the default DAM descriptor on the 640 x 480 frames of benchmarks/descriptor.py,
interleaved, and reads the minor page faults of each call from ``getrusage``. Prints one table: ms per frame
(median), faults per call, the descriptor over the forward (median paired ratio). With ``--kitchen FOLDER``, also runs
``attnloop-slam FOLDER`` twice per setting (alternating) and prints its frames/s.
"""
from __future__ import annotations

import argparse
import json
import re
import subprocess
import sys
import tempfile
import time
from pathlib import Path

SETTINGS = ("system", "kept")

_CHILD = r"""
import json, resource, statistics, sys, time
import torch
from slam.allocator import keep_freed_memory
setting, rounds, batches = sys.argv[1], int(sys.argv[2]), [int(b) for b in sys.argv[3].split(",")]
applied = keep_freed_memory() if setting == "kept" else False
sys.path.insert(0, sys.argv[4])
from descriptor import frames  # benchmarks/descriptor.py's frames: the same inputs as its table
torch.set_num_threads(1)
torch.manual_seed(0)
from attnloop import AttentionDescriptor
try:
    desc = AttentionDescriptor("efficientnet_lite0", fusion="dam", pretrained=True)
except Exception:
    desc = AttentionDescriptor("efficientnet_lite0", fusion="dam", pretrained=False)
net = desc.backbone
out = {"applied": applied, "pretrained": bool(desc.pretrained), "rows": []}
with torch.inference_mode():
    for b in batches:
        images = frames(b)
        calls = {"forward": lambda: net(images), "descriptor": lambda: desc(images)}
        ms = {k: [] for k in calls}
        faults = {k: [] for k in calls}
        for f in calls.values():
            f(); f()
        for r in range(rounds):
            for k in (list(calls) if r % 2 else list(calls)[::-1]):
                f0 = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
                t0 = time.perf_counter()
                calls[k]()
                ms[k].append(1000.0 * (time.perf_counter() - t0) / b)
                faults[k].append(resource.getrusage(resource.RUSAGE_SELF).ru_minflt - f0)
        ratio = statistics.median(d / f for d, f in zip(ms["descriptor"], ms["forward"]))
        for k in calls:
            out["rows"].append({"batch": b, "call": k, "ms": statistics.median(ms[k]),
                                "faults": statistics.median(faults[k]), "ratio": ratio})
print("RESULT " + json.dumps(out))
"""


def _child(setting: str, rounds: int, batches: list[int]) -> dict:
    here = str(Path(__file__).resolve().parent)
    done = subprocess.run([sys.executable, "-c", _CHILD, setting, str(rounds), ",".join(map(str, batches)), here],
                          capture_output=True, text=True, check=True)
    line = next(x for x in done.stdout.splitlines() if x.startswith("RESULT "))
    return json.loads(line[len("RESULT "):])


def _kitchen_fps(folder: str, setting: str) -> float:
    with tempfile.TemporaryDirectory() as out:
        cmd = ["attnloop-slam", folder, "--out", out, "--quiet"] + (["--system-malloc"] if setting == "system" else [])
        done = subprocess.run(cmd, capture_output=True, text=True, check=True)
    match = re.search(r"([0-9.]+) frames/s", done.stdout)
    if match is None:
        raise RuntimeError(f"no frames/s in the output of {' '.join(cmd)}:\n{done.stdout}")
    return float(match.group(1))


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter,
                                epilog="example:\n  python benchmarks/allocator.py --rounds 40 --batches 1 8")
    p.add_argument("--rounds", type=int, default=40, help="interleaved calls per variant (the median is reported)")
    p.add_argument("--batches", type=int, nargs="+", default=[1, 8], help="batch sizes")
    p.add_argument("--kitchen", default=None, metavar="FOLDER",
                   help="also time attnloop-slam on this sequence folder, twice per setting")
    args = p.parse_args()
    print(f"# Allocator ({time.strftime('%Y-%m-%d %H:%M')}, one thread, {args.rounds} rounds)\n")
    print("| allocator | mallopt applied | batch | call | ms/frame (median) | minor page faults per call | "
          "descriptor / forward (median paired) |")
    print("|---|---|---|---|---|---|---|")
    for setting in SETTINGS:
        res = _child(setting, args.rounds, args.batches)
        for row in res["rows"]:
            print(f"| {setting} | {res['applied']} | {row['batch']} | {row['call']} | {row['ms']:.1f} | "
                  f"{row['faults']:.0f} | {row['ratio']:.3f} |")
    if args.kitchen:
        fps = {s: [] for s in SETTINGS}
        for _ in range(2):
            for setting in SETTINGS:
                fps[setting].append(_kitchen_fps(args.kitchen, setting))
        print("\n| allocator | attnloop-slam frames/s (two runs) |\n|---|---|")
        for setting in SETTINGS:
            print(f"| {setting} | {', '.join(f'{v:.1f}' for v in fps[setting])} |")


if __name__ == "__main__":
    main()
