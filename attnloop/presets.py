"""The descriptor's named configurations: ``default`` (ours), ``paper`` and ``guclu2019`` (its baseline).

One source of truth for what ``AttentionDescriptor(backbone, preset=NAME)`` and
``slam.config.DescriptorConfig(preset=NAME)`` build; docs/method.md compares them.
"""
from __future__ import annotations

from dataclasses import dataclass, field

__all__ = ["DEFAULT_BACKBONE_SETTINGS", "PAPER_BACKBONE_SETTINGS", "PAPER_RECIPE_SETTINGS", "PRESETS", "Preset",
           "preset"]

#: Backbone name -> the tap and input size of the default descriptor.
DEFAULT_BACKBONE_SETTINGS: dict[str, dict[str, object]] = {
    "efficientnet_lite0": {"tap": "stage5", "input_size": (256, 320)},
    "vgg16": {"tap": "pool5"},
}

#: Backbone name -> the paper's tap (and its 224 x 224 input, the backbone's own).
PAPER_BACKBONE_SETTINGS: dict[str, dict[str, object]] = {
    "efficientnet_lite0": {"tap": "stage7"},
    "vgg16": {"tap": "pool5"},
}

#: The paper's steps 2-5 (its fusion DAM unless the caller chooses another): see
#: :class:`attnloop.descriptor.DescriptorRecipe`.
PAPER_RECIPE_SETTINGS: dict[str, object] = {
    "fusion": "dam", "pooling": "flat", "num_rnn": 16, "out_features": 64, "pool_scale": None, "merge": True,
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
