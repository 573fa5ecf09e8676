"""Scenes (image folders, built-in images, procedural charts) and scene-parameter sampling (Sec. 6.2)."""
from codesign.data.builtin import (
                                  PROCEDURAL_SCENES,
                                  SKIMAGE_SCENES,
                                  builtin_scene_names,
                                  procedural_scene,
)
from codesign.data.images import SceneLoadWarning, UnreadableImage, load_image
from codesign.data.paramconfig import ParamConfig
from codesign.data.params import (
                                  FIGURE_VALUES,
                                  LASER_STRENGTHS,
                                  PRESETS,
                                  ROBUSTNESS_FIXED,
                                  ROBUSTNESS_STAGES,
                                  SceneParams,
                                  fixed_scene_params,
                                  preset_names,
                                  preset_params,
                                  sample_scene_params,
)
from codesign.data.scenes import (
                                  DataConfig,
                                  SceneSampler,
                                  build_scene_sampler,
                                  build_scene_source,
)
from codesign.data.source import SceneSource, split_scene_names

__all__ = [
    "PROCEDURAL_SCENES", "SKIMAGE_SCENES", "builtin_scene_names", "procedural_scene", "SceneLoadWarning",
    "UnreadableImage", "load_image", "ParamConfig", "FIGURE_VALUES", "LASER_STRENGTHS",
    "PRESETS", "ROBUSTNESS_FIXED", "ROBUSTNESS_STAGES", "SceneParams", "fixed_scene_params", "preset_names",
    "preset_params", "sample_scene_params", "DataConfig", "SceneSampler", "build_scene_sampler",
    "build_scene_source", "SceneSource", "split_scene_names",
]
