"""Synthetic LiDAR scenes: scene sampling, the range-image ray-caster, label noise, dataset writers.
Simulation never imports the model: it only makes data with known truth.

The dataset-level entry point is :func:`labelaudit.sim.dataset.simulate_dataset`.
"""

from labelaudit.sim.noise import NoiseSpec, perturb_boxes
from labelaudit.sim.raycast import LidarSpec, RangeImage, ray_directions, render_range_image
from labelaudit.sim.scene import Scene, SceneSpec, SimObject, make_object, sample_scene

__all__ = [
    "LidarSpec",
    "NoiseSpec",
    "RangeImage",
    "Scene",
    "SceneSpec",
    "SimObject",
    "make_object",
    "perturb_boxes",
    "ray_directions",
    "render_range_image",
    "sample_scene",
]
