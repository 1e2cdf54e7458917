"""Any classifier ``nn.Module`` as a backbone: L taken at a named submodule by a forward hook.

The network runs on from L in the same pass (a generic network cannot be resumed from L alone); the clamps
sit at the max-pool outputs after the tap. Rules, dry run and modes: docs/your_own_cnn.md.
"""
from __future__ import annotations

from collections.abc import Sequence
from typing import Callable

import torch
from torch import nn

from ..guided_backprop import eval_mode
from .preprocess import check_size, prepare_images

__all__ = ["MAX_POOL_TYPES", "HookedBackbone"]

Tensor = torch.Tensor

#: Module types whose outputs are the partial guided backprop's block transitions.
MAX_POOL_TYPES = (
    nn.MaxPool1d, nn.MaxPool2d, nn.MaxPool3d,
    nn.AdaptiveMaxPool1d, nn.AdaptiveMaxPool2d, nn.AdaptiveMaxPool3d,
    nn.FractionalMaxPool2d, nn.FractionalMaxPool3d,
)


class _StopForward(Exception):
    """Raised by the tap hook of :meth:`HookedBackbone.forward_to_tap` to skip the rest of the network."""


def _main_output(out: object) -> Tensor | None:
    # a max-pool with return_indices=True returns (values, indices)
    if isinstance(out, Tensor):
        return out
    if isinstance(out, tuple) and out and isinstance(out[0], Tensor):
        return out[0]
    return None


def _replace_main_output(out: object, value: Tensor) -> object:
    return value if isinstance(out, Tensor) else (value, *out[1:])  # type: ignore[index]


