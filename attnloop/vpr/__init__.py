"""Place recognition on image collections: describe, index, query, evaluate (the ``attnloop-vpr`` command).

- :func:`describe`: descriptors of many images as resumable float32 shards and a manifest (a torch DataLoader,
  or Ray Data on a cluster); :func:`load_descriptors` reads them back as ``(paths, X)``.
- :class:`ShardedIndex`: the keyframe index (:mod:`attnloop.index`), one per row range when one would not fit.
- :mod:`attnloop.vpr.evaluate`: recall@k, AUC-PR, recall at 100 % precision against a ground truth.
- :mod:`attnloop.vpr.datasets`: sets as paths and a ground truth (``nordland(root, step)``, ``rtabmap(root)``).
"""
from attnloop.vpr.describe import VPRInputError, describe, describe_images, image_paths, load_descriptors, read_manifest
from attnloop.vpr.search import ShardedIndex

__all__ = ["ShardedIndex", "VPRInputError", "describe", "describe_images", "image_paths", "load_descriptors",
           "read_manifest"]
