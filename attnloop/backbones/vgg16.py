"""VGG16 with torchvision's state-dict keys (``vgg16-397923af.pth`` loads strictly), tapped at a max-pool output."""
from __future__ import annotations

from pathlib import Path
from typing import Callable

import torch
from torch import nn

from .preprocess import prepare_images
from .weights import VGG16_FILE, build_weighted, resolve_vgg16_weights

__all__ = ["VGG16", "VGG16_TAPS", "vgg16"]

# Block structure: (convolutions per block, channels). Each block ends with a 2x2 max-pool.
_CFG = ((2, 64), (2, 128), (3, 256), (3, 512), (3, 512))
#: Tap names and the index of their max-pool in ``features``.
VGG16_TAPS = {"pool1": 4, "pool2": 9, "pool3": 16, "pool4": 23, "pool5": 30}
_TAP_CHANNELS = {"pool1": 64, "pool2": 128, "pool3": 256, "pool4": 512, "pool5": 512}
_TAP_SIZE = {"pool1": 112, "pool2": 56, "pool3": 28, "pool4": 14, "pool5": 7}


class VGG16(nn.Module):
    """VGG16 split at a max-pool tap, with its own preprocessing.

    Args:
        tap: the tap layer L, one of ``pool1`` ... ``pool5``.

    Shape:
        - images: :math:`(B, 3, H, W)` uint8 in [0, 255] or float in [0, 1]
        - tap L: :math:`(B, 512, 7, 7)` for pool5 (see :attr:`tap_shape`)
        - logits: :math:`(B, 1000)`
    """

    # torchvision's VGG preprocessing: RGB in [0, 1], ImageNet mean and std, 224 x 224 input
    input_size = (224, 224)
    mean = (0.485, 0.456, 0.406)
    std = (0.229, 0.224, 0.225)

    def __init__(self, tap: str = "pool5") -> None:
        super().__init__()
        if tap not in VGG16_TAPS:
            raise ValueError(f"unknown VGG16 tap {tap!r}; choose one of {sorted(VGG16_TAPS)}")
        self.tap = tap
        self.tap_index = VGG16_TAPS[tap]
        self.tap_shape = (_TAP_CHANNELS[tap], _TAP_SIZE[tap], _TAP_SIZE[tap])
        layers: list[nn.Module] = []
        in_ch = 3
        for n_conv, ch in _CFG:
            for _ in range(n_conv):
                layers += [nn.Conv2d(in_ch, ch, kernel_size=3, padding=1), nn.ReLU(inplace=True)]
                in_ch = ch
            layers.append(nn.MaxPool2d(kernel_size=2, stride=2))
        self.features = nn.Sequential(*layers)
        self.avgpool = nn.AdaptiveAvgPool2d((7, 7))
        self.classifier = nn.Sequential(
            nn.Linear(512 * 7 * 7, 4096),
            nn.ReLU(inplace=True),
            nn.Dropout(0.5),
            nn.Linear(4096, 4096),
            nn.ReLU(inplace=True),
            nn.Dropout(0.5),
            nn.Linear(4096, 1000),
        )

    def reset_parameters(self, seed: int = 0) -> VGG16:
        """Seeded random weights (a private generator), torchvision's scheme."""
        gen = torch.Generator(device="cpu").manual_seed(int(seed))
        with torch.no_grad():
            for m in self.modules():
                if isinstance(m, nn.Conv2d):
                    nn.init.kaiming_normal_(m.weight, mode="fan_out", nonlinearity="relu", generator=gen)
                    nn.init.zeros_(m.bias)
                elif isinstance(m, nn.Linear):
                    nn.init.normal_(m.weight, 0.0, 0.01, generator=gen)
                    nn.init.zeros_(m.bias)
        return self

    def preprocess(self, images: torch.Tensor) -> torch.Tensor:
        """(B, 3, H, W) uint8 or [0, 1] float -> (B, 3, 224, 224) ImageNet-normalised, in the weights' dtype."""
        return prepare_images(images, self.input_size, self.mean, self.std, dtype=self.features[0].weight.dtype)

    def forward_to_tap(self, x: torch.Tensor) -> torch.Tensor:
        """Preprocessed (B, 3, 224, 224) -> tap L (B, C, h, w)."""
        for layer in self.features[: self.tap_index + 1]:
            x = layer(x)
        return x

    def forward_from_tap(
        self, tap: torch.Tensor, transition: Callable[[torch.Tensor], torch.Tensor] | None = None
    ) -> torch.Tensor:
        """Tap L (B, C, h, w) -> logits (B, 1000), ``transition`` applied to L and after every later max-pool."""
        x = transition(tap) if transition is not None else tap
        for index in range(self.tap_index + 1, len(self.features)):
            x = self.features[index](x)
            if transition is not None and isinstance(self.features[index], nn.MaxPool2d):
                x = transition(x)
        x = self.avgpool(x)
        return self.classifier(torch.flatten(x, 1))

    def forward(self, images: torch.Tensor) -> torch.Tensor:
        """Images (B, 3, H, W) -> logits (B, 1000): the plain classifier."""
        return self.forward_from_tap(self.forward_to_tap(self.preprocess(images)))


def vgg16(
    pretrained: bool = True,
    weights: str | Path | None = None,
    tap: str = "pool5",
    seed: int = 0,
) -> VGG16:
    """Build VGG16 (eval mode) tapped at ``tap``.

    Args:
        pretrained: load the ImageNet weights (``weights``, else the torch hub cache, else a download unless
            ``ATTNLOOP_OFFLINE=1``); False: seeded random weights.
        weights: an explicit checkpoint path (torchvision keys); implies ``pretrained``.
        tap: the tap layer L (``pool5`` gives (B, 512, 7, 7)).
        seed: seed of the random weights when ``pretrained`` is False.
    """
    return build_weighted(lambda: VGG16(tap=tap), pretrained, weights, resolve_vgg16_weights, VGG16_FILE, seed)
