"""The descriptor's named configurations: ``default`` (ours, measured), ``paper`` and ``guclu2019``.

One source of truth for what ``AttentionDescriptor(backbone, preset=NAME)`` and
``slam.config.DescriptorConfig(preset=NAME)`` build. The choices and their figures are in docs/method.md
("What the default changes, and why") and docs/results.md ("Place recognition").

* **default** (ours): EfficientNet-Lite0 tapped at stage6 and stage7 together (192 + 320 channels,
  7 x 9 at a 224 x 288 input, which keeps a 4:3 frame's aspect), the attention G computed and fused at
  stage7, the last stage as the paper's pool5 is VGG16's (the seeded backward then costs 5.5 % of a
  forward instead of 13.1 %; stage6 enters the pooling unfused), regional GeM pooling (p = 2, the
  whole map and a 2 x 2 grid, every region L2-normalised), and that 2560-d code, L2-normalised, is the
  descriptor: no random RNNs (on that code the paper's 16 RNNs of 64 are a lossy random projection).
  VGG16 keeps its pool5 tap at 224 x 224 with the same pooling. ``backbone="auto"``: VGG16 when its
  weights are at hand, else EfficientNet-Lite0.
* **paper**: Caglayan et al.'s descriptor: VGG16 pool5 at a direct 224 x 224 resize, the
  softmax-seeded partial guided backprop G, the fusion (DAM by default; any of them), the merge of
  channel c with c + C/2, 16 one-level random RNNs of 64 over the whole flattened map with the raw
  fused map as their input (no ``pool_scale``), 1024-d, L2 at the end. ``backbone="auto"`` means VGG16
  here, and its weights must be found (never another network in its place); EfficientNet-Lite0 (tap
  stage7) only when asked for by name.
* **guclu2019**: the paper's baseline column, the descriptor of Guclu et al. 2019 ("Fast and effective
  loop closure detection to improve SLAM performance", the CNN-randRNN encoding of Caglayan and Can):
  VGG16 pool5 without attention (fusion ``none``: the activations themselves) into 16 one-level random
  RNNs of 64 over the flattened map, WITHOUT the merge of channel pairs (the paper names that merge as
  the difference from its baseline), raw input, 1024-d, L2 at the end.

  Not confirmed against Guclu et al.'s own code (not public to our knowledge; neither their paper's text
  nor the CNN-randRNN repository could be read here): the VGG16 layer (pool5 assumed, as the paper's
  own), the input size and resize (224 x 224 direct assumed), the RNN count and size (16 x 64 assumed,
  as the paper's), how the random weights are drawn and seeded (attnloop.rnn_pool's, as the paper
  preset's), and the final L2. What is taken from the paper is only "the same encoding without the
  channel merge, without attention".
"""
from __future__ import annotations

from dataclasses import dataclass, field

__all__ = ["DEFAULT_BACKBONE_SETTINGS", "PAPER_BACKBONE_SETTINGS", "PAPER_RECIPE_SETTINGS", "PRESETS", "Preset",
           "preset"]

#: Backbone name -> the tap and input size of the default descriptor.
DEFAULT_BACKBONE_SETTINGS: dict[str, dict[str, object]] = {
    "efficientnet_lite0": {"tap": "stage6+stage7", "attend": "stage7", "input_size": (224, 288)},
    "vgg16": {"tap": "pool5"},
}

#: Backbone name -> the paper's tap (and its 224 x 224 input, the backbone's own).
PAPER_BACKBONE_SETTINGS: dict[str, dict[str, object]] = {
    "efficientnet_lite0": {"tap": "stage7"},
    "vgg16": {"tap": "pool5"},
}

#: The paper's steps 2-5 (fusion is the caller's choice): see :class:`attnloop.descriptor.DescriptorRecipe`.
PAPER_RECIPE_SETTINGS: dict[str, object] = {
    "pooling": "flat", "num_rnn": 16, "out_features": 64, "pool_scale": None, "merge": True,
}


@dataclass(frozen=True)
class Preset:
    """A named descriptor configuration.

    Attributes:
        name: the name ``preset=`` takes.
        recipe: the :class:`attnloop.descriptor.DescriptorRecipe` settings it fixes (empty: none fixed).
        backbone_settings: backbone name -> tap (and input size) of a name-built backbone.
        auto_backbone: what ``backbone="auto"`` stands for: ``"auto"`` (VGG16 when its weights are at
            hand, else EfficientNet-Lite0) or ``"vgg16"`` (its weights required).
        fusion: the fusion it fixes (None: the caller's choice).
    """

    name: str
    recipe: dict = field(default_factory=dict)
    backbone_settings: dict = field(default_factory=dict)
    auto_backbone: str = "auto"
    fusion: str | None = None

    @property
    def fixed(self) -> bool:
        """Whether the preset fixes the recipe and the tap (``paper``, ``guclu2019``)."""
        return bool(self.recipe)


#: Name -> :class:`Preset`: the values ``preset=`` accepts.
PRESETS: dict[str, Preset] = {
    "default": Preset("default", {}, DEFAULT_BACKBONE_SETTINGS),
    "paper": Preset("paper", PAPER_RECIPE_SETTINGS, PAPER_BACKBONE_SETTINGS, auto_backbone="vgg16"),
    "guclu2019": Preset("guclu2019", {**PAPER_RECIPE_SETTINGS, "merge": False}, PAPER_BACKBONE_SETTINGS,
                        auto_backbone="vgg16", fusion="none"),
}


def preset(name: str | None) -> Preset:
    """The :class:`Preset` of a name (None: ``default``).

    Raises:
        ValueError: an unknown name, naming the known ones.
    """
    if name is None:
        return PRESETS["default"]
    if not isinstance(name, str) or name not in PRESETS:
        raise ValueError(f"unknown preset {name!r}; choose one of {', '.join(PRESETS)}")
    return PRESETS[name]
