"""Place recognition on image collections: describe, index, query, evaluate (the ``attnloop-vpr`` command)."""
from attnloop.vpr.describe import VPRInputError, describe, describe_images, image_paths, load_descriptors, read_manifest
from attnloop.vpr.search import ShardedIndex

__all__ = ["ShardedIndex", "VPRInputError", "describe", "describe_images", "image_paths", "load_descriptors",
           "read_manifest"]
