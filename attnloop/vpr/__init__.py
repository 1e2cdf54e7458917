"""Place recognition on image collections: describe, index, query, evaluate (the ``attnloop-vpr`` command).

:func:`describe` (resumable shards), :func:`load_descriptors`, :class:`ShardedIndex`, :mod:`attnloop.vpr.evaluate`
(recall@k, AUC-PR, R@P100) and :mod:`attnloop.vpr.datasets` (Nordland, RTAB-Map's samples).
"""
from attnloop.vpr.describe import VPRInputError, describe, describe_images, image_paths, load_descriptors, read_manifest
from attnloop.vpr.search import ShardedIndex

__all__ = ["ShardedIndex", "VPRInputError", "describe", "describe_images", "image_paths", "load_descriptors",
           "read_manifest"]
