"""What ``AttentionDescriptor(..., differentiable=True)`` costs against the default (detached) descriptor.

One round times, in turn, on the same 640 x 480 frames (float in [0, 1], as a training loop feeds them):

- ``default``: ``AttentionDescriptor(net)(images)`` under ``torch.no_grad()``, the SLAM system's call;
- ``default, weights require grad``: the same with the backbone's parameters left trainable (a module
  you pass in is not frozen for you): how much the fast path pays for recording the head;
- ``differentiable forward``: ``differentiable=True``, the graph kept (forward below L with autograd,
  the seeded backward recorded with ``create_graph``);
- ``differentiable forward + backward``: the same plus ``loss.backward()`` of a scalar of the
  descriptors into every backbone weight (one training step without the optimiser);
- ``plain forward + backward``: the classifier's own ``net(images).logsumexp(1).sum().backward()``,
  the cost of ordinary training, for scale.

Rounds are interleaved so that outside load hits all variants alike; the table gives the median ms per
frame, the 25-75 % range and the median of the per-round ratios to ``default``. Also the peak extra
memory of the first default call and then of the first differentiable forward + backward (the growth of
the process's peak resident set, a rough figure: torch's allocator is invisible to ``tracemalloc``).

The descriptor is the library's default (its tap, input size and recipe). Weights do not change the
cost: EfficientNet-Lite0 uses its packaged ImageNet weights when installed, VGG16 seeded random weights.

Usage:
    python -m benchmarks.descriptor_autograd                                  # EfficientNet-Lite0, batch 1 and 4
    python -m benchmarks.descriptor_autograd --backbones efficientnet_lite0 vgg16 --batches 1 --rounds 6

Prints a markdown table.
"""
from __future__ import annotations

import argparse
import datetime
import platform
import resource
import statistics
import time

import torch

from attnloop import AttentionDescriptor, WeightsNotFoundError, build_backbone
from attnloop.presets import DEFAULT_BACKBONE_SETTINGS
from benchmarks._common import quartiles, test_frames


def build(name: str) -> torch.nn.Module:
    """The backbone as the default descriptor configures it (its tap and input size, attnloop.presets)."""
    settings = DEFAULT_BACKBONE_SETTINGS.get(name, {})
    try:
        return build_backbone(name, pretrained=name == "efficientnet_lite0", **settings)
    except WeightsNotFoundError:
        return build_backbone(name, pretrained=False, **settings)


def variants(name: str, images: torch.Tensor) -> dict:
    frozen = build(name).requires_grad_(False)
    trainable = build(name)  # parameters require grad
    fast = AttentionDescriptor(frozen, fusion="dam")
    fast_trainable = AttentionDescriptor(trainable, fusion="dam")
    diff = AttentionDescriptor(trainable, fusion="dam", differentiable=True)

    def no_grad(fn):
        def run():
            with torch.no_grad():
                fn()
        return run

    def diff_backward():
        trainable.zero_grad(set_to_none=True)
        d = diff(images)
        (d[:, :8].sum() + d.pow(3).sum()).backward()

    def plain_backward():
        trainable.zero_grad(set_to_none=True)
        trainable(images).logsumexp(1).sum().backward()

    return {
        "default": no_grad(lambda: fast(images)),
        "default, weights require grad": no_grad(lambda: fast_trainable(images)),
        "differentiable forward": lambda: diff(images),
        "differentiable forward + backward": diff_backward,
        "plain forward + backward": plain_backward,
    }


def peak_rss_growth_mb(fn) -> float:
    before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    fn()
    return (resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - before) / 1024.0


def bench(name: str, batch: int, rounds: int, warmup: int) -> list[str]:
    images = test_frames(batch, uint8=False)
    fns = variants(name, images)
    times: dict[str, list[float]] = {k: [] for k in fns}
    for r in range(warmup + rounds):
        for key, fn in fns.items():
            t0 = time.perf_counter()
            fn()
            if r >= warmup:
                times[key].append(1000.0 * (time.perf_counter() - t0) / batch)
    base = times["default"]
    rows = []
    for key, values in times.items():
        q25, q50, q75 = quartiles(values)
        paired = statistics.median(t / b for t, b in zip(values, base))
        rows.append(f"| {name} | {batch} | {key} | {q50:.1f} | {q25:.1f}-{q75:.1f} | {paired:.2f} |")
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description="Cost of the differentiable descriptor vs the default one.")
    parser.add_argument("--backbones", nargs="+", default=["efficientnet_lite0"],
                        choices=["efficientnet_lite0", "vgg16"], help="backbones to time")
    parser.add_argument("--batches", nargs="+", type=int, default=[1, 4], help="batch sizes")
    parser.add_argument("--rounds", type=int, default=8, help="timed rounds per variant (after the warm-up)")
    parser.add_argument("--warmup", type=int, default=2, help="untimed rounds first")
    parser.add_argument("--threads", type=int, default=1, help="torch threads (1: steadier on a shared machine)")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    torch.manual_seed(0)
    print(f"#### Differentiable descriptor cost ({datetime.datetime.now():%Y-%m-%d %H:%M}, torch {torch.__version__}, "
          f"{args.threads} thread(s), {platform.machine()}, {args.rounds} rounds)\n")
    print("| backbone | batch | variant | ms/frame (median) | 25-75 % | median paired ratio to default |")
    print("|---|---|---|---|---|---|")
    notes = []
    for name in args.backbones:
        fns = variants(name, test_frames(1, uint8=False))  # memory first, before any timing run raised the peak
        plain = peak_rss_growth_mb(fns["default"])
        diff = peak_rss_growth_mb(fns["differentiable forward + backward"])
        notes.append(f"{name}, batch 1: peak resident-set growth of the first default call {plain:.0f} MB, then of "
                     f"the first differentiable forward + backward {diff:.0f} MB")
        for batch in args.batches:
            for row in bench(name, batch, args.rounds, args.warmup):
                print(row, flush=True)
    print()
    for note in notes:
        print(note)


if __name__ == "__main__":
    main()
