"""The attention-guided CNN descriptor: backbone -> guided attention -> fusion -> pooling (-> random RNNs) -> L2.

1. L, G: the tap activations and the guided gradient (:mod:`attnloop.guided_backprop`);
2. F = fusion(L, G / max|G|) (:mod:`attnloop.fusion`);
3. ``pooling="regional"``: F's regional GeM code (:mod:`attnloop.pooling`); ``"flat"`` (the paper's): F;
4. with ``num_rnn > 0``: random RNNs (:mod:`attnloop.rnn_pool`) on that input scaled to L2 norm ``pool_scale``;
5. L2 normalisation. Steps 2-5 are one :class:`DescriptorRecipe`.
"""
from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from numbers import Integral, Real
from pathlib import Path
from typing import Any, NamedTuple

import torch
import torch.nn.functional as F
from torch import nn

from .backbones import HookedBackbone, build_backbone, resolve_backbone_name
from .backbones.preprocess import check_images
from .fusion import FUSION_MODES
from .guided_backprop import eval_mode, guided_backprop
from .pooling import POOLINGS, fuse_groups, regional_code, regional_code_dim
from .presets import preset as preset_named
from .rnn_pool import RandomRNNPool, random_rnn_pool

__all__ = [
    "AttentionDescriptor",
    "DescriptorParts",
    "DescriptorRecipe",
    "descriptor_from_attention",
]


#: The defaults of the settings that only the random RNNs read (refused with ``num_rnn=0`` when changed).
_RNN_DEFAULTS = {"out_features": 64, "pool_scale": 10.0}


def _unused_rnn_settings(out_features: int = _RNN_DEFAULTS["out_features"],
                         pool_scale: float | None = _RNN_DEFAULTS["pool_scale"],
                         merge: bool | None = None) -> list[str]:
    given = {"out_features": out_features, "pool_scale": pool_scale}
    return [k for k, v in given.items() if v != _RNN_DEFAULTS[k]] + (["merge"] if merge else [])


def _check_pool_scale(pool_scale: float | None) -> None:
    if pool_scale is not None and not (float(pool_scale) > 0 and float(pool_scale) < float("inf")):
        raise ValueError(f"pool_scale must be positive and finite, or None, got {pool_scale}")


def _check_gem_p(gem_p: float, pooling: str) -> None:
    if isinstance(gem_p, bool) or not isinstance(gem_p, Real) or not 0 < gem_p < float("inf"):
        raise ValueError(f"gem_p must be a positive finite number (the regional pooling's GeM exponent), "
                         f"got {gem_p!r}")
    default = DescriptorRecipe.gem_p
    if pooling == "flat" and gem_p != default:
        raise ValueError(f"gem_p={gem_p!r} sets the regional GeM pooling, and pooling='flat' has none; leave it at "
                         f"{default!r} or pass pooling='regional'")


