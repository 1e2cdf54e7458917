"""Random-weight EfficientNet-Lite networks whose seeded gradient is well conditioned, for comparing paths."""
from __future__ import annotations

import torch
import torch.nn.functional as F


def condition_head(net, seed: int = 0):
    """Scale a random-weight EfficientNet-Lite's head conv and classifier: head pre-activations and logits of std 2.

    Random weights fade to ~1e-9 by the head and leave a softmax flat to 1e-10. There G = J^T S is a
    cancellation (S_k - |S|^2) at rounding level, and two correct summation orders (autograd's, the closed
    form's) do not agree on it. Scaled, ReLU6 masks about half of the head and the seed is far from zero.
    The head's batch-norm gets random affine weights and statistics first (every factor of its backward
    then counts).
    Deterministic: two networks of one seed stay identical.

    Args:
        net: an :class:`attnloop.backbones.efficientnet_lite.EfficientNetLite` (any dtype), changed in place.
        seed: seed of the images the scales are measured on.

    Returns:
        ``net``.
    """
    dtype = net._fc.weight.dtype
    gen = torch.Generator().manual_seed(seed)
    images = 0.1 + 0.8 * torch.rand(4, 3, *net.input_size, generator=gen)
    with torch.no_grad():
        # batch-norm statistics and affine weights of a trained head, not the init's ones and zeros
        bn = net._bn1
        for t, lo, hi in ((bn.weight, 0.5, 2.0), (bn.bias, -0.5, 0.5), (bn.running_mean, -0.5, 0.5),
                          (bn.running_var, 0.5, 2.0)):
            t.copy_(lo + (hi - lo) * torch.rand(t.shape, generator=gen, dtype=torch.float64))
        h = F.relu6(net._bn0(net._conv_stem(net.preprocess(images.to(dtype)))))
        for block in net._blocks:
            h = block(h)
        slope = bn.weight / torch.sqrt(bn.running_var + bn.eps)
        net._conv_head.weight.mul_(2.0 / float((net._conv_head(h) * slope[:, None, None]).std()))
        pooled = F.relu6(bn(net._conv_head(h))).mean(dim=(2, 3))
        net._fc.weight.mul_(2.0 / float(net._fc(pooled).std()))
    return net
