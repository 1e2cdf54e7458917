"""Cost of the attention descriptor vs the plain forward pass of its backbone, side by side.

For each backbone (the default descriptor: VGG16 at pool5, EfficientNet-Lite0 at stage5 on a 256 x 320
input; and preset="paper") and batch size (1, 8), one round
times, in turn, the plain classifier forward ``net(images)`` (preprocessing included) and the full
``AttentionDescriptor(...)(images)`` for every fusion mode, all on the same 640 x 480 uint8 frames
under ``torch.no_grad()`` (as the SLAM system calls it). Rounds are interleaved so that load from
other processes hits all variants alike (every other round in reverse order); the table gives the median ms per
frame, the spread (25th-75th percentile) and the descriptor / plain ratio, both of the medians and as the median of
the per-round ratios (paired, less sensitive to a busy machine).

A second table splits the batch-1 descriptor into its stages (interleaved with the plain forward), and a
third compares ways to resize a 640 x 480 frame to 224 x 224.

Weights do not change the cost: VGG16 uses seeded random weights (no download needed), EfficientNet-
Lite0 the packaged ImageNet weights when installed.

Usage:
    python -m benchmarks.descriptor                       # both backbones, batch 1 and 8
    python -m benchmarks.descriptor --backbones efficientnet_lite0 --batches 1 --rounds 30
    python -m benchmarks.descriptor --threads 1           # steadier on a busy shared machine

Prints markdown tables.
"""
from __future__ import annotations

import argparse
import platform
import statistics
import time

import torch

from attnloop import AttentionDescriptor
from attnloop.fusion import FUSION_MODES
from attnloop.guided_backprop import guided_backprop
from benchmarks._common import quartiles, time_call
from benchmarks._common import test_frames as frames


def bench_backbone(name: str, batches: list[int], rounds: int, warmup: int) -> list[str]:
    pretrained = name == "efficientnet_lite0"
    try:
        AttentionDescriptor(name, pretrained=pretrained)
    except FileNotFoundError:
        pretrained = False
    # The default descriptor builds its own backbone (Lite0: stage5 at 256 x 320); the plain
    # forward is that same network's classifier pass at that input size.
    descs = {m: AttentionDescriptor(name, fusion=m, pretrained=pretrained) for m in FUSION_MODES}
    net = descs["dam"].backbone
    for d in descs.values():
        d.backbone = net
    paper = AttentionDescriptor(name, fusion="dam", pretrained=pretrained, preset="paper")
    every_stage = None
    if not all(getattr(net, "attended_groups", (True,))):
        # A/B: the same joined tap with G at every stage (what the joined tap costs without ``attend``), whose
        # backward also crosses the blocks between the stages (Lite0: 13.1 % of a forward against 5.5 %).
        every_stage = AttentionDescriptor(name, fusion="dam", pretrained=pretrained, attend=net.tap)
        # the same weights (not a copy) as the default's network, so neither gets a cache advantage
        every_stage.backbone.load_state_dict(net.state_dict(), assign=True)
    rows = []
    for batch in batches:
        images = frames(batch)
        variants = {"plain forward": lambda x=images: net(x)}
        variants.update({f"descriptor {m}": (lambda d=d, x=images: d(x)) for m, d in descs.items()})
        variants["plain forward, paper's 224 x 224 input"] = lambda x=images: paper.backbone(x)
        variants["descriptor dam, preset='paper'"] = lambda x=images: paper(x)
        if every_stage is not None:
            variants[f"descriptor dam, G at every stage of {net.tap}"] = lambda x=images: every_stage(x)
        times = {k: [] for k in variants}
        with torch.no_grad():
            for r in range(warmup + rounds):
                # every other round in reverse order: no variant always runs first or last in a round
                for key, fn in (list(variants.items()) if r % 2 == 0 else list(variants.items())[::-1]):
                    t = time_call(fn)
                    if r >= warmup:
                        times[key].append(1000.0 * t / batch)
        plain = times["plain forward"]
        p25, p50, p75 = quartiles(plain)
        rows.append(f"| {name} | {batch} | plain forward | {p50:.1f} | {p25:.1f}-{p75:.1f} | 1.000 | 1.000 |")
        for key in list(variants)[1:]:
            q25, q50, q75 = quartiles(times[key])
            paired = statistics.median(t / b for t, b in zip(times[key], plain))
            rows.append(f"| {name} | {batch} | {key} | {q50:.1f} | {q25:.1f}-{q75:.1f} | {q50 / p50:.3f} | "
                        f"{paired:.3f} |")
    return rows