@dataclass(frozen=True)
class DescriptorRecipe:
    """What the descriptor does with (L, G): fusion, pooling, random RNNs, L2 (steps 2-5), and the seed."""

    fusion: str = "none"  # "none" | "dam" | "eam" | "gaf" | "ega"
    num_rnn: int = 0  # random RNNs after the pooling (the paper's 16); 0: the descriptor is the pooled code
    out_features: int = _RNN_DEFAULTS["out_features"]  # output size of each RNN (the paper's 64)
    seed: int = 0  # seed of the RNN weights (and of a name-built backbone's random weights when not pretrained)
    normalize: bool = True  # L2-normalise the descriptor
    pool_scale: float | None = _RNN_DEFAULTS["pool_scale"]  # L2 norm of the RNNs' input; None: raw (the paper)
    merge: bool | None = None  # average element c with c + C/2 of the RNNs' input; None: for "flat" only
    pooling: str = "regional"  # "regional": regional GeM code; "flat": the whole map (the paper)
    gem_p: float = 3.0  # GeM exponent of the regional pooling (1: average, large: max); "flat" has none

    def __post_init__(self) -> None:
        if self.fusion not in FUSION_MODES:
            raise ValueError(f"unknown fusion {self.fusion!r}; choose one of {FUSION_MODES}")
        if self.pooling not in POOLINGS:
            raise ValueError(f"unknown pooling {self.pooling!r}; choose one of {POOLINGS}")
        _check_gem_p(self.gem_p, self.pooling)
        for name, least in (("num_rnn", 0), ("out_features", 1), ("seed", 0)):
            v = getattr(self, name)
            # a whole float (16.0) is fine for the counts, not for the seed
            whole = isinstance(v, Integral) or (name != "seed" and isinstance(v, float) and v.is_integer())
            if isinstance(v, bool) or not whole or v < least:
                kind = "a non-negative" if least == 0 else "a positive"
                raise ValueError(f"{name} must be {kind} integer, got {v!r}")
        if not isinstance(self.normalize, bool):
            raise TypeError(f"normalize must be True or False, got {self.normalize!r}")
        _check_pool_scale(self.pool_scale)
        if self.num_rnn == 0:
            unused = _unused_rnn_settings(self.out_features, self.pool_scale, self.merge)
            if unused:
                raise ValueError(f"{', '.join(unused)} set the random RNNs, and num_rnn=0 has none; "
                                 "pass num_rnn=16 (the paper's) to use them")
            if self.pooling == "flat":
                raise ValueError("pooling='flat' is the paper's input of the random RNNs (the whole fused map), and "
                                 "num_rnn=0 has none; pass num_rnn=16, or pooling='regional' without RNNs")

    @property
    def out_dim(self) -> int | None:
        """Size of a descriptor, ``num_rnn * out_features``; None without RNNs (set by the tap)."""
        return int(self.num_rnn) * int(self.out_features) if self.num_rnn else None

    @property
    def merges(self) -> bool:
        """Whether the RNNs' input is merged (``merge``; None: with ``flat`` pooling); False without RNNs."""
        return bool(self.num_rnn) and ((self.pooling == "flat") if self.merge is None else bool(self.merge))


_DEFAULT = DescriptorRecipe()


class _Default:
    """A recipe argument not given, told apart from its default given explicitly (which ``preset=`` may refuse)."""

    def __repr__(self) -> str:
        return "<the recipe's default>"


_UNSET: Any = _Default()


class DescriptorParts(NamedTuple):
    """Every intermediate of one descriptor computation.

    Attributes:
        tap: the tap activations L, :math:`(B, C, h, w)`.
        grad: the guided gradient G = dS/dL, :math:`(B, C, h, w)` (zero on stages not attended).
        fused: fusion(L, G / max|G|), :math:`(B, C, h, w)` (L itself on stages not attended).
        descriptor: the descriptor, :math:`(B, D)`.
    """

    tap: torch.Tensor
    grad: torch.Tensor
    fused: torch.Tensor
    descriptor: torch.Tensor


