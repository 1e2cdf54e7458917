"""Synthetic RGB-D sequences with exact ground truth: a photo-textured room or a building with twin rooms, rendered
by a ray caster in torch along trajectories with known revisits, with Kinect-like noise, written in the TUM layout.

Example:
    >>> from slam.synthetic import generate_sequence  # doctest: +SKIP
    >>> folder = generate_sequence("/tmp/synthetic_loop", trajectory="loop", num_frames=300)  # doctest: +SKIP
"""
from slam.synthetic.building import BuildingConfig, build_building_scene, building_layout
from slam.synthetic.building_tour import building_sequence, building_trajectory, generate_building_sequence
from slam.synthetic.demo import DEFAULT_DEMO_SCENE, DEMO_SCENES, DemoScene, generate_demo
from slam.synthetic.render import DepthNoiseConfig, ImageNoiseConfig, RenderOutput, render_frames
from slam.synthetic.scene import RoomConfig, Scene, build_room_scene
from slam.synthetic.sequence import DEPTH_FACTOR, SyntheticSequence, generate_sequence, synthetic_intrinsics
from slam.synthetic.trajectories import TRAJECTORIES, make_trajectory, trajectory_rates

__all__ = [
    "DEFAULT_DEMO_SCENE",
    "DEMO_SCENES",
    "DEPTH_FACTOR",
    "TRAJECTORIES",
    "BuildingConfig",
    "DemoScene",
    "DepthNoiseConfig",
    "ImageNoiseConfig",
    "RenderOutput",
    "RoomConfig",
    "Scene",
    "SyntheticSequence",
    "build_building_scene",
    "build_room_scene",
    "building_layout",
    "building_sequence",
    "building_trajectory",
    "generate_building_sequence",
    "generate_demo",
    "generate_sequence",
    "make_trajectory",
    "render_frames",
    "synthetic_intrinsics",
    "trajectory_rates",
]
