"""Synthetic traffic scenes with exact ground truth: video, truth files and a site config (`roadwatch simulate`)."""

from tools.simulate.presets import PRESETS, SceneParams, scene_params
from tools.simulate.scenario import ScenarioOutput, render_scenario
from tools.simulate.stream import SceneStream, site_config_dict

__all__ = ["PRESETS", "SceneParams", "scene_params", "ScenarioOutput", "render_scenario", "SceneStream",
           "site_config_dict"]