class HookedBackbone(nn.Module):
    """A classifier ``nn.Module`` tapped at a named submodule, with its own preprocessing settings.

    Args:
        module: any ``nn.Module`` whose ``forward(x)`` takes ``(B, 3, H, W)`` float images and returns
            class logits ``(B, K)``.
        tap: the dotted name of the submodule whose output is L (``"layer3"``, ``"4"``); it must run once
            per forward and return a ``(B, C, h, w)`` tensor.
        input_size: ``(height, width)`` every image is resized to; None: images at their own size.
        mean: per-channel mean of [0, 1] RGB values subtracted before the network; None: none.
        std: per-channel standard deviation of [0, 1] RGB values divided by; None: none.
        transitions: names of the submodules at whose outputs (after the tap) negative gradients are
            zeroed; include ``tap`` itself to clamp at L. None: the max-pools found by the dry run.
        probe_size: the image size of the dry run when ``input_size`` is None.

    Attributes:
        tap_shape: ``(C, h, w)`` of L, from the dry run.
        clamp_at_tap: whether negative gradients are zeroed at L itself.
        transitions: names of the submodules clamped after the tap (their calls after the tap only).

    Shape:
        - images: :math:`(B, 3, H, W)` uint8 in [0, 255] or float in [0, 1]
        - tap L: :math:`(B, *\\text{tap\\_shape})`
        - logits: :math:`(B, K)`
    """

    def __init__(
        self,
        module: nn.Module,
        tap: str,
        input_size: Sequence[int] | None = None,
        mean: Sequence[float] | None = None,
        std: Sequence[float] | None = None,
        transitions: Sequence[str] | None = None,
        probe_size: Sequence[int] = (224, 224),
    ) -> None:
        super().__init__()
        if not isinstance(module, nn.Module):
            raise TypeError(f"module must be an nn.Module, got {type(module).__name__}")
        if not isinstance(tap, str) or not tap:
            raise ValueError(f"tap must name a submodule of {type(module).__name__} (e.g. 'layer3'), got {tap!r}")
        self.module = module
        self.tap = tap
        self._tap_module = self._submodule(tap)
        self.input_size = check_size(input_size, "input_size")
        self.probe_size = check_size(probe_size, "probe_size")
        for name, v in (("mean", mean), ("std", std)):
            if v is not None and (len(v) != 3 or not all(torch.isfinite(torch.tensor(v, dtype=torch.float64)))):
                raise ValueError(f"{name} must be 3 finite values (one per RGB channel) or None, got {v!r}")
        if std is not None and not all(float(s) > 0 for s in std):
            raise ValueError(f"std must be positive, got {std!r}")
        self.mean = None if mean is None else tuple(float(v) for v in mean)
        self.std = None if std is None else tuple(float(v) for v in std)
        self.name = f"{type(module).__name__}.{tap}"
        if transitions is not None:
            names = tuple(str(n) for n in transitions)
            for n in names:
                self._submodule(n)
            self.clamp_at_tap = tap in names
            self.transitions = tuple(n for n in names if n != tap)
        self._dry_run(explicit=transitions is not None)

    def _submodule(self, name: str) -> nn.Module:
        try:
            sub = self.module.get_submodule(name)
        except AttributeError:
            names = [n for n, _ in self.module.named_modules() if n]
            shown = ", ".join(repr(n) for n in names[:24]) + (", ..." if len(names) > 24 else "")
            raise ValueError(f"{type(self.module).__name__} has no submodule {name!r}; its submodules: "
                             f"{shown}") from None
        if sub is self.module:
            raise ValueError(f"tap must be a submodule of {type(self.module).__name__}, not the module itself")
        return sub

    def _dtype_device(self) -> tuple[torch.dtype, torch.device]:
        for t in (*self.module.parameters(), *self.module.buffers()):
            if t.is_floating_point():
                return t.dtype, t.device
        return torch.float32, torch.device("cpu")

    def _dry_run(self, explicit: bool) -> None:
        size = self.input_size or self.probe_size
        dtype, device = self._dtype_device()
        x = torch.full((1, 3, *size), 0.5, dtype=dtype, device=device)
        events: list[tuple[str, nn.Module, object]] = []  # (name, module, output) in completion order
        handles = [m.register_forward_hook(lambda mod, inp, out, name=name: events.append((name, mod, out)))
                   for name, m in self.module.named_modules()
                   if isinstance(m, MAX_POOL_TYPES) or m is self._tap_module]
        what = f"the dry run of {type(self.module).__name__} on a (1, 3, {size[0]}, {size[1]}) image"
        try:
            with torch.no_grad(), eval_mode(self.module):
                logits = self.module(self.preprocess(x))
        except Exception as exc:
            hint = "" if self.input_size else (
                "; set input_size=(H, W) to the image size the network takes (images are resized to it), or, "
                "building HookedBackbone(module, tap, probe_size=(H, W)) yourself, the size your images already "
                "come at")
            raise ValueError(f"{what} failed ({type(exc).__name__}: {exc}){hint}") from exc
        finally:
            for h in handles:
                h.remove()
        if not isinstance(logits, Tensor) or logits.ndim != 2 or logits.shape[0] != 1:
            shape = tuple(logits.shape) if isinstance(logits, Tensor) else type(logits).__name__
            raise ValueError(f"{what} returned {shape}; the module's forward must return class logits (B, K)")
        tap_calls = [i for i, (_, m, _) in enumerate(events) if m is self._tap_module]
        if len(tap_calls) != 1:
            raise ValueError(f"in {what} the tap {self.tap!r} ran {len(tap_calls)} times; tap a submodule "
                             "that runs exactly once per forward")
        at = tap_calls[0]
        tap_out = _main_output(events[at][2])
        if tap_out is None or tap_out.ndim != 4:
            shape = tuple(tap_out.shape) if tap_out is not None else type(events[at][2]).__name__
            raise ValueError(f"the tap {self.tap!r} returns {shape}; it must return a (B, C, h, w) feature map")
        self.tap_shape = tuple(int(s) for s in tap_out.shape[1:])
        if not explicit:
            before = [_main_output(out) for _, m, out in events[:at] if isinstance(m, MAX_POOL_TYPES)]
            self.clamp_at_tap = isinstance(self._tap_module, MAX_POOL_TYPES) or any(t is tap_out for t in before)
            # each max-pool after the tap once, in the order they first ran
            self.transitions = tuple(dict.fromkeys(
                name for name, m, _ in events[at + 1:] if isinstance(m, MAX_POOL_TYPES)))

    def preprocess(self, images: Tensor) -> Tensor:
        """(B, 3, H, W) uint8 or [0, 1] float -> the network input: resized to ``input_size`` (when set),
        normalised with ``mean``/``std`` (when set), in the module's dtype."""
        return prepare_images(images, self.input_size, self.mean, self.std, dtype=self._dtype_device()[0])

    def _check_tap(self, out: object) -> Tensor:
        tap = _main_output(out)
        if tap is None or tuple(tap.shape[1:]) != self.tap_shape:
            shape = tuple(tap.shape) if tap is not None else type(out).__name__
            size = f"{self.input_size[0]} x {self.input_size[1]}" if self.input_size else \
                f"their own size (the dry run used {self.probe_size[0]} x {self.probe_size[1]})"
            raise ValueError(
                f"the tap {self.tap!r} gave L of shape {shape} but this backbone's tap_shape is "
                f"{self.tap_shape} (images at {size}); set input_size=(H, W) so that every image is resized "
                "to the size the network was set up for")
        return tap

    def forward_to_tap(self, x: Tensor) -> Tensor:
        """Preprocessed images -> L, :math:`(B, *\\text{tap\\_shape})`; the network stops at the tap."""
        captured: list[Tensor] = []

        def hook(mod: nn.Module, inp: object, out: object) -> None:
            captured.append(self._check_tap(out))
            raise _StopForward

        handle = self._tap_module.register_forward_hook(hook)
        try:
            self.module(x)
        except _StopForward:
            pass
        finally:
            handle.remove()
        if not captured:
            raise RuntimeError(f"the tap {self.tap!r} did not run in the forward pass of {type(self.module).__name__}")
        return captured[0]

    def forward_split(self, x: Tensor, at_tap: Callable[[Tensor], Tensor],
                      transition: Callable[[Tensor], Tensor] | None = None) -> Tensor:
        """One forward pass, preprocessed images -> logits, with ``at_tap(L)`` substituted for L.

        Args:
            x: the preprocessed images :math:`(B, 3, H', W')`.
            at_tap: called with L once; (a copy of) its result replaces L for the rest of the network.
            transition: applied at L (when :attr:`clamp_at_tap`) and to the outputs of :attr:`transitions`
                after the tap; identity when None.

        Returns:
            the logits :math:`(B, K)`.
        """
        state = {"after": False}

        def tap_hook(mod: nn.Module, inp: object, out: object) -> object:
            if state["after"]:
                raise RuntimeError(f"the tap {self.tap!r} ran twice in one forward pass")
            value = at_tap(self._check_tap(out))
            state["after"] = True
            value = transition(value) if (transition is not None and self.clamp_at_tap) else value.clone()
            return _replace_main_output(out, value)

        def transition_hook(mod: nn.Module, inp: object, out: object) -> object | None:
            main = _main_output(out)
            if not state["after"] or transition is None or main is None:
                return None
            return _replace_main_output(out, transition(main))

        handles = [self._tap_module.register_forward_hook(tap_hook)]
        if transition is not None:
            for name in self.transitions:
                handles.append(self.module.get_submodule(name).register_forward_hook(transition_hook))
        try:
            return self.module(x)
        finally:
            for h in handles:
                h.remove()

    def forward(self, images: Tensor) -> Tensor:
        """Images (B, 3, H, W) -> logits (B, K): the module on the preprocessed images."""
        return self.module(self.preprocess(images))

    def extra_repr(self) -> str:
        return (f"tap={self.tap!r}, tap_shape={self.tap_shape}, input_size={self.input_size}, mean={self.mean}, "
                f"std={self.std}, clamp_at_tap={self.clamp_at_tap}, transitions={self.transitions}")