def stage_breakdown(name: str, rounds: int) -> list[str]:
    """Batch-1 DAM descriptor split into (L, G) and fusion+pooling, interleaved with the plain forward."""
    try:
        desc = AttentionDescriptor(name, fusion="dam", pretrained=name == "efficientnet_lite0")
    except FileNotFoundError:
        desc = AttentionDescriptor(name, fusion="dam", pretrained=False)
    net = desc.backbone  # the default descriptor's network (Lite0: stage5 at 256 x 320)
    img = frames(1)
    stages = {"plain forward (preprocess included)": [], "preprocess (resize + normalise)": [],
              "L and G: guided_backprop (preprocess, forward, seeded backward)": [],
              "fusion + pooling (the RNNs when num_rnn > 0) + L2": []}
    with torch.no_grad():
        for r in range(rounds + 2):
            t0 = time.perf_counter()
            net(img)
            t1 = time.perf_counter()
            net.preprocess(img)
            t2 = time.perf_counter()
            tap, grad = guided_backprop(net, img)
            t3 = time.perf_counter()
            desc.from_attention(tap, grad)
            t4 = time.perf_counter()
            if r >= 2:
                for key, dt in zip(stages, (t1 - t0, t2 - t1, t3 - t2, t4 - t3)):
                    stages[key].append(1000.0 * dt)
    return [f"| {name} | {key} | {statistics.median(v):.2f} |" for key, v in stages.items()]


def resize_options(rounds: int) -> list[str]:
    import cv2

    from attnloop.backbones import prepare_images

    hwc = frames(1)[0].permute(1, 2, 0).contiguous().numpy()
    img = torch.from_numpy(hwc).permute(2, 0, 1)[None]  # what a caller builds from a cv2/numpy frame
    mean, std = (0.5,) * 3, (0.5,) * 3
    options = {
        "library: uint8 antialiased bilinear (F.interpolate), then float": lambda: prepare_images(
            img, (224, 224), mean, std),
        "float first, then antialiased bilinear": lambda: prepare_images(img.float() / 255.0, (224, 224), mean, std),
        "cv2.resize INTER_AREA beforehand, then the library": lambda: prepare_images(
            torch.from_numpy(cv2.resize(hwc, (224, 224), interpolation=cv2.INTER_AREA)).permute(2, 0, 1)[None],
            (224, 224), mean, std),
    }
    rows = []
    for key, fn in options.items():
        for _ in range(3):
            fn()
        vals = [1000.0 * time_call(fn) for _ in range(rounds)]
        rows.append(f"| {key} | {statistics.median(vals):.2f} |")
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--backbones", nargs="+", default=["efficientnet_lite0", "vgg16"],
                        help="backbones to time (vgg16 needs its weights)")
    parser.add_argument("--batches", nargs="+", type=int, default=[1, 8], help="batch sizes")
    parser.add_argument("--rounds", type=int, default=10, help="interleaved timing rounds (the median is reported)")
    parser.add_argument("--warmup", type=int, default=2, help="untimed calls first")
    parser.add_argument("--threads", type=int, default=0,
                        help="torch.set_num_threads for this run (0: torch's default); on a shared, busy "
                             "machine 1 thread gives far steadier timings than oversubscribed cores")
    args = parser.parse_args()
    if args.threads > 0:
        torch.set_num_threads(args.threads)
    print(f"# Descriptor cost ({time.strftime('%Y-%m-%d %H:%M')}, torch {torch.__version__}, "
          f"{torch.get_num_threads()} threads, {platform.machine()}, {args.rounds} rounds)\n")
    print("| backbone | batch | variant | ms/frame (median) | 25-75 % | ratio of medians | median paired ratio |")
    print("|---|---|---|---|---|---|---|")
    for name in args.backbones:
        for row in bench_backbone(name, args.batches, args.rounds, args.warmup):
            print(row, flush=True)
    print("\n| backbone | batch-1 DAM descriptor stage | ms |\n|---|---|---|")
    for name in args.backbones:
        for row in stage_breakdown(name, max(args.rounds, 5)):
            print(row, flush=True)
    print("\n| 640x480 uint8 frame -> (1, 3, 224, 224) normalised | ms |\n|---|---|")
    for row in resize_options(max(args.rounds, 20)):
        print(row)


if __name__ == "__main__":
    main()
