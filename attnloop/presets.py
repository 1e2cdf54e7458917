"""The descriptor's two configurations: the measured default, and the paper's (``preset="paper"``).

One source of truth for what ``AttentionDescriptor(backbone_name)`` builds when no tap, recipe setting
or preset is given. The choices and their figures are in docs/attention.md ("Place recognition").

* **default** (ours): EfficientNet-Lite0 tapped at stage6 and stage7 together (192 + 320 channels,
  7 x 9 at a 224 x 288 input, which keeps a 4:3 frame's aspect), the attention G computed and fused at
  stage7, the last stage as the paper's pool5 is VGG16's (the seeded backward then costs 5.5 % of a
  forward instead of 13.1 %; stage6 enters the pooling unfused), regional GeM pooling (p = 2, the
  whole map and a 2 x 2 grid, every region L2-normalised), and that 2560-d code, L2-normalised, is the
  descriptor: no random RNNs (``DescriptorRecipe.num_rnn = 0``; on that code the paper's 16 RNNs of 64
  are a lossy random projection, docs/attention.md "Session 6"). VGG16 keeps its pool5 tap at
  224 x 224 (not measured here: its weights could not be downloaded) with the same pooling.
* **paper**: the tap of the paper (VGG16 pool5; EfficientNet-Lite0's last block stage7), a direct
  224 x 224 resize, the paper's merge of channel c with c + C/2, 16 one-level RNNs of 64 over the whole
  flattened map, the raw fused map as their input (no ``pool_scale``), L2 at the end.
"""
from __future__ import annotations

__all__ = ["DEFAULT_BACKBONE_SETTINGS", "PAPER_BACKBONE_SETTINGS", "PAPER_RECIPE_SETTINGS", "PRESETS"]

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

#: The values ``AttentionDescriptor(preset=...)`` accepts.
PRESETS = ("paper",)
