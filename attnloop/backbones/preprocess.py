"""Image preprocessing shared by the backbones: check, resize to the network's input size, normalise."""
from __future__ import annotations

import math
from collections.abc import Sequence

import torch
import torch.nn.functional as F

__all__ = ["FLOAT_RANGE_TOLERANCE", "check_images", "check_size", "prepare_images"]

#: Float images may leave [0, 1] by this much (a resampled image overshoots a little): 2.5 grey levels.
FLOAT_RANGE_TOLERANCE = 0.01


def check_images(images: torch.Tensor) -> None:
    """Raise unless ``images`` is a (B, 3, H, W) uint8 tensor or a finite float tensor in [0, 1].

    Args:
        images: the tensor to check, expected shape :math:`(B, 3, H, W)`; float values within [0, 1] up
            to :data:`FLOAT_RANGE_TOLERANCE`.

    Raises:
        TypeError: ``images`` is not a tensor.
        ValueError: wrong shape or dtype, non-finite pixels, or float values outside [0, 1], each
            message naming what was expected.
    """
    if not isinstance(images, torch.Tensor):
        raise TypeError(f"images must be a torch.Tensor, got {type(images).__name__}")
    if images.ndim != 4 or images.shape[1] != 3:
        raise ValueError(f"images must have shape (B, 3, H, W), got {tuple(images.shape)}")
    if images.dtype != torch.uint8 and not images.is_floating_point():
        raise ValueError(f"images must be uint8 in [0, 255] or float in [0, 1], got dtype {images.dtype}")
    if images.shape[0] > 0 and (images.shape[2] < 1 or images.shape[3] < 1):
        raise ValueError(f"images must have a positive height and width, got {tuple(images.shape)}")
    if not images.is_floating_point() or images.numel() == 0 or images.device.type == "meta":
        return
    lo, hi = torch.aminmax(images.detach())  # NaN propagates into both
    lo_f, hi_f = float(lo), float(hi)
    tol = FLOAT_RANGE_TOLERANCE
    if lo_f >= -tol and hi_f <= 1.0 + tol:
        return
    finite = torch.isfinite(images.detach())
    if not bool(finite.all()):
        bad = (~finite).nonzero()[0].tolist()
        count = int((~finite).sum())
        raise ValueError(
            f"images hold {count} non-finite pixel value(s) (NaN or inf), the first at (b, c, y, x) = "
            f"{tuple(bad)}; expected finite float values in [0, 1] (or uint8 in [0, 255])"
        )
    hint = " (they look like [0, 255] values: divide by 255 or pass uint8)" if hi_f > 2.0 else ""
    raise ValueError(
        f"float images must have values in [0, 1] (uint8 images in [0, 255]); got values in "
        f"[{lo_f:.4g}, {hi_f:.4g}], beyond the tolerance {tol}{hint}"
    )


def check_size(size, name: str) -> tuple[int, int] | None:
    """``size`` as ``(height, width)`` ints (None stays None); ValueError naming ``name`` unless positive integers."""
    if size is None:
        return None
    try:
        ok = len(size) == 2 and all(not isinstance(s, bool) and int(s) == s and s >= 1 for s in size)
    except (TypeError, ValueError):
        ok = False
    if not ok:
        raise ValueError(f"{name} must be (height, width) in positive integers or None, got {size!r}")
    return int(size[0]), int(size[1])


def prepare_images(
    images: torch.Tensor,
    size: tuple[int, int] | None,
    mean: Sequence[float] | None,
    std: Sequence[float] | None,
    dtype: torch.dtype | None = None,
) -> torch.Tensor:
    """Check images, resize them to ``size`` and normalise them with ``mean`` and ``std`` (given for [0, 1] values).

    The resize is bilinear with antialiasing (the whole view is kept, the aspect ratio is not); ``uint8``
    images are resized as uint8 on the CPU (PyTorch's fast path, within 1 grey level of the float one).

    Args:
        images: :math:`(B, 3, H, W)` uint8 in [0, 255] or float in [0, 1] (see :func:`check_images`).
        size: the output (height, width); None keeps each batch at its own size.
        mean: per-channel mean of [0, 1] RGB values, length 3; None subtracts nothing.
        std: per-channel standard deviation of [0, 1] RGB values, length 3; None divides by nothing.
        dtype: the floating dtype of the result (the network's); None: a float image's own, else float32.

    Returns:
        :math:`(B, 3, size[0], size[1])` normalised floating point tensor on the input's device.
    """
    check_images(images)
    for name, v in (("mean", mean), ("std", std)):
        if v is not None and (len(v) != 3 or not all(math.isfinite(float(c)) for c in v)):
            raise ValueError(f"{name} must hold 3 finite values (one per RGB channel), got {v!r}")
    if std is not None and not all(float(s) > 0 for s in std):
        raise ValueError(f"std must be positive, got {std!r}")
    if dtype is not None and not (isinstance(dtype, torch.dtype) and dtype.is_floating_point):
        raise ValueError(f"dtype must be a floating-point torch.dtype or None, got {dtype!r}")
    out_dtype = dtype if dtype is not None else (images.dtype if images.is_floating_point() else torch.float32)
    height, width = check_size(size, "size") or tuple(images.shape[-2:])
    if images.shape[0] == 0:
        return images.new_zeros((0, 3, height, width), dtype=out_dtype)
    is_uint8 = images.dtype == torch.uint8
    x = images
    if not is_uint8 or x.device.type != "cpu":
        # float images resize in the network's dtype; uint8 interpolation exists only on the CPU
        x = x.to(out_dtype)
    if tuple(x.shape[-2:]) != (height, width):
        x = F.interpolate(x, size=(height, width), mode="bilinear", align_corners=False, antialias=True)
    if x.dtype == torch.uint8:
        x = x.to(out_dtype)
    scale = 255.0 if is_uint8 else 1.0
    mean_t = torch.tensor(mean if mean is not None else (0.0,) * 3, dtype=x.dtype, device=x.device).view(1, 3, 1, 1)
    std_t = torch.tensor(std if std is not None else (1.0,) * 3, dtype=x.dtype, device=x.device).view(1, 3, 1, 1)
    # (x / scale - mean) / std as one fused multiply-add
    a = 1.0 / (scale * std_t)
    b = -mean_t / std_t
    return torch.addcmul(b, x, a).contiguous()
