"""Random recursive neural network (RNN) pooling of a CNN feature map (CNN-randRNN, Caglayan et al.).

``concat_r tanh(W_r x)``, ``W_r ~ U[-0.1, 0.1]``, ``x`` the flattened map, channel ``c`` merged with ``c + C/2``
(docs/method.md); any input shape works: ``in_features = C/2 * H * W``.

Example:
    >>> pool = RandomRNNPool(512, in_size=(7, 7), num_rnn=16, out_features=64, seed=0)
    >>> pool.weights.shape
    torch.Size([16, 64, 12544])
    >>> pool(torch.rand(2, 512, 7, 7)).shape
    torch.Size([2, 1024])
"""
from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import nn

from .fusion import check_bchw

Tensor = torch.Tensor

__all__ = ["RandomRNNPool", "merge_channels", "random_rnn_pool", "random_rnn_weights"]


def merge_channels(x: Tensor) -> Tensor:
    """Average channel ``c`` with channel ``c + C/2``: ``(B, C, H, W)``, ``C`` even -> ``(B, C/2, H, W)``."""
    check_bchw(x)
    c = x.shape[1]
    if c % 2 != 0:
        raise ValueError(f"merge_channels needs an even number of channels, got x of shape {tuple(x.shape)}")
    half = c // 2
    return 0.5 * (x[:, :half] + x[:, half:])


def random_rnn_weights(
    num_rnn: int,
    in_features: int,
    out_features: int = 64,
    seed: int = 0,
    dtype: torch.dtype = torch.float32,
    device: str | torch.device | None = None,
) -> Tensor:
    """Fixed random weights of ``num_rnn`` one-level RNNs, uniform in ``[-0.1, 0.1]``.

    Drawn in float32 on a CPU generator, then converted: one seed gives the same weights on every device
    and dtype.

    Args:
        num_rnn: number of RNNs.
        in_features: size of the flattened input of each RNN.
        out_features: size of each RNN's output.
        seed: seed of the generator.
        dtype: dtype of the result.
        device: device of the result (default CPU).

    Returns:
        weights ``(num_rnn, out_features, in_features)``.
    """
    for name, v in (("num_rnn", num_rnn), ("in_features", in_features), ("out_features", out_features)):
        if isinstance(v, bool) or int(v) != v or v < 1:
            raise ValueError(f"{name} must be a positive integer, got {v!r}")
    if isinstance(seed, bool) or int(seed) != seed:
        raise ValueError(f"seed must be an integer, got {seed!r}")
    if not dtype.is_floating_point:
        raise ValueError(f"dtype must be a floating-point dtype, got {dtype}")
    num_rnn, in_features, out_features = int(num_rnn), int(in_features), int(out_features)
    gen = torch.Generator(device="cpu").manual_seed(int(seed))
    w = torch.rand((num_rnn, out_features, in_features), generator=gen, dtype=torch.float32)
    w = w.mul_(0.2).sub_(0.1)  # U[0, 1) -> U[-0.1, 0.1)
    return w.to(dtype=dtype, device=device)


def random_rnn_pool(x: Tensor, weights: Tensor, merge: bool = True) -> Tensor:
    """Random RNN pooling: ``concat_r tanh(W_r vec(merge(x)))``.

    Args:
        x: floating-point feature map ``(B, C, H, W)`` (``C`` even when ``merge``).
        weights: floating-point RNN weights ``(R, O, I)`` with ``I = C/2 * H * W`` (``C * H * W`` without
            merge), e.g. from :func:`random_rnn_weights`; cast to ``x``'s dtype, must be on ``x``'s device.
        merge: average channel ``c`` with ``c + C/2`` first (:func:`merge_channels`).

    Returns:
        descriptor ``(B, R * O)`` in ``x``'s dtype; entries ``[r * O, (r + 1) * O)`` are the output of RNN
        ``r``; an empty batch gives ``(0, R * O)``.
    """
    check_bchw(x)
    if weights.dim() != 3:
        raise ValueError(f"weights must have shape (num_rnn, out_features, in_features), got {tuple(weights.shape)}")
    if not weights.is_floating_point():
        raise TypeError(f"weights must be a floating-point tensor, got {weights.dtype}")
    if merge:
        x = merge_channels(x)
    flat = x.flatten(1)  # (B, C*H*W), also for B = 0
    r, o, i = weights.shape
    if flat.shape[1] != i:
        raise ValueError(
            f"x of shape {tuple(x.shape)}{' (after merging)' if merge else ''} flattens to {flat.shape[1]} "
            f"features but weights of shape {tuple(weights.shape)} expect {i}")
    if weights.device != flat.device:
        raise ValueError(f"weights are on {weights.device} but x is on {flat.device}; move one of them")
    w = weights.to(dtype=flat.dtype).reshape(r * o, i)
    return torch.tanh(flat @ w.t())


class RandomRNNPool(nn.Module):
    """Module wrapper of :func:`random_rnn_pool` with the seeded weights in a (saved) buffer.

    Args:
        in_channels: ``C`` of the input (even when ``merge``).
        in_size: ``(H, W)`` of the input.
        num_rnn: number of random RNNs ``R``.
        out_features: output size ``O`` of each RNN.
        seed: seed of the weights (see :func:`random_rnn_weights`).
        merge: average channel ``c`` with ``c + C/2`` first.

    Shape:
        - Input: ``(B, in_channels, H, W)``
        - Output: ``(B, num_rnn * out_features)``
    """

    weights: Tensor

    def __init__(
        self,
        in_channels: int,
        in_size: int | Sequence[int] = (7, 7),
        num_rnn: int = 16,
        out_features: int = 64,
        seed: int = 0,
        merge: bool = True,
    ) -> None:
        super().__init__()
        size: tuple[int, int] = (in_size, in_size) if isinstance(in_size, int) else tuple(in_size)  # type: ignore
        if len(size) != 2 or any(isinstance(v, bool) or int(v) != v or v < 1 for v in size):
            raise ValueError(f"in_size must be (H, W) in positive integers, got {in_size!r}")
        if isinstance(in_channels, bool) or int(in_channels) != in_channels or in_channels < 1 or (
                merge and in_channels % 2 != 0):
            kind = "positive even" if merge else "positive"
            raise ValueError(f"in_channels must be a {kind} integer, got {in_channels}")
        self.in_channels = int(in_channels)
        self.in_size = (int(size[0]), int(size[1]))
        self.num_rnn = int(num_rnn)
        self.out_features = int(out_features)
        self.seed = int(seed)
        self.merge = bool(merge)
        in_features = (self.in_channels // 2 if merge else self.in_channels) * self.in_size[0] * self.in_size[1]
        self.register_buffer("weights", random_rnn_weights(num_rnn, in_features, out_features, seed))

    @property
    def out_dim(self) -> int:
        """Size of the output descriptor, ``num_rnn * out_features``."""
        return self.num_rnn * self.out_features

    def forward(self, x: Tensor) -> Tensor:
        check_bchw(x)
        if tuple(x.shape[1:]) != (self.in_channels, *self.in_size):
            raise ValueError(f"expected x of shape (B, {self.in_channels}, {self.in_size[0]}, "
                             f"{self.in_size[1]}), got {tuple(x.shape)}")
        return random_rnn_pool(x, self.weights, merge=self.merge)

    def extra_repr(self) -> str:
        return (f"in_channels={self.in_channels}, in_size={self.in_size}, num_rnn={self.num_rnn}, "
                f"out_features={self.out_features}, seed={self.seed}, merge={self.merge}")
