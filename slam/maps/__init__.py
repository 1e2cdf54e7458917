"""Maps that outlive a run: save a run's keyframe map (:mod:`slam.maps.format`), relocalise a later recording
in it (:mod:`slam.maps.relocalise`); ``attnloop-slam --save-map DIR`` / ``--map DIR`` (docs/pipeline.md, "Maps that
persist").
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