def descriptor_from_attention(
    tap: torch.Tensor,
    grad: torch.Tensor,
    rnn_weights: torch.Tensor | None,
    fusion: str = _DEFAULT.fusion,
    normalize: bool = True,
    pool_scale: float | None = _RNN_DEFAULTS["pool_scale"],
    merge: bool | None = None,
    *,
    pooling: str = "regional",
    groups: Sequence[int] | None = None,
    attended: Sequence[bool] | None = None,
    gem_p: float = _DEFAULT.gem_p,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Steps 2-5 of the descriptor: fuse (L, G), pool, (scale and random RNN pooling), L2.

    Args:
        tap: the tap activations L, :math:`(B, C, h, w)`.
        grad: the guided gradient G, :math:`(B, C, h, w)`.
        rnn_weights: :math:`(R, O, I)` random RNN weights: for ``flat`` pooling ``I = C/2 * h * w``
            (``C * h * w`` without merge); for ``regional`` ``I = regional_code_dim(groups)``
            (halved with merge). None: no RNNs, the descriptor is the regional code (``pool_scale`` and
            ``merge`` at their defaults).
        fusion: ``none``, ``dam``, ``eam``, ``gaf`` or ``ega``.
        normalize: L2-normalise the descriptor.
        pool_scale: L2 norm the RNNs' input is scaled to; None feeds it raw (the paper).
        merge: average element c with c + C/2 of the RNNs' input; None: for ``flat`` pooling only.
        pooling: ``"regional"`` or ``"flat"``.
        groups: channel counts of a joined tap's stages, each fused and pooled on its own; None: one group.
        attended: per group, whether it is fused (else pooled as L); None: every group.
        gem_p: the GeM exponent of ``regional`` pooling (``flat``: at its default).

    Returns:
        (fused :math:`(B, C, h, w)`, descriptor :math:`(B, R \\cdot O)`, or without RNNs
        :math:`(B, \\text{regional\\_code\\_dim})`).
    """
    if pooling not in POOLINGS:
        raise ValueError(f"unknown pooling {pooling!r}; choose one of {POOLINGS}")
    _check_pool_scale(pool_scale)
    _check_gem_p(gem_p, pooling)
    fused = fuse_groups(tap, grad, fusion, groups, attended)
    if rnn_weights is None:
        unused = _unused_rnn_settings(pool_scale=pool_scale, merge=merge)
        if unused:
            raise ValueError(f"{', '.join(unused)} set the random RNNs' input, and rnn_weights=None has no RNNs; "
                             "leave them at their defaults")
        if pooling == "flat":
            raise ValueError("pooling='flat' is the paper's input of the random RNNs, and rnn_weights=None has none; "
                             "pass RNN weights, or pooling='regional'")
        desc = regional_code(fused, groups, gem_p)
    else:
        merge = pooling == "flat" if merge is None else merge
        pool_in = fused if pooling == "flat" else regional_code(fused, groups, gem_p)[:, :, None, None]
        if pool_scale is not None:  # per-sample L2 norm pool_scale; an all-zero sample stays zero
            pool_in = (F.normalize(pool_in.flatten(1), dim=1) * float(pool_scale)).reshape(pool_in.shape)
        desc = random_rnn_pool(pool_in, rnn_weights, merge=merge)
    if normalize:
        desc = F.normalize(desc, dim=1)
    return fused, desc


class AttentionDescriptor(nn.Module):
    """Images -> attention-guided CNN descriptors, as a drop-in ``nn.Module``.

    The backbone can be a name (``"auto"``: VGG16 when its weights are at hand, else EfficientNet-Lite0;
    ``"vgg16"``; ``"efficientnet_lite0"``), which the descriptor owns: frozen unless ``differentiable`` and
    always in eval mode; a backbone module of :mod:`attnloop.backbones`, used as given; or any classifier
    ``nn.Module`` with ``tap="name.of.submodule"`` (:class:`attnloop.backbones.HookedBackbone`). A module
    passed in is never frozen; it runs in eval mode during a computation only, so that a descriptor never
    depends on the rest of its batch.

    Args:
        backbone: a name, a backbone module or a classifier module (see above).
        fusion: ``"none"``, ``"dam"``, ``"eam"``, ``"gaf"`` or ``"ega"``.
        num_rnn: number of random RNNs (the paper's 16); 0 (default): the descriptor is the pooled code.
        seed: seed of the RNN weights, and of a name-built backbone's weights when not pretrained.
        pretrained: load ImageNet weights into a name-built backbone (default True); False: seeded random
            weights without any file.
        weights: explicit checkpoint path for a name-built backbone.
        normalize: L2-normalise the descriptors.
        tap: a name-built backbone's tap layer (default: the preset's, :mod:`attnloop.presets`; G at every
            stage of an explicit tap), or the submodule of a classifier module where L is taken.
        out_features: output size of each RNN (with ``num_rnn > 0``).
        pool_scale: L2 norm of the RNNs' input (None: raw, as in the paper; with ``num_rnn > 0``).
        merge: average element c with c + C/2 of the RNNs' input (None: only with ``flat`` pooling).
        input_size: a classifier module's input ``(height, width)``; None: images at their own size.
        mean: a classifier module's per-channel input mean on [0, 1] RGB; None: none.
        std: a classifier module's per-channel input std on [0, 1] RGB; None: none.
        differentiable: keep the output differentiable w.r.t. the images and the backbone's weights (default:
            detached, usable under ``torch.no_grad()`` and ``torch.inference_mode()``).
        recipe: a :class:`DescriptorRecipe` in place of ``fusion`` ... ``merge`` and ``pooling`` (and the
            GeM exponent ``gem_p``, set through a recipe only).
        preset: a name of :data:`attnloop.presets.PRESETS`: ``"paper"`` or ``"guclu2019"`` fix the recipe
            and the tap (only ``seed``, the backbone and the paper's ``fusion`` stay free) and make
            ``backbone="auto"`` VGG16, whose weights must be found; None or ``"default"``: the default.
        pooling: ``"regional"`` (default) or ``"flat"`` (the paper's RNNs over the whole fused map).
        attend: a name-built EfficientNet-Lite0's stages of a joined tap where G is computed and fused
            (e.g. ``stage7`` of ``stage6+stage7``); None: the preset's, or every stage of an explicit tap.

    Attributes:
        pretrained: whether a name-built backbone loaded ImageNet weights (None for a module passed in:
            its weights are the caller's).
        backbone_name: the backbone used: ``"vgg16"`` or ``"efficientnet_lite0"`` for a name (``"auto"``
            resolved), the class name of a backbone module, ``"Class.tap"`` for a classifier module.
        recipe: the :class:`DescriptorRecipe`.

    Shape:
        - images: :math:`(B, 3, H, W)`, uint8 in [0, 255] or finite float in [0, 1], any H and W
        - output: :math:`(B, D)`, :attr:`out_dim`: ``num_rnn * out_features`` with RNNs, else the pooled
          code's size (5 regions x the tap's channels)

    Example:
        >>> desc = AttentionDescriptor("efficientnet_lite0", fusion="dam", pretrained=False)
        >>> with torch.no_grad():
        ...     d = desc(torch.randint(0, 256, (2, 3, 240, 320), dtype=torch.uint8))
        >>> d.shape
        torch.Size([2, 560])
        >>> net = nn.Sequential(nn.Conv2d(3, 8, 3, padding=1), nn.ReLU(), nn.MaxPool2d(2),
        ...                     nn.Flatten(), nn.Linear(8 * 16 * 16, 10))
        >>> AttentionDescriptor(net, tap="2", input_size=(32, 32))(torch.rand(2, 3, 48, 64)).shape
        torch.Size([2, 40])
    """

    def __init__(
        self,
        backbone: str | nn.Module = "auto",
        fusion: str = _UNSET,
        num_rnn: int = _UNSET,
        seed: int = _UNSET,
        pretrained: bool | None = None,
        weights: str | Path | None = None,
        normalize: bool = _UNSET,
        tap: str | None = None,
        out_features: int = _UNSET,
        pool_scale: float | None = _UNSET,
        merge: bool | None = _UNSET,
        *,
        input_size: Sequence[int] | None = None,
        mean: Sequence[float] | None = None,
        std: Sequence[float] | None = None,
        differentiable: bool = False,
        recipe: DescriptorRecipe | None = None,
        preset: str | None = None,
        pooling: str = _UNSET,
        attend: str | None = None,
    ) -> None:
        super().__init__()
        # the recipe is built once it is known which settings apply (a preset or a recipe replaces them)
        passed = {"fusion": fusion, "num_rnn": num_rnn, "out_features": out_features, "seed": seed,
                  "normalize": normalize, "pool_scale": pool_scale, "merge": merge, "pooling": pooling}
        passed = {k: v for k, v in passed.items() if v is not _UNSET}  # given by the caller
        changed = [k for k, v in passed.items() if v != getattr(_DEFAULT, k)]
        chosen = preset_named(preset)  # None: the default
        if chosen.fixed:
            # a setting given explicitly must be the preset's (the seed, and the paper's fusion, stay free)
            free = ("seed",) if chosen.fusion is not None else ("fusion", "seed")
            own = {**chosen.recipe, **({"fusion": chosen.fusion} if chosen.fusion is not None else {})}
            fixed = [k for k, v in passed.items() if k not in free and v != own.get(k, getattr(_DEFAULT, k))]
            fixed += [k for k, v in (("recipe", recipe), ("tap", tap), ("attend", attend)) if v is not None]
            if fixed:
                raise ValueError(f"preset={chosen.name!r} fixes the recipe and the tap; also given: {fixed}")
            # the caller's other settings equal the preset's (else refused above) and are still type-checked
            given = DescriptorRecipe(**{**passed, **own, **{k: v for k, v in passed.items() if k in free}})
        elif recipe is not None:
            if not isinstance(recipe, DescriptorRecipe):
                raise TypeError(f"recipe must be a DescriptorRecipe, got {type(recipe).__name__}")
            if changed:
                raise ValueError(f"give either recipe= or its settings, not both (also given: {changed}); "
                                 "dataclasses.replace(recipe, ...) varies a recipe")
            given = recipe
        else:
            given = DescriptorRecipe(**passed)
        self.recipe = given
        #: The preset's name (``"default"`` unless ``preset=`` named another).
        self.preset = chosen.name
        for name, value in (("differentiable", differentiable), ("pretrained", pretrained)):
            if not isinstance(value, bool) and not (name == "pretrained" and value is None):
                raise TypeError(f"{name} must be True or False, got {value!r}")
        self.differentiable = differentiable
        self._owns_backbone = isinstance(backbone, str)
        self.pretrained: bool | None = None
        preprocessing = {"input_size": input_size, "mean": mean, "std": std}
        if isinstance(backbone, str):
            for key, value in preprocessing.items():
                if value is not None:
                    raise ValueError(f"{key}= applies to a classifier module (backbone=my_module, tap=...); "
                                     f"the built-in backbone {backbone!r} has its own preprocessing")
            use_pretrained = True if pretrained is None else bool(pretrained)
            self.pretrained = use_pretrained or weights is not None
            if backbone == "auto" and chosen.auto_backbone != "auto":
                backbone = chosen.auto_backbone  # the paper's network, its weights required: never another
            self.backbone_name = resolve_backbone_name(backbone, use_pretrained, weights)
            settings = {"tap": tap} if tap is not None else dict(chosen.backbone_settings.get(self.backbone_name, {}))
            if attend is not None:
                settings["attend"] = attend
            # outside inference mode: the seeded backward cannot use inference tensors as weights
            with torch.inference_mode(False):
                net = build_backbone(backbone, pretrained=use_pretrained, weights=weights, seed=given.seed,
                                     **settings)
            net.eval()
            if not self.differentiable:
                net.requires_grad_(False)
        elif isinstance(backbone, nn.Module):
            made = [n for n, p in backbone.named_parameters() if p.is_inference()]
            if made:  # the seeded backward cannot save them: the first call would fail with torch's error
                raise ValueError(f"{type(backbone).__name__}'s parameters ({made[0]}, ...) are inference tensors: "
                                 "the module was built under torch.inference_mode(); build it outside (calling "
                                 "the descriptor under inference_mode is fine)")
            if pretrained is not None or weights is not None:
                raise ValueError("pretrained=/weights= apply to a backbone name; a module comes with its own weights")
            if attend is not None:
                raise ValueError("attend= applies to a backbone name; build the module with it (e.g. "
                                 "efficientnet_lite0(tap='stage6+stage7', attend='stage7'))")
            # the backbone protocol of attnloop.backbones
            if all(hasattr(backbone, a) for a in ("preprocess", "forward_to_tap", "tap_shape")) and (
                    hasattr(backbone, "forward_from_tap") or hasattr(backbone, "forward_split")):
                extra = [k for k, v in {"tap": tap, **preprocessing}.items() if v is not None]
                if extra:
                    raise ValueError(f"{type(backbone).__name__} is a backbone with its own tap and preprocessing; "
                                     f"{', '.join(extra)}= apply to a plain classifier module")
                net = backbone
            elif tap is not None:
                net = HookedBackbone(backbone, tap, input_size=input_size, mean=mean, std=std)
            else:
                raise TypeError(
                    f"backbone module {type(backbone).__name__} lacks 'preprocess', 'forward_to_tap' and 'tap_shape' "
                    "(the protocol of attnloop.backbones); for any classifier pass tap='name.of.submodule' "
                    "to take L at that submodule")
            self.backbone_name = str(getattr(net, "name", type(net).__name__))
        else:
            raise TypeError(f"backbone must be a name or an nn.Module, got {type(backbone).__name__}")
        self.backbone = net
        channels, height, width = (int(v) for v in self.backbone.tap_shape)
        #: Channel counts of a joined tap's stages (None: a single tap), fused and pooled separately.
        self.tap_groups = tuple(getattr(self.backbone, "tap_groups", None) or (channels,))
        #: Per tap group, whether the attention fuses it (False: the group's L is pooled unfused).
        self.attended_groups = tuple(bool(a) for a in getattr(self.backbone, "attended_groups", None)
                                     or (True,) * len(self.tap_groups))
        if len(self.attended_groups) != len(self.tap_groups):
            raise ValueError(f"{self.backbone_name}: attended_groups {self.attended_groups} has not one flag per "
                             f"tap group {self.tap_groups}")
        if given.pooling == "regional":
            channels, height, width = regional_code_dim(self.tap_groups), 1, 1
        if given.merges and channels % 2:
            raise ValueError(f"the RNNs' input of {self.backbone_name} has {channels} channels, an odd number: "
                             "merge=True averages channel c with c + C/2; pass merge=False or tap a layer with "
                             "even channels")
        #: The random RNNs (None with ``num_rnn=0``: the descriptor is the pooled code).
        self.pool: RandomRNNPool | None = None
        self._code_dim = channels * height * width
        if given.num_rnn:
            with torch.inference_mode(False):  # as the backbone: usable in a differentiable call later
                self.pool = RandomRNNPool(channels, (height, width), given.num_rnn, given.out_features,
                                          seed=given.seed, merge=given.merges)

    @property
    def out_dim(self) -> int:
        """Size of a descriptor: ``num_rnn * out_features`` with RNNs, else the pooled code's size."""
        return self.pool.out_dim if self.pool is not None else self._code_dim

    @property
    def rnn_weights(self) -> torch.Tensor | None:
        """The RNNs' weights :math:`(R, O, I)`, None without RNNs (for :func:`descriptor_from_attention`)."""
        return None if self.pool is None else self.pool.weights

    @property
    def fusion(self) -> str:
        """The fusion mode (:attr:`recipe`; another one per call: :meth:`from_attention`'s ``fusion``)."""
        return self.recipe.fusion

    def train(self, mode: bool = True) -> AttentionDescriptor:
        """Set the training flag; a name-built backbone stays in eval mode (batch-norm, dropout)."""
        super().train(mode)
        if self._owns_backbone:
            self.backbone.eval()
        return self

    def load_state_dict(self, state_dict, strict: bool = True, assign: bool = False):
        """As :meth:`torch.nn.Module.load_state_dict`; a ``strict`` load across ``num_rnn=0`` and RNNs names
        ``num_rnn`` rather than torch's bare key lists."""
        has = "pool.weights" in state_dict
        own = {k for k in self.state_dict() if k != "pool.weights"} == {k for k in state_dict if k != "pool.weights"}
        if strict and own and has != (self.pool is not None):
            if self.pool is None:
                n = int(state_dict["pool.weights"].shape[0])
                raise RuntimeError(f"the state dict holds random RNN weights (pool.weights, shape "
                                   f"{tuple(state_dict['pool.weights'].shape)}): it was saved by a descriptor with "
                                   f"num_rnn={n}, and this one has no RNNs; build it "
                                   f"with num_rnn={n}")
            raise RuntimeError(f"this descriptor has {self.recipe.num_rnn} random RNNs (pool.weights) and the state "
                               "dict has none: it was saved by a descriptor with num_rnn=0 (the "
                               "default); build this one with num_rnn=0")
        return super().load_state_dict(state_dict, strict=strict, assign=assign)

    def _check_images(self, images: torch.Tensor) -> None:
        check_images(images)
        param = next(self.backbone.parameters(), None)
        if param is not None and images.device != param.device:
            raise ValueError(
                f"images are on {images.device} but the descriptor is on {param.device}; move one of them "
                "(e.g. descriptor.to(images.device))"
            )
        if images.requires_grad and not self.differentiable and torch.is_grad_enabled():
            raise ValueError("images require grad, but this descriptor was built with differentiable=False: its "
                             "output is detached from them; build it with differentiable=True to backpropagate "
                             "to the images (or pass images.detach())")

    def parts(self, images: torch.Tensor) -> DescriptorParts:
        """Descriptor with its intermediates (L, G, fused) for inspection; see :class:`DescriptorParts`.

        Args:
            images: :math:`(B, 3, H, W)` uint8 or [0, 1] float.

        Raises:
            ValueError: images that require grad (under autograd) given to a descriptor built with
                ``differentiable=False``, whose output would silently be detached from them.
        """
        self._check_images(images)
        if images.shape[0] == 0:
            if self.pool is not None:  # the descriptor's dtype: the RNNs' (their weights are a buffer) ...
                dtype = self.pool.weights.dtype
            else:  # ... else the backbone's
                param = next(self.backbone.parameters(), None)
                dtype = param.dtype if param is not None else torch.get_default_dtype()
            empty = images.new_zeros((0, *self.backbone.tap_shape), dtype=dtype)
            desc = images.new_zeros((0, self.out_dim), dtype=dtype)
            if self.differentiable and torch.is_grad_enabled() and not torch.is_inference_mode_enabled():
                # an empty batch stays in the graph, as an nn.Conv2d's empty output does
                tied = [t for t in (*self.parameters(), images) if t.requires_grad]
                if tied:
                    zero = (sum(t.sum() for t in tied) * 0).to(dtype)
                    empty, desc = empty + zero, desc + zero
            return DescriptorParts(empty, empty, empty, desc)
        tap, grad = guided_backprop(self.backbone, images, create_graph=self.differentiable)
        return DescriptorParts(tap, grad, *self._encode(tap, grad, self.recipe.fusion))

    def _encode(self, tap: torch.Tensor, grad: torch.Tensor, fusion: str) -> tuple[torch.Tensor, torch.Tensor]:
        r = self.recipe
        return descriptor_from_attention(tap, grad, self.rnn_weights, fusion, r.normalize, r.pool_scale, r.merges,
                                         pooling=r.pooling, groups=self.tap_groups, attended=self.attended_groups,
                                         gem_p=r.gem_p)

    def forward(self, images: torch.Tensor) -> torch.Tensor:
        if self.recipe.fusion != "none" or self.differentiable:
            return self.parts(images).descriptor
        # "none" never reads G: the network runs to the tap only
        self._check_images(images)
        if images.shape[0] == 0:
            return self.parts(images).descriptor
        with eval_mode(self.backbone), torch.no_grad():
            tap = self.backbone.forward_to_tap(self.backbone.preprocess(images))
        return self.from_attention(tap, torch.zeros_like(tap))

    def from_attention(self, tap: torch.Tensor, grad: torch.Tensor, fusion: str | None = None) -> torch.Tensor:
        """Descriptor of given (L, G), e.g. to compare fusion modes on one backbone pass.

        Args:
            tap: the tap activations L, :math:`(B, C, h, w)` of this backbone's tap shape.
            grad: the guided gradient G, same shape.
            fusion: a fusion mode; this module's own when None.

        Returns:
            :math:`(B, D)` descriptors.
        """
        if tap.ndim != 4 or tuple(tap.shape[1:]) != tuple(self.backbone.tap_shape):
            raise ValueError(f"tap must have shape (B, {', '.join(map(str, self.backbone.tap_shape))}), "
                             f"got {tuple(tap.shape)}")
        return self._encode(tap, grad, self.recipe.fusion if fusion is None else fusion)[1]

    def extra_repr(self) -> str:
        r = self.recipe
        rnn = f"num_rnn={r.num_rnn}, pool_scale={r.pool_scale}" if self.pool is not None else "num_rnn=0"
        return (f"backbone={self.backbone_name!r}, fusion={r.fusion!r}, differentiable={self.differentiable}, "
                f"normalize={r.normalize}, pooling={r.pooling!r}, {rnn}, out_dim={self.out_dim}")
