"""Maps that outlive a run: save a run's keyframe map, relocalise a later recording in it.

* :mod:`slam.maps.format`: the open, versioned folder format (``manifest.json`` + ``.npz``):
  :func:`save_map`, :func:`load_map`, :class:`SavedMap`, the named errors;
* :mod:`slam.maps.relocalise`: :class:`MapRelocaliser` (map queries per keyframe through the loop
  closer's verification, the consistent placement, the merge into the map's world) and
  :func:`capture_map` (a finished run's :class:`SavedMap`);
* :mod:`slam.maps.config`: :class:`RelocalisationConfig`.

``attnloop-slam SEQUENCE --save-map DIR`` and ``attnloop-slam SEQUENCE --map DIR`` use them through
:func:`slam.pipeline.run_slam` (docs/pipeline.md, "Maps that persist").
"""
from slam.maps.config import RelocalisationConfig
from slam.maps.format import (
                              MAP_FILES,
                              MAP_FORMAT,
                              MAP_FORMAT_VERSION,
                              MapFormatError,
                              MapVersionError,
                              SavedMap,
                              load_map,
                              prepare_map_dir,
                              save_map,
)
from slam.maps.relocalise import (
                              MapLink,
                              MapMismatchError,
                              MapRelocaliser,
                              RelocalisationReport,
                              capture_map,
                              map_world_errors,
)

__all__ = ["MAP_FILES", "MAP_FORMAT", "MAP_FORMAT_VERSION", "MapFormatError", "MapLink", "MapMismatchError",
           "MapRelocaliser", "MapVersionError", "RelocalisationConfig", "RelocalisationReport", "SavedMap",
           "capture_map", "load_map", "map_world_errors", "prepare_map_dir", "save_map"]
